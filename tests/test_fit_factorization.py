"""The factorized system A(θ) y = b: only the scene's monomials, same image as the forward model."""
from types import SimpleNamespace

import numpy as np
import pytest

from reflab.inverse.forward.factorization import Factorization
from reflab.inverse.fit.rounds import params_of
from reflab.inverse.forward.models import get_model


def _hand_trees():
    """Two pixels, two surfaces (0 lambert, 1 phong), one light; paths chosen to share monomials."""
    paths = [(), ((0, 0),), ((0, 0), (1, 1)), ((1, 1), (0, 0)), ((1, 1), (1, 1))]
    #        pixel, surface, path
    nodes = [(0, 0, 0), (0, 1, 1), (0, 0, 2), (0, 0, 3), (1, 1, 0), (1, 1, 4)]
    rng = np.random.default_rng(3)
    n = len(nodes)

    def unit(a):
        return a / np.linalg.norm(a, axis=1, keepdims=True)

    normal = unit(np.array([[0, 0, 1.0]] * n) + 0.2 * rng.normal(size=(n, 3)))
    view = unit(normal + 0.5 * rng.normal(size=(n, 3)))
    light = unit(normal + 0.5 * rng.normal(size=(n, 3)))
    return SimpleNamespace(
        width=2, height=1, depth=3,
        pixel=np.array([p for p, _, _ in nodes]), surface=np.array([s for _, s, _ in nodes], dtype=np.int32),
        path=np.array([q for _, _, q in nodes], dtype=np.int32), paths=paths,
        normal=normal, view=view, light_dir=light[:, None, :], light_dist2=rng.uniform(0.2, 0.5, (n, 1)),
        visible=np.array([[True], [True], [True], [False], [True], [True]]),
        fresnel=np.array([1.0, 0.9, 0.5, 0.4, 1.0, 0.7]))


def test_columns_are_the_scene_monomials_and_image_matches_the_tree_sum():
    tr = _hand_trees()
    models = [get_model("lambert"), get_model("phong")]
    intens = np.array([[1.0, 0.8, 0.6]])
    fac = Factorization(tr, models, intens)
    # Monomials: kd0, kd0·r0·t1 (two orders of one multiset), x1·r0, x1, x1·t1² -> 1 + 1 + 2 + 2 + 2 columns.
    # Node 3 is in shadow (V = 0) and contributes nothing, so kd0·r0·t1 comes from node 2 only.
    assert len(fac.monomials) == 5
    assert fac.n_columns == 8
    assert fac.dense_columns == 3 * 5 ** 2
    assert sorted(fac.column_names()) == sorted(["kd0", "kd0·r0·t1", "kd1·r0", "ks1·r0", "kd1", "ks1", "kd1·t1^2", "ks1·t1^2"])

    kd0, kd1, ks1, ns1 = np.array([0.3, 0.5, 0.7]), np.array([0.2, 0.1, 0.4]), np.array([0.6, 0.6, 0.5]), 12.0
    r0, t1 = np.array([0.9, 0.5, 0.2]), np.array([0.3, 0.8, 0.6])
    x = np.array([kd0, kd1, ks1])
    s = np.array([r0, np.zeros(3), np.zeros(3), t1])
    got = fac.render(np.array([ns1]), x, s)
    # The tree sum written out node by node (docs/architecture.md).
    want = np.zeros((3, 2))
    factor = {(0, 0): r0, (1, 1): t1}
    for i in range(len(tr.pixel)):
        prod = np.ones(3)
        for key in tr.paths[tr.path[i]]:
            prod = prod * factor[key]
        n, l, v = tr.normal[i:i + 1], tr.light_dir[i], tr.view[i:i + 1]
        nl = max(float(n[0] @ l[0]), 0.0)
        h = (l[0] + v[0]) / np.linalg.norm(l[0] + v[0])
        if tr.surface[i] == 0:
            brdf = kd0 * nl
        else:
            brdf = kd1 * nl + (ks1 * max(float(n[0] @ h), 0.0) ** ns1 if nl > 0 else 0.0)
        want[:, tr.pixel[i]] += tr.fresnel[i] * prod * tr.visible[i, 0] * intens[0] / tr.light_dist2[i, 0] * brdf
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)


def test_mask_drops_rows_and_nodes():
    tr = _hand_trees()
    fac = Factorization(tr, [get_model("lambert"), get_model("phong")], np.ones((1, 3)), mask=np.array([False, True]))
    assert list(fac.rows) == [1]
    assert sorted(fac.column_names()) == ["kd1", "kd1·t1^2", "ks1", "ks1·t1^2"]


@pytest.fixture(scope="module")
def lab80():
    from reflab.hardware.sim.lab import build_lab
    from reflab.inverse.forward.trees import build_trees

    lab = build_lab(80, 60, textured=False)
    return lab, build_trees(lab.scene, lab.camera, lab.lights, depth=3)


def test_lab_image_equals_forward_model_for_random_materials(lab80):
    """A(θ) y reproduces reflab.inverse.forward.rendering.render (the forward model) for parameters far from the truth."""
    from reflab.inverse.forward.rendering import render

    lab, tr = lab80
    rng = np.random.default_rng(7)
    mats = []
    for surf in lab.scene:
        m = surf.material.copy()
        for key, val in m.params.items():
            if key == "ns":
                m.params[key] = np.float64(2.0 ** rng.uniform(2, 9))
            elif key == "t" and not m.transparent:
                continue
            else:
                m.params[key] = rng.uniform(0.0, 1.0, 3)
        mats.append(m)
    fac = Factorization(tr, [get_model(m.brdf) for m in mats], lab.lights.intensities)
    p = params_of(fac, mats)
    got = fac.render(p.theta, p.x, p.s)
    want = render(tr, mats, lab.lights.intensities).reshape(-1, 3)[fac.rows].T
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-13 * want.max())
    # Far fewer columns than the dissertation's dense Kronecker vector.
    assert 0 < fac.n_columns < fac.dense_columns / 10


def test_theta_derivative_matches_finite_differences(lab80):
    lab, tr = lab80
    mats = [s.material for s in lab.scene]
    fac = Factorization(tr, [get_model(m.brdf) for m in mats], lab.lights.intensities)
    p = params_of(fac, mats)
    y = fac.y(p.x, p.s)
    A, grad = fac.matrices_and_grad(p.theta)
    imgs = grad.images(y)
    live = 0
    for q in range(fac.layout.n_theta):
        h = 1e-6 * p.theta[q]
        up, dn = p.theta.copy(), p.theta.copy()
        up[q] += h
        dn[q] -= h
        num = (fac.render(up, p.x, p.s) - fac.render(dn, p.x, p.s)) / (2 * h)
        scale = np.abs(num).max()
        live += scale > 0
        np.testing.assert_allclose(imgs[q], num, rtol=1e-5, atol=1e-7 * scale + 1e-15)
    assert live >= 2  # the box's and the tile's highlights are in view
    # Compact images: the rows a θ's surface reaches, where they equal the full ones; zero elsewhere.
    for which in ([0], [2, 0], list(range(fac.layout.n_theta))):
        small, rows = grad.images(y, which, compact=True)
        full = imgs[which]
        np.testing.assert_array_equal(small, full[:, :, rows])
        off = np.ones(fac.n_rows, dtype=bool)
        off[rows] = False
        assert not np.any(full[:, :, off]) and 0 < len(rows) < fac.n_rows


def test_linear_basis_is_reused_only_for_the_same_inputs():
    """rendering.linear_basis keeps its last result (read-only) for the same trees, θ and lamps,
    and computes anew when any of them changes (the same values as computing it afresh)."""
    from reflab.hardware.sim.lab import build_lab
    from reflab.inverse.forward.rendering import linear_basis, linear_basis_and_grad
    from reflab.inverse.forward.trees import build_trees

    lab = build_lab(40, 30)
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=2)
    mats = [s.material for s in lab.scene]
    first = linear_basis(trees, mats, lab.lights.intensities)
    assert linear_basis(trees, mats, lab.lights.intensities) is first and not first.flags.writeable
    other = [m.copy() for m in mats]
    i = next(k for k, m in enumerate(other) if m.brdf == "phong")
    other[i].params["ns"] = float(other[i]["ns"]) * 2
    for args in ((trees, other, lab.lights.intensities), (trees, mats, 2 * lab.lights.intensities),
                 (build_trees(lab.scene, lab.camera, lab.lights, depth=2), mats, lab.lights.intensities)):
        again = linear_basis(*args)
        assert again is not first
        assert np.array_equal(again, linear_basis_and_grad(*args, grad=False)[0])
    assert not np.array_equal(linear_basis(trees, other, lab.lights.intensities), first)
