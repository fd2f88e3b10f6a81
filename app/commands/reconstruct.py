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
from pathlib import Path

from reflab.app.commands._args import float_list, name_value

HELP = "recover geometry from the turntable sweep (pycolmap) and model surfaces: scene.json + meshes/"


def add_arguments(parser) -> None:
    parser.add_argument("workspace", metavar="WORKSPACE")
    parser.add_argument("--mesh", action="append", default=[], metavar="NAME=PATH", type=name_value(Path, "PATH"),
                        help="import a mesh (PLY/OBJ, metres, world frame) as surface NAME; repeatable")
    parser.add_argument("--ior", action="append", default=[], metavar="NAME=INDEX", type=name_value(float, "INDEX"),
                        help="refraction index of an imported surface (its mesh must then be closed)")
    parser.add_argument("--marks", metavar="FILE", help="corners marked in the turntable shots and what the user knows "
                                                        "per surface (default: WORKSPACE/marks.json when it has "
                                                        "'surfaces'; docs/reconstruction.md)")
    parser.add_argument("--target", metavar="COLSxROWS", help="circle target lying on the turntable, to fix the frame")
    parser.add_argument("--spacing", type=float, default=0.015, help="circle spacing of --target in metres (0.015)")
    parser.add_argument("--turntable-centre", metavar="X,Y", type=float_list,
                        help="where the turntable axis meets the ground (metres), to fix the scale without a target")
    parser.add_argument("--overlap", type=int, default=5, help="each shot is matched with the next N shots (5)")
    parser.add_argument("--free-poses", action="store_true",
                        help="keep structure from motion's free poses instead of one turntable axis and one angle "
                             "per shot (for a turntable that wobbles)")
    parser.add_argument("--no-fit", action="store_true", help="do not fit planes and boxes to the sparse points")
    parser.add_argument("--force", action="store_true", help="redo structure from motion and every surface")


def options(args):
    """The stage's options from the command's arguments; the stage checks them (OptionError naming the flag)."""
    from reflab.calibration.circles import parse_grid
    from reflab.reconstruction.stages import ReconstructOptions

    return ReconstructOptions(args.workspace, dict(args.mesh), dict(args.ior), args.marks and Path(args.marks),
                              parse_grid(args.target, "target") if args.target else None, args.spacing,
                              args.turntable_centre, args.overlap, not args.free_poses, not args.no_fit, args.force)


def run(args) -> int:
    from reflab.reconstruction.stages import reconstruct

    result = reconstruct(options(args), log=lambda line: print(line, flush=True))
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
        from reflab.core.workspace import Workspace

        ws = Workspace(args.workspace)
        print(f"wrote {ws.sfm} and {ws.sparse}")
    for m in result.modelled:
        detail = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in m.info.items()
                           if isinstance(v, (int, float)))
        print(f"surface {m.name}: {m.source}{'; ' + detail if detail else ''} -> meshes/{m.name}.ply")
    print(f"wrote {result.scene_path} ({len(result.scene)} surfaces) in {result.time_s:.1f} s")
    return 0
