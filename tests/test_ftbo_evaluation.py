"""F-TBO's evaluation made cheaper keeps its numbers: checked against the direct computations."""
import numpy as np
import pytest

from reflab.inverse.forward.models import MODELS


def _unit(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_a_models_geometry_then_theta_gives_g_and_dg_exactly(name):
    """g and dg/dθ from the θ-independent terms computed once equal the model's one-pass
    evaluation bit for bit, lights below the surface and a light opposite the viewer included."""
    model = MODELS[name]
    rng = np.random.default_rng(3)
    n, l, v = (_unit(rng.normal(size=(500, 3))) for _ in range(3))
    l[:5] = -v[:5]
    geometry = model.geometry(n, l, v)
    for theta in ([0.05], [0.4], [3.0], [120.0]):
        theta = np.array(theta[:model.n_nonlinear])
        g, dg = model.g_and_dg(np.broadcast_to(theta, (500, model.n_nonlinear)), n, l, v)
        g2, dg2 = model.g_and_dg_on(theta, geometry)
        np.testing.assert_array_equal(g2, g)
        np.testing.assert_array_equal(dg2, dg)
        assert np.any(g[:, -1] > 0)  # the lobe is lit somewhere: a comparison of zeros proves nothing
        np.testing.assert_array_equal(model.g_and_dg_on(theta, geometry, grad=False)[0], g)


def _lab():
    from reflab.hardware.sim.lab import build_lab
    from reflab.inverse.fit.problem import params_of
    from reflab.inverse.forward.factorization import Factorization
    from reflab.inverse.forward.models import get_model
    from reflab.inverse.forward.trees import build_trees

    lab = build_lab(80, 60, textured=False)
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    truth = [s.material for s in lab.scene]
    make = lambda: Factorization(trees, [get_model(m.brdf) for m in truth], lab.lights.intensities)  # noqa: E731
    return make, params_of(make(), truth)


def test_cached_surfaces_and_columns_give_a_fresh_factorizations_numbers():
    """A factorization that evaluated other θ first (its unchanged surfaces and θ-independent
    columns kept, its CSR data gathered) gives the matrices, image derivatives and θ gradient of a
    fresh one that sums its entries per slot."""
    make, p = _lab()
    used = make()
    lay = used.layout
    assert lay.n_theta >= 2
    rng = np.random.default_rng(4)
    y = rng.uniform(0.1, 1.0, (3, used.n_columns))
    res = rng.normal(size=(3, used.n_rows))
    first = p.theta.copy()
    one = first.copy()
    one[0] *= 1.3  # one surface's θ moves, the others' stay
    every = first * 0.8
    for theta in (first, one, every, first):
        used.matrices(theta * 1.01)  # a θ without derivatives in between
        A, grad = used.matrices_and_grad(theta)
        fresh = make()
        fresh._slot_order = False  # the entries summed per slot (bincount), as where two share one
        A0, grad0 = fresh.matrices_and_grad(theta)
        for c in range(3):
            np.testing.assert_array_equal(A[c].toarray(), A0[c].toarray())
            np.testing.assert_array_equal(A.gram(c), A0.gram(c))
        np.testing.assert_array_equal(grad.images(y), grad0.images(y))
        img, rows = grad.images(y, [1], compact=True)
        img0, rows0 = grad0.images(y, [1], compact=True)
        np.testing.assert_array_equal(rows, rows0)
        np.testing.assert_array_equal(img, img0)
        np.testing.assert_allclose(grad(res, y), grad0(res, y), rtol=1e-13)
        assert np.all(grad0(res, y) != 0)
    # The gradient is the image derivatives' product with the residual (its definition).
    np.testing.assert_allclose(grad(res, y), np.einsum("qcr,cr->q", grad.images(y), res), rtol=1e-10)


def test_inner_band_products_and_dy_are_the_problems():
    """The inner solve's per-band factor products, monomials and ∂y equal the problem's (all bands)."""
    from reflab.inverse.fit.ftbo import _Inner
    from reflab.inverse.fit.problem import Free, Problem

    make, p = _lab()
    fac = make()
    A = fac.matrices(p.theta)
    pb = Problem(fac, np.zeros((fac.height, fac.width, 3)), [False] * len(fac.models))
    inner = _Inner(pb, A)
    rng = np.random.default_rng(5)
    p.s = rng.uniform(0.2, 0.9, p.s.shape)
    free = Free(np.ones_like(p.x, dtype=bool), rng.uniform(size=p.s.shape) < 0.7, np.ones_like(p.theta, dtype=bool))
    assert fac.exponents.max() >= 2  # a factor squared somewhere: the derivative's power is exercised
    for c in range(3):
        np.testing.assert_array_equal(inner.products(p.s[:, c]), fac.factor_products(p.s)[:, c])
        for f in np.flatnonzero(free.s[:, c])[:3]:
            np.testing.assert_array_equal(inner.products(p.s[:, c], [f])[0], fac.factor_products(p.s, skip=f)[:, c])
        np.testing.assert_array_equal(inner.y(p, c), fac.y(p.x, p.s)[c])
        D, labels = inner.dy(p, c, free)
        D0, labels0 = pb.dy(p, c, free)
        assert labels == labels0
        np.testing.assert_array_equal(D, D0)


def test_bounds_shortcut_is_the_bounded_least_squares_solution_or_declines():
    """Started on the right bounds, the shortcut returns BVLS's minimiser; on wrong ones, None."""
    from scipy.optimize import lsq_linear

    from reflab.inverse.fit.ftbo import _on_bounds

    rng = np.random.default_rng(6)
    hits = 0
    for _ in range(200):
        n = int(rng.integers(2, 7))
        R = rng.normal(size=(n, n)) + 3 * np.eye(n)
        d = rng.normal(size=n) * 2
        ub = rng.uniform(0.2, 1.5, n)
        best = np.clip(lsq_linear(R, d, bounds=(0.0, ub), method="bvls", tol=1e-14).x, 0.0, ub)
        on_lo, on_hi = best <= 1e-12, best >= ub - 1e-12
        start = np.where(on_lo, 0.0, np.where(on_hi, ub, 0.5 * ub))
        x = _on_bounds(R, d, start, ub)
        if x is not None:
            hits += 1
            np.testing.assert_allclose(x, best, rtol=1e-9, atol=1e-12)
        wrong = start.copy()
        k = int(np.argmax(~on_lo))  # a variable off its lower bound put on it
        if not on_lo[k]:
            wrong[k] = 0.0
            assert _on_bounds(R, d, wrong, ub) is None
    assert hits >= 190  # a start on the right bounds is accepted (declined only at a degenerate tie)
