"""`reflab calibrate lights`: lights.json from rod shadows (see the package)."""
from __future__ import annotations

import sys
from pathlib import Path

HELP = "lights.json from rod shadows"


def add_arguments(parser) -> None:
    parser.add_argument("workspace", type=Path)
    parser.add_argument("images", nargs="*", type=Path, help="rod images to detect marks in (lamp --light); default: the shots of "
                        "WORKSPACE/captures/lights/, each with the lamp its manifest says was on")
    parser.add_argument("--rod-height", type=float, default=None, help="rod height in metres (default: marks.json's)")
    parser.add_argument("--marks", type=Path, default=None, help="marks.json to use instead of detecting marks")
    parser.add_argument("--light", type=int, default=None, help="lamp index of the images given (default: the lamp "
                        "captures/lights/manifest.json gives for a shot of the lights session, else 0)")
    parser.add_argument("--mark-sigma", type=float, default=None,
                        help="marking noise in px for the covariance (default: from the residuals)")
    parser.add_argument("--intensity", type=float, nargs="+", default=None,
                        help="radiant intensity (W/sr, 1 or 3 values) from the data sheet, every lamp")
    parser.add_argument("--sheet", type=Path, nargs="+", default=None,
                        help="per lamp in index order, an image of the reference sheet lit by that lamp alone")
    parser.add_argument("--sheet-reflectance", type=float, default=None,
                        help="the sheet's Lambertian reflectance (0..1; kd = reflectance / pi)")
    parser.add_argument("--sheet-region", type=float, nargs=4, default=None, metavar=("XMIN", "XMAX", "YMIN", "YMAX"),
                        help="the sheet's extent on the ground in metres (default: all visible ground)")


def run(args) -> int:
    import numpy as np

    from reflab.calibration.stages import LightsOptions, calibrate_lights

    r = calibrate_lights(LightsOptions(args.workspace, args.images, args.rod_height, args.marks, args.light,
                                       args.mark_sigma, args.intensity, args.sheet, args.sheet_reflectance,
                                       args.sheet_region))
    for _, why in r.unreadable:
        print(f"warning: skipping {why}", file=sys.stderr)  # the message names the file
    for name, light, base, tip in r.detected:
        print(f"  {name}: lamp {light}, foot ({base[0]:.1f}, {base[1]:.1f}), tip ({tip[0]:.1f}, {tip[1]:.1f})")
    if r.marks_path is not None:
        print(f"wrote {r.marks_path} (correct a mark there and rerun with --marks)")
    for lamp in r.lamps:
        if not lamp.intensity_known:
            print(f"  lamp {lamp.index}: intensity unknown, wrote 1.0; give --intensity (data sheet) or --sheet")
        p, sd = lamp.position, lamp.sigma_mm
        print(f"lamp {lamp.index}: ({p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}) m ± ({sd[0]:.1f}, {sd[1]:.1f}, {sd[2]:.1f}) mm, "
              f"intensity {np.round(lamp.intensity, 4).tolist()}, outlier marks {lamp.outliers or 'none'}")
    print(f"wrote {r.path}")
    return 0
