"""`reflab render` end to end on a small simulated-lab workspace, checked against the independent
reference renderer (hardware/sim/reference.py) with the same materials, lights, camera and texture."""
import numpy as np
import pytest

from reflab.app.cli import main
from reflab.calibration.lights import Lights
from reflab.core.images import read_image, write_image
from reflab.hardware.sim.reference import render_reference
from reflab.hardware.sim.lab import build_lab, write_lab
from reflab.core.workspace import write_json
from reflab.inverse.forward.trees import build_trees
from reflab.reconstruction.scene import Scene


def _rel_rms(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b**2)))


def _read_with_nan(path):
    """An EXR that may hold NaN (albedo AOV: unknown), which read_image rightly refuses."""
    from reflab.core.images import read_exr

    return read_exr(path)[:, :, :3]


@pytest.fixture()
def ws(tmp_path):
    lab = build_lab(80, 60)
    write_lab(tmp_path / "ws", lab)
    return tmp_path / "ws", lab


def test_render_scene_materials_matches_reference(ws, capsys):
    root, lab = ws
    assert main(["render", str(root)]) == 0
    out = capsys.readouterr().out
    assert "render.exr" in out and "scene.json" in out
    img = read_image(root / "render.exr")
    assert img.shape == (60, 80, 3) and (root / "render.png").exists()
    scene = Scene.load(root / "scene.json")
    ref = render_reference(scene, lab.camera, lab.lights)
    assert _rel_rms(img, ref) < 0.01


def test_render_uses_fit_json_new_lights_and_camera(ws, tmp_path):
    root, lab = ws
    scene = Scene.load(root / "scene.json")
    fitted = [s.material.copy() for s in scene]
    tile = scene.index("tile")
    fitted[tile].params["kd"] = np.array([0.1, 0.6, 0.2])
    fitted[tile].params["ns"] = np.float64(10.0)
    write_json(root / "fit.json", {"method": "ftbo", "depth": 3,
                                   "surfaces": [{"name": s.name, "material": m.to_json()} for s, m in zip(scene, fitted)]})
    lights = Lights([type(l)(l.position + [0.05, 0, 0.1], l.intensity * [2.0, 1.0, 0.5]) for l in lab.lights])
    lights.save(tmp_path / "L.json")
    camera = build_lab(64, 48).camera
    camera.save(tmp_path / "C.json")
    out = tmp_path / "novel.exr"
    assert main(["render", str(root), "-o", str(out), "--lights", str(tmp_path / "L.json"),
                 "--camera", str(tmp_path / "C.json")]) == 0
    img = read_image(out)
    assert img.shape == (48, 64, 3)
    for s, m in zip(scene, fitted):
        s.material = m
    ref = render_reference(scene, camera, lights)
    assert _rel_rms(img, ref) < 0.01
    before = render_reference(Scene.load(root / "scene.json"), camera, lights)
    assert _rel_rms(before, ref) > 0.02  # the fitted tile really changed the image


def test_render_uses_texture_stage_albedo(ws, capsys):
    root, lab = ws
    photo = render_reference(lab.scene, lab.camera, lab.lights, albedo=lab.albedo)
    write_image(root / "input.exr", photo)
    assert main(["render", str(root), "-o", str(root / "flat.exr")]) == 0  # one kd per surface
    assert main(["texture", str(root)]) == 0
    assert main(["render", str(root), "-o", str(root / "tex.exr")]) == 0
    assert "unknown" in capsys.readouterr().out
    # 80x60 texels are coarse against the procedural texture: 3.9% measured, against 20%+ flat.
    flat, tex = _rel_rms(read_image(root / "flat.exr"), photo), _rel_rms(read_image(root / "tex.exr"), photo)
    assert tex < 0.06 and tex < 0.5 * flat
    # The albedo AOV: recovered values where the texture stage saw the point, NaN elsewhere.
    assert main(["render", str(root), "--aov", "albedo"]) == 0
    alb = _read_with_nan(root / "albedo.exr").reshape(-1, 3)
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=1)
    true = np.full((60 * 80, 3), np.nan)
    true[trees.pixel] = lab.albedo_at(trees.surface, trees.point)
    known = np.isfinite(alb).all(axis=1)
    assert 0 < (~known).sum() < 0.1 * len(known)
    assert np.sqrt(np.mean((alb[known] - true[known]) ** 2)) < 0.03


def test_render_albedo_aov_without_textures(ws):
    root, lab = ws
    assert main(["render", str(root), "--aov", "albedo", "-o", str(root / "a.exr")]) == 0
    alb = read_image(root / "a.exr").reshape(-1, 3)
    kds = np.array([s.material["kd"] for s in lab.scene], dtype=np.float32)
    # every pixel sees some surface directly, and shows exactly that surface's kd
    match = np.isclose(alb[:, None, :], kds[None], atol=1e-6).all(axis=2)
    assert np.all(match.any(axis=1))
    assert match[:, lab.scene.index("tile")].sum() > 50


def test_render_missing_scene_names_the_file(tmp_path, capsys):
    build_lab(16, 12).camera.save(tmp_path / "camera.json")
    build_lab(16, 12).lights.save(tmp_path / "lights.json")
    assert main(["render", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "scene.json" in err and "reflab reconstruct" in err


def test_render_bad_fit_json_names_file_and_field(ws, capsys):
    root, lab = ws
    write_json(root / "fit.json", {"surfaces": [{"name": "table", "material": {"brdf": "lambert", "ior": None}}]})
    assert main(["render", str(root)]) == 2
    err = capsys.readouterr().err
    assert "fit.json" in err and "surfaces[0].name" in err and "table" in err
    write_json(root / "fit.json", {"surfaces": [{"name": "tile", "material": {"brdf": "phong", "kd": [0.5, -1, 0], "ior": None}}]})
    assert main(["render", str(root)]) == 2
    assert "surfaces[0].material.kd" in capsys.readouterr().err
