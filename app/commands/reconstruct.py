"""Reconstruct the scene's geometry from the turntable sweep and model its surfaces.

Stages, each skipped when what it makes is already there: structure from motion over
captures/turntable (pycolmap, camera.json's intrinsics held fixed) and registration into the
world frame (sfm.json, sparse.ply); surfaces fitted to the sparse points (ground plane, boxes
on it); boxes from corners marked in two or more shots (--marks); meshes imported (--mesh).
An existing scene.json is left alone unless --marks or --mesh add to it, or --force redoes it.
docs/reconstruction.md describes the files and the marks format.
"""
from __future__ import annotations

from reflab.app.console import LOG

HELP = "recover geometry from the turntable sweep (pycolmap) and model surfaces: scene.json + meshes/"


def add_arguments(parser) -> None:
    from reflab.core.options import add_arguments as table_arguments
    from reflab.reconstruction.stages import ReconstructOptions

    parser.add_argument("workspace", metavar="WORKSPACE")
    table_arguments(parser, ReconstructOptions)


def options(args):
    """The stage's options from the command's arguments; the stage checks them (OptionError naming the flag)."""
    from reflab.calibration.circles import parse_grid
    from reflab.core.options import options_from_args
    from reflab.reconstruction.stages import ReconstructOptions

    o = options_from_args(ReconstructOptions, args, workspace=args.workspace)
    o.target = parse_grid(o.target, "target") if o.target else None  # checked before any work
    return o


def run(args) -> int:
    from reflab.app.console import running
    from reflab.reconstruction.stages import reconstruct

    with running("reconstruct") as task:
        result = reconstruct(options(args), task, log=LOG.info)
    if result.skipped:
        LOG.info(f"{result.scene_path} exists: nothing to reconstruct (--marks or --mesh add surfaces, --force redoes it)")
        return 0
    r = result.sfm
    if r is not None:
        LOG.info(f"structure from motion: {r['sfm']['registered']}/{r['sfm']['images']} shots registered, "
                 f"reprojection {r['sfm']['reprojection_px']:.3f} px, {r['sfm']['points']} points, "
                 f"{r['sfm']['time_s']['total_s']:.1f} s")
        rt = r.get("rigid_turntable")
        if rt is not None and "rms_px" in rt:
            LOG.info(f"rigid turntable: reprojection {rt['rms_px']:.3f} px RMS on one axis against "
                     f"{rt['rms_px_free']:.3f} px with free poses, {rt['time_s']:.1f} s")
        if rt is not None and not rt["used"]:
            LOG.warning(f"warning: {rt['warning']}")
        if "turntable" in r:
            tt = r["turntable"]
            LOG.info(f"turntable: axis tilt {tt['axis_tilt_deg']:.3f} deg, angle error max "
                     f"{tt['max_angle_error_deg']:.3f} deg, rms {tt['rms_angle_error_deg']:.3f} deg")
        LOG.info(f"registration ({r['registration']['method']}): input view {r['reference']['centre_mm']:.2f} mm, "
                 f"{r['reference']['rotation_deg']:.3f} deg from camera.json")
        from reflab.core.workspace import Workspace

        ws = Workspace(args.workspace)
        LOG.info(f"wrote {ws.sfm} and {ws.sparse}")
    for m in result.modelled:
        detail = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in m.info.items()
                           if isinstance(v, (int, float)))
        LOG.info(f"surface {m.name}: {m.source}{'; ' + detail if detail else ''} -> meshes/{m.name}.ply")
    LOG.info(f"wrote {result.scene_path} ({len(result.scene)} surfaces) in {result.time_s:.1f} s")
    return 0
