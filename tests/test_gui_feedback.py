"""What the window says about the rig at every moment (issue 31), on the simulated lab, offscreen.

Every wait is on a signal, never a sleep; images are 80x60.
"""
import os
import tempfile

import numpy as np
import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pytestqt")

from PySide6.QtCore import Qt  # noqa: E402
from PySide6.QtWidgets import QApplication, QLabel, QPushButton, QWidget  # noqa: E402

from reflab.app.gui import MainWindow  # noqa: E402
from reflab.app.gui.main_window import progress_text  # noqa: E402
from reflab.app.gui.widgets import ImageView  # noqa: E402
from reflab.core.workspace import read_json  # noqa: E402

SIZE = (80, 60)


def open_window(qtbot, workspace, **options):
    window = MainWindow(workspace, port="sim", camera="sim", size=SIZE, live_preview_ms=0, options=options)
    window.ask_close = lambda: True  # a failed test's teardown closes without a dialog
    qtbot.addWidget(window)
    window.show()
    return window


def connect(qtbot, window):
    with qtbot.waitSignal(window.step_finished, timeout=60_000) as blocker:
        qtbot.mouseClick(window.findChild(QPushButton, "run_devices"), Qt.MouseButton.LeftButton)
    assert blocker.args == ["devices", "done"]


def banner_pixels(view: ImageView) -> int:
    """Pixels of the banner's colour in what the view draws."""
    img = view.viewport().grab().toImage().convertToFormat(view.viewport().grab().toImage().Format.Format_RGB888)
    a = np.frombuffer(img.constBits(), np.uint8).reshape(img.height(), img.bytesPerLine())[:, : 3 * img.width()]
    a = a.reshape(img.height(), img.width(), 3).astype(int)
    c = ImageView.BANNER_BACK
    return int(np.sum(np.all(np.abs(a - [c.red(), c.green(), c.blue()]) <= 2, axis=2)))


def test_the_live_view_says_when_every_lamp_is_off_and_the_status_follows_the_board(qtbot, tmp_path):
    window = open_window(qtbot, tmp_path)
    view = window.findChild(ImageView, "preview_devices")
    assert view.banner == "" and banner_pixels(view) == 0  # not connected: nothing claimed
    connect(qtbot, window)
    # Both lamps start off: the view says so, drawn on it (the camera's frame would be black).
    assert window.rig.controller.lamps == [False, False]
    assert view.banner == "all lamps off" and banner_pixels(view) > 50
    assert "once the rig is connected" not in view.placeholder.text()
    status = window.findChild(QLabel, "status_devices")
    with qtbot.waitSignal(window.hardware_done, timeout=30_000):
        qtbot.mouseClick(window.findChild(QPushButton, "jog_p10"), Qt.MouseButton.LeftButton)
    assert "turntable 10.0°" in status.text() and "lamp 0 off" in status.text()
    with qtbot.waitSignal(window.hardware_done, timeout=30_000):
        window.findChild(QWidget, "lamp_0").click()
    assert "turntable 10.0°" in status.text() and "lamp 0 on" in status.text(), status.text()
    assert window.rig.sim.lamp_outputs() and view.banner == "" and banner_pixels(view) == 0
    qtbot.mouseClick(window.findChild(QPushButton, "hw_disconnect"), Qt.MouseButton.LeftButton)
    assert "disconnected" in status.text() and view.banner == ""


def test_labels_name_the_buttons_that_exist(qtbot, tmp_path):
    window = open_window(qtbot, tmp_path)
    buttons = {b.text() for b in window.findChildren(QPushButton)}
    for step in ("calibrate_camera", "calibrate_lights", "sweep", "input", "fit", "texture", "reconstruct", "results"):
        text = window.findChild(QLabel, f"instructions_{step}").text()
        run = window.findChild(QPushButton, f"run_{step}").text()
        assert "Run " not in text, (step, text)
        if "“" in text:
            assert f"“{run}”" in text and run in buttons, (step, text)
    assert "“Capture and calibrate” takes that shot" in window.findChild(QLabel, "instructions_calibrate_camera").text()


def test_pause_takes_no_further_shot_and_says_paused(qtbot, tmp_path):
    window = open_window(qtbot, tmp_path, sweep={"count": 8})
    connect(qtbot, window)
    window.go_to("sweep")
    window.run_step("sweep")
    status = window.findChild(QLabel, "status_sweep")
    with qtbot.waitSignal(window.worker.progress, timeout=30_000) as first:  # the first shot is written
        pass
    assert first.args[2].startswith("sweep: ") and window.progress.format().startswith("sweep: shot 1 of 8 (")
    qtbot.mouseClick(window.findChild(QPushButton, "pause"), Qt.MouseButton.LeftButton)
    assert status.text().startswith("paused") and window.progress.format().startswith("paused")
    assert "Resume to go on" in window.log_pane.toPlainText().splitlines()[-1]
    folder = tmp_path / "captures" / "turntable"
    files = sorted(p.name for p in folder.glob("*.exr"))
    # Held: a shot being exposed when Pause was pressed is not written while paused.
    qtbot.waitUntil(window.worker.task.holding.is_set, timeout=30_000)
    assert sorted(p.name for p in folder.glob("*.exr")) == files and window.running == "sweep"
    qtbot.mouseClick(window.findChild(QPushButton, "pause"), Qt.MouseButton.LeftButton)  # Resume
    assert status.text().startswith("running")
    with qtbot.waitSignal(window.worker.progress, timeout=30_000) as nxt:
        pass
    assert nxt.args[0] == len(files) + 1
    # Esc cancels the running step.
    window.activateWindow()
    with qtbot.waitSignal(window.step_finished, timeout=30_000) as blocker:
        qtbot.keyClick(window, Qt.Key.Key_Escape)
    assert blocker.args == ["sweep", "cancelled"]
    assert read_json(folder / "manifest.json")["status"] == "cancelled"


def test_progress_text_counts_shots():
    assert progress_text(3, 36, "sweep: 0002.exr") == "sweep: shot 3 of 36 (0002.exr)"
    assert progress_text(2, 10, "fit iteration 2, RMS per band [1, 2, 3]") == "fit iteration 2, RMS per band [1, 2, 3] (2 of 10)"


def test_the_lamps_page_live_view_is_not_a_narrow_column(qtbot, tmp_path):
    window = open_window(qtbot, tmp_path)
    window.go_to("calibrate_lights")
    qtbot.waitExposed(window)
    view = window.findChild(ImageView, "preview_calibrate_lights")
    page = window.findChild(QWidget, "page_calibrate_lights")
    assert view.width() >= 0.25 * page.width() and view.width() >= 300, (view.width(), page.width())


def test_ctrl_q_quits_and_a_closed_window_leaves_no_temporary_files(qtbot, tmp_path, monkeypatch):
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    window = open_window(qtbot, tmp_path / "ws")
    connect(qtbot, window)
    assert any(scratch.iterdir())  # the simulated board's pseudo-terminal lives there while connected
    window.activateWindow()
    qtbot.keyClick(window, Qt.Key.Key_Q, Qt.KeyboardModifier.ControlModifier)
    qtbot.waitUntil(lambda: not window.isVisible(), timeout=10_000)
    assert not window.rig.connected and list(scratch.iterdir()) == []
