"""The CLI and capture sessions against GRBL 1.1h itself (gnea/grbl built for the host with grbl-sim).

The firmware runs on a pseudo-terminal (tests/grbl_firmware.py); its *probe* reports the step
counters and the spindle and coolant pins as they physically are, so every check compares what
reflab says or keeps with what the board really did. Skipped, saying why, where the project's
../shared/third_party sources or a C compiler are missing.
"""
import json
import random
import sys
import threading
import time

import numpy as np
import pytest

from reflab.app.cli import main as cli
from reflab.core.images import read_image
from reflab.core.workspace import read_json
from reflab.hardware.capture import CaptureError, CaptureSession, plan_sweep
from reflab.hardware.grbl import GrblAlarm, GrblConfig, GrblController

sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
import grbl_firmware  # noqa: E402

STEPS = 100.0  # $100: steps per degree
SETTINGS = ["$100=100", "$110=18000", "$120=3000"]  # 300 deg/s, 3000 deg/s^2: fast moves
CONFIG = dict(feed_deg_per_min=18000.0, timeout_s=1.0, boot_wait_s=1.6, reconnects=0, move_timeout_s=20.0)
IDLE, ALARM, CYCLE, HOLD = 0, 1, 8, 16  # GRBL's sys.state bits


@pytest.fixture(scope="module")
def exe():
    why = grbl_firmware.missing()
    if why:
        pytest.skip(why)
    return grbl_firmware.build()


@pytest.fixture
def board(exe, tmp_path):
    fw = grbl_firmware.Firmware(exe, tmp_path / "board").start()
    try:
        fw.configure(SETTINGS)
        yield fw
    finally:
        fw.stop()


def _config(tmp_path, **kw):
    path = tmp_path / "hardware.json"
    path.write_text(json.dumps(dict(CONFIG, **kw)))
    return str(path)


def _hw(board, config, *args):
    return cli(["hardware", "--port", board.port, "--config", config, *args])


def _angle(truth):
    return truth["steps"][0] / STEPS


def _in_thread(fn, *args):
    out = {}
    t = threading.Thread(target=lambda: out.setdefault("rc", fn(*args)), daemon=True)
    t.start()
    return t, out


def _wait_for(cond, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "the firmware never reached the awaited state"
        time.sleep(0.002)


def test_status_moves_and_each_lamp(board, tmp_path, capsys):
    cfg = _config(tmp_path)
    assert _hw(board, cfg, "lamp", "0", "on") == 0
    assert _hw(board, cfg, "lamp", "1", "on") == 0
    capsys.readouterr()
    assert _hw(board, cfg, "status") == 0  # the A: field is absent from most reports: not "off"
    assert "Idle  angle 0.000 deg  lamps: 0 on, 1 on  (GRBL 1.1h" in capsys.readouterr().out
    t = board.truth()
    assert (t["spindle"], t["flood"], t["mist"]) == (True, True, False)
    assert _hw(board, cfg, "lamp", "1", "off") == 0
    assert "lamps: 0 on, 1 off" in capsys.readouterr().out
    t = board.truth()
    assert (t["spindle"], t["flood"]) == (True, False)
    assert _hw(board, cfg, "rotate", "90") == 0
    assert "Idle  angle 90.000 deg" in capsys.readouterr().out and _angle(board.truth()) == 90.0
    assert _hw(board, cfg, "rotate", "--relative", "-32.5") == 0
    assert _angle(board.truth()) == 57.5
    assert _hw(board, cfg, "lamp", "0", "off") == 0
    assert not board.truth()["spindle"]


@pytest.mark.parametrize("lamps, message", [
    (["spindle", "mist"], "this GRBL build has no M7"),
    (["flood", "mist"], "M9, switches flood AND mist off"),
])
def test_lamps_the_firmware_cannot_drive_alone_are_refused(board, tmp_path, capsys, lamps, message):
    assert _hw(board, _config(tmp_path, lamps=lamps), "lamp", "0", "on") == 2  # a wiring the board cannot drive is bad input (exit 2)
    assert message in capsys.readouterr().err
    assert not any(m in bytes(board.received) for m in (b"M3", b"M7", b"M8", b"M9"))  # none reached the board
    t = board.truth()
    assert not (t["spindle"] or t["flood"] or t["mist"])


def test_power_up_alarm_then_unlock(board, exe, tmp_path, capsys):
    cfg = _config(tmp_path)
    board.configure(["$22=1"], wait_banner=False)  # homing enabled: GRBL boots locked
    board.stop()
    board.start()  # the same EEPROM.DAT: a power cycle
    assert _hw(board, cfg, "status") == 1
    assert "GRBL is in the Alarm state" in capsys.readouterr().err
    assert _hw(board, cfg, "rotate", "10") == 1
    assert _angle(board.truth()) == 0.0
    assert _hw(board, cfg, "unlock") == 0
    assert "Idle  angle 0.000 deg" in capsys.readouterr().out
    assert _hw(board, cfg, "rotate", "10") == 0 and _angle(board.truth()) == 10.0


def test_soft_reset_mid_move_stops_with_alarm_3_then_unlock(board, tmp_path, capsys):
    cfg = _config(tmp_path)
    assert _hw(board, cfg, "lamp", "0", "on") == 0
    t, out = _in_thread(_hw, board, cfg, "rotate", "270")
    _wait_for(lambda: _angle(board.truth()) > 60.0)
    board.inject(b"\x18")  # the reset button, or another program
    t.join(20)
    assert out["rc"] == 1 and "ALARM:3 (reset while in motion" in capsys.readouterr().err
    truth = board.truth()
    assert truth["state"] == ALARM and 60.0 < _angle(truth) < 270.0 and not truth["spindle"]
    assert _hw(board, cfg, "unlock") == 0
    assert f"Idle  angle {_angle(truth):.3f} deg  lamps: 0 off, 1 off" in capsys.readouterr().out


def test_feed_hold_mid_move_and_a_board_left_held(board, tmp_path, capsys):
    cfg = _config(tmp_path)
    assert _hw(board, cfg, "lamp", "1", "on") == 0
    t, out = _in_thread(_hw, board, cfg, "rotate", "270")
    _wait_for(lambda: _angle(board.truth()) > 60.0)
    board.inject(b"!")  # the hold button
    t.join(20)
    assert out["rc"] == 1 and "went into Hold" in capsys.readouterr().err
    truth = board.truth()
    assert truth["state"] == IDLE and 60.0 < _angle(truth) < 270.0 and not truth["flood"]  # stopped, lamps off
    # A board someone left in Hold:0: no line is answered there until ~ or a reset.
    board.configure(["G90 G1 X0 F18000"], wait_banner=False)
    _wait_for(lambda: board.truth()["state"] == CYCLE)
    board.inject(b"!")
    _wait_for(lambda: board.truth()["state"] == HOLD)
    time.sleep(0.3)  # the deceleration ends: Hold:0
    held = _angle(board.truth())
    capsys.readouterr()
    assert _hw(board, cfg, "status") == 0
    printed = capsys.readouterr().out
    assert "the board was in state Hold" in printed and f"Idle  angle {held:.3f} deg" in printed
    assert board.truth()["state"] == IDLE and _angle(board.truth()) == held


class ProbeCamera:
    """A camera whose 'image' is the rig as it physically is at the start and end of the exposure."""

    def __init__(self, board, exposure_s=0.05):
        self.board, self.exposure_s = board, exposure_s
        self.shots = 0

    def _row(self):
        t = self.board.truth()
        return [_angle(t) / 360.0, float(t["spindle"]), float(t["flood"])]

    def capture(self, exposure=None):
        start = self._row()
        time.sleep(self.exposure_s)
        self.shots += 1
        return np.array([[start, self._row()]], dtype=np.float32)

    def describe(self):
        return {"type": "probe"}


def _check_kept(folder, manifest):
    """Every kept shot's image shows its manifest's angle and lamps, at both ends of its exposure."""
    assert manifest["status"] == "complete" and len(manifest["shots"]) == len(manifest["plan"])
    for rec in manifest["shots"]:
        img = read_image(folder / rec["file"])
        for end in img[0]:
            assert end[0] * 360.0 == pytest.approx(rec["angle"], abs=0.011), rec["file"]
            assert [bool(x > 0.5) for x in end[1:]] == rec["lamps"], rec["file"]
        for when in ("before", "after"):
            assert rec["confirmed"][when]["lamps"] == rec["lamps"]
            assert rec["confirmed"][when]["angle"] == pytest.approx(rec["angle"], abs=0.011)


def test_a_reset_during_the_settle_discards_the_shot_and_takes_it_again(board, tmp_path):
    cfg = GrblConfig(**CONFIG)
    camera, logs = ProbeCamera(board), []
    with GrblController(board.port, cfg) as ctl:
        set_lamps = ctl.set_lamps

        def set_lamps_then_reset(states):  # the reset comes while the session waits for the lamps
            set_lamps(states)
            if not logs:
                board.inject(b"\x18")
                logs.append("reset injected")

        ctl.set_lamps = set_lamps_then_reset
        manifest = CaptureSession(tmp_path, "sweep", plan_sweep(2, 2), ctl, camera, settle_s=0.3, log=logs.append).run()
    assert any("reset while waiting" in m and "discarded and taken again" in m for m in logs)
    assert camera.shots == 2  # the shot under the wrong light was never exposed, let alone kept
    _check_kept(tmp_path / "captures" / "turntable", manifest)
    t = board.truth()
    assert not (t["spindle"] or t["flood"]) and t["state"] == IDLE  # lamps off after the sweep


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_sweep_with_a_reset_at_a_random_point_of_every_shot_keeps_only_valid_shots(board, tmp_path, seed):
    rng = random.Random(seed)
    cfg = GrblConfig(**CONFIG)
    camera, logs = ProbeCamera(board), []
    plan = plan_sweep(2, 4)
    timers = []

    def arm(*_):  # one reset at a random moment of the next shot (move, lamps, settle, exposure)
        timers.append(threading.Timer(rng.uniform(0.0, 0.8), board.inject, (b"\x18",)))
        timers[-1].start()

    ctl = GrblController(board.port, cfg)
    ctl.connect()
    stops, resume = 0, False
    try:
        while True:
            arm()
            try:
                manifest = CaptureSession(tmp_path, "sweep", plan, ctl, camera, settle_s=0.1, resume=resume,
                                          progress=arm, log=logs.append).run()
                break
            except CaptureError as exc:  # a reset while moving: ALARM:3, unlock and resume
                assert "ALARM:3" in str(exc) or "reset" in str(exc), str(exc)
                stops += 1
                assert stops < 20
                for t in timers:
                    t.cancel()
                try:
                    ctl.connect()
                except GrblAlarm:
                    ctl.unlock()
                resume = True
    finally:
        for t in timers:
            t.cancel()
        ctl.close()
    _check_kept(tmp_path / "captures" / "turntable", manifest)
    assert stops + sum("discarded" in m for m in logs) > 0  # the resets did land inside shots
