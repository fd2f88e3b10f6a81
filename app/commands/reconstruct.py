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
    parser.add_argument("--marks", metavar="FILE", help="corners marked in the turntable shots and what the user knows "
                                                        "per surface (default: WORKSPACE/marks.json when it has "
                                                        "'surfaces'; docs/reconstruction.md)")
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


def options(args):
    """The stage's options from the command's arguments (ValueError naming the bad flag)."""
    from pathlib import Path

    from calibration.circles import parse_grid
    from reconstruction.stages import ReconstructOptions

    meshes = {k: Path(v) for k, v in _pairs(args.mesh, "--mesh").items()}
    try:
        iors = {k: float(v) for k, v in _pairs(args.ior, "--ior").items()}
    except ValueError as exc:
        raise ValueError(f"--ior: {exc}") from None
    unknown = set(iors) - set(meshes)
    if unknown:
        raise ValueError(f"--ior: no --mesh named {sorted(unknown)[0]!r}")
    centre = None
    if args.turntable_centre is not None:
        try:
            centre = tuple(float(v) for v in args.turntable_centre.split(","))
        except ValueError:
            centre = ()
        if len(centre) != 2:
            raise ValueError(f"--turntable-centre: expected X,Y in metres, got {args.turntable_centre!r}")
    return ReconstructOptions(args.workspace, meshes, iors, args.marks and Path(args.marks),
                              parse_grid(args.target, "target") if args.target else None, args.spacing, centre, args.overlap,
                              not args.free_poses, not args.no_fit, args.force)


def run(args) -> int:
    from reconstruction.stages import reconstruct

    try:
        opts = options(args)
    except ValueError as exc:
        from app.commands._args import error_text

        print(f"reflab reconstruct: error: {error_text(exc)}", file=sys.stderr)
        return 2
    result = reconstruct(opts, log=lambda line: print(line, flush=True))
    if result.skipped:
        print(f"{result.scene_path} exists: nothing to reconstruct (--marks or --mesh add surfaces, --force redoes it)")
        return 0
    r = result.sfm
    if r is not None:
        print(f"structure from motion: {r['sfm']['registered']}/{r['sfm']['images']} shots registered, "
              f"reprojection {r['sfm']['reprojection_px']:.3f} px, {r['sfm']['points']} points, "
              f"{r['sfm']['time_s']['total_s']:.1f} s")
        rt = r.get("rigid_turntable")
        if rt is not None and "rms_px" in rt:
            print(f"rigid turntable: reprojection {rt['rms_px']:.3f} px RMS on one axis against "
                  f"{rt['rms_px_free']:.3f} px with free poses, {rt['time_s']:.1f} s")
        if rt is not None and not rt["used"]:
            print(f"warning: {rt['warning']}", file=sys.stderr)
        if "turntable" in r:
            tt = r["turntable"]
            print(f"turntable: axis tilt {tt['axis_tilt_deg']:.3f} deg, angle error max "
                  f"{tt['max_angle_error_deg']:.3f} deg, rms {tt['rms_angle_error_deg']:.3f} deg")
        print(f"registration ({r['registration']['method']}): input view {r['reference']['centre_mm']:.2f} mm, "
              f"{r['reference']['rotation_deg']:.3f} deg from camera.json")
        from hardware.workspace import Workspace

        ws = Workspace(args.workspace)
        print(f"wrote {ws.sfm} and {ws.sparse}")
    for m in result.modelled:
        detail = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in m.info.items()
                           if isinstance(v, (int, float)))
        print(f"surface {m.name}: {m.source}{'; ' + detail if detail else ''} -> meshes/{m.name}.ply")
    print(f"wrote {result.scene_path} ({len(result.scene)} surfaces) in {result.time_s:.1f} s")
    return 0
