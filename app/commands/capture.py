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
import sys
from pathlib import Path

from reflab.app.commands._args import float_list, image_size

HELP = "capture calibration, rod-shadow, turntable or input images (hardware or simulated devices)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("kind", choices=["calibration", "lights", "sweep", "input", "inputs"])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("--port", required=True, help="serial port of the GRBL board, or 'sim' for the simulated board")
    parser.add_argument("--camera", required=True, help="sim | opencv:N | opencv:URL | folder:PATH (tethered camera)")
    parser.add_argument("--config", help="hardware JSON (default: WORKSPACE/hardware.json when it exists)")
    parser.add_argument("--angles", type=float_list, default=None,
                        help="turntable angles: calibration, of the target on its wedge (default 0,45,90,135,225,270,315, "
                             "after one shot of it lying flat); lights, of the rod (default 0,90,180,270)")
    parser.add_argument("--count", type=int, default=36, help="sweep: number of shots over 360 degrees (default 36)")
    parser.add_argument("--start", type=float, default=0.0, help="sweep: first angle; input: the angle (default 0)")
    parser.add_argument("--ambient", action="store_true", help="input: also take a lamps-off frame and subtract it")
    parser.add_argument("--plan", action="store_true", help="inputs: the shots of plan.json (made first if missing); "
                        "without it, one shot per --angles angle with every lamp on")
    parser.add_argument("--exposure", type=float, help="exposure passed to the camera and recorded (seconds)")
    parser.add_argument("--settle", type=float, default=0.0, help="seconds to wait after the lamps change")
    parser.add_argument("--format", choices=["exr", "png", "tif"], default="exr", help="image files (default exr)")
    again = parser.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true", help="continue a stopped session; take only the missing shots")
    again.add_argument("--overwrite", action="store_true", help="discard an earlier session of this kind and start again")
    parser.add_argument("--unlock", action="store_true", help="if the board is in ALARM, soft-reset and unlock it first")
    parser.add_argument("--trigger", help="folder camera: command that takes a shot (e.g. 'gphoto2 --trigger-capture')")
    parser.add_argument("--camera-timeout", type=float, default=60.0, help="folder camera: seconds to wait for a file")
    sim = parser.add_argument_group("simulated camera (--camera sim)")
    sim.add_argument("--size", type=image_size, default=None,
                     help="image size WxH (default: camera.json's, else 480x360: at 320x240 structure from motion "
                          "registers too few sweep shots; every capture of a workspace must have the same size)")
    sim.add_argument("--depth", type=int, default=3, help="ray depth of the simulated camera (default 3)")
    sim.add_argument("--centre", type=float_list, default=[0.0, 0.0], help="turntable axis x,y in metres (default 0,0)")
    sim.add_argument("--room-light", type=float, default=0.0, help="ambient radiance added to every pixel")
    sim.add_argument("--grain", type=float, default=0.2,
                     help="fine print grain of the lab's textures (default 0.2, as printed paper has; 0 = the plain "
                          "procedural lab, too poorly textured for structure from motion)")


def run(args) -> int:
    from reflab.app.devices import SIM_SIZE, Devices, SimOptions, load_config
    from reflab.hardware.cameras import CameraError
    from reflab.hardware.capture import CaptureCancelled, CaptureError, CaptureOptions, calibrated_size, run_capture
    from reflab.hardware.grbl import GrblError
    from reflab.core.workspace import Workspace, WorkspaceError

    ws = Workspace(args.workspace)
    config = load_config(args.config or (ws.hardware if ws.hardware.exists() else None))

    def on_shot(done, total, rec):
        lamps = "".join("1" if x else "0" for x in rec["lamps"])
        print(f"[{done}/{total}] {rec['file']}  angle {rec['angle']:.3f}  lamps {lamps}", flush=True)

    calibrated = calibrated_size(ws)
    if args.camera == "sim" and args.size is None:
        args.size = calibrated or SIM_SIZE
    elif args.camera == "sim" and calibrated and tuple(args.size) != calibrated and args.kind != "calibration":
        raise WorkspaceError(ws.camera, "width/height",
                             f"captures of the calibrated size {calibrated[0]}x{calibrated[1]} (leave --size out, "
                             "or calibrate again at the new size)", got=f"--size {args.size[0]}x{args.size[1]}")
    try:
        sim = SimOptions(args.size, args.depth, args.centre, args.room_light, args.grain)
        with Devices(args.port, args.camera, config=config, unlock=args.unlock, sim=sim, trigger=args.trigger,
                 camera_timeout=args.camera_timeout) as rig:
            if args.kind == "inputs":
                from reflab.app.steps import further_photographs

                shots = None if args.plan else [{"name": f"a{a:g}".replace("-", "m"), "angle_deg": a,
                                                 "lamps": list(range(len(config.lamps)))} for a in args.angles or []]
                print(further_photographs(ws.root, rig, log=print, shots=shots, recapture=args.overwrite).summary)
                return 0
            result = run_capture(CaptureOptions(
                args.workspace, args.kind, rig.controller, rig.camera, args.angles, args.count, args.start,
                args.ambient, args.format, args.exposure, args.settle, args.resume, args.overwrite, on_shot, print))
            print(f"wrote {len(result.shots)} images and {result.manifest_path}")
            if args.camera == "sim" and args.kind == "sweep":
                from reflab.hardware.sim.user import mark_sweep

                path = mark_sweep(ws.root, rig.camera.sim_lab, result.manifest, centre=args.centre)
                print(f"the simulated user marked the mirror's and the sheet's corners and named the surfaces in {path}")
        return 0
    except CaptureCancelled as exc:
        print(f"reflab capture: {exc}", file=sys.stderr)
        return 130
    except WorkspaceError:
        raise  # the CLI names the file and field, exit status 2
    except (CaptureError, GrblError, CameraError, ValueError) as exc:
        from reflab.app.commands._args import error_text

        print(f"reflab capture: error: {error_text(exc)}", file=sys.stderr)
        return 1
