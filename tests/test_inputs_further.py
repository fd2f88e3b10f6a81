"""`reflab capture inputs --plan` on the simulated rig: the planned shots taken, each with a sidecar
that matches what the camera saw.

Ground truth from elsewhere: the simulated camera renders the lab with Mitsuba (the reference
renderer, turning the set on the board's real turntable axis); the sidecar's camera and lamps are
checked by rendering the true scene from them with the forward model (pixel-intensity trees),
which must reproduce that photograph.
"""
from __future__ import annotations

import json

import numpy as np

from reflab.app import steps
from reflab.core.images import read_image
from reflab.core.workspace import Workspace, read_json


def test_planned_shots_are_taken_with_sidecars_that_match_the_photographs(tmp_path):
    from reflab.app.devices import Devices, SimOptions
    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights
    from reflab.hardware.sim.lab import write_lab
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees
    from reflab.inverse.stages import FitOptions, fit

    root = tmp_path / "ws"
    with Devices("sim", "sim", sim=SimOptions(size=(80, 60), depth=3), log=lambda line: None) as rig:
        lab = rig.camera.sim_lab
        write_lab(root, lab, materials=False)  # the user's camera, lamps and geometry: here the truth's
        steps.step("input").run(root, rig=rig)
        fit(FitOptions(root, texture_rounds=0))
        log = []
        r = steps.further_photographs(root, rig, log=log.append, turntable_centre=(0.0, 0.0), max_shots=2)
    ws = Workspace(root)
    plan = read_json(ws.plan)
    assert len(r.value) == len(plan["shots"]) >= 1
    truth = [s.material for s in lab.scene]
    for shot in plan["shots"]:
        side = json.loads(ws.input_sidecar(shot["name"]).read_text())
        assert side["shot"] == {"angle_deg": shot["angle_deg"], "lamps": shot["lamps"]}
        camera, lights = Camera.from_json(side["camera"]), Lights.from_json(side["lights"])
        assert len(lights) == len(shot["lamps"])
        photo = read_image(ws.input_photo(shot["name"]))
        trees = build_trees(lab.scene, camera, lights, depth=3)
        want = render(trees, truth, lights.intensities, kd_nodes=lab.albedo_at(trees.surface, trees.point))
        # Mitsuba against the trees, one ray per pixel both: edges and the lab's print grain differ.
        err = np.sqrt(np.mean((photo - want) ** 2)) / np.sqrt(np.mean(want ** 2))
        assert err < 0.08, (shot["name"], err)
        # A sidecar turned the wrong way would not match: the same check at the opposite angle fails.
        from reflab.inverse.forward.photographs import turned_view

        wrong_cam, wrong_lights = turned_view(Camera.load(ws.camera), Lights.load(ws.lights), -shot["angle_deg"],
                                              (0.0, 0.0), lit=shot["lamps"])
        if abs(shot["angle_deg"]) > 10:
            t2 = build_trees(lab.scene, wrong_cam, wrong_lights, depth=3)
            bad = render(t2, truth, wrong_lights.intensities, kd_nodes=lab.albedo_at(t2.surface, t2.point))
            assert np.sqrt(np.mean((photo - bad) ** 2)) / np.sqrt(np.mean(bad ** 2)) > 2 * err
    report = fit(FitOptions(root, texture_rounds=0)).report
    assert [p["name"] for p in report["photographs"]] == ["input", *sorted(s["name"] for s in plan["shots"])]


def test_further_photographs_at_twice_the_calibrated_size(tmp_path):
    """A further photograph at the camera's full resolution (twice camera.json's size): the
    simulated camera shoots at the session's size, the sidecar's camera is camera.json's scaled
    (the lab's true camera at that size, as write_lab gave camera.json the true one), and the
    forward model from that sidecar reproduces the photograph; a size of another aspect ratio is
    refused naming the photograph; the next capture is back at the calibrated size."""
    import pytest

    from reflab.app.devices import Devices, SimOptions
    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights
    from reflab.core.workspace import WorkspaceError
    from reflab.hardware.sim.lab import write_lab
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees

    root = tmp_path / "ws"
    shot = {"name": "a30", "angle_deg": 30.0, "lamps": [0, 1]}
    with Devices("sim", "sim", sim=SimOptions(size=(80, 60), depth=3), log=lambda line: None) as rig:
        lab = rig.camera.sim_lab
        write_lab(root, lab, materials=False)
        steps.step("input").run(root, rig=rig)
        r = steps.further_photographs(root, rig, log=lambda line: None, shots=[shot], size=(160, 120),
                                      turntable_centre=(0.0, 0.0))
        assert r.value == ["a30"]
        with pytest.raises(WorkspaceError, match=r"a30\.exr.*aspect ratio.*got '100x60'"):
            steps.further_photographs(root, rig, log=lambda line: None, shots=[shot], size=(100, 60),
                                      turntable_centre=(0.0, 0.0))
        steps.step("input").run(root, rig=rig, recapture=True)
    ws = Workspace(root)
    assert read_image(ws.input_image).shape == (60, 80, 3)
    photo = read_image(ws.input_photo("a30"))
    side = json.loads(ws.input_sidecar("a30").read_text())
    camera, lights = Camera.from_json(side["camera"]), Lights.from_json(side["lights"])
    assert photo.shape == (120, 160, 3) and (camera.width, camera.height) == (160, 120)
    true = lab.camera.scaled(160, 120)
    assert np.allclose(camera.K, true.K) and np.allclose(camera.dist, true.dist)
    assert np.allclose(camera.center, rotate_back(true.center, 30.0), atol=1e-9)
    trees = build_trees(lab.scene, camera, lights, depth=3)
    truth = [s.material for s in lab.scene]
    want = render(trees, truth, lights.intensities, kd_nodes=lab.albedo_at(trees.surface, trees.point))
    err = np.sqrt(np.mean((photo - want) ** 2)) / np.sqrt(np.mean(want ** 2))
    assert err < 0.08, err


def rotate_back(point, degrees: float):
    """``point`` turned by -``degrees`` about the vertical axis through the origin (the camera seen
    from the turned set)."""
    from reflab.hardware.sim.camera import rotate_about_z

    return rotate_about_z(np.asarray(point)[None], -degrees, (0.0, 0.0))[0]
