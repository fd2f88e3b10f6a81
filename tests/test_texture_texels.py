"""Texel parameterization: planar charts, UV atlas, bilinear weights, footprints, index round trip."""
import numpy as np
import pytest

from reflab.calibration.camera import Camera
from reflab.hardware.sim.lab import box_mesh, plane_mesh
from reflab.inverse.texture.texels import PAD, TexelMap, bilinear_weights, build_texel_map, choose_texel_size, pixel_footprint
from reflab.reconstruction.scene import Mesh


def _random_surface_points(mesh, n, seed=0):
    rng = np.random.default_rng(seed)
    tri = rng.integers(0, len(mesh.triangles), n)
    bary = rng.dirichlet([1, 1, 1], n)
    pts = np.einsum("nk,nkx->nx", bary, mesh.vertices[mesh.triangles[tri]])
    return tri, bary, pts


def _rot_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def test_box_charts_reproduce_a_linear_albedo_exactly():
    # Bilinear interpolation is exact for a function linear in the surface coordinates, so texel
    # values set from the texel centres' world positions must give the function back anywhere.
    mesh = box_mesh((0.10, 0.07, 0.06), (-0.07, 0.03, 0.03), _rot_z(12.0))
    tm = build_texel_map(1, "box", mesh, 0.002)
    assert tm.kind == "planar" and len(tm.charts) == 6
    idx, centres = tm.texel_centers()
    assert len(np.unique(idx)) == len(idx), "charts overlap in the atlas"
    assert idx.min() >= 0 and idx.max() < tm.n_texels
    a, c = np.array([3.0, -2.0, 5.0]), 0.4
    values = np.zeros(tm.n_texels)
    values[idx] = centres @ a + c
    tri, bary, pts = _random_surface_points(mesh, 2000)
    index, weight = tm.bilinear(tri, bary[:, 1:])
    np.testing.assert_allclose(weight.sum(1), 1.0, atol=1e-12)
    assert np.all(weight >= 0)
    assert np.all(np.isin(index[weight > 0], idx)), "a bilinear footprint reaches outside its chart"
    np.testing.assert_allclose((weight * values[index]).sum(1), pts @ a + c, atol=1e-9)
    # Texel spacing is the requested size: neighbours along a chart's column axis are 2 mm apart.
    ch = tm.charts[0]
    np.testing.assert_allclose(np.linalg.norm(ch.axis_u), 1.0)
    assert abs(ch.axis_u @ ch.axis_v) < 1e-12


def test_cropped_charts_hold_their_region_on_the_same_lattice():
    # The fit's texture rounds crop each chart to what the trees see: a corner of a box, nothing of
    # some faces. Every region point's bilinear footprint stays in its own chart's block, reading
    # the same linear albedo exactly, and the texel centres are the uncropped map's.
    mesh = box_mesh((0.10, 0.07, 0.06), (-0.07, 0.03, 0.03), _rot_z(12.0))
    tri, bary, pts = _random_surface_points(mesh, 4000, seed=3)
    near = np.linalg.norm(pts - mesh.vertices[0], axis=1) < 0.04
    full = build_texel_map(1, "box", mesh, 0.002)
    crop = build_texel_map(1, "box", mesh, 0.002, region=(tri[near], pts[near]))
    assert crop.n_texels < full.n_texels / 3
    _, centres_full = full.texel_centers()
    idx, centres = crop.texel_centers()
    assert len(np.unique(idx)) == len(idx) and idx.max() < crop.n_texels
    a, c = np.array([3.0, -2.0, 5.0]), 0.4
    values = np.zeros(crop.n_texels)
    values[idx] = centres @ a + c
    index, weight = crop.bilinear(tri[near], bary[near, 1:])
    assert np.all(np.isin(index[weight > 0], idx)), "a region point reads outside its chart"
    np.testing.assert_allclose((weight * values[index]).sum(1), pts[near] @ a + c, atol=1e-9)
    # Same lattice: every cropped texel centre is one of the full map's.
    from scipy.spatial import cKDTree

    assert cKDTree(centres_full).query(centres)[0].max() < 1e-9


def test_box_face_chart_is_the_minimum_rectangle():
    # A 10 cm x 6 cm face rotated in the plane: its chart must be aligned with its edges.
    mesh = box_mesh((0.10, 0.06, 0.001), (0, 0, 0), _rot_z(33.0))
    tm = build_texel_map(0, "slab", mesh, 0.001)
    big = max(tm.charts, key=lambda c: c.shape[0] * c.shape[1])
    assert sorted(big.shape) == sorted((60 + 1 + 2 * PAD, 100 + 1 + 2 * PAD))


def test_uv_atlas_for_a_curved_mesh():
    import open3d as o3d

    sphere = o3d.geometry.TriangleMesh.create_sphere(0.05, 16)
    mesh = Mesh(np.asarray(sphere.vertices), np.asarray(sphere.triangles))
    tm = build_texel_map(0, "ball", mesh, 0.002)
    assert tm.kind == "uvatlas"
    assert np.all(tm.tri_uv >= -0.5) and np.all(tm.tri_uv <= tm.width - 0.5)
    # Edge lengths in texels against metres / texel size: a stretch-bounded atlas stays near 1.
    v = mesh.vertices[mesh.triangles]
    metres = np.linalg.norm(v[:, 1] - v[:, 0], axis=1)
    texels = np.linalg.norm(tm.tri_uv[:, 1] - tm.tri_uv[:, 0], axis=1)
    ratio = np.median(texels * tm.texel_size / metres)
    assert 0.6 < ratio < 1.6
    tri, bary, pts = _random_surface_points(mesh, 500)
    np.testing.assert_allclose(tm.texel_coords(pts), tm.coords_at(tri, bary[:, 1:]), atol=1e-6)


def test_bilinear_weights_clamp_to_the_atlas():
    idx, w = bilinear_weights(np.array([[-3.0, 2.5], [9.7, 99.0]]), 10, 5)
    assert idx.min() >= 0 and idx.max() < 50
    np.testing.assert_allclose(w.sum(1), 1.0)


def test_footprint_of_a_plane_seen_from_above():
    # Camera 0.5 m above the ground looking straight down: footprint = height / focal length.
    cam = Camera.look_at(80, 60, 40.0, eye=(0, 0, 0.5), target=(0, 0, 0), up=(0, 1, 0))
    o, d = cam.pixel_rays()
    t = -o[:, 2] / d[:, 2]
    pts = o + t[:, None] * d
    fp = pixel_footprint(np.arange(len(pts)), np.zeros(len(pts), np.int64), pts, cam.width)
    centre = (30 * 80 + 40)
    assert fp[centre] == pytest.approx(0.5 / cam.K[0, 0], rel=1e-3)
    assert np.isnan(fp[-1])  # the last pixel has no right or lower neighbour
    assert choose_texel_size(fp, 2.0, 0.0) == pytest.approx(2 * np.nanmin(fp))
    assert choose_texel_size(np.full(3, np.nan)) is None


def test_footprint_of_an_oblique_plane_is_the_square_root_of_the_pixel_area():
    # 45° view of the ground from 0.707 m: a pixel covers D/f across and D/(f cos 45°) along the
    # slope, so sqrt(area) = D / (f sqrt(cos 45°)); the shorter side alone would be D/f.
    cam = Camera.look_at(81, 61, 40.0, eye=(0, -0.5, 0.5), target=(0, 0, 0), up=(0, 0, 1))
    o, d = cam.pixel_rays()
    pts = o + (-o[:, 2] / d[:, 2])[:, None] * d
    fp = pixel_footprint(np.arange(len(pts)), np.zeros(len(pts), np.int64), pts, cam.width)
    D = np.sqrt(0.5)
    assert fp[30 * 81 + 40] == pytest.approx(D / (cam.K[0, 0] * np.sqrt(np.cos(np.radians(45)))), rel=0.01)
    # Nodes of different paths never pair up (odd width: right and lower neighbours alternate).
    assert np.all(np.isnan(pixel_footprint(np.arange(len(pts)), np.arange(len(pts)) % 2, pts, cam.width)))


def test_index_entry_round_trip(tmp_path):
    mesh = box_mesh((0.12, 0.12, 0.008), (0.11, -0.06, 0.004), _rot_z(20.0))
    tm = build_texel_map(4, "tile", mesh, 0.0015)
    back = TexelMap.from_json(tm.to_json(), 4, mesh, tmp_path / "index.json", "surfaces[0]")
    np.testing.assert_allclose(back.tri_uv, tm.tri_uv, atol=1e-9)
    assert (back.width, back.height) == (tm.width, tm.height)
    other = plane_mesh((0, 1), (0, 1))
    from reflab.core.workspace import WorkspaceError

    with pytest.raises(WorkspaceError, match="triangles"):
        TexelMap.from_json(tm.to_json(), 4, other, tmp_path / "index.json", "surfaces[0]")
    with pytest.raises(ValueError, match="texel size"):
        build_texel_map(0, "x", mesh, float("nan"))
