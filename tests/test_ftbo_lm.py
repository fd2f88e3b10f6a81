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
