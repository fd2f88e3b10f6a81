"""The guided acquisition as one ordered list of steps, shared by the GUI and ``reflab demo``.

Each :class:`Step` has the contract's name (docs/formats.md, GUI: ``devices``, ``calibrate_camera``,
``calibrate_lights``, ``sweep``, ``reconstruct``, ``input``, ``fit``, ``texture``, ``results``), a
title, ``done(workspace)`` read from the workspace's files, and
``run(workspace, task=None, *, rig=None, log=print, **options) -> StepResult``, which captures what
the step needs (when it is given an opened :class:`reflab.app.devices.Devices`) and then calls the stage
function (``reflab.calibration.stages``, ``reflab.reconstruction.stages``, ``reflab.inverse.stages``,
``reflab.hardware.capture.run_capture``).

``options`` are the stage's options (the fields of its ``*Options`` dataclass, e.g. ``grid`` and
``spacing`` for ``calibrate_camera``) plus, for a step that captures, those of
:class:`reflab.hardware.capture.CaptureOptions` (``angles``, ``count``, ``start``, ``ambient``,
``format``, ``exposure``, ``settle``) and ``recapture`` (take the shots again even when a
complete session of the same plan is there). An unknown option is a ``ValueError`` naming it.

A capture already complete with the same plan is kept; an unfinished one resumes; so a step
run again after ``Cancelled`` continues where it stopped. Nothing here imports anything heavy
at module level.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from reflab.core.workspace import Workspace

#: Options of a capturing step that go to reflab.hardware.capture.CaptureOptions.
CAPTURE_FIELDS = ("angles", "count", "start", "ambient", "format", "exposure", "settle")


@dataclass
class StepResult:
    """A step's one-line ``summary`` and the stage's typed result (``value``; None when the step
    had nothing to run) and the capture's (``capture``, when the step took shots)."""

    summary: str
    value: object = None
    capture: object = None


@dataclass
class Step:
    """One step of the guided acquisition (see the module's description)."""

    name: str
    title: str
    done: Callable[[object], bool]
    run: Callable[..., StepResult]
    captures: str | None = None  # the capture kind the step takes, if any


# ---------------------------------------------------------------------- helpers
def _split(options: dict, stage_cls, capture: bool, step: str) -> tuple[dict, dict, bool]:
    """(stage options, capture options, recapture) from one dict; unknown keys are an error."""
    stage_fields = {f.name for f in dataclasses.fields(stage_cls)} - {"workspace"} if stage_cls else set()
    stage, cap, recapture = {}, {}, bool(options.get("recapture", False))
    for key, value in options.items():
        if key == "recapture" and capture:
            continue
        if key in stage_fields:
            stage[key] = value
        elif capture and key in CAPTURE_FIELDS:
            cap[key] = value
        else:
            known = sorted(stage_fields | (set(CAPTURE_FIELDS) | {"recapture"} if capture else set()))
            raise ValueError(f"step {step}: unknown option {key!r} (known: {', '.join(known) or 'none'})")
    return stage, cap, recapture


def capture(workspace, kind: str, rig, task=None, *, log=print, recapture: bool = False, **options):
    """Take the shots of ``kind`` with ``rig`` (an opened :class:`reflab.app.devices.Devices`): a complete
    session of the same plan is kept (unless ``recapture``), an unfinished one resumes, another
    plan starts again. Returns :class:`reflab.hardware.capture.CaptureResult`, or None when kept."""
    from dataclasses import asdict

    from reflab.hardware.capture import CaptureOptions, CaptureResult, plan, run_capture
    from reflab.core.workspace import read_json

    ws = Workspace(workspace)
    opts = CaptureOptions(workspace=ws.root, kind=kind, controller=rig.controller, camera=rig.camera, log=log,
                          **options)
    shots = plan(kind, len(rig.controller.config.lamps), opts)
    path = ws.manifest(kind)
    old = read_json(path) if path.exists() else {}
    same = old.get("plan") == [asdict(s) for s in shots]
    if options.get("size") is not None:  # shots of another size are another session
        same = same and all(rec.get("size") == list(options["size"]) for rec in old.get("shots", []))
    if same and old.get("status") == "complete" and not recapture:
        log(f"{kind}: the {len(shots)} shots are already taken")
        return CaptureResult(path, old)
    opts.resume = bool(old) and same and not recapture
    opts.overwrite = bool(old) and not opts.resume
    if kind == "input" and ws.input_image.exists() and not opts.resume:
        opts.overwrite = True  # the step retakes the input photograph
    return run_capture(opts, task)


def _exists(attr: str, *parts: str):
    def done(workspace) -> bool:
        return getattr(Workspace(workspace), attr).joinpath(*parts).exists()

    return done


def _complete(kind: str):
    def done(workspace) -> bool:
        from reflab.core.workspace import WorkspaceError, read_json

        path = Workspace(workspace).manifest(kind)
        try:
            return path.exists() and read_json(path).get("status") == "complete"
        except WorkspaceError:
            return False

    return done


# ---------------------------------------------------------------------- the steps
def _devices(workspace, task=None, *, rig=None, log=print, **options) -> StepResult:
    from reflab.core.workspace import write_json

    _split(options, None, False, "devices")
    if rig is None:
        raise ValueError("step devices: needs the opened devices (rig)")
    path = write_json(Workspace(workspace).hardware, rig.config.to_json())
    return StepResult(f"devices connected; wrote {path}")


def _capture_only(kind: str, name: str):
    def run(workspace, task=None, *, rig=None, log=print, **options) -> StepResult:
        _, cap, recapture = _split(options, None, True, name)
        if rig is None:
            if _complete(kind)(workspace):
                return StepResult(f"{kind}: captured earlier")
            raise ValueError(f"step {name}: needs the opened devices (rig) to take the {kind} shots")
        shots = capture(workspace, kind, rig, task, log=log, recapture=recapture, **cap)
        extra = f"; input photograph {Workspace(workspace).input_image.name}" if kind == "input" else ""
        return StepResult(f"{len(shots.shots)} {kind} shots in {shots.manifest_path.parent}{extra}", None, shots)

    return run


def _calibrate_camera(workspace, task=None, *, rig=None, log=print, **options) -> StepResult:
    from reflab.calibration.stages import CameraOptions, calibrate_camera

    stage, cap, recapture = _split(options, CameraOptions, True, "calibrate_camera")
    shots = capture(workspace, "calibration", rig, task, log=log, recapture=recapture, **cap) if rig else None
    r = calibrate_camera(CameraOptions(Path(workspace), **stage), task)
    for path, why in r.skipped + r.unreadable:
        log(f"skipping {path}: {why}")
    return StepResult(f"camera.json written: {len(r.views)} views, reprojection RMS {r.rms_px:.3f} px", r, shots)


def _calibrate_lights(workspace, task=None, *, rig=None, log=print, **options) -> StepResult:
    """Rod shots (when given a rig), then the lamps: without images or a marks file the stage
    detects the rod in the lights session's single-lamp shots (its manifest names the lamp)."""
    from reflab.calibration.stages import LightsOptions, calibrate_lights

    stage, cap, recapture = _split(options, LightsOptions, True, "calibrate_lights")
    shots = capture(workspace, "lights", rig, task, log=log, recapture=recapture, **cap) if rig else None
    r = calibrate_lights(LightsOptions(Path(workspace), **stage), task)
    for name, light, base, tip in r.detected:
        log(f"{name}: lamp {light}, foot ({base[0]:.1f}, {base[1]:.1f}), tip ({tip[0]:.1f}, {tip[1]:.1f})")
    return StepResult(f"lights.json written: {len(r.lamps)} lamps", r, shots)


def _reconstruct(workspace, task=None, *, rig=None, log=print, **options) -> StepResult:
    from reflab.reconstruction.stages import ReconstructOptions, reconstruct

    stage, _, _ = _split(options, ReconstructOptions, False, "reconstruct")
    r = reconstruct(ReconstructOptions(Path(workspace), **stage), task, log=log)
    if r.skipped:
        return StepResult("scene.json exists: nothing to reconstruct", r)
    return StepResult(f"scene.json written: {len(r.scene)} surfaces", r)


def _fit(workspace, task=None, *, rig=None, log=print, **options) -> StepResult:
    from reflab.inverse.stages import FitOptions, fit

    stage, _, _ = _split(options, FitOptions, False, "fit")
    r = fit(FitOptions(Path(workspace), **stage), task,
            on_round=lambda rec: log(f"texture round {rec['round']}: refit RMS per band "
                                     f"{[round(v, 4) for v in rec['rms']]}"))
    for text in r.warnings:
        log(f"warning: {text}")
    rms = ", ".join(f"{v:.3g}" for v in r.report["rms"])
    return StepResult(f"fit.json written: {r.status}, RMS per band [{rms}], {r.fit.iterations} iterations "
                      f"in {r.report['time_s']:.1f} s", r)


def _texture(workspace, task=None, *, rig=None, log=print, **options) -> StepResult:
    from reflab.inverse.stages import TextureOptions, texture

    stage, _, _ = _split(options, TextureOptions, False, "texture")
    r = texture(TextureOptions(Path(workspace), **stage), task, log=log)
    return StepResult(f"textures written for {len(r.result.maps)} surfaces", r)


def _results(workspace, task=None, *, rig=None, log=print, **options) -> StepResult:
    import numpy as np

    from reflab.core.images import read_image
    from reflab.inverse.stages import RenderOptions, render

    stage, _, _ = _split(options, RenderOptions, False, "results")
    ws = Workspace(workspace)
    photo = read_image(ws.require(ws.input_image, "the input step"))
    r = render(RenderOptions(ws.root, **stage), task, log=log)
    if r.image.shape != photo.shape or stage.get("camera") or stage.get("lights"):
        return StepResult(f"model rendered to {r.path}", r)
    rel = float(np.sqrt(np.mean((r.image - photo) ** 2)) / max(np.sqrt(np.mean(photo.astype(np.float64) ** 2)), 1e-300))
    return StepResult(f"model re-rendered to {r.path.name}: RMS difference {100 * rel:.2f}% of the input", r)


def further_photographs(workspace, rig, task=None, *, log=print, shots=None, recapture: bool = False,
                        turntable_centre=None, size=None, **plan_options) -> StepResult:
    """Take further photographs of the scene into ``inputs/`` with ``rig`` (docs/formats.md "inputs/").

    ``shots`` (dicts with ``name``, ``angle_deg`` from the input's view and ``lamps``): these;
    None: plan.json's, planned first (:func:`reflab.inverse.stages.plan`, ``plan_options``) when
    it is missing or older than fit.json. The turntable turns to each shot, its lamps alone lit;
    each photograph gets its sidecar from camera.json, lights.json and the turntable axis
    (``turntable_centre`` (x, y), turning counter-clockwise; by default the axis reconstruct found).
    ``size`` (width, height): the photographs' size, by default camera.json's; a larger one with its
    aspect ratio (the camera's full resolution) holds detail finer than the calibrated size's pixels,
    and each sidecar's camera is camera.json's scaled to it.
    """
    from reflab.core.workspace import read_json
    from reflab.inverse.forward.photographs import inputs_from_capture

    ws = Workspace(workspace)
    if rig is None:
        raise ValueError("further photographs need the opened devices (rig)")
    if shots is None:
        if not ws.plan.exists() or (ws.fit.exists() and ws.plan.stat().st_mtime < ws.fit.stat().st_mtime) or plan_options:
            from reflab.inverse.stages import PlanOptions, plan

            plan(PlanOptions(ws.root, turntable_centre=turntable_centre, **plan_options), task, log=log)
        shots = read_json(ws.plan).get("shots") or []
    if not shots:
        return StepResult("no further photograph planned: the plan expects no shot to gain enough")
    result = capture(ws.root, "inputs", rig, task, log=log, recapture=recapture, shots=list(shots),
                     size=None if size is None else tuple(size))
    names = inputs_from_capture(ws, centre=turntable_centre, direction=None if turntable_centre is None else 1.0, log=log)
    return StepResult(f"{len(names)} further photographs in {ws.inputs}: {', '.join(names)}", names, result)


def detail_photographs(workspace, rig, task=None, *, angles=(0.0, 30.0, -30.0), scale: int = 2, size=None,
                       log=print) -> StepResult:
    """Photographs for the texture's detail into ``inputs/``: every lamp on, the turntable at each of
    ``angles`` (degrees from the input's view), at ``scale`` times camera.json's size (a camera's
    full resolution; ``size`` (width, height) instead when given), each with its sidecar
    (camera.json scaled, the lamps, the turn).

    A texture at ``--texel-scale 1/scale`` then has texels as fine as these photographs' pixels;
    views close to the input's keep the registration error below the print's grain. As
    ``reflab capture inputs WS --angles A,.. --size WxH`` takes them.
    """
    from reflab.hardware.capture import calibrated_size

    ws = Workspace(workspace)
    if rig is None:
        raise ValueError("detail photographs need the opened devices (rig)")
    if int(scale) != scale or scale < 1:
        raise ValueError(f"detail photographs: scale must be a whole number >= 1, got {scale!r}")
    angles = [float(a) for a in angles]
    if not angles:
        raise ValueError("detail photographs: no turntable angle given")
    if size is None:
        size = calibrated_size(ws.root)
        if size is None:
            raise ValueError(f"detail photographs are sized from {ws.camera.name}: calibrate the camera first")
        size = int(scale) * size[0], int(scale) * size[1]
    w, h = (int(v) for v in size)
    lamps = list(range(len(rig.controller.config.lamps)))
    shots = [{"name": f"a{a:g}".replace("-", "m").replace(".", "p"), "angle_deg": a, "lamps": lamps} for a in angles]
    log(f"photographs for the texture's detail at {w}x{h}, every lamp on, turntable at "
        f"{', '.join(f'{a:g}' for a in angles)} deg from the input's view")
    return further_photographs(ws.root, rig, task, log=log, shots=shots, size=(w, h))


STEPS = [
    Step("devices", "Devices", _exists("hardware"), _devices),
    Step("calibrate_camera", "Calibrate the camera", _exists("camera"), _calibrate_camera, "calibration"),
    Step("calibrate_lights", "Calibrate the lamps", _exists("lights"), _calibrate_lights, "lights"),
    Step("sweep", "Turntable sweep", _complete("sweep"), _capture_only("sweep", "sweep"), "sweep"),
    Step("reconstruct", "Reconstruct the geometry", _exists("scene"), _reconstruct),
    Step("input", "Input photograph", lambda ws: Workspace(ws).input_image.exists(), _capture_only("input", "input"),
         "input"),
    Step("fit", "Fit the materials", _exists("fit"), _fit),
    Step("texture", "Recover the textures", _exists("texture_index"), _texture),
    Step("results", "Results", lambda ws: Workspace(ws).render().exists(), _results),
]

#: Step names in order (docs/formats.md, GUI).
NAMES = [s.name for s in STEPS]


def step(name: str) -> Step:
    """The step called ``name``."""
    for s in STEPS:
        if s.name == name:
            return s
    raise ValueError(f"no step {name!r}; steps: {', '.join(NAMES)}")


def first_missing(workspace) -> int:
    """Index of the step an existing workspace reopens at: the first not done after the last done."""
    done = [s.done(workspace) for s in STEPS]
    last = max((i for i, d in enumerate(done) if d), default=-1)
    later = [i for i in range(last + 1, len(STEPS)) if not done[i]]
    return later[0] if later else (len(STEPS) - 1 if last >= 0 else 0)
