"""The window's steps: app/steps.py's ordered steps, with what each page asks of the user.

Each :class:`GuiStep` wraps one :class:`reflab.app.steps.Step` (the contract's name, its title and
``done(workspace)`` from the workspace's files) and adds the sentence shown at the rig and
``run(ctx, task)``: it connects the rig when the step captures, holds the rig while the step
runs, hands the page's options to the step, and returns the step's one-line summary. A stage's
error message becomes the step's failure line. The lamp step first detects the rod in every
shot it can and saves those marks, so that the user marks only the shots where it failed.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from reflab.app import steps as core
from reflab.app.gui.worker import StepFailed
from reflab.core.options import default, info
from reflab.core.workspace import Workspace, read_json, write_json


@dataclass
class Context:
    """What a running step may use: the workspace, the rig, its page's options and the log."""

    workspace: Path
    rig: object
    options: dict = field(default_factory=dict)
    log: Callable[[str], None] = print

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
    """Run ``reflab NAME ARGV`` in this thread (for app-level commands without a step, the report),
    its output to the log; a non-zero exit raises StepFailed with its last error line."""
    from reflab.app.console import setup

    setup()  # the command's lines go through the reflab logger, to the streams redirected below
    module = importlib.import_module(f"reflab.app.commands.{name}")
    parser = argparse.ArgumentParser(prog=f"reflab {name}")
    module.add_arguments(parser)
    args = parser.parse_args([str(a) for a in argv])
    errors = []
    with contextlib.redirect_stdout(_Lines(ctx.log)), contextlib.redirect_stderr(_Lines(lambda l: (errors.append(l), ctx.log(l)))):
        code = module.run(args) or 0
    if code:
        raise StepFailed(errors[-1].split(": error: ", 1)[-1] if errors else f"reflab {name}: exit status {code}")


# ------------------------------------------------------------------ workspace files the pages read
def manifest_status(workspace, kind: str) -> dict:
    """The capture manifest of ``kind`` ({} when there is none)."""
    path = Workspace(workspace).manifest(kind)
    return read_json(path) if path.exists() else {}


def read_marks_file(workspace) -> dict:
    path = Workspace(workspace).marks
    return read_json(path) if path.exists() else {}


def update_marks_file(workspace, **sections) -> Path:
    """Replace the given top-level sections of marks.json (``rod_height``, ``marks``, ``surfaces``), keep the others."""
    obj = read_marks_file(workspace)
    obj.update({k: v for k, v in sections.items() if v is not None})
    return write_json(Workspace(workspace).marks, obj)


def rod_shots(workspace) -> list:
    """The rod shots taken (``reflab.calibration.rod.RodShot``: image, lamp, room-light frame), [] before any."""
    from reflab.calibration.rod import rod_shots as shots
    from reflab.core.workspace import WorkspaceError

    try:
        return shots(workspace)
    except WorkspaceError:
        return []


# ------------------------------------------------------------------ running a step
def _run(ctx: Context, task, name: str, **options):
    """Run reflab.app.steps' step ``name`` with the rig (connected first when the step captures)."""
    step = core.step(name)
    rig = ctx.rig
    if step.captures is None and name != "devices":
        return step.run(ctx.workspace, task, log=ctx.log, **options)
    if not rig.connected:
        ctx.log(rig.connect())
    with rig.lock:
        return step.run(ctx.workspace, task, rig=rig.devices, log=ctx.log, **options)


def _floats(text, what: str, count: int | None = None):
    """Comma-separated numbers from an option field; None when it is empty."""
    text = str(text or "").strip()
    if not text:
        return None
    try:
        values = [float(x) for x in text.replace(" ", ",").split(",") if x]
    except ValueError:
        raise StepFailed(f"{what}: expected comma-separated numbers, got {text!r}") from None
    if count is not None and len(values) != count:
        raise StepFailed(f"{what}: expected {count} numbers, got {text!r}")
    return values


def _capture_options(o: dict) -> dict:
    out = {"recapture": bool(o.get("recapture"))}
    angles = _floats(o.get("angles"), "turntable angles")
    if angles:
        out["angles"] = angles
    return out


def _devices(ctx, task) -> str:
    return _run(ctx, task, "devices").summary + f" — {ctx.rig.status()}"


def _calibrate_camera(ctx, task) -> str:
    o = ctx.options
    from reflab.calibration.stages import CameraOptions as C

    return _run(ctx, task, "calibrate_camera", grid=o.get("grid", default(C, "grid")),
                spacing=float(o.get("spacing", default(C, "spacing"))), **_capture_options(o)).summary


def _calibrate_lights(ctx, task) -> str:
    """Capture the rod shots, detect the rod in every shot not marked yet (saving what it finds),
    stop naming the shots left to mark by hand, then locate the lamps from marks.json."""
    from reflab.calibration.lamps import Mark, read_marks, write_marks
    from reflab.calibration.rod import detect_marks
    from reflab.calibration.stages import LightsOptions
    from reflab.core.images import read_image

    o = ctx.options
    height = float(o.get("rod_height", info(LightsOptions, "rod_height")["typical"]))
    card = {}
    if float(o.get("card_reflectance") or 0) > 0:
        card = {"sheet_reflectance": float(o["card_reflectance"]),
                "sheet_region": _floats(o.get("card_region"), "card region (x0, x1, y0, y1)", 4)}
    capture = _capture_options(o)
    before = {s.image for s in rod_shots(ctx.workspace)} if capture["recapture"] else set()
    rig = ctx.rig
    if not rig.connected:
        ctx.log(rig.connect())
    with rig.lock:  # a complete session of the same plan is kept, an unfinished one resumes
        core.capture(ctx.workspace, "lights", rig.devices, task, log=ctx.log, **capture)
    capture["recapture"] = False
    if before and "marks" in read_marks_file(ctx.workspace):  # marks of retaken shots do not apply to them
        _, old = read_marks(ctx.ws.marks)
        write_marks(ctx.ws.marks, height, [m for m in old if m.image not in before])
    marks = {m.image: m for m in (read_marks(ctx.ws.marks)[1] if "marks" in read_marks_file(ctx.workspace) else [])}
    missing = []
    for shot in rod_shots(ctx.workspace):
        task.check()
        if shot.image in marks:  # found earlier or placed by hand: kept
            continue
        try:
            (mark,) = detect_marks(ctx.workspace, [shot], lambda p: read_image(p, linear=False))
        except ValueError as exc:
            ctx.log(str(exc))
            missing.append(shot.image)
            continue
        marks[shot.image] = Mark(shot.image, shot.light, mark.base, mark.tip)
        ctx.log(f"{shot.image}: lamp {shot.light}, foot ({mark.base[0]:.1f}, {mark.base[1]:.1f}), "
                f"tip ({mark.tip[0]:.1f}, {mark.tip[1]:.1f}) (detected)")
    write_marks(ctx.ws.marks, height, list(marks.values()))
    if missing:
        raise StepFailed(f"rod not found in {len(missing)} shot(s) ({', '.join(Path(m).name for m in missing)}): "
                         "click the rod's foot and its shadow's tip on each (Rod marks), save, then run again")
    return _run(ctx, task, "calibrate_lights", rod_height=height, marks=ctx.ws.marks, **card, **capture).summary


def _sweep(ctx, task) -> str:
    from reflab.hardware.capture import CaptureOptions

    return _run(ctx, task, "sweep", count=int(ctx.options.get("count", default(CaptureOptions, "count"))),
                recapture=bool(ctx.options.get("recapture"))).summary


def _reconstruct(ctx, task) -> str:
    o = ctx.options
    centre = _floats(o.get("turntable_centre"), "turntable axis x,y", 2)
    marks = ctx.ws.marks if read_marks_file(ctx.workspace).get("surfaces") else None
    return _run(ctx, task, "reconstruct", turntable_centre=tuple(centre) if centre else None, marks=marks,
                force=bool(o.get("force"))).summary


def _input(ctx, task) -> str:
    from reflab.hardware.capture import CaptureOptions

    o = ctx.options
    summary = _run(ctx, task, "input", start=float(o.get("angle", default(CaptureOptions, "start"))),
                   ambient=bool(o.get("ambient", default(CaptureOptions, "ambient"))),
                   recapture=bool(o.get("recapture"))).summary
    if o.get("further"):
        if not ctx.ws.fit.exists():
            raise StepFailed("further photographs are planned from fit.json: run Fit first, then this step again")
        with ctx.rig.lock:
            more = core.further_photographs(ctx.workspace, ctx.rig.devices, task, log=ctx.log)
        summary = f"{summary}; {more.summary}; run Fit again to use them"
    if o.get("detail"):
        angles = _floats(o.get("detail_angles"), "detail turntable angles")
        if not angles:
            raise StepFailed("detail turntable angles: give at least one angle, e.g. 0, 30, -30")
        scale = int(o.get("detail_scale") or 2)
        with ctx.rig.lock:
            more = core.detail_photographs(ctx.workspace, ctx.rig.devices, task, angles=angles, scale=scale,
                                           log=ctx.log)
        summary = f"{summary}; {more.summary}; recover the textures with texel scale {1 / scale:g} to use them"
    return summary


def _fit(ctx, task) -> str:
    from reflab.inverse.stages import FitOptions

    o = ctx.options
    result = _run(ctx, task, "fit", max_seconds=o.get("max_seconds") or None,
                  texture_rounds=int(o.get("texture_rounds", default(FitOptions, "texture_rounds"))))
    if result.value.status == "poor fit":
        raise StepFailed(f"poor fit: {result.summary}; the fitted model does not explain the image (fit.json says why)")
    return result.summary


def _texture(ctx, task) -> str:
    from reflab.inverse.stages import TextureOptions

    o = ctx.options
    return _run(ctx, task, "texture", texel_scale=float(o.get("texel_scale", default(TextureOptions, "texel_scale"))),
                smoothness=float(o.get("smoothness", default(TextureOptions, "smoothness")))).summary


def _results(ctx, task) -> str:
    from reflab.inverse.stages import RenderOptions

    summary = _run(ctx, task, "results", depth=int(ctx.options.get("depth", default(RenderOptions, "depth")))).summary
    task.check()
    try:
        run_command(ctx, "report", [ctx.workspace])
    except StepFailed as exc:
        ctx.log(f"report: {exc}")
    return summary


INSTRUCTIONS = {
    "devices": "Plug in the turntable/lamp board and the camera, then connect. Jog the turntable and switch each "
               "lamp to check the wiring; the live view shows what the camera sees.",
    "calibrate_camera": "Lay the printed circle target flat on the table, the camera in the pose of the input "
                        "photograph; Run takes that shot, then one per turntable angle with the target tilted on its "
                        "wedge on the turntable, and calibrates.",
    "calibrate_lights": "Stand the rod upright on the turntable, off its axis, with the grey card on the table. Run "
                        "takes one shot per lamp at each angle (and one with the lamps off), finds the rod's foot and "
                        "its shadow's tip, and locates every lamp. Drag a mark that is off, save, run again.",
    "sweep": "Put the objects on the turntable (no target, no rod). Run turns the table a full circle, one shot per "
             "step. Mark the corners of mirrors and glass on two or more shots below.",
    "reconstruct": "Nothing to do at the rig. Run recovers the shots' poses and the sparse points, fits the ground "
                   "and the boxes, and adds the surfaces whose corners you marked; then name the fitted surfaces.",
    "input": "Turn the table back to the input pose and darken the room. Run takes the one photograph the model is "
             "fitted to (tick 'ambient frame' to subtract the room light).",
    "fit": "Nothing to do at the rig. Run fits each surface's diffuse, specular, mirror and transmission "
           "parameters to the input photograph; the curve shows the error falling.",
    "texture": "Nothing to do at the rig. Run recovers every textured surface's colour per texel, seen directly, "
               "in the mirror or through the sheet.",
    "results": "Compare the re-rendered model with the photograph, then move the camera and dim the lamps to see "
               "the model from a view and under a light it was never photographed in.",
}

_RUN = {"devices": _devices, "calibrate_camera": _calibrate_camera, "calibrate_lights": _calibrate_lights,
        "sweep": _sweep, "reconstruct": _reconstruct, "input": _input, "fit": _fit, "texture": _texture,
        "results": _results}

STEPS = [GuiStep(s.name, s.title, INSTRUCTIONS[s.name], s.done, _RUN[s.name]) for s in core.STEPS]
NAMES = [s.name for s in STEPS]
resume_index = core.first_missing


def sim_defaults() -> dict:
    """Option values for the simulated lab's props (hardware/sim/props.py): what its user printed and measured."""
    from reflab.hardware.sim.props import LabProps

    p = LabProps()
    x0, x1, y0, y1 = p.card
    inset = 0.005  # inside the card's edges
    return {"calibrate_camera": {"grid": p.grid, "spacing": p.spacing},
            "calibrate_lights": {"rod_height": p.rod_height, "card_reflectance": p.card_reflectance,
                                 "card_region": f"{x0 + inset:g}, {x1 - inset:g}, {y0 + inset:g}, {y1 - inset:g}"}}
