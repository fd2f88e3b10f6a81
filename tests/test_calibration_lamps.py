"""Lamp calibration against known lamps: synthetic marks, Mitsuba-rendered rods, marks.json, bad input.

Synthetic marks are cv2.projectPoints of the true rod foot and shadow tip (the tip from the true
lamp by similar triangles) plus Gaussian noise; rendered images come from Mitsuba's point emitter.
"""
import json
import re

import numpy as np
import pytest

from reflab.app.cli import main
from reflab.calibration.camera import Camera
from reflab.calibration.lamps import Mark, detect_rod_marks, lamp_intensity, locate_lamp, read_marks, write_marks
from reflab.calibration.lights import Lights
from reflab.hardware.sim import props as st
from reflab.core.images import write_image
from reflab.core.workspace import WorkspaceError, write_json

CAM = Camera.look_at(640, 480, 55, eye=[0.0, -0.4, 0.4], target=[0, 0, 0], dist=[-0.1, 0.02, 0, 0, 0])
LAMP = np.array([0.6, 0.3, 0.6])  # oblique: long shadows, where the plain intersection suffers
LAMP_R = np.array([0.25, 0.3, 0.7])  # for rendered rods: shadows stay inside the frame
H = 0.2
CHI2_3DOF_3SIGMA = 14.16  # 99.73% quantile of chi-square with 3 degrees of freedom


def synthetic_marks(seed, n=10, noise=0.5, lamp=LAMP, spread=0.15):
    rng = np.random.default_rng(seed)
    feet = np.column_stack([rng.uniform(-spread, spread, n), rng.uniform(-0.7 * spread, 0.7 * spread, n), np.zeros(n)])
    tips = np.array([st.RodScene(f, H, 0.0015, lamp).tip for f in feet])
    return (CAM.project(feet) + rng.normal(0, noise, (n, 2)), CAM.project(tips) + rng.normal(0, noise, (n, 2)))


def test_lamp_accuracy_and_covariance_over_20_trials():
    dist = np.linalg.norm(LAMP)  # lamp distance from the rods' area (world origin)
    refined, plain, mahal = [], [], []
    for seed in range(20):
        fit = locate_lamp(CAM, *synthetic_marks(seed), H, mark_sigma=0.5)
        e = fit.position - LAMP
        refined.append(np.linalg.norm(e) / dist)
        plain.append(np.linalg.norm(fit.intersection - LAMP) / dist)
        mahal.append(e @ np.linalg.solve(fit.covariance, e))
    assert np.median(refined) < 0.005  # measured 0.32%
    assert np.median(refined) < np.median(plain)  # refinement on the marks beats the plain intersection (0.48%)
    assert max(mahal) < CHI2_3DOF_3SIGMA  # every error inside the reported 3-sigma ellipsoid
    assert 1.0 < np.mean(mahal) < 6.0  # and the covariance is not inflated (expected mean 3)


def test_outlier_mark_is_named_and_left_out():
    base, tip = synthetic_marks(7)
    tip[4] += [25.0, -10.0]
    fit = locate_lamp(CAM, base, tip, H)
    assert fit.outliers == [4]
    assert np.linalg.norm(fit.position - LAMP) / np.linalg.norm(LAMP) < 0.01
    assert np.linalg.norm(fit.residuals[4], axis=1).max() > 10


def test_bad_lamp_inputs():
    base, tip = synthetic_marks(1)
    with pytest.raises(ValueError, match="at least 2"):
        locate_lamp(CAM, base[:1], tip[:1], H)
    with pytest.raises(ValueError, match="rod height"):
        locate_lamp(CAM, base, tip, 0.0)
    sky = tip.copy()
    sky[2] = [320, -2000]  # above the horizon: no ground there
    with pytest.raises(ValueError, match=r"tip\)\[2\].*does not see the ground"):
        locate_lamp(CAM, base, sky, H)


def test_marks_json_round_trip_and_validation(tmp_path):
    marks = [Mark("captures/lights/0000.png", 0, [10.5, 20.0], [30.0, 40.25]),
             Mark("captures/lights/0001.png", 1, [1.0, 2.0], [3.0, 4.0])]
    write_marks(tmp_path / "marks.json", 0.1, marks)
    h, back = read_marks(tmp_path / "marks.json")
    assert h == 0.1 and [m.light for m in back] == [0, 1]
    np.testing.assert_array_equal(back[0].tip, [30.0, 40.25])
    good = json.loads((tmp_path / "marks.json").read_text())
    cases = {"rod_height": ({**good, "rod_height": -1}, "positive"),
             "marks": ({**good, "marks": []}, "non-empty"),
             "marks[1].light": ({**good, "marks": [good["marks"][0], {**good["marks"][1], "light": -2}]}, "lamp index"),
             "marks[0].base": ({**good, "marks": [{**good["marks"][0], "base": [1, 2, 3]}]}, "shape 2"),
             "marks[0].tip": ({**good, "marks": [{k: v for k, v in good["marks"][0].items() if k != "tip"}]}, "this field")}
    for fieldname, (obj, expected) in cases.items():
        write_json(tmp_path / "bad.json", obj)
        with pytest.raises(WorkspaceError, match=f"bad.json: field '{re.escape(fieldname)}'.*{expected}"):
            read_marks(tmp_path / "bad.json")


@pytest.fixture(scope="module")
def rod_images():
    feet = [[0.05, 0.05, 0.0], [-0.1, 0.08, 0.0], [0.12, 0.0, 0.0]]
    rods = [st.RodScene(np.array(f), H, 0.0015, LAMP_R) for f in feet]
    return rods, [st.render_rod(CAM, r, seed=i) for i, r in enumerate(rods)]


def test_auto_detected_marks_agree_with_true_marks(rod_images):
    for rod, img in zip(*rod_images):
        base, tip = detect_rod_marks(img)
        assert np.linalg.norm(base - CAM.project(rod.foot[None])[0]) < 2.0
        assert np.linalg.norm(tip - CAM.project(rod.tip[None])[0]) < 2.0
    with pytest.raises(ValueError, match="rod not found"):
        detect_rod_marks(np.full((48, 64, 3), 0.3, np.float32))


def test_cli_lights_from_images_then_from_marks(tmp_path, rod_images, capsys):
    CAM.save(tmp_path / "camera.json")
    paths = []
    for i, img in enumerate(rod_images[1]):
        paths.append(write_image(tmp_path / "captures" / "lights" / f"{i:04d}.exr", img))
    assert main(["calibrate", "lights", str(tmp_path), *map(str, paths), "--rod-height", "0.2", "--intensity", "0.3"]) == 0
    h, marks = read_marks(tmp_path / "marks.json")
    assert h == 0.2 and [m.image for m in marks] == [f"captures/lights/{i:04d}.exr" for i in range(3)]
    lamp = Lights.load(tmp_path / "lights.json")[0]
    assert np.linalg.norm(lamp.position - LAMP_R) / np.linalg.norm(LAMP_R) < 0.03  # 3 rods, ~1 px marks
    np.testing.assert_allclose(lamp.intensity, 0.3)
    # A user's marks.json with two lamps (synthetic, 0.5 px noise); intensity kept from lights.json.
    lamp2 = np.array([-0.4, 0.5, 0.7])
    marks = [Mark(f"a{i}.png", k, b, t) for k, L in enumerate((LAMP, lamp2))
             for i, (b, t) in enumerate(zip(*synthetic_marks(10 + k, lamp=L)))]
    write_marks(tmp_path / "user_marks.json", H, marks)
    assert main(["calibrate", "lights", str(tmp_path), "--marks", str(tmp_path / "user_marks.json")]) == 0
    lights = Lights.load(tmp_path / "lights.json")
    assert len(lights) == 2 and lights[0].sigma_position is not None
    for got, want in zip(lights.positions, (LAMP, lamp2)):
        assert np.linalg.norm(got - want) / np.linalg.norm(want) < 0.01
    np.testing.assert_allclose(lights[0].intensity, 0.3)
    capsys.readouterr()
    # Lamp indices must run 0..K-1.
    write_marks(tmp_path / "gap.json", H, [Mark(m.image, m.light + 1, m.base, m.tip) for m in marks])
    assert main(["calibrate", "lights", str(tmp_path), "--marks", str(tmp_path / "gap.json")]) == 2
    assert "expected 0..1" in capsys.readouterr().err


def test_lamp_power_from_a_sheet_of_known_reflectance():
    rho, intensity = 0.5, np.array([0.8, 0.6, 0.4])
    img = st.render_lit_ground(CAM, LAMP, intensity, rho)
    est, spread = lamp_intensity(img, CAM, LAMP, rho / np.pi, region=(-0.15, 0.15, -0.1, 0.1))
    np.testing.assert_allclose(est, intensity, rtol=0.02)
    assert np.all(spread < 0.05)
    with pytest.raises(ValueError, match="kd must be positive"):
        lamp_intensity(img, CAM, LAMP, 0.0)
