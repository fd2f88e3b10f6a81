"""The simulated lab: the set docs/method.md §5 describes, written as a valid workspace."""
import numpy as np
import pytest

from reflab.calibration.camera import Camera
from reflab.calibration.lights import Lights
from reflab.hardware.sim.reference import render_reference
from reflab.hardware.sim.lab import A4, ALBEDO_RANGE, build_lab, write_lab
from reflab.reconstruction.scene import Scene


@pytest.fixture(scope="module")
def lab():
    return build_lab()


def test_camera_looks_down_at_45_degrees_from_60_cm(lab):
    cam = lab.camera
    assert (cam.width, cam.height) == (640, 480)
    assert cam.dist[0] == pytest.approx(-0.05)
    centre = cam.center
    assert 0.5 < np.linalg.norm(centre) < 0.7
    forward = cam.R[2]  # camera z axis in world coordinates
    assert np.degrees(np.arcsin(-forward[2])) == pytest.approx(45, abs=5)
    # The A4 sheet's corners are in the image.
    corners = np.array([[sx * A4[0] / 2, sy * A4[1] / 2, 0] for sx in (-1, 1) for sy in (-1, 1)])
    uv = cam.project(corners)
    assert np.all((uv >= 0) & (uv < [640, 480]))
    # Smaller sizes keep the field of view: a world point lands on the same relative position.
    small = build_lab(160, 120).camera
    uv_small = small.project(corners)
    np.testing.assert_allclose((uv_small + 0.5) * 4, uv + 0.5, atol=1e-6)


def test_surfaces_and_materials(lab):
    s = {x.name: x for x in lab.scene}
    assert list(s) == ["ground", "box", "sheet", "mirror", "tile"]
    assert s["sheet"].material.ior == 1.46 and not s["sheet"].textured and s["sheet"].mesh.is_closed()
    assert np.all(s["sheet"].material["t"] > 0)
    assert s["mirror"].material.ior is None and np.allclose(s["mirror"].material["r"], 0.85)
    assert s["box"].mesh.is_closed() and s["tile"].mesh.is_closed()
    for name in ("box", "tile"):
        assert s[name].material.brdf == "phong" and s[name].material["ks"].max() > 0.1
    # Lamps 0.5-0.7 m from the scene's centre.
    d = np.linalg.norm(lab.lights.positions - [0, 0, 0.03], axis=1)
    assert np.all((d > 0.5) & (d < 0.75))
    # Sheet thickness 3 mm: its box's smallest extent along its own normal.
    v = s["sheet"].mesh.vertices
    extent = np.linalg.svd(v - v.mean(0), compute_uv=False)
    assert extent.min() == pytest.approx(0.003 * np.sqrt(8) / 2, rel=1e-6)


def test_albedo_is_smooth_detailed_and_in_range(lab):
    rng = np.random.default_rng(1)
    for i, surf in enumerate(lab.scene):
        v = surf.mesh.vertices
        pts = v.min(0) + rng.random((5000, 3)) * (v.max(0) - v.min(0))
        alb = lab.albedo(i, pts)
        assert alb.shape == (5000, 3) and np.all(np.isfinite(alb))
        if surf.textured:
            assert np.all((alb >= ALBEDO_RANGE[0]) & (alb <= ALBEDO_RANGE[1]))
            assert alb.std(axis=0).max() > 0.05  # detailed
            # smooth: 0.2 mm apart, albedo changes little (bounded gradient)
            step = lab.albedo(i, pts + [2e-4, 0, 0]) - alb
            assert np.abs(step).max() < 0.1
            # kd in the scene is the texture's mean
            assert np.all(np.abs(surf.material["kd"] - alb.mean(0)) < 0.1)
        else:
            np.testing.assert_array_equal(alb, np.broadcast_to(surf.material["kd"], alb.shape))
    flat = lab.homogeneous()
    np.testing.assert_array_equal(flat.albedo(0, np.zeros((3, 3))), np.tile(lab.scene[0].material["kd"], (3, 1)))
    vec = lab.albedo_at(np.array([0, 1, 4]), np.zeros((3, 3)))
    np.testing.assert_allclose(vec[1], lab.albedo(1, np.zeros((1, 3)))[0])


def test_write_lab_round_trips(tmp_path, lab):
    small = build_lab(80, 60)
    written = write_lab(tmp_path / "ws", small)
    assert {"camera", "lights", "scene", "ground", "sheet"} <= set(written)
    cam = Camera.load(tmp_path / "ws" / "camera.json")
    np.testing.assert_allclose(cam.K, small.camera.K)
    np.testing.assert_allclose(Lights.load(tmp_path / "ws" / "lights.json").positions, small.lights.positions)
    scene = Scene.load(tmp_path / "ws" / "scene.json")
    assert scene.names == small.scene.names
    for a, b in zip(scene, small.scene):
        np.testing.assert_allclose(a.mesh.vertices, b.mesh.vertices, atol=1e-12)
        assert a.material.to_json() == b.material.to_json()
        assert a.textured == b.textured


def test_image_peak_and_lamp_power():
    lab = build_lab(80, 60)
    stats = {}
    img = render_reference(lab.scene, lab.camera, lab.lights, depth=3, albedo=lab.albedo, stats=stats)
    assert 0.5 < np.percentile(img, 99.9) < 1.0
    assert stats["nodes_per_level"][0] == 80 * 60  # the view is filled: every primary ray hits
    with pytest.raises(ValueError, match="2x2"):
        build_lab(1, 1)
