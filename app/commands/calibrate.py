"""Calibrate the camera from views of a circle target (Tsai), or the lamps from rod shadows.

`reflab calibrate camera WORKSPACE [images...] --grid COLSxROWS --spacing 0.015 [--reference N]`
writes camera.json (OpenCV form plus Tsai's parameters, the pose of view N, and a "calibration"
block with per-view errors, uncertainties and the cv2.calibrateCamera cross-check).

`reflab calibrate lights WORKSPACE [images...] --rod-height H [--marks marks.json]` locates each
lamp from rod shadows and writes lights.json. Without --marks it detects the rod's foot and the
shadow's tip in the images (lamp --light), merges them into WORKSPACE/marks.json (edit that file
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
    li.add_argument("images", nargs="*", type=Path, help="rod images to detect marks in (lamp --light)")
    li.add_argument("--rod-height", type=float, default=None, help="rod height in metres (default: marks.json's)")
    li.add_argument("--marks", type=Path, default=None, help="marks.json to use instead of detecting marks")
    li.add_argument("--light", type=int, default=0, help="lamp index of the images given (default 0)")
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
        print(f"reflab calibrate {args.what}: error: {exc}", file=sys.stderr)
        return 2


def _images(explicit, folder: Path) -> list[Path]:
    if explicit:
        return list(explicit)
    from hardware.images import image_files

    return image_files(folder)


def _camera(args) -> int:
    import numpy as np

    from calibration.circles import detect_grid, parse_grid
    from calibration.tsai import CalibrationError, calibrate
    from hardware.images import read_image
    from calibration.target import target_points
    from hardware.workspace import Workspace, WorkspaceError

    ws = Workspace(args.workspace)
    cols, rows = parse_grid(args.grid)
    if not args.spacing > 0:
        raise ValueError(f"--spacing must be a positive number of metres, got {args.spacing}")
    paths = _images(args.images, ws.captures / "calibration")
    if not paths:
        raise ValueError(f"no target images given and none in {ws.captures / 'calibration'}")
    if not 0 <= args.reference < len(paths):
        raise ValueError(f"--reference {args.reference} is not an image index (0..{len(paths) - 1})")
    used, obs, areas, blobs, reasons = [], [], [], [], ""
    size = None
    for i, path in enumerate(paths):
        try:  # any image a camera writes (8-bit JPEG too); one unreadable photo is not fatal
            img = read_image(path, linear=False)
        except WorkspaceError as exc:
            if i == args.reference:
                raise
            print(f"warning: skipping {path}: {exc}", file=sys.stderr)
            continue
        shape = (img.shape[1], img.shape[0])
        if size is None:
            size = shape
        elif shape != size:
            raise ValueError(f"{path}: image is {shape[0]}x{shape[1]}, the others {size[0]}x{size[1]}")
        det = detect_grid(img, cols, rows)
        blobs.append(det.n_blobs)
        if not det.found:
            reasons += det.reason
            print(f"skipping {path}: grid {cols}x{rows} not found: {det.reason}")
            continue
        used.append(i)
        obs.append(det.centres)
        areas.append(det.areas)
    if not blobs:
        raise ValueError(f"none of the {len(paths)} target images could be read")
    if not used and (np.median(blobs) != cols * rows or "grid size" in reasons):
        raise ValueError(f"grid {cols}x{rows} ({cols * rows} circles) found in none of {len(paths)} images; "
                         f"they show about {int(np.median(blobs))} dark blobs: check --grid (COLSxROWS)")
    if args.reference not in used:
        raise ValueError(f"the reference image {paths[args.reference]} has no detectable grid; "
                         "its pose is the one camera.json needs")
    try:
        res = calibrate(obs, target_points(cols, rows, args.spacing), size, radius=args.radius,
                        pixel_size=args.pixel_size, reference=used.index(args.reference),
                        bias_correction=not args.no_bias_correction, areas=areas)
    except CalibrationError as exc:
        if exc.view is None:
            raise
        raise ValueError(f"{paths[used[exc.view]]}: {exc}") from None
    cam = res.camera
    cam.extra["calibration"] = dict(res.report([str(paths[i]) for i in used]), grid=[cols, rows],
                                    spacing=args.spacing, reference_image=str(paths[args.reference]),
                                    skipped=[str(p) for i, p in enumerate(paths) if i not in used])
    out = cam.save(ws.camera)
    s = res.sigma
    for j, r, w in zip(res.views, res.rms, res.worst):
        print(f"  {paths[used[j]]}: rms {r:.3f} px, worst {w:.3f} px")
    for j, r in res.rejected.items():
        print(f"warning: left out {paths[used[j]]}: it reprojects at {r:.2f} px RMS, far worse than the other views "
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
    print(f"wrote {out} ({res.time_s:.1f} s)")
    return 0


def _lights(args) -> int:
    import numpy as np

    from calibration.camera import Camera
    from calibration.lamps import Mark, detect_rod_marks, lamp_intensity, locate_lamps, read_marks, write_marks
    from calibration.lights import Lights, PointLight
    from hardware.images import read_image
    from hardware.workspace import Workspace

    ws = Workspace(args.workspace)
    camera = Camera.load(ws.require(ws.camera, "reflab calibrate camera"))
    marks_path = args.marks or ws.root / "marks.json"
    height, marks = read_marks(marks_path) if (args.marks or (marks_path.exists() and not args.images)) else (None, [])
    if args.images:
        if args.marks:
            raise ValueError("give either images to detect marks in or --marks, not both")
        if marks_path.exists():
            height, marks = read_marks(marks_path)
        for path in args.images:
            try:
                base, tip = detect_rod_marks(read_image(path, linear=False))
            except ValueError as exc:
                raise ValueError(f"{path}: {exc}; mark it by hand in marks.json") from None
            name = str(path.relative_to(ws.root)) if path.is_relative_to(ws.root) else str(path)
            marks = [m for m in marks if m.image != name] + [Mark(name, args.light, base, tip)]
            print(f"  {name}: lamp {args.light}, foot ({base[0]:.1f}, {base[1]:.1f}), tip ({tip[0]:.1f}, {tip[1]:.1f})")
    if args.rod_height is not None:
        height = args.rod_height
    if height is None or not height > 0:
        raise ValueError(f"--rod-height must be a positive number of metres (got {height})")
    if not marks:
        raise ValueError(f"no marks: give rod images or --marks (nothing in {marks_path})")
    if args.images:
        write_marks(marks_path, height, marks)
        print(f"wrote {marks_path} (correct a mark there and rerun with --marks)")
    fits = locate_lamps(camera, marks, height, mark_sigma=args.mark_sigma)
    if [f.light for f in fits] != list(range(len(fits))):
        raise ValueError(f"lamp indices in the marks are {[f.light for f in fits]}; expected 0..{len(fits) - 1}")

    old = Lights.load(ws.lights) if ws.lights.exists() else None
    if args.sheet and len(args.sheet) != len(fits):
        raise ValueError(f"--sheet: {len(args.sheet)} images for {len(fits)} lamps")
    if args.sheet and args.sheet_reflectance is None:
        raise ValueError("--sheet needs --sheet-reflectance")
    lights = []
    for k, fit in enumerate(fits):
        extra = {"calibration": fit.report()}
        if args.sheet:
            inten, spread = lamp_intensity(read_image(args.sheet[k]), camera, fit.position,
                                           args.sheet_reflectance / np.pi, region=args.sheet_region)
            extra["calibration"]["intensity_spread"] = spread
        elif args.intensity:
            inten = np.broadcast_to(np.asarray(args.intensity, float), (3,)) if len(args.intensity) in (1, 3) else None
            if inten is None:
                raise ValueError(f"--intensity takes 1 or 3 values, got {len(args.intensity)}")
        elif old is not None and k < len(old):
            inten = old[k].intensity
        else:
            inten = np.ones(3)
            print(f"  lamp {k}: intensity unknown, wrote 1.0; give --intensity (data sheet) or --sheet")
        lights.append(PointLight(fit.position, inten, fit.covariance, extra))
        sd = np.sqrt(np.diag(fit.covariance)) * 1000
        print(f"lamp {k}: ({fit.position[0]:.4f}, {fit.position[1]:.4f}, {fit.position[2]:.4f}) m "
              f"± ({sd[0]:.1f}, {sd[1]:.1f}, {sd[2]:.1f}) mm, intensity {np.round(inten, 4).tolist()}, "
              f"outlier marks {fit.outliers or 'none'}")
    out = Lights(lights).save(ws.lights)
    print(f"wrote {out}")
    return 0
