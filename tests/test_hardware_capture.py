"""Capture sessions on the simulated board (real pty) and the simulated camera (Mitsuba-rendered lab).

Every fault stops the session with a clear message, leaves no half-written or lost image, and
resume takes exactly the missing shots; a 36-shot sweep matches the angles the board received.
"""
import re

import numpy as np
import pytest

from reflab.app.cli import main as cli
from reflab.hardware.sim.camera import SimulatedCamera, lab_renderer, rotate_about_z
from reflab.hardware.capture import (CaptureCancelled, CaptureError, CaptureSession, Control, plan_calibration, plan_input,
                              plan_lights, plan_sweep)
from reflab.hardware.grbl import GrblAlarm, GrblConfig, GrblController
from reflab.core.images import read_image
from reflab.hardware.sim.reference import render_reference
from reflab.hardware.sim.device import SimulatedGrbl
from reflab.hardware.sim.lab import build_lab
from reflab.core.workspace import WorkspaceError, read_json

CFG = GrblConfig(timeout_s=2.0, boot_wait_s=0.4, reconnect_delay_s=0.05, reconnects=2, feed_deg_per_min=36000.0)


@pytest.fixture(scope="module")
def lab():
    return build_lab(24, 18)


@pytest.fixture
def sim():
    with SimulatedGrbl(time_scale=20.0) as board:
        yield board


class Rig:
    """The simulated camera bound to the board's true axis and outputs; counts the shots it renders."""

    def __init__(self, lab, board, ambient=0.0):
        self.render = lab_renderer(lab, depth=1)
        self.angles = []
        self.camera = SimulatedCamera(self._render, lambda: (board.turntable("X"), CFG.lamp_states(board.lamp_outputs())),
                                      ambient=ambient)

    def _render(self, angle, lamps):
        self.angles.append(angle)
        return self.render(angle, lamps)


def _files(folder):
    return sorted(p.name for p in folder.iterdir())


def _stats(folder, names):
    return {n: ((folder / n).stat().st_ino, (folder / n).stat().st_mtime_ns) for n in names}


def test_rotation_about_the_turntable_axis():
    p = np.array([[2.0, 1.0, 0.3], [1.0, 1.0, 0.0]])
    np.testing.assert_allclose(rotate_about_z(p, 90.0, (1.0, 1.0)), [[1.0, 2.0, 0.3], [1.0, 1.0, 0.0]], atol=1e-12)


@pytest.mark.parametrize("fault, options, message", [
    ("garble", {}, "garbled reply"),
    ("error", {"code": 33}, r"error:33 \(motion command target is invalid\)"),
    ("alarm", {"code": 1}, r"ALARM:1 \(hard limit"),
    ("silent", {}, r"no answer to 'G90 G1 X180.000"),
    ("disconnect", {}, "reconnect attempts failed"),
])
def test_fault_stops_cleanly_and_resume_takes_exactly_the_missing_shots(tmp_path, lab, sim, fault, options, message):
    plan = plan_sweep(2, 6)  # 0, 60, … 300 degrees; shot 0 needs no move
    sim.inject(fault, match="G1", skip=2, **options)  # the move to 180 degrees (shot 3)
    rig = Rig(lab, sim)
    folder = tmp_path / "captures" / "turntable"
    with GrblController(sim.port, CFG) as ctl:
        with pytest.raises(CaptureError, match="stopped after 3 of 6 shots") as info:
            CaptureSession(tmp_path, "sweep", plan, ctl, rig.camera).run()
    assert re.search(message, str(info.value))
    assert "--resume" in str(info.value)
    manifest = read_json(folder / "manifest.json")
    assert manifest["status"] == "stopped" and re.search(message, manifest["error"])
    assert [r["file"] for r in manifest["shots"]] == ["0000.exr", "0001.exr", "0002.exr"]
    assert _files(folder) == ["0000.exr", "0001.exr", "0002.exr", "manifest.json"]  # no temporary, no orphan
    before = _stats(folder, ["0000.exr", "0001.exr", "0002.exr"])

    if fault == "disconnect":
        sim.replug()
    ctl = GrblController(sim.port, CFG)
    if fault == "alarm":
        with pytest.raises(GrblAlarm):
            ctl.connect()
        ctl.unlock()
    else:
        ctl.connect()
    rig.angles.clear()
    manifest = CaptureSession(tmp_path, "sweep", plan, ctl, rig.camera, resume=True).run()
    ctl.close()
    assert rig.angles == pytest.approx([180.0, 240.0, 300.0])  # exactly the missing shots, at their angles
    assert _stats(folder, before) == before  # finished shots untouched
    assert manifest["status"] == "complete" and manifest["error"] is None
    assert [r["file"] for r in manifest["shots"]] == [s.file for s in plan]
    assert [r["angle_reported"] for r in manifest["shots"]] == pytest.approx([s.angle for s in plan], abs=1e-3)
    assert _files(folder) == [s.file for s in plan] + ["manifest.json"]
    # The resumed shot shows the lab turned by its angle.
    np.testing.assert_allclose(read_image(folder / "0004.exr"), rig.render(240.0, [True, True]), rtol=1e-5, atol=1e-7)


def test_sweep_of_36_matches_the_commanded_angles(tmp_path, lab, sim):
    rig = Rig(lab, sim)
    plan = plan_sweep(2, 36)
    seen = []
    with GrblController(sim.port, CFG) as ctl:
        manifest = CaptureSession(tmp_path, "sweep", plan, ctl, rig.camera, exposure=0.5,
                                  progress=lambda done, total, rec: seen.append((done, total))).run()
    assert seen == [(i, 36) for i in range(1, 37)]
    shots = manifest["shots"]
    assert [r["angle"] for r in shots] == pytest.approx([10.0 * i for i in range(36)], abs=1e-12)
    assert [r["angle_reported"] for r in shots] == pytest.approx([10.0 * i for i in range(36)], abs=1e-3)
    assert all(r["lamps"] == [True, True] and r["exposure"] == 0.5 for r in shots)
    # What the board was told and what the camera saw, shot by shot.
    moves = [float(re.search(r"X(-?[0-9.]+)", l).group(1)) for _, l in sim.lines if l.startswith("G90 G1")]
    assert moves == pytest.approx([10.0 * i for i in range(1, 36)])
    assert rig.angles == pytest.approx([10.0 * i for i in range(36)], abs=1e-3)
    assert sim.max_in_flight == 1
    polls = np.asarray(sim.polls)  # at most 5 Hz; two gaps together, as one stamp may come late under load
    assert np.min(polls[2:] - polls[:-2]) >= 0.4
    assert read_json(tmp_path / "captures" / "turntable" / "manifest.json") == manifest
    # Angle 0 against an independent render of the unturned lab (exposure 0.5 halves the radiance).
    truth = render_reference(lab.scene, lab.camera, lab.lights, 1, lab.albedo)
    np.testing.assert_allclose(read_image(tmp_path / "captures" / "turntable" / "0000.exr"), 0.5 * truth, rtol=1e-5, atol=1e-7)
    assert not np.allclose(read_image(tmp_path / "captures" / "turntable" / "0009.exr"), 0.5 * truth, atol=1e-3)


def test_one_lamp_shots_add_up_to_the_input_and_ambient_is_subtracted(tmp_path, lab, sim):
    rig = Rig(lab, sim, ambient=0.05)  # room light on every frame
    with GrblController(sim.port, CFG) as ctl:
        CaptureSession(tmp_path, "lights", plan_lights(2, [0.0]), ctl, rig.camera).run()
        CaptureSession(tmp_path, "calibration", plan_calibration(2, [0.0]), ctl, rig.camera).run()
        manifest = CaptureSession(tmp_path, "input", plan_input(2, ambient=True), ctl, rig.camera).run()
    lights = read_json(tmp_path / "captures" / "lights" / "manifest.json")
    assert [r["lamps"] for r in lights["shots"]] == [[True, False], [False, True], [False, False]]
    assert [r["role"] for r in lights["shots"]] == ["lamp 0", "lamp 1", "room light"]
    one = [read_image(tmp_path / "captures" / "lights" / f"000{k}.exr") - 0.05 for k in range(2)]
    both = read_image(tmp_path / "captures" / "calibration" / "0000.exr") - 0.05
    np.testing.assert_allclose(one[0] + one[1], both, atol=2e-6)  # light adds linearly
    assert one[0].max() > 0.01 and one[1].max() > 0.01
    truth = render_reference(lab.scene, lab.camera, lab.lights, 1, lab.albedo)
    np.testing.assert_allclose(read_image(tmp_path / "input.exr"), truth, atol=2e-6)
    assert manifest["input"] == {"file": "input.exr", "ambient_subtracted": True}


def test_cancel_keeps_finished_shots_and_resume_finishes(tmp_path, lab, sim):
    control = Control()
    rig = Rig(lab, sim)
    plan = plan_sweep(2, 5)

    def progress(done, total, rec):
        if done == 2:
            control.cancel()

    with GrblController(sim.port, CFG) as ctl:
        with pytest.raises(CaptureCancelled, match="after 2 of 5 shots"):
            CaptureSession(tmp_path, "sweep", plan, ctl, rig.camera, control=control, progress=progress).run()
        assert read_json(tmp_path / "captures" / "turntable" / "manifest.json")["status"] == "cancelled"
        with pytest.raises(WorkspaceError, match="unfinished .2 of 5 shots.* --resume"):
            CaptureSession(tmp_path, "sweep", plan, ctl, rig.camera).run()
        with pytest.raises(WorkspaceError, match="field 'plan'"):
            CaptureSession(tmp_path, "sweep", plan_sweep(2, 6), ctl, rig.camera, resume=True).run()
        rig.angles.clear()
        manifest = CaptureSession(tmp_path, "sweep", plan, ctl, rig.camera, resume=True).run()
    assert rig.angles == pytest.approx([144.0, 216.0, 288.0])
    assert manifest["status"] == "complete" and len(manifest["shots"]) == 5


def test_a_shot_whose_image_vanished_is_retaken(tmp_path, lab, sim):
    rig = Rig(lab, sim)
    plan = plan_sweep(2, 3)
    with GrblController(sim.port, CFG) as ctl:
        CaptureSession(tmp_path, "sweep", plan, ctl, rig.camera).run()
        (tmp_path / "captures" / "turntable" / "0001.exr").unlink()
        rig.angles.clear()
        manifest = CaptureSession(tmp_path, "sweep", plan, ctl, rig.camera, resume=True).run()
    assert rig.angles == pytest.approx([120.0])
    assert sorted(r["file"] for r in manifest["shots"]) == ["0000.exr", "0001.exr", "0002.exr"]


def test_cli_capture_and_hardware_on_the_simulated_devices(tmp_path, capsys):
    ws = tmp_path / "ws"
    args = ["capture", "sweep", str(ws), "--port", "sim", "--camera", "sim", "--size", "16x12", "--depth", "1", "--count", "3"]
    assert cli(args) == 0
    out = capsys.readouterr().out
    assert "[3/3] 0002.exr  angle 240.000  lamps 11" in out
    assert cli(args) == 2  # an existing session is not silently overwritten
    assert "--resume" in capsys.readouterr().err
    assert cli(args + ["--resume"]) == 0
    assert "[" not in capsys.readouterr().out.replace("[3/3]", "")  # nothing retaken
    manifest = read_json(ws / "captures" / "turntable" / "manifest.json")
    assert [r["angle"] for r in manifest["shots"]] == [0.0, 120.0, 240.0]
    assert cli(["hardware", "--port", "sim", "rotate", "30"]) == 0
    assert "Idle  angle 30.000 deg" in capsys.readouterr().out
    assert cli(["hardware", "--port", "sim", "lamp", "1", "on"]) == 0
    assert "lamps: 0 off, 1 on" in capsys.readouterr().out
