"""F-TBO's Levenberg–Marquardt safeguards against creeping (issue #35): checked on closed forms."""
import numpy as np

from reflab.inverse.fit.ftbo import _secant_curvature, _slope_fails


def test_secant_curvature_gives_the_model_the_true_change_along_the_step():
    """ε(u) = ½ uᵀHu with Gauss–Newton seeing only part of H: after the correction, the model's
    change along the tried step equals ε's own (a quadratic: exact), and nothing changes across it."""
    H = np.array([[4.0, 1.0], [1.0, 3.0]])
    S = np.array([[4.0, 1.0], [1.0, 0.01]])  # the second direction's curvature missed
    u = np.array([0.5, -2.0])
    g = H @ u
    d = np.array([0.1, 1.5])
    dE = 0.5 * (u + d) @ H @ (u + d) - 0.5 * u @ H @ u
    B = _secant_curvature(S, g, d, dE)
    assert np.isclose(g @ d + 0.5 * d @ (S + B) @ d, dE, rtol=1e-12)
    e = np.array([-d[1], d[0]])  # orthogonal to the step: untouched
    assert np.allclose(B @ e, 0.0, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(B) >= -1e-12)
    # A model that already overestimates the curvature is left alone (only added curvature is learnt).
    assert not _secant_curvature(10 * H, g, d, dE).any()


def test_slope_fails_only_when_the_rise_is_first_order_in_the_step():
    """ε rising as c·|d| (a wrong slope) ends the damping; rising as c·|d|² (curvature) or with a
    step that does not shrink (clipped onto a bound) does not."""
    steps = [1.0, 0.25, 0.0625]
    assert _slope_fails([(3e-6 * d, d) for d in steps])
    assert not _slope_fails([(3e-6 * d * d, d) for d in steps])
    assert not _slope_fails([(3e-6, 5.5)] * 3)
    assert not _slope_fails([(3e-6 * d, d) for d in steps[:2]])


def test_theta_gradient_through_a_ks_held_on_its_upper_bound_matches_central_differences():
    """The lab's box is rendered with ks 6 above its plausible 1/L(30) = 4.53, so the exact inner
    solve holds it on that θ-dependent bound: the profiled ε's slope in the box's log2 ns must
    include the bound's pull (the envelope partial alone has it of the wrong size)."""
    from reflab.hardware.sim.lab import build_lab
    from reflab.inverse.fit.ftbo import _evaluator
    from reflab.inverse.fit.problem import Free, Problem, params_of
    from reflab.inverse.fit.ranges import linear_upper
    from reflab.inverse.forward.factorization import Factorization
    from reflab.inverse.forward.models import get_model
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees

    lab = build_lab(80, 60, textured=False)
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    truth = [s.material.copy() for s in lab.scene]
    truth[1].params["ks"] = np.full(3, 6.0)
    fac = Factorization(trees, [get_model(m.brdf) for m in truth], lab.lights.intensities)
    pb = Problem(fac, render(trees, truth, lab.lights.intensities), [m.transparent for m in truth])
    p = params_of(fac, truth)
    p.x = np.minimum(p.x, linear_upper(fac, p.theta)[:, None])
    free = Free(np.ones_like(p.x, dtype=bool), np.ones_like(p.s, dtype=bool), np.ones_like(p.theta, dtype=bool))
    q = np.flatnonzero(free.theta)
    evaluate = _evaluator(pb, free, q)
    u = pb.search.to_u(p.theta)[q]
    E, g, cur, *_ = evaluate(u, p)
    ks = fac.layout.x_offset[1] + list(fac.models[1].linear).index("ks")
    assert np.allclose(cur.x[ks], linear_upper(fac, cur.theta)[ks])  # held on the bound
    k = list(q).index(fac.layout.theta_offset[1])
    h = 1e-4
    up, dn = u.copy(), u.copy()
    up[k] += h
    dn[k] -= h
    slope = (evaluate(up, cur)[0] - evaluate(dn, cur)[0]) / (2 * h)
    assert abs(g[k] - slope) <= 1e-3 * abs(slope)
