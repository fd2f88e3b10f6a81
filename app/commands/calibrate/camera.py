"""`reflab calibrate camera`: camera.json from views of a printed circle grid (Tsai; see the package)."""
from __future__ import annotations

import sys
from pathlib import Path

HELP = "camera.json from views of a printed circle grid"


def add_arguments(parser) -> None:
    parser.add_argument("workspace", type=Path)
    parser.add_argument("images", nargs="*", type=Path,
                        help="target images (default: WORKSPACE/captures/calibration/*)")
    parser.add_argument("--grid", required=True, help="circles per row and column, COLSxROWS (e.g. 11x8)")
    parser.add_argument("--spacing", type=float, default=0.015, help="circle spacing in metres (default 0.015)")
    parser.add_argument("--radius", type=float, default=None,
                        help="printed circle radius in metres (default: estimated from the images)")
    parser.add_argument("--reference", type=int, default=0,
                        help="index of the image taken from the input photograph's pose (default 0)")
    parser.add_argument("--pixel-size", type=float, default=0.005,
                        help="sensor element size in mm, Tsai's dx = dy (default 0.005)")
    parser.add_argument("--no-bias-correction", action="store_true",
                        help="fit projected circle centres (as OpenCV does) instead of ellipse centres")


def run(args) -> int:
    from reflab.calibration.stages import CameraOptions, calibrate_camera

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
