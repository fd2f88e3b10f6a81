"""app/steps.py: the ordered step list, done() from the workspace's files, and runs through the stages."""
import numpy as np
import pytest

from reflab.app import steps
from reflab.core.images import read_image
from reflab.core.workspace import Workspace, read_json

CONTRACT = ["devices", "calibrate_camera", "calibrate_lights", "sweep", "reconstruct", "input", "fit", "texture",
            "results"]


def test_names_are_the_contracts_in_order():
    assert steps.NAMES == CONTRACT
    assert all(s.title for s in steps.STEPS)
    with pytest.raises(ValueError, match="no step 'calib'"):
        steps.step("calib")


def test_done_follows_files_and_fit_texture_results_run_the_stages(lab_workspace):
    root, lab, photo = lab_workspace
    done = {s.name: s.done(root) for s in steps.STEPS}
    assert done == {"devices": False, "calibrate_camera": True, "calibrate_lights": True, "sweep": False,
                    "reconstruct": True, "input": True, "fit": False, "texture": False, "results": False}
    assert steps.first_missing(root) == steps.NAMES.index("fit")
    with pytest.raises(ValueError, match="unknown option 'grid'.*method"):
        steps.step("fit").run(root, grid="11x8")

    lines = []
    r = steps.step("fit").run(root, texture_rounds=1, log=lines.append)
    assert r.summary.startswith("fit.json written") and r.value.path == Workspace(root).fit
    assert read_json(root / "fit.json")["status"] == r.value.status
    assert any(line.startswith("texture round 1") for line in lines)
    r = steps.step("texture").run(root, log=lines.append)
    assert len(r.value.result.maps) == 3 and (root / "textures" / "index.json").exists()
    r = steps.step("results").run(root, log=lines.append)
    image = read_image(root / "render.exr")
    # The recovered model re-renders the photograph (truth: the forward model with true textures).
    rel = np.sqrt(np.mean((image - photo) ** 2)) / np.sqrt(np.mean(photo ** 2))
    assert rel < 0.06 and f"{100 * rel:.2f}%" in r.summary
    assert all(s.done(root) for s in steps.STEPS if s.name not in ("devices", "sweep"))


def test_capture_steps_take_resume_and_keep_shots(tmp_path):
    from reflab.app.devices import Devices, SimOptions

    root = tmp_path / "ws"
    with Devices("sim", "sim", sim=SimOptions(size=(48, 36)), log=lambda line: None) as rig:
        r = steps.step("devices").run(root, rig=rig)
        assert steps.step("devices").done(root) and "hardware.json" in r.summary
        with pytest.raises(ValueError, match="unknown option 'grid'"):
            steps.step("sweep").run(root, rig=rig, grid="3x3")
        r = steps.step("sweep").run(root, rig=rig, count=3)
        manifest = read_json(Workspace(root).manifest("sweep"))
        assert manifest["status"] == "complete" and [s["angle"] for s in manifest["shots"]] == [0.0, 120.0, 240.0]
        assert steps.step("sweep").done(root) and r.capture.shots == manifest["shots"]
        log = []
        steps.step("sweep").run(root, rig=rig, count=3, log=log.append)  # the same plan: kept, not retaken
        assert read_json(Workspace(root).manifest("sweep"))["shots"] == manifest["shots"]
        assert any("already taken" in line for line in log)
        steps.step("input").run(root, rig=rig)
        assert read_image(Workspace(root).input_image).shape == (36, 48, 3) and steps.step("input").done(root)
