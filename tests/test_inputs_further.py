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
