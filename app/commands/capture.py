"""Capture images with the turntable, the lamps and a camera into WORKSPACE/captures/<kind>/.

Kinds: `calibration` (every lamp on, one shot per angle), `lights` (one lamp at a time per
angle, for rod shadows), `sweep` (N angles over a full turn), `input` (the input photograph,
optionally with a lamps-off ambient frame that is subtracted into WORKSPACE/input.exr), `inputs`
(further photographs into WORKSPACE/inputs/ with their camera and lamps: plan.json's with --plan).
After every shot the image and captures/<kind>/manifest.json are written atomically; after a
fault or Ctrl-C, the same command with --resume takes exactly the missing shots.
"""
from __future__ import annotations

import argparse

from reflab.app.console import LOG

HELP = "capture calibration, rod-shadow, turntable or input images (hardware or simulated devices)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from pathlib import Path

    from reflab.app.devices import SimOptions
    from reflab.core.options import add_arguments as table_arguments
    from reflab.hardware.capture import CaptureOptions

    parser.add_argument("kind", choices=["calibration", "lights", "sweep", "input", "inputs"])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--port", required=True, help="serial port of the GRBL board, or 'sim' for the simulated board")
    parser.add_argument("--camera", required=True, help="the camera to photograph with: sim | opencv:N | opencv:URL | "
                                                        "folder:PATH (tethered camera)")
    parser.add_argument("--config", help="hardware JSON (default: WORKSPACE/hardware.json when it exists)")
    parser.add_argument("--plan", action="store_true", help="inputs: the shots of plan.json (planned first when "
                        "missing or older than fit.json); without it, one shot per --angles angle, every lamp on")
    table_arguments(parser, CaptureOptions, skip=("resume", "overwrite"))
    again = parser.add_mutually_exclusive_group()
    table_arguments(again, CaptureOptions, only=("resume", "overwrite"))
    parser.add_argument("--unlock", action="store_true", help="if the board is in ALARM, soft-reset and unlock it first")
    parser.add_argument("--trigger", help="folder camera: command that takes a shot (e.g. 'gphoto2 --trigger-capture')")
    parser.add_argument("--camera-timeout", type=float, default=60.0, help="folder camera: seconds to wait for a file")
    sim = parser.add_argument_group("simulated camera (--camera sim)")
    table_arguments(sim, SimOptions, override={"size": {"default": None, "help": (
        "image size WxH (default: camera.json's, else 480x360: at 320x240 structure from motion registers too few "
        "sweep shots; every capture of a workspace must have the same size, except inputs: any with camera.json's "
        "aspect ratio, e.g. twice it for detail finer than the calibrated pixels)")}})


def run(args) -> int:
    from reflab.app.console import running
    from reflab.app.devices import SIM_SIZE, Devices, SimOptions, load_config
    from reflab.core.options import options_from_args
    from reflab.core.workspace import Workspace, WorkspaceError
    from reflab.hardware.cameras import CameraError
    from reflab.hardware.capture import CaptureCancelled, CaptureError, CaptureOptions, calibrated_size, run_capture
    from reflab.hardware.grbl import GrblError

    ws = Workspace(args.workspace)
    config = load_config(args.config or (ws.hardware if ws.hardware.exists() else None))

    def on_shot(done, total, rec):
        lamps = "".join("1" if x else "0" for x in rec["lamps"])
        LOG.info(f"[{done}/{total}] {rec['file']}  angle {rec['angle']:.3f}  lamps {lamps}")

    calibrated = calibrated_size(ws)
    if args.camera == "sim" and args.size is None:
        args.size = calibrated or SIM_SIZE
    elif args.camera == "sim" and calibrated and tuple(args.size) != calibrated and args.kind != "calibration" and (
            args.kind != "inputs" or args.size[0] * calibrated[1] != args.size[1] * calibrated[0]):
        raise WorkspaceError(ws.camera, "width/height",
                             f"captures of the calibrated size {calibrated[0]}x{calibrated[1]} (leave --size out, "
                             "or calibrate again at the new size; inputs: its aspect ratio)",
                             got=f"--size {args.size[0]}x{args.size[1]}")
    try:
        sim = options_from_args(SimOptions, args)
        with Devices(args.port, args.camera, config=config, unlock=args.unlock, sim=sim, trigger=args.trigger,
                     camera_timeout=args.camera_timeout, log=LOG.info) as rig, running("capture") as task:
            if args.kind == "inputs":
                from reflab.app.steps import further_photographs

                shots = None if args.plan else [{"name": f"a{a:g}".replace("-", "m"), "angle_deg": a,
                                                 "lamps": list(range(len(config.lamps)))} for a in args.angles or []]
                LOG.info(further_photographs(ws.root, rig, task, log=LOG.info, shots=shots, recapture=args.overwrite,
                                             size=args.size).summary)
                return 0
            options = options_from_args(CaptureOptions, args, workspace=args.workspace, kind=args.kind,
                                        controller=rig.controller, camera=rig.camera, on_shot=on_shot, log=LOG.info)
            result = run_capture(options, task)
            LOG.info(f"wrote {len(result.shots)} images and {result.manifest_path}")
            if args.camera == "sim" and args.kind == "sweep":
                from reflab.hardware.sim.user import mark_sweep

                path = mark_sweep(ws.root, rig.camera.sim_lab, result.manifest, centre=args.centre)
                LOG.info(f"the simulated user marked the mirror's and the sheet's corners and named the surfaces in {path}")
        return 0
    except CaptureCancelled as exc:
        LOG.error(f"reflab capture: {exc}")
        return 130
    except WorkspaceError:
        raise  # the CLI names the file and field, exit status 2
    except (CaptureError, GrblError, CameraError, ValueError) as exc:
        from reflab.app.commands._args import error_text

        LOG.error(f"reflab capture: error: {error_text(exc, args)}")
        return 2 if getattr(exc, "bad_input", False) else 1
