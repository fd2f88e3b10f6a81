"""`reflab calibrate camera`: camera.json from views of a printed circle grid (Tsai; see the package)."""
from __future__ import annotations

from pathlib import Path

from reflab.app.console import LOG

HELP = "camera.json from views of a printed circle grid"


def add_arguments(parser) -> None:
    from reflab.calibration.stages import CameraOptions
    from reflab.core.options import add_arguments as table_arguments

    parser.add_argument("workspace", type=Path)
    parser.add_argument("images", nargs="*", type=Path,
                        help="target images (default: WORKSPACE/captures/calibration/*)")
    table_arguments(parser, CameraOptions)


def run(args) -> int:
    from reflab.app.console import running
    from reflab.calibration.stages import CameraOptions, calibrate_camera
    from reflab.core.options import options_from_args

    with running("calibrate camera") as task:
        r = calibrate_camera(options_from_args(CameraOptions, args, workspace=args.workspace, images=args.images), task)
    for _, why in r.unreadable:
        LOG.warning(f"warning: skipping {why}")  # the message names the file
    for path, why in r.skipped:
        LOG.info(f"skipping {path}: {why}")
    res, cam = r.calibration, r.camera
    s = res.sigma
    for path, rms, worst in r.views:
        LOG.info(f"  {path}: rms {rms:.3f} px, worst {worst:.3f} px")
    for text in res.warnings:
        LOG.warning(f"warning: {text}")
    for path, rms in r.rejected:
        LOG.warning(f"warning: left out {path}: it reprojects at {rms:.2f} px RMS, far worse than the other views "
                    "(target moved, blur, wrong circle order?)")
    K, d = cam.K, cam.dist
    LOG.info(f"fx {K[0, 0]:.2f} ± {s['fx']:.2f}  fy {K[1, 1]:.2f} ± {s['fy']:.2f}  cx {K[0, 2]:.2f} ± {s['cx']:.2f}  "
             f"cy {K[1, 2]:.2f} ± {s['cy']:.2f}  k1 {d[0]:.4f} ± {s['k1']:.4f}  k2 {d[1]:.4f} ± {s['k2']:.4f}")
    t = cam.tsai
    LOG.info(f"Tsai: f {t['f']:.4f} mm, kappa1 {t['kappa1']:.5f} /mm², sx {t['sx']:.5f}, "
             f"Cx {t['Cx']:.2f}, Cy {t['Cy']:.2f}; circle radius {res.radius * 1000:.2f} mm")
    cc = res.crosscheck
    LOG.info(f"rms {res.rms_all:.3f} px over {len(res.views)} views; cv2.calibrateCamera (uncorrected centres): "
             f"fx {cc['fx']:.2f} cx {cc['cx']:.2f} cy {cc['cy']:.2f} k1 {cc['k1']:.4f}, rms {cc['rms_px']:.3f} px")
    LOG.info(f"wrote {r.path} ({res.time_s:.1f} s)")
    return 0
