"""Reconstruct the scene's geometry from the turntable sweep and model its surfaces.

Stages, each skipped when what it makes is already there: structure from motion over
captures/turntable (pycolmap, camera.json's intrinsics held fixed) and registration into the
world frame (sfm.json, sparse.ply); surfaces fitted to the sparse points (ground plane, boxes
on it); boxes from corners marked in two or more shots (--marks); meshes imported (--mesh).
An existing scene.json is left alone unless --marks or --mesh add to it, or --force redoes it.
docs/reconstruction.md describes the files and the marks format.
"""
from __future__ import annotations

import sys

HELP = "recover geometry from the turntable sweep (pycolmap) and model surfaces: scene.json + meshes/"


def add_arguments(parser) -> None:
    parser.add_argument("workspace", metavar="WORKSPACE")
    parser.add_argument("--mesh", action="append", default=[], metavar="NAME=PATH",
                        help="import a mesh (PLY/OBJ, metres, world frame) as surface NAME; repeatable")
    parser.add_argument("--ior", action="append", default=[], metavar="NAME=INDEX",
                        help="refraction index of an imported surface (its mesh must then be closed)")
    parser.add_argument("--marks", metavar="FILE", help="corners marked in the turntable shots (docs/reconstruction.md)")
    parser.add_argument("--target", metavar="COLSxROWS", help="circle target lying on the turntable, to fix the frame")
    parser.add_argument("--spacing", type=float, default=0.015, help="circle spacing of --target in metres (0.015)")
    parser.add_argument("--turntable-centre", metavar="X,Y",
                        help="where the turntable axis meets the ground (metres), to fix the scale without a target")
    parser.add_argument("--overlap", type=int, default=5, help="each shot is matched with the next N shots (5)")
    parser.add_argument("--free-poses", action="store_true",
                        help="keep structure from motion's free poses instead of one turntable axis and one angle "
                             "per shot (for a turntable that wobbles)")
    parser.add_argument("--no-fit", action="store_true", help="do not fit planes and boxes to the sparse points")
    parser.add_argument("--force", action="store_true", help="redo structure from motion and every surface")


def _pairs(items, option):
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name or not value:
            raise ValueError(f"{option}: expected NAME=VALUE, got {item!r}")
        out[name] = value
    return out


def run(args) -> int:
    import time
    from pathlib import Path

    from calibration.camera import Camera
    from hardware.workspace import Workspace, WorkspaceError
    from reconstruction import surfaces as surf
    from reconstruction.scene import Scene

    t0 = time.perf_counter()
    ws = Workspace(args.workspace)
    meshes = _pairs(args.mesh, "--mesh")
    iors = {k: float(v) for k, v in _pairs(args.ior, "--ior").items()}
    unknown = set(iors) - set(meshes)
    if unknown:
        raise ValueError(f"--ior: no --mesh named {sorted(unknown)[0]!r}")
    existing = Scene.load(ws.scene) if ws.scene.exists() and not args.force else None
    if existing is not None and not meshes and not args.marks:
        print(f"{ws.scene} exists: nothing to reconstruct (--marks or --mesh add surfaces, --force redoes it)")
        return 0

    modelled = [surf.import_mesh(name, Path(path), iors.get(name)) for name, path in meshes.items()]
    sfm_file = ws.root / "sfm.json"
    need_sfm = bool(args.marks) or (existing is None and not meshes)
    if need_sfm:
        camera = Camera.load(ws.require(ws.camera, "reflab calibrate camera"))
        fresh = args.force or not sfm_file.exists()
        if fresh:
            from reconstruction.registration import reconstruct_sweep

            result = reconstruct_sweep(ws, camera, target=args.target, spacing=args.spacing,
                                       turntable_centre=args.turntable_centre, overlap=args.overlap,
                                       rigid_turntable=not args.free_poses, log=lambda line: print(line, flush=True))
            r = result["report"]
            print(f"structure from motion: {r['sfm']['registered']}/{r['sfm']['images']} shots registered, "
                  f"reprojection {r['sfm']['reprojection_px']:.3f} px, {r['sfm']['points']} points, "
                  f"{r['sfm']['time_s']['total_s']:.1f} s")
            if "rigid_turntable" in r:
                rt = r["rigid_turntable"]
                if "rms_px" in rt:
                    print(f"rigid turntable: reprojection {rt['rms_px']:.3f} px RMS on one axis against "
                          f"{rt['rms_px_free']:.3f} px with free poses, {rt['time_s']:.1f} s")
                if not rt["used"]:
                    print(f"warning: {rt['warning']}", file=sys.stderr)
            if "turntable" in r:
                tt = r["turntable"]
                print(f"turntable: axis tilt {tt['axis_tilt_deg']:.3f} deg, angle error max "
                      f"{tt['max_angle_error_deg']:.3f} deg, rms {tt['rms_angle_error_deg']:.3f} deg")
            print(f"registration ({r['registration']['method']}): input view {r['reference']['centre_mm']:.2f} mm, "
                  f"{r['reference']['rotation_deg']:.3f} deg from camera.json")
            print(f"wrote {sfm_file} and {ws.root / 'sparse.ply'}")
        from reconstruction.registration import load_views

        views, points = load_views(ws, camera)
        if fresh and not args.no_fit and not meshes:
            fitted = surf.fit_scene_points(points, camera=camera)
            modelled = fitted + modelled
        if args.marks:
            for spec in surf.load_marks(args.marks):
                modelled.append(surf.box_from_marks(spec, views))
    if not modelled:
        raise WorkspaceError(ws.scene, expected="at least one surface (fitted, marked or imported)", got="none")
    scene = surf.write_scene(ws.root, modelled, existing)
    for m in modelled:
        detail = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in m.info.items()
                           if isinstance(v, (int, float)))
        print(f"surface {m.name}: {m.source}{'; ' + detail if detail else ''} -> meshes/{m.name}.ply")
    print(f"wrote {ws.scene} ({len(scene)} surfaces) in {time.perf_counter() - t0:.1f} s")
    return 0
