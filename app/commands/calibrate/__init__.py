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

from reflab.app.commands.calibrate import camera, lights
from reflab.app.console import LOG

HELP = "calibrate the camera (circle target, Tsai) or the lamps (rod shadows)"


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="what", metavar="WHAT", required=True)
    camera.add_arguments(sub.add_parser("camera", help=camera.HELP))
    lights.add_arguments(sub.add_parser("lights", help=lights.HELP))


def run(args) -> int:
    try:
        return camera.run(args) if args.what == "camera" else lights.run(args)
    except ValueError as exc:  # CalibrationError and argument problems; WorkspaceError goes to the CLI
        from reflab.core.workspace import WorkspaceError

        if isinstance(exc, WorkspaceError):
            raise
        from reflab.app.commands._args import error_text

        LOG.error(f"reflab calibrate {args.what}: error: {error_text(exc, args)}")
        return 2
