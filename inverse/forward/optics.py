"""Ideal optics of the pixel-intensity trees: mirror reflection, Snell refraction, Fresnel.

All functions are vectorised over a leading batch axis and work in float64. Directions point
along the travelling light/ray (an incoming direction ``d`` points *toward* the surface).
"""
from __future__ import annotations

import numpy as np


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def normalize(v: np.ndarray) -> np.ndarray:
    """Unit vectors along ``v`` (..., 3); zero vectors stay zero instead of becoming NaN."""
    v = np.asarray(v, dtype=np.float64)
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)


def reflect(d: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Mirror direction of ``d`` (..., 3) about the unit normal ``n`` (either orientation).

    Parameters
    ----------
    d : (..., 3) ndarray
        Incoming direction (toward the surface).
    n : (..., 3) ndarray
        Unit normal.

    Returns
    -------
    (..., 3) ndarray
        ``d - 2 (d·n) n``, of the length of ``d``.
    """
    d = np.asarray(d, dtype=np.float64)
    n = np.asarray(n, dtype=np.float64)
    return d - 2.0 * _dot(d, n)[..., None] * n


def refract(d: np.ndarray, n: np.ndarray, eta) -> tuple[np.ndarray, np.ndarray]:
    """Snell refraction of unit direction ``d`` through the interface of unit normal ``n``.

    Parameters
    ----------
    d : (..., 3) ndarray
        Unit incoming direction.
    n : (..., 3) ndarray
        Unit normal; its orientation does not matter (it is flipped to face ``-d``).
    eta : float or (...,) ndarray
        ``n1 / n2``, index of the incoming side over that of the outgoing side.

    Returns
    -------
    t : (..., 3) ndarray
        Unit refracted direction; zero where total internal reflection occurs.
    tir : (...,) bool ndarray
        True where there is no refracted ray (total internal reflection).
    """
    d = np.asarray(d, dtype=np.float64)
    n = np.asarray(n, dtype=np.float64)
    eta = np.asarray(eta, dtype=np.float64)
    cos_i = -_dot(d, n)
    n = np.where((cos_i < 0)[..., None], -n, n)  # face the incoming ray
    cos_i = np.abs(cos_i)
    sin2_t = eta**2 * np.maximum(0.0, 1.0 - cos_i**2)
    tir = sin2_t >= 1.0
    cos_t = np.sqrt(np.maximum(0.0, 1.0 - sin2_t))
    t = eta[..., None] * d + (eta * cos_i - cos_t)[..., None] * n
    t = np.where(tir[..., None], 0.0, normalize(t))
    return t, np.broadcast_to(tir, cos_i.shape).copy()


def fresnel_amplitudes(cos_i, n1, n2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fresnel amplitude reflection coefficients ``rs``, ``rp`` from cosines (no angle functions).

    ``rs = (n1 cos_i - n2 cos_t) / (n1 cos_i + n2 cos_t)``,
    ``rp = (n2 cos_i - n1 cos_t) / (n2 cos_i + n1 cos_t)``; at grazing incidence both tend to ±1,
    and under total internal reflection ``|rs| = |rp| = 1`` (returned as 1).

    Parameters
    ----------
    cos_i : array_like
        Cosine of the incidence angle (its sign is ignored).
    n1, n2 : array_like
        Refraction indices of the incoming and the outgoing media (broadcast with ``cos_i``).

    Returns
    -------
    rs, rp : ndarray
        Amplitude coefficients (float64).
    tir : ndarray of bool
        Where total internal reflection occurs.
    """
    cos_i = np.minimum(np.abs(np.asarray(cos_i, dtype=np.float64)), 1.0)
    n1 = np.asarray(n1, dtype=np.float64)
    n2 = np.asarray(n2, dtype=np.float64)
    cos_i, n1, n2 = np.broadcast_arrays(cos_i, n1, n2)
    sin2_t = (n1 / n2) ** 2 * (1.0 - cos_i**2)
    tir = sin2_t >= 1.0
    cos_t = np.sqrt(np.maximum(0.0, 1.0 - sin2_t))
    den_s = n1 * cos_i + n2 * cos_t
    den_p = n2 * cos_i + n1 * cos_t
    # Both denominators vanish only at exact grazing incidence with n1 == n2, where the limit is
    # total reflection (|r| -> 1), as for any grazing ray.
    ok = ~tir & (den_s > 0) & (den_p > 0)
    rs = np.divide(n1 * cos_i - n2 * cos_t, den_s, out=np.ones_like(cos_i), where=ok)
    rp = np.divide(n2 * cos_i - n1 * cos_t, den_p, out=np.ones_like(cos_i), where=ok)
    return rs, rp, tir


def fresnel(cos_i, n1, n2) -> np.ndarray:
    """Unpolarised Fresnel reflectance (dissertation eq. 2.3), ``F = (rs² + rp²) / 2``.

    Equal to ``½ sin²(θi−θt)/sin²(θi+θt) · [1 + cos²(θi+θt)/cos²(θi−θt)]`` but computed from
    cosines, so it is exact at normal incidence (``((n1−n2)/(n1+n2))²``), 1 at grazing incidence
    and 1 under total internal reflection.

    Parameters
    ----------
    cos_i : array_like
        Cosine of the incidence angle (sign ignored).
    n1, n2 : array_like
        Refraction indices of the incoming and the outgoing media.

    Returns
    -------
    ndarray
        F in [0, 1], float64, shape of the broadcast inputs.
    """
    rs, rp, _ = fresnel_amplitudes(cos_i, n1, n2)
    return np.clip(0.5 * (rs * rs + rp * rp), 0.0, 1.0)
