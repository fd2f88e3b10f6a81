"""The window's steps: what each asks the user to do, when it is done, and how it runs.

One small adapter between the window and the stage code: each :class:`GuiStep` has the
contract's name (INTERFACES.md, GUI), a title, the sentence shown at the rig, ``done(workspace)``
from the workspace's files, and ``run(ctx, task)`` that captures what the step needs (through the
shared :class:`app.gui.rig.Rig`) and runs the stage, returning a one-line summary. Stages run
through their ``reflab`` subcommand modules with the output sent to the log pane; a stage's
error line becomes the step's one-line failure message.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import io
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

from app.gui.worker import StepFailed
from hardware.workspace import Workspace, read_json, write_json


@dataclass
class Context:
    """What a running step may use: the workspace, the rig, its page's options and the reporters."""

    workspace: Path
    rig: object
    options: dict = field(default_factory=dict)
    log: Callable[[str], None] = print
    image: Callable[[object], None] = lambda img: None

    @property
    def ws(self) -> Workspace:
        return Workspace(self.workspace)


@dataclass
class GuiStep:
    name: str
    title: str
    instructions: str
    done: Callable[[Path], bool]
    run: Callable[[Context, object], str]


# ------------------------------------------------------------------ running a subcommand
class _Lines(io.TextIOBase):
    """A text stream that hands every complete line to ``sink`` (the log pane)."""

    def __init__(self, sink):
        self.sink, self.pending = sink, ""

    def write(self, text: str) -> int:
        self.pending += text
        *lines, self.pending = self.pending.split("\n")
        for line in lines:
            if line.strip():
                self.sink(line)
        return len(text)


def run_command(ctx: Context, name: str, argv: list) -> None:
    """Run ``reflab NAME ARGV`` in this thread (for app-level commands without a stage function),
    its output to the log; a non-zero exit raises StepFailed with its last error line."""
    module = importlib.import_module(f"app.commands.{name}")
    parser = argparse.ArgumentParser(prog=f"reflab {name}")
    module.add_arguments(parser)
    args = parser.parse_args([str(a) for a in argv])
    errors = []
    with contextlib.redirect_stdout(_Lines(ctx.log)), contextlib.redirect_stderr(_Lines(lambda l: (errors.append(l), ctx.log(l)))):
        code = module.run(args) or 0
    if code:
        raise StepFailed(errors[-1].split(": error: ", 1)[-1] if errors else f"reflab {name}: exit status {code}")


# ------------------------------------------------------------------ captures
def manifest_status(workspace, kind: str) -> dict:
    """The capture manifest of ``kind`` ({} when there is none)."""
    from hardware.capture import FOLDERS

    path = Workspace(workspace).captures / FOLDERS[kind] / "manifest.json"
    return read_json(path) if path.exists() else {}


def capture(ctx: Context, task, kind: str, **options) -> dict:
    """Take the shots of ``kind`` not yet taken: resume an unfinished session of the same plan,
    keep a complete one (unless the page's ``recapture`` is ticked), start again over another plan."""
    from hardware.capture import FOLDERS, CaptureOptions, plan, run_capture
    from hardware.images import read_image

    rig = ctx.rig
    if not rig.connected:
        ctx.log(rig.connect())
    folder = ctx.ws.captures / FOLDERS[kind]

    def on_shot(done, total, record):  # the session steps the task itself (progress bar, cancel)
        ctx.image(read_image(folder / record["file"]))

    with rig.lock:
        opts = CaptureOptions(ctx.workspace, kind, rig.require(), rig.camera, on_shot=on_shot, log=ctx.log, **options)
        old = manifest_status(ctx.workspace, kind)
        same = old.get("plan") == [asdict(s) for s in plan(kind, len(rig.config.lamps), opts)]
        if same and old.get("status") == "complete" and not ctx.options.get("recapture"):
            ctx.log(f"{kind}: the {len(old['shots'])} shots are already taken (tick 'capture again' to retake them)")
            return old
        opts.resume = bool(old) and same and not ctx.options.get("recapture")
        opts.overwrite = bool(old) and not opts.resume
        return run_capture(opts, task).manifest


def _angles(text) -> list[float]:
    try:
        return [float(x) for x in str(text).split(",") if x.strip()] or [0.0]
    except ValueError:
        raise StepFailed(f"angles must be comma-separated degrees, got {text!r}") from None


# ------------------------------------------------------------------ marks.json (rod marks and marked corners)
def read_marks_file(workspace) -> dict:
    path = Workspace(workspace).root / "marks.json"
    return read_json(path) if path.exists() else {}


def update_marks_file(workspace, **sections) -> Path:
    """Replace the given top-level sections of marks.json (``rod_height``, ``marks``, ``surfaces``), keep the others."""
    obj = read_marks_file(workspace)
    obj.update({k: v for k, v in sections.items() if v is not None})
    return write_json(Workspace(workspace).root / "marks.json", obj)


# ------------------------------------------------------------------ the steps
def _devices(ctx, task) -> str:
    status = ctx.rig.connect()
    ctx.rig.write_config()
    return f"connected: {status}"


def _calibrate_camera(ctx, task) -> str:
    from calibration.stages import CameraOptions, calibrate_camera

    o = ctx.options
    capture(ctx, task, "calibration", angles=_angles(o.get("angles", "0")))
    result = calibrate_camera(CameraOptions(ctx.workspace, grid=o.get("grid", "11x8"),
                                            spacing=float(o.get("spacing", 0.015))), task)
    skipped = f", {len(result.skipped)} skipped" if result.skipped else ""
    return f"camera.json written: {len(result.used)} views{skipped}, reprojection RMS {result.rms_px:.3f} px"


def rod_shots(workspace) -> list[tuple[str, int]]:
    """(image relative to the workspace, lamp index) of every rod shot taken (one lamp on)."""
    shots = []
    for rec in manifest_status(workspace, "lights").get("shots", []):
        on = [k for k, x in enumerate(rec.get("lamps", [])) if x]
        if len(on) == 1:
            shots.append((f"captures/lights/{rec['file']}", on[0]))
    return shots


def _calibrate_lights(ctx, task) -> str:
    from calibration.lamps import detect_rod_marks
    from calibration.stages import LightsOptions, calibrate_lights
    from hardware.images import read_image

    o = ctx.options
    capture(ctx, task, "lights", angles=_angles(o.get("angles", "0")))
    height = float(o.get("rod_height", 0.10))
    marks = {m["image"]: m for m in read_marks_file(ctx.workspace).get("marks", [])}
    missing = []
    for image, lamp in rod_shots(ctx.workspace):
        task.check()
        if image in marks:  # found earlier or placed by hand: kept
            continue
        try:
            base, tip = detect_rod_marks(read_image(ctx.workspace / image))
        except ValueError as exc:
            ctx.log(f"{image}: {exc}")
            missing.append(image)
            continue
        marks[image] = {"image": image, "light": lamp, "base": [float(x) for x in base], "tip": [float(x) for x in tip]}
        ctx.log(f"{image}: lamp {lamp}, foot ({base[0]:.1f}, {base[1]:.1f}), tip ({tip[0]:.1f}, {tip[1]:.1f}) (detected)")
    update_marks_file(ctx.workspace, rod_height=height, marks=list(marks.values()))
    if missing:
        raise StepFailed(f"rod not found in {len(missing)} shot(s) ({', '.join(Path(m).name for m in missing)}): "
                         "mark the rod's foot and its shadow's tip on the shot, then run again")
    result = calibrate_lights(LightsOptions(ctx.workspace, marks=ctx.ws.root / "marks.json", rod_height=height), task)
    return f"lights.json written: {len(result.lamps)} lamps from {len(marks)} rod marks"


def _sweep(ctx, task) -> str:
    manifest = capture(ctx, task, "sweep", count=int(ctx.options.get("count", 36)))
    return f"{len(manifest['shots'])} turntable shots in captures/turntable"


def _reconstruct(ctx, task) -> str:
    from reconstruction.stages import ReconstructOptions, reconstruct

    o = ctx.options
    centre = None
    if str(o.get("turntable_centre", "")).strip():
        try:
            centre = tuple(float(x) for x in str(o["turntable_centre"]).split(","))
        except ValueError:
            raise StepFailed(f"turntable axis must be x,y in metres, got {o['turntable_centre']!r}") from None
    marks = ctx.ws.root / "marks.json" if read_marks_file(ctx.workspace).get("surfaces") else None
    result = reconstruct(ReconstructOptions(ctx.workspace, marks=marks, turntable_centre=centre,
                                            force=bool(o.get("force"))), task, log=ctx.log)
    if result.skipped:
        return "scene.json already there: nothing to do (tick 'redo from scratch' to rebuild it)"
    sfm = f"{result.sfm['sfm']['registered']}/{result.sfm['sfm']['images']} shots registered, " if result.sfm else ""
    return f"scene.json written: {sfm}{len(result.scene)} surfaces in {result.time_s:.1f} s"


def _input(ctx, task) -> str:
    capture(ctx, task, "input", start=float(ctx.options.get("angle", 0.0)), ambient=bool(ctx.options.get("ambient", False)))
    return f"input photograph: {ctx.ws.input_image.name}"


def _fit(ctx, task) -> str:
    from inverse.stages import FitOptions, fit

    o = ctx.options
    result = fit(FitOptions(ctx.workspace, o.get("method", "ftbo"), int(o.get("depth", 3)),
                            max_seconds=o.get("max_seconds") or None, texture_rounds=int(o.get("texture_rounds", 2))),
                 task, on_round=lambda rec: ctx.log(f"texture round {rec['round']}: refit RMS per band "
                                                    f"{[round(v, 4) for v in rec['rms']]}"))
    report = result.report
    for text in report.get("warnings", []):
        ctx.log(f"warning: {text}")
    rms = ", ".join(f"{v:.3g}" for v in report["rms"])
    if report.get("status") == "poor fit":
        raise StepFailed(f"poor fit (RMS per band [{rms}]): the fitted model does not explain the image; "
                         "fit.json says why")
    return (f"fit.json written: {report.get('status', 'ok')}, RMS per band [{rms}], {result.fit.iterations} iterations "
            f"in {report['time_s']:.1f} s")


def _texture(ctx, task) -> str:
    from inverse.stages import TextureOptions, texture

    result = texture(TextureOptions(ctx.workspace), task, log=ctx.log)
    st = result.result.stats
    return (f"textures written for {len(result.result.maps)} surfaces: {st['unknowns']} texels, "
            f"residual RMS per band [{', '.join(f'{v:.3g}' for v in st['residual_rms'])}]")


def _results(ctx, task) -> str:
    import numpy as np

    from hardware.images import read_image
    from inverse.stages import RenderOptions, render

    ws = ctx.ws
    photo = read_image(ws.require(ws.input_image, "the Input photograph step"))
    result = render(RenderOptions(ctx.workspace, output=ws.root / "render.exr", depth=int(ctx.options.get("depth", 3))),
                    task, log=ctx.log)
    image = result.image
    rel = float(np.sqrt(np.mean((image - photo) ** 2)) / max(np.sqrt(np.mean(photo ** 2)), 1e-300))
    task.check()
    try:
        run_command(ctx, "report", [ctx.workspace])
    except StepFailed as exc:
        ctx.log(f"report: {exc}")
    return f"model re-rendered: RMS difference {100 * rel:.2f}% of the input"


def _exists(name):
    return lambda ws: (Path(ws) / name).exists()


STEPS = [
    GuiStep("devices", "Devices",
            "Plug in the turntable/lamp board and the camera, then connect. Jog the turntable and switch each "
            "lamp to check the wiring; the live view shows what the camera sees.",
            _exists("hardware.json"), _devices),
    GuiStep("calibrate_camera", "Calibrate the camera",
            "Lay the printed circle target flat on the turntable where the objects will stand, with the camera "
            "in the pose of the input photograph. Run takes one shot per turntable angle and calibrates.",
            _exists("camera.json"), _calibrate_camera),
    GuiStep("calibrate_lights", "Calibrate the lamps",
            "Stand the rod upright on the table in view of the camera. Run takes one shot per lamp, finds the "
            "rod's foot and its shadow's tip, and locates every lamp. Drag a mark that is off, then run again.",
            _exists("lights.json"), _calibrate_lights),
    GuiStep("sweep", "Turntable sweep",
            "Put the objects on the turntable (no target, no rod). Run turns the table a full circle, one shot "
            "per step. For mirrors and glass, mark their corners on two or more shots below.",
            lambda ws: manifest_status(ws, "sweep").get("status") == "complete", _sweep),
    GuiStep("reconstruct", "Reconstruct the geometry",
            "Nothing to do at the rig. Run recovers the shots' poses and the sparse points, fits the ground and "
            "the boxes, and adds the surfaces whose corners you marked.",
            _exists("scene.json"), _reconstruct),
    GuiStep("input", "Input photograph",
            "Turn the table back to the input pose and darken the room. Run takes the one photograph the model "
            "is fitted to (tick 'ambient frame' to subtract the room light).",
            lambda ws: Workspace(ws).input_image.exists(), _input),
    GuiStep("fit", "Fit the materials",
            "Nothing to do at the rig. Run fits each surface's diffuse, specular, mirror and transmission "
            "parameters to the input photograph; the curve shows the error falling.",
            _exists("fit.json"), _fit),
    GuiStep("texture", "Recover the textures",
            "Nothing to do at the rig. Run recovers every textured surface's colour per texel, seen directly, "
            "in the mirror or through the sheet.",
            _exists("textures/index.json"), _texture),
    GuiStep("results", "Results",
            "Compare the re-rendered model with the photograph, then move the camera and dim the lamps to see "
            "the model from a view and under a light it was never photographed in.",
            _exists("render.exr"), _results),
]

NAMES = [s.name for s in STEPS]


def resume_index(workspace) -> int:
    """The step an existing workspace reopens at: the first one not done after the last one done."""
    done = [s.done(workspace) for s in STEPS]
    last = max((i for i, d in enumerate(done) if d), default=-1)
    later = [i for i in range(last + 1, len(STEPS)) if not done[i]]
    return later[0] if later else (len(STEPS) - 1 if last >= 0 else 0)
