"""The results page exports the recovered model (reflab export's stage function, off the UI thread)."""
import os

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pytestqt")

from PySide6.QtCore import Qt  # noqa: E402
from PySide6.QtWidgets import QComboBox, QLabel, QLineEdit, QPushButton  # noqa: E402

from reflab.app.gui import MainWindow  # noqa: E402

SIZE = (80, 60)


@pytest.fixture
def fitted_workspace(tmp_path):
    """The simulated lab (materials unknown), its photograph, fitted: fit.json's materials."""
    from reflab.core.images import write_image
    from reflab.hardware.sim.lab import build_lab, write_lab
    from reflab.hardware.sim.reference import render_reference
    from reflab.inverse.stages import FitOptions, fit

    lab = build_lab(*SIZE)
    write_lab(tmp_path, lab, materials=False)
    write_image(tmp_path / "input.exr", render_reference(lab.scene, lab.camera, lab.lights, depth=3, albedo=lab.albedo))
    fit(FitOptions(tmp_path, max_iterations=20, texture_rounds=0))
    assert (tmp_path / "fit.json").is_file()
    return tmp_path


def test_results_page_exports_gltf_with_the_scenes_surfaces(qtbot, fitted_workspace, tmp_path_factory):
    from reflab.core.workspace import Workspace
    from reflab.inverse.export.gltf import read_glb
    from reflab.reconstruction.scene import Scene

    window = MainWindow(fitted_workspace, port="sim", camera="sim", size=SIZE, live_preview_ms=0)
    qtbot.addWidget(window)
    window.show()
    window.go_to("results")
    page = window.page("results")
    combo = window.findChild(QComboBox, "export_format")
    combo.setCurrentText("gltf")
    folder = window.findChild(QLineEdit, "export_output")
    assert folder.text() == str(fitted_workspace / "export-gltf")  # reflab export's default folder
    out = tmp_path_factory.mktemp("exported")
    folder.setText(str(out))  # what the Choose… dialog fills in
    with qtbot.waitSignal(page.exported, timeout=120_000) as blocker:
        qtbot.mouseClick(window.findChild(QPushButton, "export_run"), Qt.MouseButton.LeftButton)
    assert blocker.args[0], blocker.args[1]
    status = window.findChild(QLabel, "export_status").text()
    assert status.startswith("done") and str(out / "scene.glb") in status
    doc, _ = read_glb(out / "scene.glb")
    names = Scene.load(Workspace(fitted_workspace).scene).names
    assert sorted(m["name"] for m in doc["meshes"]) == sorted(names) and len(names) >= 4
    # A failure shows in the status line with the stage's message: a file where the folder should be.
    (out / "blocked").write_text("a file")
    folder.setText(str(out / "blocked"))
    with qtbot.waitSignal(page.exported, timeout=60_000) as blocker:
        qtbot.mouseClick(window.findChild(QPushButton, "export_run"), Qt.MouseButton.LeftButton)
    assert not blocker.args[0]
    status = window.findChild(QLabel, "export_status").text()
    assert status.startswith("failed") and "blocked" in status and "expected a folder to export into" in status
    assert window.findChild(QPushButton, "export_run").isEnabled()
