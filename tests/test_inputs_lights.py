"""`reflab calibrate lights` finds what earlier stages and a user left in the workspace (issue 18).

The rod shots of a lights session (captures/lights/ and its manifest, as `reflab capture lights`
plans them; 8-bit PNG, as a camera writes them): no image names and no lamp indices on the
command line, each shot's lamp from the manifest (also for shots named on the command line); one
cut-off shot is skipped with a warning while its lamp keeps two others. A marks.json made by hand
without `rod_height`: --rod-height fills it in. Truth: the lamps that lit the rendered rods
(Mitsuba's point emitter), and for the hand-made marks the projected true foot and shadow tip.
"""
import hashlib
import json
from dataclasses import asdict

import cv2
import numpy as np
import pytest

from reflab.app.cli import main
from reflab.calibration.camera import Camera
from reflab.calibration.lights import Lights
from reflab.hardware.capture import plan_lights
from reflab.core.images import to_display
from reflab.hardware.sim import props as st

CAM = Camera.look_at(640, 480, 55, eye=[0.0, -0.4, 0.4], target=[0, 0, 0], dist=[-0.1, 0.02, 0, 0, 0])
LAMPS = np.array([[0.25, 0.3, 0.7], [-0.3, 0.35, 0.7]])
FEET = np.array([[0.05, 0.05, 0.0], [-0.1, 0.08, 0.0], [0.0, 0.1, 0.0]])  # one rod placement per angle
ANGLES = [0.0, 90.0, 180.0]
H = 0.2


def snapshot(folder):
    return {str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in folder.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def session_images():
    """File name -> 8-bit sRGB image of the plan of `reflab capture lights` for two lamps."""
    out = {}
    for shot in plan_lights(len(LAMPS), ANGLES, ext="png"):
        foot = FEET[ANGLES.index(shot.angle)]
        on = [k for k, state in enumerate(shot.lamps) if state]
        rod = st.RodScene(foot, H, 0.0015, LAMPS[on[0]] if on else LAMPS[0])
        img = st.render_rod(CAM, rod, intensity=0.3 if on else 0.0, seed=len(out))
        out[shot.file] = to_display(img, exposure=1.0)[:, :, ::-1]
    return out


def write_session(ws, images):
    """What `reflab capture lights` leaves: captures/lights/ with its images and manifest."""
    CAM.save(ws / "camera.json")
    folder = ws / "captures" / "lights"
    folder.mkdir(parents=True)
    for name, img in images.items():
        assert cv2.imwrite(str(folder / name), img)
    plan = [asdict(s) for s in plan_lights(len(LAMPS), ANGLES, ext="png")]
    (folder / "manifest.json").write_text(json.dumps({"kind": "lights", "status": "complete", "plan": plan,
                                                      "shots": plan}))
    return folder


def lamp_errors(ws):
    """Each located lamp's distance from the true one, relative to the true lamp's distance."""
    got = Lights.load(ws / "lights.json").positions
    assert len(got) == len(LAMPS)
    return np.linalg.norm(got - LAMPS, axis=1) / np.linalg.norm(LAMPS, axis=1)


def test_lamps_from_the_lights_session_with_lamp_indices_from_its_manifest(session_images, tmp_path, capsys):
    ws = tmp_path / "ws"
    write_session(ws, session_images)
    before = snapshot(ws)
    assert main(["calibrate", "lights", str(ws), "--rod-height", str(H), "--intensity", "0.3"]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    marks = json.loads((ws / "marks.json").read_text())
    assert marks["rod_height"] == H
    # The single-lamp shots, each with the lamp its manifest says was on (room-light frames are not rod shots).
    assert [(m["image"], m["light"]) for m in marks["marks"]] == [
        (f"captures/lights/{i:04d}.png", k) for a in range(len(ANGLES)) for k, i in ((0, 3 * a), (1, 3 * a + 1))]
    assert np.all(lamp_errors(ws) < 0.01), lamp_errors(ws)  # 3 rods per lamp, ~1 px marks: 0.2 and 0.4 %
    after = snapshot(ws)
    assert {k: v for k, v in after.items() if k in before} == before  # the captures are untouched
    assert sorted(set(after) - set(before)) == ["lights.json", "marks.json"]


def test_a_cut_off_rod_shot_is_skipped_while_its_lamp_has_two_others(session_images, tmp_path, capsys):
    ws = tmp_path / "ws"
    folder = write_session(ws, session_images)
    data = (folder / "0004.png").read_bytes()
    (folder / "0004.png").write_bytes(data[: len(data) // 3])  # lamp 1 at 90 degrees: the card was pulled
    assert main(["calibrate", "lights", str(ws), "--rod-height", str(H), "--intensity", "0.3"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: skipping") and "0004.png" in err[0], err
    marks = json.loads((ws / "marks.json").read_text())["marks"]
    assert len(marks) == 5 and "captures/lights/0004.png" not in [m["image"] for m in marks]
    assert np.all(lamp_errors(ws) < 0.015), lamp_errors(ws)  # lamp 1 from two rods: 0.6 %
    # A second cut-off shot of lamp 1 leaves it one: refused, one line, nothing written.
    for name in ("marks.json", "lights.json"):
        (ws / name).unlink()
    data = (folder / "0001.png").read_bytes()
    (folder / "0001.png").write_bytes(data[: len(data) // 3])
    before = snapshot(ws)
    assert main(["calibrate", "lights", str(ws), "--rod-height", str(H)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "lamp 1" in err[0] and "retake" in err[0], err
    assert snapshot(ws) == before


def test_rod_height_fills_a_marks_json_made_without_it(tmp_path, capsys):
    """Marks clicked by hand before the rod was measured: no session, no rod_height in the file."""
    ws = tmp_path / "ws"
    ws.mkdir()
    CAM.save(ws / "camera.json")
    rng = np.random.default_rng(0)
    feet = np.column_stack([rng.uniform(-0.12, 0.12, 8), rng.uniform(-0.08, 0.08, 8), np.zeros(8)])
    marks = []
    for k, lamp in enumerate(LAMPS):
        tips = np.array([st.RodScene(f, H, 0.0015, lamp).tip for f in feet])
        base, tip = (CAM.project(p) + rng.normal(0, 0.3, (len(p), 2)) for p in (feet, tips))
        marks += [{"image": f"photo{k}{i}.jpg", "light": k, "base": b.tolist(), "tip": t.tolist()}
                  for i, (b, t) in enumerate(zip(base, tip))]
    (ws / "marks.json").write_text(json.dumps({"marks": marks}))
    before = snapshot(ws)
    # Without a height anywhere: one line naming the file, the field and the option; nothing written.
    assert main(["calibrate", "lights", str(ws)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "marks.json" in err[0] and "rod_height" in err[0] and "--rod-height" in err[0], err
    assert snapshot(ws) == before
    # The user's file given with --marks is read, never rewritten.
    assert main(["calibrate", "lights", str(ws), "--marks", str(ws / "marks.json"), "--rod-height", str(H)]) == 0
    assert snapshot(ws)["marks.json"] == before["marks.json"] and (ws / "lights.json").exists()
    assert np.all(lamp_errors(ws) < 0.01), lamp_errors(ws)
    # The workspace's own marks.json (no --marks, no lights session): used as it is, the height filled in.
    assert main(["calibrate", "lights", str(ws), "--rod-height", str(H)]) == 0
    capsys.readouterr()
    obj = json.loads((ws / "marks.json").read_text())
    assert obj["rod_height"] == H and obj["marks"] == marks
    assert np.all(lamp_errors(ws) < 0.01), lamp_errors(ws)


def test_rod_shots_named_on_the_command_line_take_their_lamp_from_the_manifest(session_images, tmp_path,
                                                                               monkeypatch, capsys):
    ws = tmp_path / "ws"
    write_session(ws, session_images)
    monkeypatch.chdir(tmp_path)  # the shots named as a user types them, relative to where they are
    shots = [f"ws/captures/lights/{i:04d}.png" for i in (0, 1, 3, 4, 6, 7)]
    assert main(["calibrate", "lights", "ws", *shots, "--rod-height", str(H)]) == 0
    capsys.readouterr()
    marks = json.loads((ws / "marks.json").read_text())["marks"]
    assert [(m["image"], m["light"]) for m in marks] == [(s[3:], k) for s, k in zip(shots, [0, 1] * 3)]
    assert np.all(lamp_errors(ws) < 0.01), lamp_errors(ws)
