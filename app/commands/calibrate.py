"""Calibrate the camera from views of a circle target (Tsai), or the lamps from rod shadows.

`reflab calibrate camera WORKSPACE [images...] --grid COLSxROWS --spacing 0.015 [--reference N]`
writes camera.json (OpenCV form plus Tsai's parameters, the pose of view N, and a "calibration"
block with per-view errors, uncertainties and the cv2.calibrateCamera cross-check).

`reflab calibrate lights WORKSPACE [images...] --rod-height H [--marks marks.json]` locates each
lamp from rod shadows and writes lights.json. Without --marks it detects the rod's foot and the
shadow's tip in the images (lamp --light; by default in captures/lights/, whose manifest says
which lamp was on in each shot), merges them into WORKSPACE/marks.json (edit that file
to correct a mark, then rerun with --marks) and uses every mark there.
"""
from __future__ import annotations

import sys
from pathlib import Path

HELP = "calibrate the camera (circle target, Tsai) or the lamps (rod shadows)"

def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="what", metavar="WHAT", required=True)
    cam = sub.add_parser("camera", help="camera.json from views of a printed circle grid")
    cam.add_argument("workspace", type=Path)
    cam.add_argument("images", nargs="*", type=Path,
                     help="target images (default: WORKSPACE/captures/calibration/*)")
    cam.add_argument("--grid", required=True, help="circles per row and column, COLSxROWS (e.g. 11x8)")
    cam.add_argument("--spacing", type=float, default=0.015, help="circle spacing in metres (default 0.015)")
    cam.add_argument("--radius", type=float, default=None,
                     help="printed circle radius in metres (default: estimated from the images)")
    cam.add_argument("--reference", type=int, default=0,
                     help="index of the image taken from the input photograph's pose (default 0)")
    cam.add_argument("--pixel-size", type=float, default=0.005,
                     help="sensor element size in mm, Tsai's dx = dy (default 0.005)")
    cam.add_argument("--no-bias-correction", action="store_true",
                     help="fit projected circle centres (as OpenCV does) instead of ellipse centres")

    li = sub.add_parser("lights", help="lights.json from rod shadows")
    li.add_argument("workspace", type=Path)
    li.add_argument("images", nargs="*", type=Path, help="rod images to detect marks in (lamp --light); default: the shots of "
                         "WORKSPACE/captures/lights/, each with the lamp its manifest says was on")
    li.add_argument("--rod-height", type=float, default=None, help="rod height in metres (default: marks.json's)")
    li.add_argument("--marks", type=Path, default=None, help="marks.json to use instead of detecting marks")
    li.add_argument("--light", type=int, default=None, help="lamp index of the images given (default: the lamp "
                    "captures/lights/manifest.json gives for a shot of the lights session, else 0)")
    li.add_argument("--mark-sigma", type=float, default=None,
                    help="marking noise in px for the covariance (default: from the residuals)")
    li.add_argument("--intensity", type=float, nargs="+", default=None,
                    help="radiant intensity (W/sr, 1 or 3 values) from the data sheet, every lamp")
    li.add_argument("--sheet", type=Path, nargs="+", default=None,
                    help="per lamp in index order, an image of the reference sheet lit by that lamp alone")
    li.add_argument("--sheet-reflectance", type=float, default=None,
                    help="the sheet's Lambertian reflectance (0..1; kd = reflectance / pi)")
    li.add_argument("--sheet-region", type=float, nargs=4, default=None, metavar=("XMIN", "XMAX", "YMIN", "YMAX"),
                    help="the sheet's extent on the ground in metres (default: all visible ground)")


def run(args) -> int:
    try:
        return _camera(args) if args.what == "camera" else _lights(args)
    except ValueError as exc:  # CalibrationError and argument problems; WorkspaceError goes to the CLI
        from hardware.workspace import WorkspaceError

        if isinstance(exc, WorkspaceError):
            raise
        from app.commands._args import error_text

        print(f"reflab calibrate {args.what}: error: {error_text(exc)}", file=sys.stderr)
        return 2


def _camera(args) -> int:
    from calibration.stages import CameraOptions, calibrate_camera

    r = calibrate_camera(CameraOptions(args.workspace, args.grid, args.spacing, args.images, args.radius,
                                       args.reference, args.pixel_size, not args.no_bias_correction))
    for _, why in r.unreadable:
        print(f"warning: skipping {why}", file=sys.stderr)  # the message names the file
    for path, why in r.skipped:
        print(f"skipping {path}: {why}")
    res, cam = r.calibration, r.camera
    s = res.sigma
    for path, rms, worst in r.views:
        print(f"  {path}: rms {rms:.3f} px, worst {worst:.3f} px")
    for text in res.warnings:
        print(f"warning: {text}", file=sys.stderr)
    for path, rms in r.rejected:
        print(f"warning: left out {path}: it reprojects at {rms:.2f} px RMS, far worse than the other views "
              "(target moved, blur, wrong circle order?)", file=sys.stderr)
    K, d = cam.K, cam.dist
    print(f"fx {K[0, 0]:.2f} ± {s['fx']:.2f}  fy {K[1, 1]:.2f} ± {s['fy']:.2f}  cx {K[0, 2]:.2f} ± {s['cx']:.2f}  "
          f"cy {K[1, 2]:.2f} ± {s['cy']:.2f}  k1 {d[0]:.4f} ± {s['k1']:.4f}  k2 {d[1]:.4f} ± {s['k2']:.4f}")
    t = cam.tsai
    print(f"Tsai: f {t['f']:.4f} mm, kappa1 {t['kappa1']:.5f} /mm², sx {t['sx']:.5f}, "
          f"Cx {t['Cx']:.2f}, Cy {t['Cy']:.2f}; circle radius {res.radius * 1000:.2f} mm")
    cc = res.crosscheck
    print(f"rms {res.rms_all:.3f} px over {len(res.views)} views; cv2.calibrateCamera (uncorrected centres): "
          f"fx {cc['fx']:.2f} cx {cc['cx']:.2f} cy {cc['cy']:.2f} k1 {cc['k1']:.4f}, rms {cc['rms_px']:.3f} px")
    print(f"wrote {r.path} ({res.time_s:.1f} s)")
    return 0


def _lights(args) -> int:
    import numpy as np

    from calibration.stages import LightsOptions, calibrate_lights

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
