"""Capture sessions: calibration shots, rod-shadow shots, a turntable sweep, the input image.

A session is a *plan* (one :class:`Shot` per image: file, turntable angle, lamp states) run
against a controller (:class:`reflab.hardware.grbl.GrblController`) and a camera
(:mod:`reflab.hardware.cameras`). After every shot the image is written atomically and then
``captures/<folder>/manifest.json`` (also atomically), so a fault or Ctrl-C never leaves a
half-written file and never loses a finished shot; ``resume=True`` takes exactly the shots the
manifest does not list. docs/hardware.md describes the manifest.

A shot is kept only when the board confirms (``?`` and ``$G``) the planned angle and lamps just
before and just after the exposure; a reset or change in between discards it (it is taken again,
at most ``retakes`` times). Whatever stops a session leaves the board stopped and the lamps off.
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from reflab.core.options import float_list, opt
from reflab.core.task import Cancelled, Task
from reflab.core.workspace import CAPTURE_FOLDERS, Workspace, WorkspaceError, read_json, write_json

#: Session kind -> folder under WORKSPACE/captures (docs/formats.md).
FOLDERS = CAPTURE_FOLDERS


class CaptureError(RuntimeError):
    """A session stopped on a fault; the finished shots are kept and ``resume`` continues."""


class CaptureCancelled(CaptureError, Cancelled):
    """The user cancelled; the finished shots are kept and ``resume`` continues."""


class _Changed(Exception):
    """The board's confirmed angle or lamps differ from the shot's: the shot is discarded."""


@dataclass
class Shot:
    """One planned image: its file name, the turntable angle and each lamp's state."""

    file: str
    angle: float
    lamps: list
    role: str = ""


def _name(i: int, ext: str) -> str:
    return f"{i:04d}.{ext}"


#: Default turntable angles of the calibration shots (the target on its wedge; at 180 degrees it
#: would face away from the camera) and of the rod shots (the rod at four places).
CALIBRATION_ANGLES = (0.0, 45.0, 90.0, 135.0, 225.0, 270.0, 315.0)
LIGHTS_ANGLES = (0.0, 90.0, 180.0, 270.0)


def plan_calibration(n_lamps: int, angles=CALIBRATION_ANGLES, ext: str = "exr") -> list[Shot]:
    """Every lamp on: first the target lying flat at the first angle (the reference view: it
    defines the world frame, camera.json's pose), then one shot per angle with the target tilted
    on its wedge on the turntable (the varied orientations the intrinsics need)."""
    angles = [float(a) for a in angles]
    return [Shot(_name(0, ext), angles[0], [True] * n_lamps, "target flat")] + [
        Shot(_name(i + 1, ext), a, [True] * n_lamps, "target on wedge") for i, a in enumerate(angles)]


def plan_lights(n_lamps: int, angles=LIGHTS_ANGLES, ext: str = "exr") -> list[Shot]:
    """At each angle (the rod standing on the turntable off its axis): one lamp at a time, then a
    lamps-off frame of the room light: each lamp image holds one rod shadow (marks.json's ``light``);
    the lamp image minus the room-light frame is that lamp's light alone (its power, on a grey card)."""
    shots = []
    for a in angles:
        for k in range(n_lamps):
            shots.append(Shot(_name(len(shots), ext), float(a), [j == k for j in range(n_lamps)], f"lamp {k}"))
        shots.append(Shot(_name(len(shots), ext), float(a), [False] * n_lamps, "room light"))
    return shots


def plan_sweep(n_lamps: int, count: int, start: float = 0.0, ext: str = "exr") -> list[Shot]:
    """``count`` shots at ``start + 360 i / count`` degrees, every lamp on."""
    if count < 1:
        raise ValueError(f"a sweep needs at least one shot, got {count}")
    return [Shot(_name(i, ext), float(start + 360.0 * i / count), [True] * n_lamps, "sweep") for i in range(count)]


def plan_input(n_lamps: int, angle: float = 0.0, ambient: bool = False, ext: str = "exr") -> list[Shot]:
    """The input photograph (every lamp on) and optionally a lamps-off frame of the ambient light."""
    shots = [Shot(f"input.{ext}", float(angle), [True] * n_lamps, "input")]
    if ambient:
        shots.append(Shot(f"ambient.{ext}", float(angle), [False] * n_lamps, "ambient"))
    return shots


def plan_inputs(n_lamps: int, shots, start: float = 0.0, ext: str = "exr") -> list[Shot]:
    """Further photographs (plan.json's ``shots``: ``name``, ``angle_deg`` from the input's view,
    ``lamps`` lit): the turntable at ``start + angle_deg``, those lamps on, one shot each."""
    if not shots:
        raise ValueError("further inputs need shots to take (reflab plan writes them to plan.json)")
    out = []
    for s in shots:
        lamps = [int(k) for k in s["lamps"]]
        if not lamps or min(lamps) < 0 or max(lamps) >= n_lamps:
            raise ValueError(f"shot {s.get('name')!r}: lamps {lamps} are not among the rig's {n_lamps} lamps")
        out.append(Shot(f"{s['name']}.{ext}", float(start + float(s["angle_deg"])),
                        [k in lamps for k in range(n_lamps)], "further input"))
    return out


class Control(Task):
    """Pause, resume and cancel of a running session: the one task object of every stage
    (:class:`reflab.core.task.Task`), with ``wait``, its old name for :meth:`Task.check`. A pause
    takes effect between shots, and during a turntable move as a feed hold."""

    def wait(self) -> None:
        self.check()


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def calibrated_size(workspace) -> tuple[int, int] | None:
    """(width, height) of the workspace's camera.json, or None when there is none yet."""
    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    if not ws.camera.exists():
        return None
    obj = read_json(ws.camera)
    size = obj.get("width"), obj.get("height")
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size):
        raise WorkspaceError(ws.camera, "width/height", "positive integers", got=list(size))
    return size


class CaptureSession:
    """Run a plan, writing each image and the manifest after every shot.

    Parameters
    ----------
    workspace : path-like
    kind : str
        ``calibration``, ``lights``, ``sweep`` or ``input`` (:data:`FOLDERS`).
    plan : list of Shot
    controller : GrblController
        Connected; the session calls ``rotate_to``, ``set_lamps`` and reads ``angle``.
    camera : object with ``capture(exposure)``, ``describe()``
    exposure : float, optional
        Passed to the camera and recorded (seconds for the simulated and most cameras).
    settle_s : float
        Wait after the lamps change before the shot (lamp warm-up, vibration).
    resume : bool
        Continue a stopped session: keep its finished shots, take the others.
    overwrite : bool
        Start again over a previous session of this kind (its images are removed first).
    progress : callable, optional
        ``progress(done, total, record)`` after every shot.
    control : reflab.core.task.Task, optional
        Pause, resume, cancel; told ``step(done, total, file)`` after every shot.
    log : callable, optional
    size : (width, height), optional
        The image size every shot must have; by default camera.json's when it exists (except for
        the calibration kind, which may calibrate a new size). A camera whose resolution is a
        setting (``set_size((width, height))``, the simulated one) is set to it first (to its own
        with no size); a shot of another size stops the session before it is written.
    retakes : int
        How many times one shot is taken again after the board reset or changed during it, before
        the session stops.
    """

    def __init__(self, workspace, kind: str, plan: list[Shot], controller, camera, *, exposure: float | None = None,
                 settle_s: float = 0.0, resume: bool = False, overwrite: bool = False, progress=None,
                 control: Task | None = None, log=None, size: tuple[int, int] | None = None, retakes: int = 3):
        if kind not in FOLDERS:
            raise ValueError(f"capture kind must be one of {sorted(FOLDERS)}, got {kind!r}")
        if resume and overwrite:
            raise ValueError("resume and overwrite exclude each other")
        names = [s.file for s in plan]
        if len(set(names)) != len(names) or not plan:
            raise ValueError("a plan needs at least one shot and distinct file names")
        self.workspace = Workspace(workspace)
        self.kind, self.plan = kind, plan
        self.folder = self.workspace.captures_of(kind)
        self.manifest_path = self.workspace.manifest(kind)
        self.controller, self.camera = controller, camera
        self.exposure, self.settle_s = exposure, float(settle_s)
        self.resume, self.overwrite = resume, overwrite
        self.progress = progress or (lambda done, total, record: None)
        self.control = control or Task()
        # A Control subclass may override wait (its old name); a plain Task checks.
        self._wait = getattr(self.control, "wait", self.control.check)
        self.log = log or (lambda msg: None)
        self.manifest: dict = {}
        self.size = tuple(size) if size is not None else None
        self.retakes = int(retakes)
        if self.size is None and kind != "calibration":
            self.size = calibrated_size(self.workspace)

    # ------------------------------------------------------------------ manifest
    def _plan_json(self) -> list[dict]:
        return [asdict(s) for s in self.plan]

    def _load_previous(self) -> list[dict]:
        """Finished shots to keep: those of a resumable manifest whose image is still there."""
        if not self.manifest_path.exists():
            return []
        old = read_json(self.manifest_path)
        if self.overwrite:
            for rec in old.get("shots", []):
                (self.folder / str(rec.get("file"))).unlink(missing_ok=True)
            return []
        done = len(old.get("shots", []))
        if not self.resume:
            what = "a complete" if old.get("status") == "complete" else f"an unfinished ({done} of {len(old.get('plan', []))} shots)"
            raise WorkspaceError(self.manifest_path, "status",
                                 f"no earlier session; this folder holds {what} {old.get('kind')} session. "
                                 "Pass --resume to continue it or --overwrite to start again", got=old.get("status"))
        if old.get("kind") != self.kind:
            raise WorkspaceError(self.manifest_path, "kind", f"{self.kind!r} to resume", got=old.get("kind"))
        if old.get("plan") != self._plan_json():
            raise WorkspaceError(self.manifest_path, "plan",
                                 "the same shots as this command's (same angles, lamps, count and format); "
                                 "resume with the options of the first run, or pass --overwrite", got="a different plan")
        shots = old.get("shots")
        if not isinstance(shots, list):
            raise WorkspaceError(self.manifest_path, "shots", "a list", got=shots)
        kept = [rec for rec in shots if isinstance(rec, dict) and (self.folder / str(rec.get("file"))).exists()]
        if len(kept) < len(shots):
            self.log(f"{len(shots) - len(kept)} shot(s) listed in {self.manifest_path} lost their image; retaking them")
        return kept

    def _write_manifest(self, status: str, error: str | None = None) -> None:
        self.manifest.update(status=status, error=error, updated=_now(),
                             reconnects=getattr(self.controller, "reconnect_count", 0))
        write_json(self.manifest_path, self.manifest)

    # ------------------------------------------------------------------ running
    def run(self) -> dict:
        """Take every shot not yet taken; return the manifest.

        Raises
        ------
        CaptureError
            On a device or camera fault, with the fault's message; the manifest says ``stopped``.
        CaptureCancelled
            On ``control.cancel()`` or Ctrl-C; the manifest says ``cancelled``. It is a
            :class:`reflab.core.task.Cancelled`.
        """
        from reflab.hardware.cameras import CameraError
        from reflab.hardware.grbl import GrblError

        kept = self._load_previous()
        existing = self.workspace.input_image
        if self.kind == "input" and existing.exists() and not (self.overwrite or self.resume):
            raise WorkspaceError(existing, expected="no input photograph yet: pass --overwrite to replace it, or move "
                                                    "it away", got="an existing file")
        self.folder.mkdir(parents=True, exist_ok=True)
        if hasattr(self.camera, "set_size"):  # None (a calibration of a new size): the camera's own
            self.camera.set_size(self.size)
        ctl = self.controller
        self.manifest = {
            "kind": self.kind, "plan": self._plan_json(), "shots": kept,
            "controller": {"port": getattr(ctl, "port", None), "version": getattr(ctl, "version", None),
                           "config": ctl.config.to_json() if hasattr(ctl, "config") else None},
            "camera": self.camera.describe(), "started": _now(),
        }
        done = {rec["file"] for rec in kept}
        todo = [s for s in self.plan if s.file not in done]
        if kept:
            self.log(f"resuming: {len(kept)} of {len(self.plan)} shots kept, {len(todo)} to take")
        self._write_manifest("running")
        try:
            for shot in todo:
                self._wait()
                record = self._take(shot)
                self.manifest["shots"].append(record)
                self._write_manifest("running")
                self.progress(len(self.manifest["shots"]), len(self.plan), record)
                self.control.step(len(self.manifest["shots"]), len(self.plan), f"{self.kind}: {record['file']}")
            self._finish()
        except (Cancelled, KeyboardInterrupt):
            self._write_manifest("cancelled", "cancelled by the user")
            self._stop_board()  # GRBL would finish a move it has: feed hold, reset, lamps off
            raise CaptureCancelled(self._stopped_message("cancelled by the user")) from None
        except (GrblError, CameraError, OSError) as exc:
            self._write_manifest("stopped", str(exc))
            self._stop_board()
            raise CaptureError(self._stopped_message(str(exc))) from exc
        self._stop_board()  # the lamps are not left on after the last shot
        self._write_manifest("complete")
        return self.manifest

    def _hold(self) -> bool:
        """Whether a turntable move is to hold (paused); a Task's ``holding`` says it is held."""
        paused = bool(self.control.paused)
        holding = getattr(self.control, "holding", None)
        if holding is not None:
            holding.set() if paused else holding.clear()
        return paused

    def _stop_board(self) -> None:
        stop = getattr(self.controller, "safe_stop", None)
        if stop is not None:
            with contextlib.suppress(Exception):
                stop()

    def _stopped_message(self, why: str) -> str:
        n = len(self.manifest["shots"])
        return (f"{self.kind} capture stopped after {n} of {len(self.plan)} shots: {why}\n"
                f"The {n} finished shots are kept in {self.folder}; fix the cause and run the same command "
                "with --resume to take the others.")

    def _take(self, shot: Shot) -> dict:
        """One shot, taken again while the board resets or changes during it (``retakes`` times)."""
        from reflab.hardware.grbl import BoardReset, GrblError

        for attempt in range(self.retakes + 1):
            try:
                return self._attempt(shot)
            except (BoardReset, _Changed) as exc:
                why = str(exc)
                self.log(f"{shot.file}: {why}; the shot is discarded and taken again")
        raise GrblError(f"{shot.file} was discarded {self.retakes + 1} times: {why}. The board keeps resetting or "
                        "changing during shots: check its power supply and that no other program drives it")

    def _confirm(self, shot: Shot, when: str) -> dict:
        """The board's word on the angle and lamps; :class:`_Changed` unless they are the shot's."""
        ctl = self.controller
        now = ctl.confirm()
        if (now.state != "Idle" or abs(now.angle - shot.angle) > ctl.config.angle_tolerance_deg
                or list(now.lamps) != [bool(x) for x in shot.lamps]):
            raise _Changed(f"{when} the exposure the board reported {now.state}, {now.angle:.3f} deg, lamps "
                           f"{[bool(x) for x in now.lamps]} instead of {shot.angle:.3f} deg, lamps {list(shot.lamps)}")
        return now.to_json()

    def _attempt(self, shot: Shot) -> dict:
        from reflab.hardware.grbl import MoveCancelled
        from reflab.core.images import write_image

        ctl = self.controller
        if ctl.position is None or abs(ctl.angle - shot.angle) > ctl.config.angle_tolerance_deg:
            try:
                ctl.rotate_to(shot.angle, hold=self._hold, cancelled=lambda: self.control.cancelled)
            except MoveCancelled:
                raise CaptureCancelled("cancelled") from None
        changed = ctl.lamps != list(shot.lamps)
        ctl.set_lamps(shot.lamps)
        if changed and self.settle_s > 0:
            time.sleep(self.settle_s)
        self._wait()
        before = self._confirm(shot, "before")
        prepare = getattr(self.camera, "prepare", None)
        if prepare is not None:  # a camera that shows what the shot is for (the simulated one's props)
            prepare(shot)
        if hasattr(self.camera, "cancelled"):  # a camera that waits for the shutter stops waiting on cancel
            self.camera.cancelled = lambda: self.control.cancelled
        t0 = time.monotonic()
        image = self.camera.capture(self.exposure)
        capture_s = time.monotonic() - t0
        after = self._confirm(shot, "after")  # a reset during the exposure: the image is never written
        if getattr(self.control, "paused", False):  # paused during the exposure: no shot is written while paused
            self._wait()
            after = self._confirm(shot, "after the pause")
        if not np.all(np.isfinite(image)):
            from reflab.hardware.cameras import CameraError

            raise CameraError(f"the camera returned {int((~np.isfinite(image)).sum())} NaN/inf values for {shot.file}")
        if self.size is not None and (image.shape[1], image.shape[0]) != self.size:
            from reflab.hardware.cameras import CameraError

            raise CameraError(f"the camera gives {image.shape[1]}x{image.shape[0]} images, camera.json is calibrated "
                              f"for {self.size[0]}x{self.size[1]}: set the camera to that size or calibrate again")
        write_image(self.folder / shot.file, image)
        return {"file": shot.file, "role": shot.role, "angle": shot.angle, "angle_reported": before["angle"],
                "lamps": list(shot.lamps), "time": _now(), "exposure": self.exposure,
                "capture_s": round(capture_s, 4), "size": [int(image.shape[1]), int(image.shape[0])],
                "confirmed": {"before": before, "after": after}}

    def _finish(self) -> None:
        """For the input kind: WORKSPACE/input.<ext>, the lamps-on frame minus the ambient frame."""
        if self.kind != "input":
            return
        from reflab.core.images import read_image, write_image

        shots = {s.role: s for s in self.plan}
        lit = read_image(self.folder / shots["input"].file)
        if "ambient" in shots:
            # Noise around black goes negative: data for the fit (docs/formats.md, Images), not clipped.
            lit = lit - read_image(self.folder / shots["ambient"].file)
        ext = Path(shots["input"].file).suffix
        target = self.workspace.root / f"input{ext}"  # Workspace.input_image finds it
        write_image(target, lit)
        self.manifest["input"] = {"file": target.name, "ambient_subtracted": "ambient" in shots}
        self.log(f"wrote {target}")


# ---------------------------------------------------------------------- the capture stage
@dataclass(kw_only=True)
class CaptureOptions:
    """Options of :func:`run_capture`.

    ``controller`` (a connected :class:`reflab.hardware.grbl.GrblController`) and ``camera`` (an object
    with ``capture(exposure)`` and ``describe()``) are the opened devices: the caller opens them
    (``app/devices.py`` for hardware or the simulated lab) and closes them. ``angles`` are the
    turntable angles of calibration/lights shots; ``count`` and ``start`` the sweep's (``start``
    is the input's angle); ``ambient`` adds a lamps-off frame to the input; ``format`` is the
    image files' suffix. ``on_shot(done, total, record)`` is told every shot, ``log(message)``
    what happened. ``size`` (width, height) every shot must have: by default camera.json's
    (except for the calibration kind); further photographs (``inputs``) may be larger than the
    calibration, with camera.json's aspect ratio (their sidecars' cameras are scaled).
    """

    workspace: Path
    kind: str
    controller: object = None
    camera: object = None
    angles: list | None = opt(None, "turntable angles: calibration, of the target on its wedge (default "
                                    f"{','.join(f'{a:g}' for a in CALIBRATION_ANGLES)}, after one shot of it lying "
                                    f"flat); lights, of the rod (default {','.join(f'{a:g}' for a in LIGHTS_ANGLES)})",
                              unit="deg", type=float_list)
    count: int = opt(36, "sweep: number of shots over 360 degrees")
    start: float = opt(0.0, "sweep: first angle; input: the angle", unit="deg")
    ambient: bool = opt(False, "input: also take a lamps-off frame and subtract it")
    format: str = opt("exr", "image files", choices=["exr", "png", "tif"])
    exposure: float | None = opt(None, "exposure passed to the camera and recorded", unit="s", type=float)
    settle: float = opt(0.0, "time to wait after the lamps change", unit="s")
    resume: bool = opt(False, "continue a stopped session; take only the missing shots")
    overwrite: bool = opt(False, "discard an earlier session of this kind and start again")
    on_shot: object = None
    log: object = None
    size: tuple | None = None
    shots: list | None = None  # inputs: plan.json's shots (name, angle_deg, lamps)


@dataclass
class CaptureResult:
    """What :func:`run_capture` wrote: ``manifest`` (as in manifest.json) and its path."""

    manifest_path: Path
    manifest: dict

    @property
    def shots(self) -> list:
        return list(self.manifest["shots"])


def plan(kind: str, n_lamps: int, options: CaptureOptions) -> list[Shot]:
    """The shots of one capture kind (:data:`FOLDERS`)."""
    o = options
    if kind == "calibration":
        return plan_calibration(n_lamps, o.angles or CALIBRATION_ANGLES, o.format)
    if kind == "lights":
        return plan_lights(n_lamps, o.angles or LIGHTS_ANGLES, o.format)
    if kind == "sweep":
        return plan_sweep(n_lamps, o.count, o.start, o.format)
    if kind == "input":
        return plan_input(n_lamps, o.start, o.ambient, o.format)
    if kind == "inputs":
        return plan_inputs(n_lamps, o.shots, o.start, o.format)
    raise ValueError(f"capture kind must be one of {sorted(FOLDERS)}, got {kind!r}")


def run_capture(options: CaptureOptions, task: Task | None = None) -> CaptureResult:
    """Take every shot of ``options.kind`` not yet taken (see :class:`CaptureSession`).

    Raises :class:`CaptureCancelled` (a :class:`reflab.core.task.Cancelled`) when ``task`` is
    cancelled, :class:`CaptureError` on a device fault; either way the finished shots are kept
    and ``resume=True`` takes the others.
    """
    o = options
    if o.controller is None or o.camera is None:
        raise ValueError("run_capture needs opened devices: options.controller and options.camera")
    shots = plan(o.kind, len(o.controller.config.lamps), o)
    session = CaptureSession(o.workspace, o.kind, shots, o.controller, o.camera, exposure=o.exposure,
                             settle_s=o.settle, resume=o.resume, overwrite=o.overwrite, progress=o.on_shot,
                             control=task, log=o.log, size=o.size)
    manifest = session.run()
    return CaptureResult(session.manifest_path, manifest)
