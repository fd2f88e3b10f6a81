"""The window completes the model: the input step plans and takes the further photographs, the
results page says which photographs determined each parameter (docs/gui.md)."""
import os

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pytestqt")

from PySide6.QtCore import Qt  # noqa: E402
from PySide6.QtWidgets import QCheckBox, QLabel, QPushButton, QWidget  # noqa: E402

from reflab.app.gui import MainWindow  # noqa: E402
from reflab.core.workspace import Workspace, read_json  # noqa: E402

SIZE = (80, 60)


def _run(qtbot, window, step, timeout=180_000):
    with qtbot.waitSignal(window.step_finished, timeout=timeout) as blocker:
        qtbot.mouseClick(window.findChild(QPushButton, f"run_{step}"), Qt.MouseButton.LeftButton)
    return blocker.args[1], window.findChild(QLabel, f"status_{step}").text()


def test_input_step_takes_the_planned_shots_and_results_name_who_determined_what(qtbot, tmp_path):
    from reflab.hardware.sim.lab import build_lab, write_lab

    root = tmp_path / "ws"
    write_lab(root, build_lab(*SIZE, grain=0.2), materials=False)  # the simulated rig's own set
    # The turntable axis the sweep would give (the simulated board turns about x = y = 0).
    window = MainWindow(root, port="sim", camera="sim", size=SIZE, live_preview_ms=0,
                        options={"fit": {"texture_rounds": 0}})
    qtbot.addWidget(window)
    window.show()
    outcome, status = _run(qtbot, window, "input")
    assert outcome == "done", status
    further = window.findChild(QCheckBox, "option_input_further")
    further.setChecked(True)
    outcome, status = _run(qtbot, window, "input")  # no fit.json yet: says what to do
    assert outcome == "failed" and "run Fit first" in status
    outcome, status = _run(qtbot, window, "fit")
    assert outcome == "done", status
    ws = Workspace(root)
    (ws.root / "sfm.json").write_text('{"images": ["a", "b", "c"], "reference_shot": "a", "turntable": '
                                      '{"angles_deg": [0, 90, 180], "direction": 1}, "poses": ' + _poses(ws) + "}")
    outcome, status = _run(qtbot, window, "input")
    assert outcome == "done" and "further photographs" in status, status
    plan = read_json(ws.plan)
    table = window.findChild(QWidget, "plan_table")
    assert table.rowCount() == len(plan["shots"]) >= 1
    assert table.item(0, 0).text() == plan["shots"][0]["name"]
    outcome, status = _run(qtbot, window, "fit")
    assert outcome == "done", status
    window.page("results").refresh()
    params = window.findChild(QWidget, "results_parameters")
    cells = [[params.item(i, j).text() for j in range(4)] for i in range(params.rowCount())]
    fit = read_json(ws.fit)
    assert len(fit["photographs"]) == 1 + len(plan["shots"])
    shot_names = {s["name"] for s in plan["shots"]}
    # Every parameter a further photograph determined says so; undetermined ones say that instead.
    assert any(shot_names & set(row[3].split(", ")) for row in cells), cells
    for s in fit["surfaces"]:
        for key in s["undetermined"]:
            if s["material"].get(key) is not None:
                assert any(r[0] == s["name"] and r[1] == key and r[2].startswith("undetermined") for r in cells)


def _poses(ws) -> str:
    """Poses of a camera turned about the vertical axis through the origin by 0, 90 and 180 degrees."""
    import json

    from reflab.calibration.camera import Camera
    from reflab.reconstruction.sfm import turntable_poses

    R, t = turntable_poses(Camera.load(ws.camera), [0.0, 90.0, 180.0], (0.0, 0.0), 1.0)
    return json.dumps({n: {"R": R[i].tolist(), "t": t[i].tolist()} for i, n in enumerate("abc")})


def test_input_step_takes_detail_photographs_and_the_texture_uses_their_texels(qtbot, tmp_path):
    """Ticked, the input step takes the photographs for the texture's detail: every lamp on, at
    twice camera.json's size, from the angles given, each with camera.json's camera scaled to it;
    the Textures page's texel scale then halves the texels, and the texture reads them."""
    import numpy as np

    from reflab.calibration.camera import Camera
    from reflab.core.images import read_image
    from reflab.hardware.sim.lab import build_lab, write_lab

    root = tmp_path / "ws"
    write_lab(root, build_lab(*SIZE, grain=0.2), materials=False)
    window = MainWindow(root, port="sim", camera="sim", size=SIZE, live_preview_ms=0,
                        options={"fit": {"texture_rounds": 0}})
    qtbot.addWidget(window)
    window.show()
    ws = Workspace(root)
    (ws.root / "sfm.json").write_text('{"images": ["a", "b", "c"], "reference_shot": "a", "turntable": '
                                      '{"angles_deg": [0, 90, 180], "direction": 1}, "poses": ' + _poses(ws) + "}")
    window.findChild(QCheckBox, "option_input_detail").setChecked(True)
    angles = window.findChild(QWidget, "option_input_detail_angles")
    angles.setText("0, x")
    outcome, status = _run(qtbot, window, "input")
    assert outcome == "failed" and "detail turntable angles" in status and "'0, x'" in status, status
    angles.setText("0, 20")
    outcome, status = _run(qtbot, window, "input")
    assert outcome == "done" and "a0, a20" in status, status
    calibrated = Camera.load(ws.camera)
    for name, turn in (("a0", 0.0), ("a20", 20.0)):
        image = read_image(ws.inputs / f"{name}.exr")
        assert image.shape[:2] == (2 * SIZE[1], 2 * SIZE[0])
        side = read_json(ws.inputs / f"{name}.json")
        K = np.asarray(side["camera"]["K"])
        assert np.allclose(K[:2, :2], 2 * calibrated.K[:2, :2]) and len(side["lights"]["lights"]) == 2
        # The scene's frame: the camera turned by -turn about the vertical axis through the origin.
        centre = -np.asarray(side["camera"]["R"]).T @ np.asarray(side["camera"]["t"])
        true = -calibrated.R.T @ calibrated.t
        a = np.radians(-turn)
        turned = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) @ true
        assert np.allclose(centre, turned, atol=1e-9), (name, centre, turned)
    outcome, status = _run(qtbot, window, "fit")
    assert outcome == "done", status
    texels = {}
    for scale in (1.0, 0.5):
        window.findChild(QWidget, "option_texture_texel_scale").setValue(scale)
        outcome, status = _run(qtbot, window, "texture")
        assert outcome == "done", status
        index = read_json(ws.root / "textures" / "index.json")
        assert index["options"]["texel_scale"] == scale and len(index["photographs"]) == 3
        texels[scale] = {s["surface"]: s["texel_size"] for s in index["surfaces"]}
    assert texels[1.0] and all(texels[0.5][k] == pytest.approx(texels[1.0][k] / 2, rel=0.02) for k in texels[1.0])
