"""The proof: the forward model (reflab.inverse.forward.trees + reflab.inverse.forward.rendering) agrees with the independent
reference renderer (reflab.hardware.sim.reference, Mitsuba ray casting) on the simulated lab, where mirror
reflection, refraction through the sheet and total internal reflection all occur.
"""
import numpy as np
import pytest

from reflab.hardware.sim.reference import render_reference
from reflab.hardware.sim.lab import build_lab
from reflab.inverse.forward.rendering import render
from reflab.inverse.forward.trees import build_trees


def _rel_rms(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b**2)))


@pytest.fixture(scope="module")
def small():
    lab = build_lab(160, 120)
    return lab, build_trees(lab.scene, lab.camera, lab.lights, depth=3)


@pytest.mark.parametrize("size", [(160, 120), (320, 240)])
def test_forward_model_matches_reference_homogeneous(size):
    lab = build_lab(*size, textured=False)
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    ours = render(trees, [s.material for s in lab.scene], lab.lights.intensities)
    stats = {}
    ref = render_reference(lab.scene, lab.camera, lab.lights, depth=3, stats=stats)
    assert ref.max() > 0.3
    assert _rel_rms(ours, ref) < 0.01
    # Disagreement is confined to a handful of pixels on silhouettes (float32 ray casting).
    assert np.mean(np.abs(ours - ref).max(axis=2) > 1e-3) < 0.001
    # Both renderers met the same ideal interactions (up to rays grazing an edge).
    assert trees.stats["total_internal_reflections"] == pytest.approx(stats["tir"], rel=0.05)
    assert trees.stats["rays"]["refraction"] == pytest.approx(stats["refractions"], rel=0.01)
    assert stats["tir"] >= 20 and stats["refractions"] >= 1000


def test_forward_model_matches_reference_textured(small):
    lab, trees = small
    kd_nodes = lab.albedo_at(trees.surface, trees.point)
    ours = render(trees, [s.material for s in lab.scene], lab.lights.intensities, kd_nodes=kd_nodes)
    ref = render_reference(lab.scene, lab.camera, lab.lights, depth=3, albedo=lab.albedo)
    assert _rel_rms(ours, ref) < 0.01
    # The textured image is not the homogeneous one: the texture is really in both.
    flat = render(trees, [s.material for s in lab.scene], lab.lights.intensities)
    assert _rel_rms(flat, ref) > 0.05


def test_lab_exercises_mirror_sheet_highlights_and_shadows(small):
    lab, trees = small
    names = lab.scene.names
    box, sheet, mirror, tile = (names.index(n) for n in ("box", "sheet", "mirror", "tile"))
    paths = trees.paths
    via_mirror = np.array([any(s == mirror and k == 0 for s, k in p) for p in paths])[trees.path]
    through_sheet = np.array([any(s == sheet and k == 1 for s, k in p) for p in paths])[trees.path]
    # The box's back face (outward normal = the box's +y axis) is seen only in the mirror.
    back = lab.textures[box].frame[:, 1]
    on_back = (trees.surface == box) & (trees.normal @ back > 0.99)
    assert not np.any(on_back & (trees.level == 1))
    assert np.count_nonzero(on_back & via_mirror) >= 5
    # The sheet covers part of the textured box and ground.
    assert np.count_nonzero(through_sheet & (trees.surface == box)) >= 20
    # Highlights: the specular term alone reaches a good part of the brightest pixels on the tile.
    mats = [s.material for s in lab.scene]
    matte = [m.copy() for m in mats]
    for m in matte:
        if "ks" in m.params:
            m.params["ks"] = np.zeros(3)
    spec = render(trees, mats, lab.lights.intensities) - render(trees, matte, lab.lights.intensities)
    tile_pix = np.zeros(trees.width * trees.height, bool)
    tile_pix[trees.pixel[(trees.surface == tile) & (trees.level == 1)]] = True
    assert spec.reshape(-1, 3)[tile_pix].max() > 0.15
    # Shadows: a part of the directly seen ground misses one lamp or both.
    ground = (trees.surface == names.index("ground")) & (trees.level == 1)
    assert 0.03 < np.mean(~trees.visible[ground].all(axis=1)) < 0.6


def test_forward_model_matches_reference_ward_and_oren_nayar():
    from reflab.reconstruction.scene import Material

    lab = build_lab(120, 90)
    box, ground = lab.scene[lab.scene.index("box")], lab.scene[lab.scene.index("ground")]
    box.material = Material("ward", {"kd": box.material["kd"], "ks": np.full(3, 0.3), "alpha": np.float64(0.15),
                                     "r": np.full(3, 0.04), "t": np.zeros(3)})
    ground.material = Material("oren-nayar", {"kd": ground.material["kd"], "sigma": np.float64(0.4),
                                              "r": np.zeros(3), "t": np.zeros(3)})
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    ours = render(trees, [s.material for s in lab.scene], lab.lights.intensities)
    ref = render_reference(lab.scene, lab.camera, lab.lights, depth=3)
    assert _rel_rms(ours, ref) < 0.01
    # The models matter: Lambert in their place gives another image.
    plain = [s.material.copy() for s in lab.scene]
    for m in plain:
        if m.brdf in ("ward", "oren-nayar"):
            m.brdf = "lambert"
    assert _rel_rms(render(trees, plain, lab.lights.intensities), ref) > 0.02
