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
    report: Callable[[float, float, str], None] = lambda done, total, message: None

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
    """A text stream that hands every complete line to ``sink`` (the log pane) and keeps the last error."""

    def __init__(self, sink, keep_last: bool):
        self.sink, self.keep_last, self.pending, self.last = sink, keep_last, "", ""

    def write(self, text: str) -> int:
        self.pending += text
        *lines, self.pending = self.pending.split("\n")
        for line in lines:
            if line.strip():
                self.sink(line)
                if self.keep_last:
                    self.last = line
        return len(text)


def run_command(ctx: Context, name: str, argv: list) -> int:
    """Run ``reflab NAME ARGV`` in this thread, its output to the log; a failure raises StepFailed."""
    module = importlib.import_module(f"app.commands.{name}")
    parser = argparse.ArgumentParser(prog=f"reflab {name}")
    module.add_arguments(parser)
    try:
        args = parser.parse_args([str(a) for a in argv])
    except SystemExit:
        raise StepFailed(f"reflab {name}: bad options {argv}") from None
    out, err = _Lines(ctx.log, False), _Lines(ctx.log, True)
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = module.run(args) or 0
    if code:
        message = err.last.split(": error: ", 1)[-1] if err.last else f"reflab {name} stopped with exit status {code}"
        raise StepFailed(message)
    return code


# ------------------------------------------------------------------ captures
def _control(task):
    """A capture Control driven by the window's Task (cancel, pause)."""
    from hardware.capture import CaptureCancelled, Control
    from hardware.task import Cancelled

    class TaskControl(Control):
        paused = property(lambda self: task.paused)
        cancelled = property(lambda self: task.cancelled)

        def wait(self):
            try:
                task.check()
            except Cancelled:
                raise CaptureCancelled("cancelled") from None

    return TaskControl()


def manifest_status(workspace, kind: str) -> dict:
    """The capture manifest of ``kind`` ({} when there is none)."""
    from hardware.capture import FOLDERS

    path = Workspace(workspace).captures / FOLDERS[kind] / "manifest.json"
    return read_json(path) if path.exists() else {}


def capture(ctx: Context, task, kind: str, plan) -> dict:
    """Take the shots of ``plan`` not yet taken: resume an unfinished session of the same plan,
    keep a complete one (unless the page's ``recapture`` is ticked), start again over another plan."""
    from hardware.capture import FOLDERS, CaptureSession
    from hardware.images import read_image

    old = manifest_status(ctx.workspace, kind)
    same = old.get("plan") == [asdict(s) for s in plan]
    if same and old.get("status") == "complete" and not ctx.options.get("recapture"):
        ctx.log(f"{kind}: the {len(plan)} shots are already taken (tick 'capture again' to retake them)")
        return old
    resume, overwrite = bool(old) and same and not ctx.options.get("recapture"), bool(old)
    overwrite = overwrite and not resume
    rig = ctx.rig
    if not rig.connected:
        ctx.log(rig.connect())
    folder = ctx.ws.captures / FOLDERS[kind]

    def progress(done, total, record):
        ctx.report(done, total, f"{kind}: shot {done} of {total} at {record['angle']:.1f}°")
        ctx.image(read_image(folder / record["file"]))

    with rig.lock:
        session = CaptureSession(ctx.workspace, kind, plan, rig.require(), rig.camera, resume=resume,
                                 overwrite=overwrite, progress=progress, control=_control(task), log=ctx.log)
        return session.run()


def _lamps(ctx) -> int:
    from app.commands.hardware import load_config

    config = ctx.rig.config or load_config(ctx.workspace / "hardware.json" if (ctx.workspace / "hardware.json").exists() else None)
    return len(config.lamps)


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
    from hardware.capture import plan_calibration

    o = ctx.options
    capture(ctx, task, "calibration", plan_calibration(_lamps(ctx), _angles(o.get("angles", "0"))))
    task.check()
    run_command(ctx, "calibrate", ["camera", ctx.workspace, "--grid", o.get("grid", "11x8"),
                                   "--spacing", o.get("spacing", 0.015)])
    cal = read_json(ctx.ws.camera).get("calibration", {})
    return f"camera.json written: {len(cal.get('views', []))} views, reprojection RMS {cal.get('rms_px', float('nan')):.3f} px"


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
    from hardware.capture import plan_lights
    from hardware.images import read_image

    o = ctx.options
    capture(ctx, task, "lights", plan_lights(_lamps(ctx), _angles(o.get("angles", "0"))))
    height = float(o.get("rod_height", 0.10))
    marks = {m["image"]: m for m in read_marks_file(ctx.workspace).get("marks", [])}
    missing = []
    for image, lamp in rod_shots(ctx.workspace):
        task.check()
        if image in marks:
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
    run_command(ctx, "calibrate", ["lights", ctx.workspace, "--marks", ctx.workspace / "marks.json",
                                   "--rod-height", height])
    n = len(read_json(ctx.ws.lights)["lights"])
    return f"lights.json written: {n} lamps from {len(marks)} rod marks"


def _sweep(ctx, task) -> str:
    from hardware.capture import plan_sweep

    count = int(ctx.options.get("count", 36))
    manifest = capture(ctx, task, "sweep", plan_sweep(_lamps(ctx), count))
    return f"{len(manifest['shots'])} turntable shots in captures/turntable"


def _reconstruct(ctx, task) -> str:
    o = ctx.options
    argv = [ctx.workspace]
    if o.get("turntable_centre"):
        argv += ["--turntable-centre", o["turntable_centre"]]
    if read_marks_file(ctx.workspace).get("surfaces"):
        argv += ["--marks", ctx.workspace / "marks.json"]
    if o.get("force"):
        argv.append("--force")
    run_command(ctx, "reconstruct", argv)
    scene = read_json(ctx.ws.scene)
    return f"scene.json written: {len(scene.get('surfaces', []))} surfaces"


def _input(ctx, task) -> str:
    from hardware.capture import plan_input

    capture(ctx, task, "input", plan_input(_lamps(ctx), float(ctx.options.get("angle", 0.0)),
                                           bool(ctx.options.get("ambient", False))))
    return f"input photograph: {ctx.ws.input_image.name}"


def _fit(ctx, task) -> str:
    from inverse.fitting import fit_workspace

    o = ctx.options
    report, result = fit_workspace(ctx.workspace, o.get("method", "ftbo"), int(o.get("depth", 3)),
                                   max_seconds=o.get("max_seconds") or None,
                                   texture_rounds=int(o.get("texture_rounds", 2)), task=task,
                                   progress=lambda rec: ctx.log(f"texture round {rec['round']}: refit RMS per band "
                                                                f"{[round(v, 4) for v in rec['rms']]}"))
    for text in report.get("warnings", []):
        ctx.log(f"warning: {text}")
    rms = ", ".join(f"{v:.3g}" for v in report["rms"])
    if report.get("status") == "poor fit":
        raise StepFailed(f"poor fit (RMS per band [{rms}]): the fitted model does not explain the image; "
                         "fit.json says why")
    return (f"fit.json written: {report.get('status', 'ok')}, RMS per band [{rms}], {result.iterations} iterations "
            f"in {report['time_s']:.1f} s")


def _texture(ctx, task) -> str:
    run_command(ctx, "texture", [ctx.workspace])
    n = len(list(ctx.ws.textures.glob("*_mask.png")))
    return f"textures written for {n} surfaces"


def _results(ctx, task) -> str:
    import numpy as np

    from app.commands.render import render_workspace
    from hardware.images import read_image, write_image, write_preview

    ws = ctx.ws
    photo = read_image(ws.require(ws.input_image, "the Input step"))
    image, info = render_workspace(ctx.workspace, depth=int(ctx.options.get("depth", 3)))
    task.check()
    write_image(ws.root / "render.exr", image)
    write_preview(ws.root / "render.png", image)
    rel = float(np.sqrt(np.mean((image - photo) ** 2)) / max(np.sqrt(np.mean(photo ** 2)), 1e-300))
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
