"""The one copy of each shared geometry helper (calibration/rotations.py, sRGB in core/images.py), against closed forms."""
import numpy as np

from reflab.calibration.rotations import axis_rotation, nearest_rotation, rodrigues, rotation_vector


def test_quarter_turns_about_z_and_x():
    np.testing.assert_allclose(axis_rotation((0, 0, 1), 90.0) @ [1.0, 0, 0], [0, 1.0, 0], atol=1e-15)
    np.testing.assert_allclose(axis_rotation((2, 0, 0), 90.0) @ [0, 1.0, 0], [0, 0, 1.0], atol=1e-15)
    R = axis_rotation((0, 0, 1), [0.0, 90.0, 180.0])
    assert R.shape == (3, 3, 3)
    np.testing.assert_allclose(R[2], np.diag([-1.0, -1.0, 1.0]), atol=1e-15)


def test_rodrigues_round_trip_and_nearest_rotation():
    rng = np.random.default_rng(3)
    r = rng.normal(size=(5, 3))
    R = rodrigues(r)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    for k in range(5):
        np.testing.assert_allclose(rodrigues(rotation_vector(R[k])), R[k], atol=1e-9)
        noisy = R[k] + 1e-3 * rng.normal(size=(3, 3))
        Q = nearest_rotation(noisy)
        np.testing.assert_allclose(Q @ Q.T, np.eye(3), atol=1e-12)
        assert np.linalg.norm(Q - R[k]) < np.linalg.norm(noisy - R[k]) * 2


def test_srgb_curves_invert_each_other():
    from reflab.core.images import linear_to_srgb, srgb_to_linear

    x = np.linspace(0.0, 1.0, 101)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    np.testing.assert_allclose(linear_to_srgb([0.0, 0.0031308, 0.5, 1.0]), [0.0, 0.04044, 0.73536, 1.0], atol=1e-5)
