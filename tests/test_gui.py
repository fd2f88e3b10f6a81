"""The guided lab window on the simulated lab, driven through docs/formats.md's object names.

Every wait is on a signal (the window's ``step_finished``, a worker's ``progress``), never a sleep.
Images are 80x60 so that each test takes seconds.
"""
import os
import time

import numpy as np
import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
pytest.importorskip("pytestqt")

from PySide6.QtCore import QPoint, Qt  # noqa: E402
from PySide6.QtWidgets import QLabel, QProgressBar, QPushButton, QWidget  # noqa: E402

from reflab.app.gui import MainWindow  # noqa: E402
from reflab.app.gui.stages import NAMES  # noqa: E402
from reflab.core.workspace import read_json  # noqa: E402

SIZE = (80, 60)


def open_window(qtbot, workspace, **options):
    window = MainWindow(workspace, port="sim", camera="sim", size=SIZE, live_preview_ms=0, options=options)
    qtbot.addWidget(window)
    window.show()
    return window


def run(qtbot, window, step, timeout=120_000):
    """Click run_<step> and wait for the step's thread to end; return (outcome, status text)."""
    with qtbot.waitSignal(window.step_finished, timeout=timeout) as blocker:
        qtbot.mouseClick(window.findChild(QPushButton, f"run_{step}"), Qt.MouseButton.LeftButton)
    assert blocker.args[0] == step
    return blocker.args[1], window.findChild(QLabel, f"status_{step}").text()


def wheel(view, u, v, steps=1):
    """Turn the mouse wheel ``steps`` notches forward with the cursor over pixel (u, v) of an image view."""
    from PySide6.QtCore import QPointF
    from PySide6.QtGui import QWheelEvent
    from PySide6.QtWidgets import QApplication

    for _ in range(steps):
        at = QPointF(view.mapFromScene(u + 0.5, v + 0.5))
        QApplication.sendEvent(view.viewport(), QWheelEvent(at, view.viewport().mapToGlobal(at), QPoint(), QPoint(0, 120),
                                                            Qt.MouseButton.NoButton, Qt.KeyboardModifier.NoModifier,
                                                            Qt.ScrollPhase.NoScrollPhase, False))


def drag(qtbot, view, start, end):
    """Press on pixel ``start`` of an image view, move to ``end`` and release there."""
    a, b = (view.mapFromScene(u + 0.5, v + 0.5) for u, v in (start, end))
    qtbot.mousePress(view.viewport(), Qt.MouseButton.LeftButton, pos=QPoint(a.x(), a.y()))
    for t in (0.25, 0.5, 0.75, 1.0):
        qtbot.mouseMove(view.viewport(), pos=QPoint(round(a.x() + t * (b.x() - a.x())), round(a.y() + t * (b.y() - a.y()))))
    qtbot.mouseRelease(view.viewport(), Qt.MouseButton.LeftButton, pos=QPoint(b.x(), b.y()))


@pytest.fixture
def lab_workspace(tmp_path):
    """The simulated lab's camera, lamps and geometry (materials unknown) and its photograph, 80x60."""
    from reflab.core.images import write_image
    from reflab.hardware.sim.lab import build_lab, write_lab
    from reflab.hardware.sim.reference import render_reference

    lab = build_lab(*SIZE)
    write_lab(tmp_path, lab, materials=False)
    write_image(tmp_path / "input.exr", render_reference(lab.scene, lab.camera, lab.lights, depth=3, albedo=lab.albedo))
    return tmp_path


def test_object_names_of_the_contract_and_resume_at_first_missing_step(qtbot, lab_workspace, tmp_path_factory):
    window = open_window(qtbot, lab_workspace)
    assert NAMES == ["devices", "calibrate_camera", "calibrate_lights", "sweep", "reconstruct", "input", "fit",
                     "texture", "results"]
    for step in NAMES:
        page = window.findChild(QWidget, f"page_{step}")
        assert page is not None, step
        assert isinstance(page.findChild(QPushButton, f"run_{step}"), QPushButton)
        assert isinstance(page.findChild(QLabel, f"status_{step}"), QLabel)
    assert isinstance(window.findChild(QProgressBar, "progress"), QProgressBar)
    assert isinstance(window.findChild(QPushButton, "cancel"), QPushButton)
    steps = window.findChild(QWidget, "steps")
    # camera, lights, scene and input exist: it reopens at the fit, and the list ticks what is done
    assert window.current_step() == "fit"
    ticked = [steps.item(i).text().startswith("✓") for i in range(steps.count())]
    assert ticked == [False, True, True, False, True, True, False, False, False]
    fresh = open_window(qtbot, tmp_path_factory.mktemp("empty"))
    assert fresh.current_step() == "devices"
    # each page but the last leads on to the next; the pages with something to set up draw it
    for step, following in zip(NAMES, NAMES[1:]):
        qtbot.mouseClick(fresh.findChild(QPushButton, f"next_{step}"), Qt.MouseButton.LeftButton)
        assert fresh.current_step() == following
    assert fresh.findChild(QPushButton, "next_results") is None
    drawn = [step for step in NAMES if fresh.findChild(QWidget, f"sketch_{step}") is not None]
    assert drawn == ["devices", "calibrate_camera", "calibrate_lights", "sweep", "input"]


def test_sweep_cancel_then_resume_keeps_the_finished_shots(qtbot, tmp_path):
    window = open_window(qtbot, tmp_path, sweep={"count": 6})
    assert run(qtbot, window, "devices")[0] == "done"
    assert (tmp_path / "hardware.json").exists()

    started = []
    assert window.run_step("sweep")
    worker = window.worker
    # cancel once the second shot is written (a queued slot, in the UI thread)
    worker.progress.connect(lambda done, total, msg: done >= 2 and not started and
                            (started.append(time.monotonic()),
                             qtbot.mouseClick(window.findChild(QPushButton, "cancel"), Qt.MouseButton.LeftButton)))
    with qtbot.waitSignal(window.step_finished, timeout=60_000) as blocker:
        pass
    assert blocker.args == ["sweep", "cancelled"]
    assert time.monotonic() - started[0] < 1.0  # the step stopped within a second of Cancel (seen 0.02-0.1 s)
    assert window.findChild(QLabel, "status_sweep").text().startswith("cancelled")
    manifest = read_json(tmp_path / "captures/turntable/manifest.json")
    assert manifest["status"] == "cancelled"
    kept = {r["file"]: r["time"] for r in manifest["shots"]}
    assert 2 <= len(kept) < 6

    outcome, status = run(qtbot, window, "sweep")
    assert (outcome, status.split(":")[0]) == ("done", "done")
    manifest = read_json(tmp_path / "captures/turntable/manifest.json")
    assert manifest["status"] == "complete" and len(manifest["shots"]) == 6
    # the shots taken before the cancel were kept, not retaken
    assert {r["file"]: r["time"] for r in manifest["shots"][:len(kept)]} == kept
    angles = [r["angle"] for r in manifest["shots"]]
    assert angles == pytest.approx([0, 60, 120, 180, 240, 300])
    assert window.findChild(QWidget, "steps").item(NAMES.index("sweep")).text().startswith("✓")

    # mark two corners of a transparent sheet on two shots each; reconstruct's reader takes the file
    from reflab.reconstruction.surfaces import load_marks

    window.go_to("sweep")
    shots, view = window.findChild(QWidget, "sweep_shots"), window.findChild(QWidget, "sweep_view")
    window.findChild(QWidget, "corner_surface").setCurrentText("sheet")
    window.findChild(QWidget, "corner_kind").setCurrentIndex(1)
    window.findChild(QWidget, "corner_ior").setValue(1.46)
    window.findChild(QWidget, "corner_thickness").setValue(0.003)
    clicks = {(0, 0): (30.0, 20.0), (0, 1): (31.0, 22.0), (1, 0): (50.0, 21.0), (1, 1): (52.0, 23.0)}
    shots.setCurrentRow(0)
    fitted = view.transform().m11()
    wheel(view, 40.0, 21.0, steps=3)  # zoom in on the corners, which stay under the cursor
    assert view.transform().m11() == pytest.approx(fitted * 1.25 ** 3)
    for (corner, shot), (u, v) in clicks.items():
        window.findChild(QWidget, "corner_label").setCurrentIndex(corner)
        shots.setCurrentRow(shot)
        at = view.mapFromScene(u + 0.5, v + 0.5)
        qtbot.mouseClick(view.viewport(), Qt.MouseButton.LeftButton, pos=QPoint(at.x(), at.y()))
    qtbot.mouseClick(window.findChild(QPushButton, "save_corner_marks"), Qt.MouseButton.LeftButton)
    (spec,) = load_marks(tmp_path / "marks.json")
    assert (spec["name"], spec["ior"], spec["textured"], spec["size"][1]) == ("sheet", 1.46, False, 0.003)
    scale = 1.0 / view.transform().m11()
    for k, (label, marks) in enumerate(spec["corners"]):
        assert list(label) == [[-1, -1, 1], [1, -1, 1]][k]
        for shot in (0, 1):
            assert np.allclose(marks[f"captures/turntable/{shot:04d}.exr"], clicks[(k, shot)], atol=scale)


def test_failed_step_shows_the_stage_message_in_the_page(qtbot, tmp_path):
    window = open_window(qtbot, tmp_path)
    outcome, status = run(qtbot, window, "fit")
    assert outcome == "failed"
    assert status.startswith("failed: ")
    assert "camera.json" in status and "reflab calibrate camera" in status and "Traceback" not in status
    assert "camera.json" in window.findChild(QWidget, "log").toPlainText()
    assert window.findChild(QPushButton, "run_fit").isEnabled()


def test_fit_texture_results_on_the_simulated_lab(qtbot, lab_workspace):
    window = open_window(qtbot, lab_workspace, fit={"texture_rounds": 0})
    for step in ("fit", "texture", "results"):
        outcome, status = run(qtbot, window, step)
        assert outcome == "done", status
    fit = read_json(lab_workspace / "fit.json")
    # the curve was drawn live, one point per iteration, from the errors fit.json's trace records
    live = window.page("fit").live
    assert len(live) >= 2
    traced = {tuple(float(f"{v:.4g}") for v in rms) for _, rms in fit["trace"]}
    assert all(tuple(point[1:]) in traced for point in live)
    assert [p[0] for p in live] == sorted(p[0] for p in live)
    table = window.findChild(QWidget, "fit_table")
    ground_kd = next(s for s in fit["surfaces"] if s["name"] == "ground")["material"]["kd"]
    shown = [table.item(i, 2).text() for i in range(table.rowCount())
             if table.item(i, 0).text() == "ground" and table.item(i, 1).text() == "kd"]
    assert shown == ["[" + ", ".join(f"{v:.3g}" for v in ground_kd) + "]"]
    # every parameter fit.json calls undetermined says so in the σ column, and no other
    flagged = {(table.item(i, 0).text(), table.item(i, 1).text()) for i in range(table.rowCount())
               if table.item(i, 3).text().startswith("undetermined")}
    assert flagged == {(s["name"], k) for s in fit["surfaces"] for k in s["undetermined"]
                       if s["material"].get(k) is not None}
    assert flagged  # the lab's matte ground has no mirror term to determine
    assert (lab_workspace / "textures/index.json").exists() and (lab_workspace / "render.exr").exists()
    # the texture page shows every recovered texture
    maps = {p.stem for p in (lab_workspace / "textures").glob("*.exr") if not p.stem.endswith("_diag")}
    shown = {w.objectName()[len("texture_"):] for w in window.page("texture").findChildren(QWidget)
             if w.objectName().startswith("texture_") and w.array is not None}
    assert maps and shown == maps
    # the page's figure is the re-render's RMS difference, computed here from the files
    from reflab.core.images import read_image

    photo, model = read_image(lab_workspace / "input.exr"), read_image(lab_workspace / "render.exr")
    rel = np.sqrt(np.mean((model - photo) ** 2)) / np.sqrt(np.mean(photo ** 2))
    assert f"{100 * rel:.2f}%" in window.findChild(QLabel, "results_summary").text()
    assert rel < 0.15
    # the novel view: the camera orbited and raised, lamp 1 dimmed, from the sliders, off the UI thread
    window.findChild(QWidget, "novel_azimuth").setValue(20)
    window.findChild(QWidget, "novel_elevation").setValue(-5)
    window.findChild(QWidget, "dim_lamp_1").setValue(30)
    with qtbot.waitSignal(window.page("results").novel_rendered, timeout=60_000) as blocker:
        qtbot.mouseClick(window.findChild(QPushButton, "render_novel"), Qt.MouseButton.LeftButton)
    assert blocker.args[0] and blocker.args[1].startswith("orbit +20°, raise -5°, lamps 100%, 30%")
    assert window.findChild(QWidget, "novel_view").array.shape[:2] == (SIZE[1], SIZE[0])


def test_rod_marks_clicked_on_a_shot_are_saved_as_marks_json(qtbot, tmp_path):
    from reflab.calibration.lamps import read_marks

    window = open_window(qtbot, tmp_path, calibrate_lights={"rod_height": 0.12, "angles": "0"})
    assert run(qtbot, window, "devices")[0] == "done"
    run(qtbot, window, "calibrate_lights")  # takes one shot per lamp (marks detected or not)
    window.go_to("calibrate_lights")
    page = window.page("calibrate_lights")
    shots = window.findChild(QWidget, "rod_shots")
    assert shots.count() == 2
    view = window.findChild(QWidget, "rod_view")
    page.marks = {}
    clicks = {0: [(20.0, 40.0), (55.0, 30.0)], 1: [(22.0, 41.0), (10.0, 25.0)]}
    for row, (foot, tip) in clicks.items():
        shots.setCurrentRow(row)
        view.clear_marks()
        for u, v in (foot, tip):
            at = view.mapFromScene(u + 0.5, v + 0.5)
            qtbot.mouseClick(view.viewport(), Qt.MouseButton.LeftButton, pos=QPoint(at.x(), at.y()))
    # the foot on the second shot was off: drag it to where it belongs
    drag(qtbot, view, clicks[1][0], (26.0, 44.0))
    clicks[1][0] = (26.0, 44.0)
    qtbot.mouseClick(window.findChild(QPushButton, "save_rod_marks"), Qt.MouseButton.LeftButton)
    height, marks = read_marks(tmp_path / "marks.json")
    assert height == pytest.approx(0.12)
    assert sorted((m.image, m.light) for m in marks) == [("captures/lights/0000.exr", 0), ("captures/lights/0001.exr", 1)]
    # a click lands on the pixel under the cursor: within the view's scale of one screen pixel
    scale = 1.0 / view.transform().m11()
    for m in marks:
        foot, tip = clicks[m.light]
        assert np.allclose(m.base, foot, atol=scale) and np.allclose(m.tip, tip, atol=scale)
    assert list(view.marks) == ["base", "tip"]  # the drag moved the mark, it did not add one


def test_reflab_help_imports_no_qt():
    """`reflab --help` and `reflab gui --help` answer without loading the Qt binding."""
    import subprocess
    import sys

    code = ("import sys, contextlib, io\n"
            "from reflab.app.cli import main\n"
            "for argv in (['--help'], ['gui', '--help']):\n"
            "    with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.suppress(SystemExit):\n"
            "        main(argv)\n"
            "    assert 'usage: reflab' in out.getvalue(), argv\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('PySide6', 'shiboken6', 'pytestqt')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_closing_with_a_step_running_asks_first(qtbot, tmp_path):
    window = open_window(qtbot, tmp_path, sweep={"count": 20})
    assert run(qtbot, window, "devices")[0] == "done"
    asked = []
    window.ask_close = lambda: asked.append(True) or len(asked) > 1  # refuse once, then accept
    window.run_step("sweep")
    with qtbot.waitSignal(window.worker.progress, timeout=30_000):  # the first shot is taken
        pass
    assert not window.close() and window.running == "sweep" and window.isVisible()
    with qtbot.waitSignal(window.step_finished, timeout=30_000) as blocker:
        assert window.close()
    assert asked == [True, True] and blocker.args == ["sweep", "cancelled"]


def test_cancelling_the_fit_writes_no_fit_json(qtbot, lab_workspace):
    window = open_window(qtbot, lab_workspace, fit={"texture_rounds": 0})
    window.run_step("fit")
    cancelled = []
    window.worker.progress.connect(lambda done, total, msg: msg.startswith("F-TBO") and not cancelled and
                                   (cancelled.append(done), window.cancel()))
    with qtbot.waitSignal(window.step_finished, timeout=60_000) as blocker:
        pass
    assert cancelled and blocker.args == ["fit", "cancelled"]
    assert window.findChild(QLabel, "status_fit").text().startswith("cancelled")
    assert not (lab_workspace / "fit.json").exists()
    assert run(qtbot, window, "fit")[0] == "done" and (lab_workspace / "fit.json").exists()


def test_hardware_page_jogs_the_turntable_and_switches_lamps_on_the_board(qtbot, tmp_path):
    window = open_window(qtbot, tmp_path)
    assert run(qtbot, window, "devices")[0] == "done"
    board, axis = window.rig.sim, window.rig.config.axis
    with qtbot.waitSignal(window.hardware_done, timeout=30_000) as blocker:
        qtbot.mouseClick(window.findChild(QPushButton, "jog_p90"), Qt.MouseButton.LeftButton)
    assert blocker.args[0] and "turntable 90.0°" in blocker.args[1]
    assert board.turntable(axis) == pytest.approx(90.0, abs=0.01)  # the simulated board's axis moved
    with qtbot.waitSignal(window.hardware_done, timeout=30_000):
        window.findChild(QWidget, "lamp_1").click()  # the box is wider than its label: click() hits the label
    assert window.rig.config.lamp_states(board.lamp_outputs()) == [False, True]
    assert window.findChild(QLabel, "hw_status").text().endswith(f"on {window.rig.controller.port})")
    qtbot.mouseClick(window.findChild(QPushButton, "hw_disconnect"), Qt.MouseButton.LeftButton)
    assert not window.rig.connected and not window.findChild(QPushButton, "jog_p90").isEnabled()


def test_the_qt_binding_keeps_its_references_to_none(qtbot):
    """PySide6 6.12.0 on Python 3.11 dropped a reference to None per void call (pyproject pins < 6.12)."""
    import sys

    label = QLabel()
    qtbot.addWidget(label)
    before = sys.getrefcount(None)
    for _ in range(2000):
        label.setText("x")
    assert sys.getrefcount(None) > before - 100


def test_naming_a_fitted_surface_by_clicking_it_writes_marks_json(qtbot, lab_workspace):
    window = open_window(qtbot, lab_workspace)
    window.go_to("reconstruct")
    view = window.findChild(QWidget, "reconstruct_view")
    assert view.array is not None and view.array.shape[:2] == (SIZE[1], SIZE[0])  # the input view, overlaid
    at = view.mapFromScene(60.5, 45.5)
    qtbot.mouseClick(view.viewport(), Qt.MouseButton.LeftButton, pos=QPoint(at.x(), at.y()))
    window.findChild(QWidget, "point_name").setText("tile")
    window.findChild(QWidget, "point_kind").setCurrentIndex(4)  # transparent
    window.findChild(QWidget, "point_ior").setValue(1.52)
    qtbot.mouseClick(window.findChild(QPushButton, "point_add"), Qt.MouseButton.LeftButton)
    (entry,) = read_json(lab_workspace / "marks.json")["surfaces"]
    assert (entry["name"], entry["ior"]) == ("tile", 1.52)
    assert np.allclose(entry["at"], [60.0, 45.0], atol=1.0 / view.transform().m11())
    assert window.findChild(QWidget, "point_list").count() == 1


def test_novel_view_orbits_the_input_camera_and_relights_linearly(lab_workspace):
    from reflab.app.gui.pages.results import novel_view, orbit
    from reflab.calibration.camera import Camera
    from reflab.inverse.stages import render_workspace

    cam = Camera.load(lab_workspace / "camera.json")
    same = orbit(cam, 0.0, 0.0)
    assert np.allclose(same.R, cam.R) and np.allclose(same.t, cam.t)
    moved = orbit(cam, 30.0, 10.0)
    target = cam.center + cam.R[2] * (cam.center[2] / -cam.R[2][2])
    # the orbit keeps the distance to the point looked at, and that point stays at the image centre's ray
    assert np.linalg.norm(moved.center - target) == pytest.approx(np.linalg.norm(cam.center - target))
    assert np.allclose(moved.R[2], (target - moved.center) / np.linalg.norm(target - moved.center))
    assert np.degrees(np.arctan2(moved.center[2] - target[2], np.hypot(*(moved.center - target)[:2]))) == pytest.approx(
        np.degrees(np.arctan2(cam.center[2] - target[2], np.hypot(*(cam.center - target)[:2]))) + 10.0)
    base, _ = render_workspace(lab_workspace)
    half, _ = novel_view(lab_workspace, 0.0, 0.0, [0.5, 0.5])
    assert np.allclose(half, 0.5 * base, rtol=1e-6, atol=1e-9)  # radiance is linear in the lamps' intensity
    one_lamp, _ = novel_view(lab_workspace, 0.0, 0.0, [0.0, 1.0])
    other, _ = novel_view(lab_workspace, 0.0, 0.0, [1.0, 0.0])
    assert np.allclose(one_lamp + other, base, rtol=1e-6, atol=1e-9)


def test_lamps_located_from_the_rod_shots_the_window_takes(qtbot, tmp_path):
    """The lamp page on the simulated lab's rod and grey card (160x120): rod found in every shot,
    lamps located near the lab's true lamps. The camera is the lab's true one (camera
    calibration needs larger images than a quick test takes)."""
    from reflab.calibration.lights import Lights
    from reflab.hardware.sim.lab import build_lab

    lab = build_lab(160, 120)
    lab.camera.save(tmp_path / "camera.json")
    window = MainWindow(tmp_path, size=(160, 120), live_preview_ms=0)
    qtbot.addWidget(window)
    outcome, status = run(qtbot, window, "calibrate_lights")  # connects the rig itself
    assert outcome == "done", status
    found = Lights.load(tmp_path / "lights.json")
    for lamp, true in zip(found, lab.lights):
        assert np.linalg.norm(lamp.position - true.position) < 0.04  # metres, lamps ~0.6 m away (seen: 4-27 mm)
        assert np.allclose(lamp.intensity, true.intensity, rtol=0.15)  # from the grey card (seen: 1-9%)
    window.go_to("calibrate_lights")
    assert window.findChild(QWidget, "rod_shots").count() == 8  # 4 angles x 2 lamps
    assert window.findChild(QWidget, "lamp_table").rowCount() == 2


def test_camera_calibrated_from_the_target_shots_the_window_takes(qtbot, tmp_path):
    """The camera page on the simulated lab's circle target (320x240): the flat reference shot and
    the target on its wedge at the turntable's angles; intrinsics and pose against the lab's camera."""
    from reflab.calibration.camera import Camera
    from reflab.hardware.sim.lab import build_lab

    window = MainWindow(tmp_path, size=(320, 240), live_preview_ms=0)
    qtbot.addWidget(window)
    outcome, status = run(qtbot, window, "calibrate_camera", timeout=300_000)
    assert outcome == "done", status
    true, found = build_lab(320, 240).camera, Camera.load(tmp_path / "camera.json")
    assert found.K[0, 0] == pytest.approx(true.K[0, 0], rel=0.01)  # seen 0.23%
    assert np.linalg.norm(found.center - true.center) < 0.005  # metres (seen 0.9 mm): the flat shot is the input pose
    views = read_json(tmp_path / "camera.json")["calibration"]["views"]
    window.go_to("calibrate_camera")
    table = window.findChild(QWidget, "camera_views")
    assert table.rowCount() == len(views) >= 4
    assert [table.item(i, 1).text() for i in range(table.rowCount())] == [f"{v['rms_px']:.3f}" for v in views]
    # the worst view is shown with its residuals drawn over it; another row shows that view's
    worst = max(range(len(views)), key=lambda i: views[i]["rms_px"])
    caption = window.findChild(QLabel, "camera_residual_caption")
    assert caption.text().startswith(f"{views[worst]['image'].rsplit('/', 1)[-1]}: residuals × ")
    table.selectRow((worst + 1) % len(views))
    assert caption.text().startswith(views[(worst + 1) % len(views)]["image"].rsplit("/", 1)[-1])
    assert window.findChild(QWidget, "camera_residuals").array.shape[:2] == (240, 320)


def test_a_missing_serial_port_fails_the_devices_step_with_its_name(qtbot, tmp_path):
    window = MainWindow(tmp_path, port=str(tmp_path / "ttyUSB9"), camera="sim", size=SIZE, live_preview_ms=0)
    qtbot.addWidget(window)
    outcome, status = run(qtbot, window, "devices")
    assert outcome == "failed" and status.startswith("failed: cannot open") and "ttyUSB9" in status
    assert not window.rig.connected and not (tmp_path / "hardware.json").exists()


def test_a_paused_sweep_holds_and_cancel_ends_it(qtbot, tmp_path):
    window = open_window(qtbot, tmp_path, sweep={"count": 8})
    assert run(qtbot, window, "devices")[0] == "done"
    window.run_step("sweep")
    with qtbot.waitSignal(window.worker.progress, timeout=30_000):  # the first shot is taken
        pass
    qtbot.mouseClick(window.findChild(QPushButton, "pause"), Qt.MouseButton.LeftButton)
    taken = window.worker.task.done  # shots written when the pause was asked
    assert window.worker.task.paused and window.findChild(QPushButton, "pause").text() == "Resume"
    with qtbot.waitSignal(window.step_finished, timeout=30_000) as blocker:
        qtbot.mouseClick(window.findChild(QPushButton, "cancel"), Qt.MouseButton.LeftButton)
    assert blocker.args == ["sweep", "cancelled"]
    shots = read_json(tmp_path / "captures/turntable/manifest.json")["shots"]
    assert 1 <= taken <= len(shots) <= taken + 1 < 8  # held after the shot it was taking when paused
    pause = window.findChild(QPushButton, "pause")
    assert not pause.isEnabled() and not pause.isChecked() and pause.text() == "Pause"


def test_sweep_reconstruct_and_input_through_the_window(qtbot, tmp_path):
    """The sweep, the reconstruction from its shots and the input photograph, each run by its
    button on the simulated lab (480x360, 24 shots as `reflab demo --quick`); the lab's true camera stands in for the
    camera step (tested above at 320x240)."""
    from reflab.hardware.sim.lab import build_lab

    build_lab(480, 360).camera.save(tmp_path / "camera.json")
    window = MainWindow(tmp_path, size=(480, 360), live_preview_ms=0, options={"sweep": {"count": 24}})
    qtbot.addWidget(window)
    window.show()
    for step in ("sweep", "reconstruct", "input"):
        outcome, status = run(qtbot, window, step, timeout=300_000)
        assert outcome == "done", (step, status)
    sfm = read_json(tmp_path / "sfm.json")["sfm"]
    assert sfm["registered"] == sfm["images"] == 24
    summary = window.findChild(QLabel, "reconstruct_summary").text()
    assert f"<b>24/24</b> shots registered, <b>{sfm['points']}</b> sparse points" in summary
    names = [s["name"] for s in read_json(tmp_path / "scene.json")["surfaces"]]
    assert "ground" in names and len(names) >= 2 and all(n in summary for n in names)
    assert window.findChild(QWidget, "reconstruct_view").array.shape == (360, 480, 3)  # the input view, overlaid
    assert (tmp_path / "input.exr").exists()
    assert window.findChild(QLabel, "input_summary").text().startswith("input.exr: 480×360")
    assert window.findChild(QWidget, "input_view").array.shape[:2] == (360, 480)
    assert [window.step_list.item(i).text().startswith("✓") for i in range(len(NAMES))][3:6] == [True] * 3


def test_a_tethered_camera_previews_its_newest_shot_without_taking_one(qtbot, tmp_path):
    """`--camera folder:PATH`: the live view shows the folder's newest image and never waits for a
    new one (a shot would wait up to the camera's 60 s timeout, holding the rig from the steps)."""
    from reflab.core.images import write_image

    folder = tmp_path / "tether"
    folder.mkdir()
    write_image(folder / "a.exr", np.full((30, 40, 3), 0.2))
    window = MainWindow(tmp_path / "ws", port="sim", camera=f"folder:{folder}", size=SIZE, live_preview_ms=20)
    qtbot.addWidget(window)
    window.show()
    assert run(qtbot, window, "devices")[0] == "done"
    view = window.findChild(QWidget, "preview_devices")
    qtbot.waitUntil(lambda: view.array is not None, timeout=10_000)
    assert view.array.shape[:2] == (30, 40)
    write_image(folder / "b.exr", np.full((20, 10, 3), 0.5))  # the user took a shot
    qtbot.waitUntil(lambda: view.array.shape[:2] == (20, 10), timeout=10_000)
    assert sorted(p.name for p in folder.iterdir()) == ["a.exr", "b.exr"]


def test_cancel_stops_a_sweep_waiting_for_the_tethered_cameras_shot(qtbot, tmp_path):
    """A tethered camera waits (up to 60 s) for the user's shutter; Cancel stops that wait at once."""
    folder = tmp_path / "tether"
    folder.mkdir()
    window = MainWindow(tmp_path / "ws", port="sim", camera=f"folder:{folder}", size=SIZE, live_preview_ms=0,
                        options={"sweep": {"count": 3}})
    qtbot.addWidget(window)
    window.show()
    window.ask_close = lambda: True  # no question box at teardown if the step is still running
    assert run(qtbot, window, "devices")[0] == "done"
    manifest = tmp_path / "ws/captures/turntable/manifest.json"
    camera = window.rig.camera
    idle = camera.cancelled
    window.run_step("sweep")
    qtbot.waitUntil(lambda: camera.cancelled is not idle, timeout=10_000)  # the capture waits for the shutter
    with qtbot.waitSignal(window.step_finished, timeout=10_000) as blocker:
        clicked = time.monotonic()
        qtbot.mouseClick(window.findChild(QPushButton, "cancel"), Qt.MouseButton.LeftButton)
    assert blocker.args == ["sweep", "cancelled"] and time.monotonic() - clicked < 1.0
    assert read_json(manifest)["status"] == "cancelled" and read_json(manifest)["shots"] == []
