"""Cancelling each long stage mid-way: it raises Cancelled at its next check, leaves no
half-written output, and the same call run again finishes (core/task.py).

The cancel comes from the task's own progress callback at a chosen step, or from a check count
inside a loop (texture CG), or from another thread (structure from motion, whose COLMAP calls
take a cancellation token); where it fired is asserted from the steps reported. The user's cancel
comes from another thread (the GUI's button) while the stage computes: each long stage is run so
and must end within a second of it (:func:`test_each_long_stage_stops_within_a_second`).
"""
import threading
import time

import numpy as np
import pytest

from reflab.core.task import Cancelled, Task
from reflab.core.workspace import Workspace


def _leftovers(root):
    """Temporary files an interrupted atomic write would leave (hidden, with a random infix)."""
    return [p for p in root.rglob(".*") if p.is_file()]


def _cancel_at(prefix: str, seen: list):
    """A task that records every step and cancels itself at the first one starting with ``prefix``."""
    task = None

    def progress(done, total, message):
        seen.append(message)
        if message.startswith(prefix):
            task.cancel()

    task = Task(progress)
    return task


def _cancel_from_another_thread(run, prefix: str):
    """Run ``run(task)`` in a worker thread and cancel it from this one as soon as it reports a step
    starting with ``prefix``: (seconds from ``cancel()`` to the stage's end, what it raised)."""
    reached = threading.Event()
    task = Task(lambda done, total, message: reached.set() if message.startswith(prefix) else None)
    out = {}

    def work():
        try:
            run(task)
        except Exception as exc:  # noqa: BLE001 - handed to the test
            out["raised"] = exc
        out["end"] = time.perf_counter()

    worker = threading.Thread(target=work, daemon=True)
    worker.start()
    assert reached.wait(120), f"the stage never reported a step {prefix!r}"
    start = time.perf_counter()
    task.cancel()
    worker.join(60)
    assert not worker.is_alive(), "the stage did not stop within a minute of the cancel"
    return out["end"] - start, out.get("raised")


def _fixture(name: str):
    """A workspace-making step: the root of the named fixture."""
    def prepare(request, tmp_path):
        value = request.getfixturevalue(name)
        return value[0] if isinstance(value, tuple) else value

    return prepare


def _random_sweep(request, tmp_path):
    """A workspace whose sweep is noise: structure from motion extracts features, then fails."""
    from reflab.calibration.camera import Camera
    from reflab.core.images import write_image

    ws = Workspace(tmp_path / "ws")
    Camera.look_at(320, 240, 50.0, (0, -0.4, 0.4), (0, 0, 0)).save(ws.camera)
    rng = np.random.default_rng(1)
    for i in range(6):
        write_image(ws.captures_of("sweep") / f"{i:04d}.exr", rng.random((240, 320, 3)).astype(np.float32))
    return ws.root


def _capture_sweep(root, task):
    from reflab.app import steps
    from reflab.app.devices import Devices, SimOptions

    with Devices("sim", "sim", sim=SimOptions(size=(48, 36)), log=lambda line: None) as rig:
        steps.step("sweep").run(root, task, rig=rig, count=5)


def _stage(module: str, function: str, options: str, **kw):
    """``run(root, task)`` of a stage function: ``module.function(module.options(root, **kw), task)``."""
    import importlib

    def run(root, task):
        mod = importlib.import_module(module)
        return getattr(mod, function)(getattr(mod, options)(root, **kw), task)

    return run


#: Each long stage: how its workspace is made, the step after which the cancel comes, its run.
LONG_STAGES = {
    "trees (render)": (_fixture("lab_workspace"), "trees: level 2", _stage("reflab.inverse.stages", "render", "RenderOptions")),
    "texture CG": (_fixture("lab_workspace"), "texture: conjugate gradient",
                   _stage("reflab.inverse.stages", "texture", "TextureOptions")),
    "fit iterations": (_fixture("homogeneous_workspace"), "F-TBO iteration",
                       _stage("reflab.inverse.stages", "fit", "FitOptions", texture_rounds=0)),
    "structure from motion (reconstruct)": (_random_sweep, "structure from motion: features",
                                            _stage("reflab.reconstruction.stages", "reconstruct", "ReconstructOptions",
                                                   turntable_centre=(0.0, 0.0))),
    "captures": (lambda request, tmp_path: tmp_path / "ws", "sweep: 0001", _capture_sweep),
    "target detection (calibrate camera)": (_fixture("target_workspace"), "detecting the target in 01",
                                            _stage("reflab.calibration.stages", "calibrate_camera", "CameraOptions")),
    "least squares (calibrate camera)": (_fixture("target_workspace"), "calibrating",
                                         _stage("reflab.calibration.stages", "calibrate_camera", "CameraOptions")),
}


@pytest.mark.parametrize("stage", list(LONG_STAGES))
def test_each_long_stage_stops_within_a_second(stage, request, tmp_path):
    """Cancelled from another thread mid-way, the stage raises Cancelled within a second and writes
    nothing half-done: only finished parts that a re-run reuses stay (a capture's shots and manifest,
    trees cached before a fit or texture was cancelled) and COLMAP's log."""
    prepare, prefix, run = LONG_STAGES[stage]
    root = prepare(request, tmp_path)
    before = set(root.rglob("*")) if root.exists() else set()
    seconds, raised = _cancel_from_another_thread(lambda task: run(root, task), prefix)
    assert isinstance(raised, Cancelled), f"{stage}: ended with {raised!r}, not Cancelled"
    assert seconds < 1.0, f"{stage}: stopped {seconds:.2f} s after the cancel"
    assert not _leftovers(root)
    ws = Workspace(root)
    made = {p for p in root.rglob("*") if p.is_file() and p not in before}
    kept = {p for p in made if p.parent in (ws.captures_of("sweep"), ws.cache, ws.logs)}
    assert not made - kept if stage != "captures" else made == kept, sorted(made)
    print(f"{stage}: stopped {seconds:.3f} s after the cancel")


def test_trees_cancelled_between_levels_then_rebuilt(lab_workspace):
    from reflab.inverse.stages import RenderOptions, render

    root, _, _ = lab_workspace
    ws = Workspace(root)
    seen = []
    with pytest.raises(Cancelled):
        render(RenderOptions(root), _cancel_at("trees: level 2", seen))
    assert seen[-1].startswith("trees: level 2") and not any(m.startswith("trees: level 3") for m in seen)
    assert not ws.render().exists() and not list(ws.cache.glob("trees-*")) and not _leftovers(root)
    r = render(RenderOptions(root))
    assert r.path.exists() and len(list(ws.cache.glob("trees-*"))) == 1


def test_texture_cg_cancelled_inside_its_iterations_then_rerun(lab_workspace):
    from reflab.inverse.stages import TextureOptions, texture

    root, _, _ = lab_workspace

    class CancelInCG(Task):
        """Cancels at the 3rd check after conjugate gradient started: inside the CG loop."""

        def __init__(self):
            super().__init__()
            self.in_cg, self.checks = False, 0

        def step(self, done, total, message=""):
            self.in_cg = self.in_cg or message.startswith("texture: conjugate gradient")
            super().step(done, total, message)

        def check(self):
            if self.in_cg:
                self.checks += 1
                if self.checks == 3:
                    self.cancel()
            super().check()

    task = CancelInCG()
    with pytest.raises(Cancelled):
        texture(TextureOptions(root), task)
    assert task.checks == 3  # stopped at the check that saw the cancel, two CG iterations in
    assert not Workspace(root).textures.exists() and not _leftovers(root)
    r = texture(TextureOptions(root))
    assert (root / "textures" / "index.json").exists() and r.result.stats["iterations"] > 2


def test_fit_cancelled_between_iterations_then_rerun(homogeneous_workspace):
    from reflab.inverse.stages import FitOptions, fit

    root, _, _ = homogeneous_workspace  # scene.json says only what a user knows: F-TBO iterates
    seen = []
    task = _cancel_at("F-TBO iteration", seen)
    with pytest.raises(Cancelled):
        fit(FitOptions(root, texture_rounds=0), task)
    assert sum(m.startswith("F-TBO iteration") for m in seen) == 1
    assert not Workspace(root).fit.exists() and not _leftovers(root)
    r = fit(FitOptions(root, texture_rounds=0))
    assert r.path.exists() and r.fit.iterations > 1 and r.report["method"] == "ftbo"


def test_structure_from_motion_stops_inside_colmap(tmp_path):
    """A cancel from another thread while COLMAP extracts features: its token stops it."""
    from reflab.calibration.camera import Camera
    from reflab.reconstruction.sfm import run_sfm

    cam = Camera.look_at(320, 240, 50.0, (0, -0.4, 0.4), (0, 0, 0))
    rng = np.random.default_rng(0)
    images = [rng.random((240, 320, 3)).astype(np.float32) for _ in range(6)]
    seen = []

    def progress(done, total, message):
        seen.append(message)
        if message.endswith("features"):
            threading.Timer(0.05, task.cancel).start()

    task = Task(progress)
    with pytest.raises(Cancelled):
        run_sfm(images, [f"{i:04d}.exr" for i in range(6)], cam, workdir=tmp_path / "sfm", auto_mask=False,
                task=task)
    assert seen[0].endswith("features") and not any(m.endswith("mapping") for m in seen)


def test_reconstruct_cancelled_writes_nothing(tmp_path):
    from reflab.calibration.camera import Camera
    from reflab.core.images import write_image
    from reflab.reconstruction.stages import ReconstructOptions, reconstruct

    root = tmp_path / "ws"
    ws = Workspace(root)
    Camera.look_at(64, 48, 50.0, (0, -0.4, 0.4), (0, 0, 0)).save(ws.camera)
    rng = np.random.default_rng(1)
    for i in range(4):
        write_image(ws.captures_of("sweep") / f"{i:04d}.exr", rng.random((48, 64, 3)).astype(np.float32))
    seen = []
    with pytest.raises(Cancelled):
        reconstruct(ReconstructOptions(root, turntable_centre=(0.0, 0.0)), _cancel_at("structure from motion", seen))
    assert not ws.sfm.exists() and not ws.sparse.exists() and not ws.scene.exists() and not _leftovers(root)


def test_capture_cancelled_after_two_shots_then_resumed(tmp_path):
    from reflab.app import steps
    from reflab.app.devices import Devices, SimOptions
    from reflab.hardware.capture import CaptureCancelled
    from reflab.core.workspace import read_json

    root = tmp_path / "ws"
    ws = Workspace(root)
    seen = []
    with Devices("sim", "sim", sim=SimOptions(size=(48, 36)), log=lambda line: None) as rig:
        task = _cancel_at("sweep: 0001", seen)
        with pytest.raises(CaptureCancelled) as info:
            steps.step("sweep").run(root, task, rig=rig, count=5)
        assert isinstance(info.value, Cancelled)
        manifest = read_json(ws.manifest("sweep"))
        assert manifest["status"] == "cancelled" and [s["file"] for s in manifest["shots"]] == ["0000.exr", "0001.exr"]
        assert sorted(p.name for p in ws.captures_of("sweep").glob("*.exr")) == ["0000.exr", "0001.exr"]
        assert not _leftovers(root) and not steps.step("sweep").done(root)
        steps.step("sweep").run(root, rig=rig, count=5)  # the same plan: resumes, takes the other three
    manifest = read_json(ws.manifest("sweep"))
    assert manifest["status"] == "complete" and len(manifest["shots"]) == 5
    assert [s["file"] for s in manifest["shots"][:2]] == ["0000.exr", "0001.exr"]


def test_calibrate_camera_cancelled_while_detecting_then_rerun(target_workspace, target_views):
    from reflab.calibration.stages import CameraOptions, calibrate_camera

    ws, seen = Workspace(target_workspace), []
    with pytest.raises(Cancelled):
        calibrate_camera(CameraOptions(ws.root), _cancel_at("detecting the target in 02", seen))
    assert seen[-1] == "detecting the target in 02.exr" and not ws.camera.exists() and not _leftovers(ws.root)
    r = calibrate_camera(CameraOptions(ws.root))
    assert r.path == ws.camera and ws.camera.exists() and len(r.views) == 6
    assert abs(r.camera.K[0, 0] / target_views[1][0].K[0, 0] - 1) < 0.01
