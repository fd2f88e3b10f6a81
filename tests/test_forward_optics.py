"""Optics and BRTDF models against textbook values and independent angle-based formulas."""
import numpy as np
import pytest

from reflab.inverse.forward.models import MODELS, get_model
from reflab.inverse.forward.optics import fresnel, fresnel_amplitudes, reflect, refract
from reflab.reconstruction.scene import BRDF_PARAMS


def fresnel_eq23(theta_i, theta_t):
    """Dissertation eq. 2.3, literally, with angles."""
    return 0.5 * np.sin(theta_i - theta_t) ** 2 / np.sin(theta_i + theta_t) ** 2 * (
        1 + np.cos(theta_i + theta_t) ** 2 / np.cos(theta_i - theta_t) ** 2)


@pytest.mark.parametrize("n", [1.0, 1.33, 1.46, 1.52, 2.4])
def test_fresnel_normal_incidence(n):
    expected = ((n - 1) / (n + 1)) ** 2
    assert fresnel(1.0, 1.0, n) == pytest.approx(expected, abs=1e-15)
    assert fresnel(1.0, n, 1.0) == pytest.approx(expected, abs=1e-15)
    assert fresnel(-1.0, 1.0, n) == pytest.approx(expected, abs=1e-15)  # orientation of the cosine


def test_fresnel_matches_eq23_both_ways():
    theta_i = np.radians(np.linspace(1, 89, 50))
    for n1, n2 in [(1.0, 1.5), (1.5, 1.0), (1.0, 1.46), (1.33, 1.52)]:
        sin_t = n1 / n2 * np.sin(theta_i)
        ok = sin_t < 1
        theta_t = np.arcsin(sin_t[ok])
        np.testing.assert_allclose(fresnel(np.cos(theta_i[ok]), n1, n2), fresnel_eq23(theta_i[ok], theta_t), rtol=1e-10)


def test_brewster_angle_kills_p_polarisation():
    for n1, n2 in [(1.0, 1.5), (1.5, 1.0), (1.0, 1.33)]:
        theta_b = np.arctan(n2 / n1)
        rs, rp, tir = fresnel_amplitudes(np.cos(theta_b), n1, n2)
        assert abs(rp) < 1e-14 and not tir
        assert fresnel(np.cos(theta_b), n1, n2) == pytest.approx(0.5 * rs**2, rel=1e-12)


def test_total_internal_reflection_and_grazing():
    critical = np.arcsin(1 / 1.5)
    cos = np.cos([critical + 1e-6, np.radians(60), np.radians(89.9)])
    np.testing.assert_array_equal(fresnel(cos, 1.5, 1.0), 1.0)
    below = fresnel(np.cos(critical - 1e-3), 1.5, 1.0)
    assert 0.2 < below < 1.0  # rises steeply to 1 just before the critical angle
    assert fresnel(0.0, 1.0, 1.5) == 1.0  # grazing incidence reflects everything
    assert 0.99 < fresnel(1e-6, 1.0, 1.5) <= 1.0
    assert fresnel(0.0, 1.0, 1.0) == 1.0 and fresnel(0.5, 1.0, 1.0) == 0.0  # no interface, except grazing
    d = np.array([[np.sin(critical + 0.01), 0, -np.cos(critical + 0.01)]])
    t, tir = refract(d, np.array([[0, 0, 1.0]]), 1.5)
    assert tir[0] and np.all(t == 0)


def test_snell_and_mirror_directions():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(200, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for eta in (1 / 1.5, 1.5, 1.0):
        t, tir = refract(d, n, eta)
        cos_i = np.abs(np.sum(d * n, axis=1))
        sin_i = np.sqrt(1 - cos_i**2)
        assert np.array_equal(tir, eta * sin_i >= 1)
        ok = ~tir
        sin_t = np.linalg.norm(np.cross(t[ok], n[ok]), axis=1)
        np.testing.assert_allclose(sin_t, eta * sin_i[ok], atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(t[ok], axis=1), 1, atol=1e-12)
        # same side as d (transmitted), in the plane of d and n
        assert np.all(np.sign(np.sum(t[ok] * n[ok], axis=1)) == np.sign(np.sum(d[ok] * n[ok], axis=1)))
        np.testing.assert_allclose(np.sum(np.cross(d[ok], n[ok]) * t[ok], axis=1), 0, atol=1e-12)
        if eta == 1.0:
            np.testing.assert_allclose(t, d, atol=1e-12)
    r = reflect(d, n)
    np.testing.assert_allclose(np.sum(r * n, axis=1), -np.sum(d * n, axis=1), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 1, atol=1e-12)


# ------------------------------------------------------------------------ models
def _configs(n_samples=400, seed=0):
    """Random unit n, l, v with the viewer above the surface (as the trees guarantee)."""
    rng = np.random.default_rng(seed)
    n = np.tile([0.0, 0.0, 1.0], (n_samples, 1))
    l = rng.normal(size=(n_samples, 3))
    v = rng.normal(size=(n_samples, 3))
    v[:, 2] = np.abs(v[:, 2]) + 0.05
    return n, l / np.linalg.norm(l, axis=1, keepdims=True), v / np.linalg.norm(v, axis=1, keepdims=True)


def test_models_match_scene_parameter_names():
    assert set(MODELS) == set(BRDF_PARAMS)
    for name, model in MODELS.items():
        assert get_model(name) is model
        assert set(model.linear + model.nonlinear) == set(BRDF_PARAMS[name])
        assert model.linear[0] == "kd"
    with pytest.raises(ValueError, match="unknown BRTDF model"):
        get_model("blinn")


def test_models_against_angle_formulas():
    n, l, v = _configs()
    theta_i, theta_o = np.arccos(np.clip(l[:, 2], -1, 1)), np.arccos(v[:, 2])
    phi_i, phi_o = np.arctan2(l[:, 1], l[:, 0]), np.arctan2(v[:, 1], v[:, 0])
    lit = l[:, 2] > 0
    h = (l + v) / np.linalg.norm(l + v, axis=1, keepdims=True)
    delta = np.arccos(np.clip(h[:, 2], -1, 1))

    g = get_model("phong").g(np.full((len(n), 1), 20.0), n, l, v)
    np.testing.assert_allclose(g[:, 0], np.where(lit, np.cos(theta_i), 0), atol=1e-12)
    np.testing.assert_allclose(g[:, 1], np.where(lit, np.cos(delta) ** 20, 0), atol=1e-12)

    alpha = 0.3
    ward = np.exp(-np.tan(delta) ** 2 / alpha**2) / (4 * np.pi * alpha**2 * np.sqrt(np.abs(np.cos(theta_i) * np.cos(theta_o))) + 1e-300)
    g = get_model("ward").g([[alpha]], n, l, v)
    np.testing.assert_allclose(g[lit, 1], (ward * np.cos(theta_i))[lit], rtol=1e-9, atol=1e-14)
    assert np.all(g[~lit] == 0)

    sigma = 0.4
    A = 1 - 0.5 * sigma**2 / (sigma**2 + 0.33)
    B = 0.45 * sigma**2 / (sigma**2 + 0.09)
    on = np.cos(theta_i) * (A + B * np.maximum(0, np.cos(phi_i - phi_o)) * np.sin(np.maximum(theta_i, theta_o)) * np.tan(np.minimum(theta_i, theta_o)))
    g = get_model("oren-nayar").g([[sigma]], n, l, v)
    np.testing.assert_allclose(g[lit, 0], on[lit], rtol=1e-9, atol=1e-12)
    assert np.all(g[~lit] == 0)


@pytest.mark.parametrize("name,theta", [("phong", 1.0), ("phong", 37.0), ("phong", 2.0**14), ("ward", 0.05),
                                        ("ward", 0.4), ("oren-nayar", 0.0), ("oren-nayar", 0.7)])
def test_dg_matches_finite_differences(name, theta):
    model = get_model(name)
    n, l, v = _configs(seed=3)
    if name == "phong" and theta > 1000:  # put half vectors near n, where a sharp lobe is nonzero
        v = l * [-1, -1, 1] + 1e-3 * v
        v /= np.linalg.norm(v, axis=1, keepdims=True)
    th = np.full((len(n), 1), theta)
    step = 1e-6 * max(theta, 1.0)
    fd = (model.g(th + step, n, l, v) - model.g(th - step, n, l, v)) / (2 * step)
    dg = model.dg(th, n, l, v)
    assert dg.shape == (len(n), model.n_linear, 1)
    np.testing.assert_allclose(dg[:, :, 0], fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max() + 1e-12)
    assert np.abs(fd).max() > 0 or name == "oren-nayar" and theta == 0.0


def test_lambert_has_no_nonlinear_parameters():
    n, l, v = _configs()
    assert get_model("lambert").dg(np.zeros((len(n), 0)), n, l, v).shape == (len(n), 1, 0)


def test_phong_extreme_exponents_are_finite():
    model = get_model("phong")
    n = np.tile([0.0, 0, 1], (4, 1))
    # h = n (head-on, and grazing light opposite a grazing view), a typical angle, a mirror pair
    l = np.array([[0, 0, 1.0], [1, 0, 1e-9], [0.6, 0, 0.8], [0, 0.6, 0.8]])
    v = np.array([[0, 0, 1.0], [-1, 0, 1e-9], [0, 0, 1.0], [0, -0.6, 0.8]])
    l /= np.linalg.norm(l, axis=1, keepdims=True)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    nh = np.cos(np.arctan(1 / 3))  # half vector of (0.6, 0, 0.8) and (0, 0, 1)
    for ns in (1e-3, 1.0, 2.0**14, 2.0**20):
        with np.errstate(under="ignore"):
            expected = nh**ns
        with np.errstate(all="raise"):
            g, dg = model.g_and_dg([[ns]], n, l, v)
            assert np.all(np.isfinite(g)) and np.all(np.isfinite(dg))
            assert g[0, 1] == 1.0 and dg[0, 1, 0] == 0.0
            assert g[3, 1] == 1.0  # mirror configuration: h = n
        assert g[2, 1] == pytest.approx(expected, rel=1e-12, abs=1e-300)
    assert g[2, 1] == 0.0 and dg[2, 1, 0] == 0.0  # underflow at ns = 2^20, no warning
