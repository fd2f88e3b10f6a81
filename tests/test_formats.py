"""Workspace formats: round trips and validation messages that name the file, field and expectation."""
import json

import numpy as np
import pytest

from reflab.calibration.camera import Camera
from reflab.calibration.lights import Lights
from reflab.core.images import read_image, write_image
from reflab.core.workspace import WorkspaceError, write_json
from reflab.reconstruction.scene import INITIAL, Mesh, Scene


def _camera_json():
    return {"width": 64, "height": 48, "K": [[50, 0, 31.5], [0, 50, 23.5], [0, 0, 1]],
            "dist": [-0.1, 0.01, 0, 0, 0], "R": np.eye(3).tolist(), "t": [0, 0, 1]}


def _box(size=(1, 1, 1)):
    sx, sy, sz = size
    v = np.array([[x, y, z] for x in (0, sx) for y in (0, sy) for z in (0, sz)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tri = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    return Mesh(v, tri)


def _plane():
    return Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])


def test_camera_round_trip_and_rays(tmp_path):
    cam = Camera.from_json(_camera_json())
    cam.save(tmp_path / "camera.json")
    back = Camera.load(tmp_path / "camera.json")
    np.testing.assert_allclose(back.K, cam.K)
    np.testing.assert_allclose(back.dist, cam.dist)
    # A ray through a pixel, re-projected with distortion, lands on that pixel.
    uv = np.array([[0.0, 0.0], [63.0, 47.0], [10.3, 30.7]])
    o, d = back.rays(uv)
    np.testing.assert_allclose(back.project(o + 2.0 * d), uv, atol=1e-6)
    o, d = back.pixel_rays()
    assert o.shape == (64 * 48, 3) and np.allclose(np.linalg.norm(d, axis=1), 1)
    np.testing.assert_allclose(back.center, [0, 0, -1])


def test_camera_scaled_keeps_field_of_view():
    cam = Camera.from_json(_camera_json())
    small = cam.scaled(32, 24)
    # The image corners map to the same rays (pixel-centre convention: corner = -0.5).
    corner_big = np.linalg.solve(cam.K, [-0.5, -0.5, 1])
    corner_small = np.linalg.solve(small.K, [-0.5, -0.5, 1])
    np.testing.assert_allclose(corner_big, corner_small)


@pytest.mark.parametrize("edit, field, expected", [
    (lambda o: o.pop("K"), "'K'", "this field"),
    (lambda o: o.__setitem__("K", [[1, 0], [0, 1]]), "'K'", "shape 3x3"),
    (lambda o: o.__setitem__("t", [0, float("nan"), 1]), "'t'", "finite"),
    (lambda o: o.__setitem__("R", (2 * np.eye(3)).tolist()), "'R'", "rotation"),
    (lambda o: o.__setitem__("width", -3), "'width'", "positive integer"),
])
def test_camera_validation_names_field(tmp_path, edit, field, expected):
    obj = _camera_json()
    edit(obj)
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(obj).replace("NaN", "NaN"))
    with pytest.raises(WorkspaceError) as err:
        Camera.load(path)
    msg = str(err.value)
    assert str(path) in msg and field in msg and expected in msg


def test_lights_validation(tmp_path):
    path = tmp_path / "lights.json"
    write_json(path, {"lights": [{"type": "point", "position": [0, 0, 1], "intensity": [1, 2, 3]}]})
    lights = Lights.load(path)
    np.testing.assert_allclose(lights.intensities, [[1, 2, 3]])
    write_json(path, {"lights": [{"type": "point", "position": [0, 0, 1], "intensity": [1, -2, 3]}]})
    with pytest.raises(WorkspaceError, match=r"lights\[0\]\.intensity.*non-negative"):
        Lights.load(path)
    write_json(path, {"lights": [{"position": [0, 1]}]})
    with pytest.raises(WorkspaceError, match=r"lights\[0\]\.intensity.*this field"):
        Lights.load(path)


def _write_scene(root, surfaces):
    write_json(root / "scene.json", {"surfaces": surfaces})
    return root / "scene.json"


def test_scene_round_trip_and_defaults(tmp_path):
    (tmp_path / "meshes").mkdir()
    _plane().save(tmp_path / "meshes/floor.ply")
    _box((0.1, 0.1, 0.002)).save(tmp_path / "meshes/sheet.ply")
    path = _write_scene(tmp_path, [
        {"name": "floor", "mesh": "meshes/floor.ply", "material": {"brdf": "phong", "kd": [0.5, 0.4, 0.3], "ior": None}},
        {"name": "sheet", "mesh": "meshes/sheet.ply", "textured": False, "material": {"brdf": "lambert", "ior": 1.46}},
    ])
    scene = Scene.load(path)
    floor, sheet = scene.surfaces
    np.testing.assert_allclose(floor.material["kd"], [0.5, 0.4, 0.3])
    assert floor.material["ns"] == pytest.approx(INITIAL["ns"]) and "ns" in floor.material.defaulted
    np.testing.assert_allclose(floor.material["t"], 0)  # opaque: nothing transmitted
    assert sheet.material.transparent and sheet.mesh.is_closed() and not floor.mesh.is_closed()
    scene.save(tmp_path / "scene2.json", write_meshes=False)
    again = Scene.load(tmp_path / "scene2.json")
    assert again.names == ["floor", "sheet"] and again[1].textured is False
    # a value scene.json did not give stays absent on saving: the fit holds given values only
    assert again[0].material.defaulted == floor.material.defaulted and "kd" not in again[0].material.defaulted
    assert again[1].material.defaulted == sheet.material.defaulted


@pytest.mark.parametrize("surface, field, expected", [
    ({"name": "a", "mesh": "meshes/missing.ply", "material": {"brdf": "phong", "ior": None}}, "surfaces[0].mesh", "existing mesh file"),
    ({"name": "a", "mesh": "meshes/plane.ply", "material": {"brdf": "phong", "ior": 1.5}}, "surfaces[0].mesh", "closed mesh"),
    ({"name": "a", "mesh": "meshes/plane.ply", "material": {"brdf": "blinn", "ior": None}}, "surfaces[0].material.brdf", "one of"),
    ({"name": "a", "mesh": "meshes/plane.ply", "material": {"brdf": "phong"}}, "surfaces[0].material.ior", "null (opaque)"),
    ({"name": "a", "mesh": "meshes/plane.ply", "material": {"brdf": "phong", "ior": None, "kd": [0.1, -1, 0]}}, "surfaces[0].material.kd", "non-negative"),
    ({"name": "a", "mesh": "meshes/plane.ply", "material": {"brdf": "phong", "ior": None, "r": [2, 0, 0]}}, "surfaces[0].material.r", "[0, 1]"),
    ({"name": "a", "material": {"brdf": "phong", "ior": None}}, "surfaces[0].mesh", "mesh path"),
])
def test_scene_validation_names_field(tmp_path, surface, field, expected):
    (tmp_path / "meshes").mkdir()
    _plane().save(tmp_path / "meshes/plane.ply")
    path = _write_scene(tmp_path, [surface])
    with pytest.raises(WorkspaceError) as err:
        Scene.load(path)
    msg = str(err.value)
    assert str(path) in msg and field in msg and expected in msg


def test_images_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 2, (6, 8, 3)).astype(np.float32)
    img[0, 0] = [1.0, 0.0, 0.0]  # red stays red: RGB order is preserved
    write_image(tmp_path / "a.exr", img)
    np.testing.assert_array_equal(read_image(tmp_path / "a.exr"), img)
    write_image(tmp_path / "a.png", np.clip(img, 0, 1))
    np.testing.assert_allclose(read_image(tmp_path / "a.png"), np.clip(img, 0, 1), atol=1 / 65535)
    with pytest.raises(ValueError, match="NaN"):
        write_image(tmp_path / "b.exr", np.full((2, 2, 3), np.nan))
    assert not (tmp_path / "b.exr").exists() and not list(tmp_path.glob(".b*"))


def test_write_json_is_atomic_and_refuses_nan(tmp_path):
    path = tmp_path / "fit.json"
    write_json(path, {"rms": [0.1, 0.2, 0.3]})
    with pytest.raises(ValueError):
        write_json(path, {"rms": [float("nan")]})
    assert json.loads(path.read_text()) == {"rms": [0.1, 0.2, 0.3]}  # the old file survives
    assert [p.name for p in tmp_path.iterdir()] == ["fit.json"]


def test_cli_help_is_light():
    import subprocess
    import sys

    code = ("import sys, reflab.app.cli; reflab.app.cli.build_parser();"
            "heavy = [m for m in ('mitsuba', 'open3d', 'pycolmap', 'PySide6', 'cv2', 'scipy', 'matplotlib', 'jinja2') if m in sys.modules];"
            "print(heavy); sys.exit(bool(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
