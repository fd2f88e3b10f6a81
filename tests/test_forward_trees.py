"""Trees + renderer against closed-form images: each expected pixel comes from an analytic ray-plane
intersection, Snell's law with angles and eq. 2.3 computed here, never from inverse/."""
import numpy as np
import pytest

from reflab.calibration.camera import Camera
from reflab.calibration.lights import Lights, PointLight
from reflab.core.workspace import WorkspaceError
from reflab.inverse.forward.rendering import linear_basis_and_grad, node_parameters, render, render_albedo
from reflab.inverse.forward.trees import REFLECTION, TRANSMISSION, Trees, build_trees
from reflab.reconstruction.scene import Material, Mesh, Scene, Surface

W, H = 40, 30


def material(brdf="phong", ior=None, **params):
    return Material.from_json(dict(brdf=brdf, ior=ior, **params), "test", "material")


def quad(corner, e1, e2):
    c, e1, e2 = (np.asarray(a, dtype=float) for a in (corner, e1, e2))
    return Mesh([c, c + e1, c + e1 + e2, c + e2], [[0, 1, 2], [0, 2, 3]])


def box(lo, hi):
    """Closed axis-aligned box with outward winding."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return Mesh(v, [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def scene(*surfaces):
    return Scene([Surface(f"s{i}", f"meshes/s{i}.ply", m, True, mesh) for i, (mesh, m) in enumerate(surfaces)])


def camera_rays(cam):
    """Pixel-centre rays from K, R, t directly (no distortion)."""
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    d = np.linalg.solve(cam.K, pix.T).T @ cam.R
    return -cam.R.T @ cam.t, d / np.linalg.norm(d, axis=1, keepdims=True)


def phong_radiance(p, n, v, light, intensity, kd, ks, ns):
    """kd (n·l) + ks (n·h)^ns times intensity / d², per band (p, v: (M, 3); n: (3,))."""
    to_l = light - p
    d2 = np.sum(to_l**2, axis=1)
    l = to_l / np.sqrt(d2)[:, None]
    h = l + v
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    nl = l @ n
    with np.errstate(under="ignore"):
        spec = np.power(np.clip(h @ n, 0, 1), ns)
    rad = (np.outer(nl, kd) + np.outer(spec, ks)) * np.asarray(intensity) / d2[:, None]
    return np.where((nl > 0)[:, None], rad, 0.0)


def plane_hits(o, d, z=0.0):
    t = (z - np.asarray(o)[..., 2]) / d[:, 2]
    return t, o + t[:, None] * d


KD, KS = np.array([0.6, 0.5, 0.3]), np.array([0.2, 0.3, 0.25])
INTENSITY = np.array([1.0, 0.8, 0.6])


@pytest.mark.parametrize("case", ["ns1", "ns2^14", "grazing", "lamp_1mm"])
def test_single_plane_matches_closed_form(case):
    ns = {"ns1": 1.0, "ns2^14": 2.0**14}.get(case, 30.0)
    eye, target, light, half = (0.3, -0.8, 0.9), (0.0, 0.0, 0.0), np.array([0.2, 0.1, 0.5]), 0.4
    if case == "grazing":
        eye, target, half = (0.0, -3.0, 0.02), (0.0, 3.0, 0.0), 5.0
    if case == "lamp_1mm":
        light = np.array([0.02, 0.03, 0.001])
    cam = Camera.look_at(W, H, 50.0, eye, target)
    floor = material(kd=KD.tolist(), ks=KS.tolist(), ns=ns)
    sc = scene((quad((-half, -half, 0), (2 * half, 0, 0), (0, 2 * half, 0)), floor))
    lights = Lights([PointLight(light, INTENSITY)])
    trees = build_trees(sc, cam, lights, depth=3)
    img = render(trees, [floor], lights.intensities)

    o, d = camera_rays(cam)
    t, p = plane_hits(o, d)
    inside = (t > 0) & np.all(np.abs(p[:, :2]) < half, axis=1)
    safe = (t < 0) | np.all(np.abs(np.abs(p[:, :2]) - half) > 1e-4 * half, axis=1)
    expected = np.zeros((H * W, 3))
    expected[inside] = phong_radiance(p[inside], np.array([0, 0, 1.0]), -d[inside], light, INTENSITY, KD, KS, ns)
    got = img.reshape(-1, 3)
    assert np.all(np.isfinite(img)) and inside.sum() > 0.3 * H * W and safe.sum() > 0.9 * H * W
    np.testing.assert_allclose(got[safe], expected[safe], rtol=1e-9, atol=1e-12 * expected.max())
    # the default r = 0.1 sends reflection rays, which leave the scene: they add nothing
    assert trees.stats["rays"]["reflection"] == inside.sum() and trees.stats["escaped"] == inside.sum()
    assert set(trees.level.tolist()) == {1}
    albedo = render_albedo(trees, [floor]).reshape(-1, 3)
    np.testing.assert_array_equal(albedo[inside & safe], np.broadcast_to(KD, (np.sum(inside & safe), 3)))
    assert np.all(np.isnan(albedo[~inside & safe]))


def _mirror_scene():
    floor = material(kd=KD.tolist(), ks=KS.tolist(), ns=10.0, r=0.0)
    mirror = material("lambert", kd=0.0, r=[0.8, 0.7, 0.9])
    sc = scene((quad((-1, -1, 0), (1.5, 0, 0), (0, 2, 0)), floor),
               (quad((0.5, -1, 0), (0, 0, 1), (0, 2, 0)), mirror))
    cam = Camera.look_at(W, H, 60.0, (-0.8, 0.0, 0.6), (0.5, 0.0, 0.3))
    lights = Lights([PointLight([0.0, 0.3, 0.8], INTENSITY)])
    return sc, cam, lights


def test_mirror_shows_floor_times_r():
    sc, cam, lights = _mirror_scene()
    mats = [s.material for s in sc]
    trees = build_trees(sc, cam, lights, depth=3)
    got = render(trees, mats, lights.intensities).reshape(-1, 3)

    o, d = camera_rays(cam)
    n = np.array([0, 0, 1.0])
    t_m = (0.5 - o[0]) / d[:, 0]
    p_m = o + t_m[:, None] * d
    t_f, p_f = plane_hits(o, d)
    on_mirror = (t_m > 0) & (np.abs(p_m[:, 1]) < 1) & (p_m[:, 2] > 0) & (p_m[:, 2] < 1) & ~((t_f > 0) & (t_f < t_m))
    on_floor = ~on_mirror & (t_f > 0) & (p_f[:, 0] < 0.5) & (p_f[:, 0] > -1) & (np.abs(p_f[:, 1]) < 1)
    d2 = d * [-1, 1, 1]  # mirrored about x = 0.5
    t2 = -p_m[:, 2] / d2[:, 2]
    p2 = p_m + t2[:, None] * d2
    expected = np.zeros_like(got)
    expected[on_floor] = phong_radiance(p_f[on_floor], n, -d[on_floor], lights[0].position, INTENSITY, KD, KS, 10.0)
    seen = on_mirror & (t2 > 0) & (p2[:, 0] > -1) & (np.abs(p2[:, 1]) < 1)
    expected[seen] = [0.8, 0.7, 0.9] * phong_radiance(p2[seen], n, -d2[seen], lights[0].position, INTENSITY, KD, KS, 10.0)
    # away from the mirror's edges and the crease where it meets the floor
    safe = (np.abs(p_m[:, 2]) > 0.01) & (np.abs(np.abs(p_m[:, 1]) - 1) > 0.01)
    assert seen.sum() > 100 and on_floor.sum() > 100
    np.testing.assert_allclose(got[safe], expected[safe], rtol=1e-9, atol=1e-12)
    # the floor has r given as 0: no branch from it, counted
    assert trees.stats["pruned"]["r_zero"] == np.sum(trees.surface == 0)
    assert trees.paths[trees.path[trees.level == 2][0]] == ((1, REFLECTION),)


def eq23(ti, tt):
    return 0.5 * np.sin(ti - tt) ** 2 / np.sin(ti + tt) ** 2 * (1 + np.cos(ti + tt) ** 2 / np.cos(ti - tt) ** 2)


@pytest.mark.parametrize("ior", [1.5, 1.0])
def test_dielectric_slab_transmission(ior):
    floor = material(kd=KD.tolist(), ks=KS.tolist(), ns=10.0, r=0.0)
    t_slab = [0.9, 0.8, 0.7] if ior > 1 else [1.0, 1.0, 1.0]
    slab = material("lambert", ior=ior, kd=0.0, r=0.0 if ior > 1 else 1.0, t=t_slab)
    z0, z1, half = 0.2, 0.21, 0.15
    sc = scene((quad((-1, -1, 0), (2, 0, 0), (0, 2, 0)), floor), (box((-half, -half, z0), (half, half, z1)), slab))
    cam = Camera.look_at(W, H, 50.0, (0.1, -0.3, 1.0), (0.0, 0.0, 0.0))
    light = np.array([1.0, 0.0, 0.1])  # below the slab: its shadow falls outside the floor seen
    lights = Lights([PointLight(light, INTENSITY)])
    mats = [floor, slab]
    trees = build_trees(sc, cam, lights, depth=3)
    got = render(trees, mats, lights.intensities).reshape(-1, 3)

    o, d = camera_rays(cam)
    t1, p1 = plane_hits(o, d, z1)
    through = np.all(np.abs(p1[:, :2]) < half - 0.005, axis=1)
    ti = np.arccos(-d[:, 2])
    tt = np.arcsin(np.sin(ti) / ior)
    horiz = d[:, :2] / np.maximum(np.linalg.norm(d[:, :2], axis=1, keepdims=True), 1e-300)
    d_in = np.concatenate([horiz * np.sin(tt)[:, None], -np.cos(tt)[:, None]], axis=1)
    p2 = p1 + ((z0 - z1) / d_in[:, 2])[:, None] * d_in
    through &= np.all(np.abs(p2[:, :2]) < half - 0.005, axis=1)
    t3, p3 = plane_hits(p2, d)
    F = eq23(ti, tt) if ior > 1 else np.zeros(len(d))
    expected = np.asarray(t_slab) ** 2 * ((1 - F) ** 2)[:, None] * phong_radiance(
        p3, np.array([0, 0, 1.0]), -d, light, INTENSITY, KD, KS, 10.0)
    assert through.sum() > 50
    np.testing.assert_allclose(got[through], expected[through], rtol=1e-9)
    _, pf = plane_hits(o, d)
    beside = np.all(np.abs(p1[:, :2]) > half + 0.005, axis=1) & np.all(np.abs(pf[:, :2]) < 1, axis=1)
    direct = phong_radiance(pf, np.array([0, 0, 1.0]), -d, light, INTENSITY, KD, KS, 10.0)
    np.testing.assert_allclose(got[beside], direct[beside], rtol=1e-9)
    if ior == 1.0:  # F = 0: every reflection branch of the slab weighs 0 and is pruned
        assert trees.stats["rays"]["reflection"] == 0 and trees.stats["pruned"]["weight"] > 0
    else:
        assert trees.stats["pruned"]["r_zero"] > 0 and trees.stats["rays"]["reflection"] == 0
    assert ((1, TRANSMISSION), (1, TRANSMISSION)) in trees.paths


def test_total_internal_reflection_in_a_prism():
    """A right-angle prism: down through the top leg, TIR on the hypotenuse, out the side leg."""
    # cross-section in x-z: (-0.1, 0.3), (0.1, 0.3), (0.1, 0.1); extruded along y
    xz = np.array([[-0.1, 0.3], [0.1, 0.3], [0.1, 0.1]])
    v = np.array([[x, y, z] for y in (-0.2, 0.2) for x, z in xz])
    tris = [[0, 2, 1], [3, 4, 5], [0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4], [2, 0, 3], [2, 3, 5]]
    prism_mesh = Mesh(v, tris)
    assert prism_mesh.is_closed()
    centroid = v.mean(axis=0)
    centres = v[prism_mesh.triangles].mean(axis=1)
    assert np.all(np.sum(prism_mesh.face_normals() * (centres - centroid), axis=1) > 0)  # outward
    prism = material("lambert", ior=1.5, kd=0.0, r=0.95, t=0.9)
    wall = material("lambert", kd=[0.5, 0.6, 0.7], r=0.0)
    sc = scene((prism_mesh, prism), (quad((0.5, -1, -1), (0, 2, 0), (0, 0, 2)), wall))
    cam = Camera.look_at(5, 5, 0.6, (-0.02, 0.0, 10.0), (-0.02, 0.0, 0.0), up=(0, 1, 0))
    light = np.array([0.3, 0.0, 0.2])
    lights = Lights([PointLight(light, INTENSITY)])
    trees = build_trees(sc, cam, lights, depth=4)
    img = render(trees, [prism, wall], lights.intensities)

    centre = 2 * 5 + 2
    on_wall = (trees.pixel == centre) & (trees.surface == 1)
    assert on_wall.sum() == 1
    path = trees.paths[trees.path[on_wall][0]]
    assert path == ((0, TRANSMISSION), (0, REFLECTION), (0, TRANSMISSION))
    f0 = (0.5 / 2.5) ** 2
    assert trees.fresnel[on_wall][0] == pytest.approx((1 - f0) ** 2, rel=1e-12)
    np.testing.assert_allclose(trees.point[on_wall][0], [0.5, 0.0, 0.22], atol=1e-12)
    d2 = np.sum((light - [0.5, 0, 0.22]) ** 2)
    nl = (0.5 - 0.3) / np.sqrt(d2)
    expected = 0.9 * 0.95 * 0.9 * (1 - f0) ** 2 * np.array([0.5, 0.6, 0.7]) * INTENSITY * nl / d2
    np.testing.assert_allclose(img[2, 2], expected, rtol=1e-9)  # the prism's own kd is 0
    assert trees.stats["total_internal_reflections"] >= 1
    # no refracted node beyond the hypotenuse: nothing on the path (T, T)
    assert ((0, TRANSMISSION), (0, TRANSMISSION)) not in [trees.paths[i] for i in trees.path[trees.pixel == centre]]


def test_save_load_gradient_and_texture_override(tmp_path):
    sc, cam, lights = _mirror_scene()
    mats = [s.material for s in sc]
    trees = build_trees(sc, cam, lights, depth=2)
    img = render(trees, mats, lights.intensities)
    trees.save(tmp_path / "trees.npz")
    back = Trees.load(tmp_path / "trees.npz")
    assert back.paths == trees.paths and back.key == trees.key and back.stats == trees.stats
    np.testing.assert_array_equal(render(back, mats, lights.intensities), img)
    with pytest.raises(WorkspaceError, match="missing"):
        Trees.load(tmp_path / "nope.npz")

    # d basis / d ns against a central difference on the floor's ns
    basis, dbasis = linear_basis_and_grad(trees, mats, lights.intensities)
    hi, lo = [m.copy() for m in mats], [m.copy() for m in mats]
    hi[0].params["ns"] = np.float64(10.0 + 1e-5)
    lo[0].params["ns"] = np.float64(10.0 - 1e-5)
    fd = (linear_basis_and_grad(trees, hi, lights.intensities, grad=False)[0]
          - linear_basis_and_grad(trees, lo, lights.intensities, grad=False)[0]) / 2e-5
    np.testing.assert_allclose(dbasis[..., 0], fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())
    assert np.abs(fd).max() > 0

    # kd per node: the materials' own kd reproduces the image; scaling it scales the diffuse part
    x, _ = node_parameters(trees, mats)
    np.testing.assert_allclose(render(trees, mats, lights.intensities, kd_nodes=x[:, :, 0], basis=basis), img, rtol=1e-12)
    no_spec = [m.copy() for m in mats]
    no_spec[0].params["ks"] = np.zeros(3)
    diffuse = render(trees, no_spec, lights.intensities)
    twice = render(trees, no_spec, lights.intensities, kd_nodes=2 * x[:, :, 0])
    np.testing.assert_allclose(twice, 2 * diffuse, rtol=1e-12)


def test_bad_inputs_are_named():
    sc, cam, lights = _mirror_scene()
    with pytest.raises(ValueError, match="depth"):
        build_trees(sc, cam, lights, depth=0)
    trees = build_trees(sc, cam.scaled(8, 6), lights, depth=1)
    with pytest.raises(ValueError, match="intensities"):
        render(trees, [s.material for s in sc], np.ones((2, 3)))
    with pytest.raises(ValueError, match="materials"):
        render(trees, [sc[0].material], lights.intensities)
