"""`reflab calibrate lights`: lights.json from rod shadows (see the package)."""
from __future__ import annotations

from pathlib import Path

from reflab.app.console import LOG

HELP = "lights.json from rod shadows"


def add_arguments(parser) -> None:
    from reflab.calibration.stages import LightsOptions
    from reflab.core.options import add_arguments as table_arguments

    parser.add_argument("workspace", type=Path)
    parser.add_argument("images", nargs="*", type=Path, help="rod images to detect marks in (lamp --light); default: the shots of "
                        "WORKSPACE/captures/lights/, each with the lamp its manifest says was on")
    table_arguments(parser, LightsOptions)


def run(args) -> int:
    import numpy as np

    from reflab.app.console import running
    from reflab.calibration.stages import LightsOptions, calibrate_lights
    from reflab.core.options import options_from_args

    with running("calibrate lights") as task:
        r = calibrate_lights(options_from_args(LightsOptions, args, workspace=args.workspace, images=args.images), task)
    for _, why in r.unreadable:
        LOG.warning(f"warning: skipping {why}")  # the message names the file
    for name, light, base, tip in r.detected:
        LOG.info(f"  {name}: lamp {light}, foot ({base[0]:.1f}, {base[1]:.1f}), tip ({tip[0]:.1f}, {tip[1]:.1f})")
    if r.marks_path is not None:
        LOG.info(f"wrote {r.marks_path} (correct a mark there and rerun with --marks)")
    for lamp in r.lamps:
        if not lamp.intensity_known:
            LOG.info(f"  lamp {lamp.index}: intensity unknown, wrote 1.0; give --intensity (data sheet) or --sheet")
        p, sd = lamp.position, lamp.sigma_mm
        LOG.info(f"lamp {lamp.index}: ({p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}) m ± ({sd[0]:.1f}, {sd[1]:.1f}, {sd[2]:.1f}) mm, "
                 f"intensity {np.round(lamp.intensity, 4).tolist()}, outlier marks {lamp.outliers or 'none'}")
    LOG.info(f"wrote {r.path}")
    return 0
