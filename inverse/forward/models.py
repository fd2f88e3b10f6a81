"""Partially linear BRTDF models (dissertation eq. 2.2): radiance = I · g(θ; n, l, v) · x.

Each model names its linear parameters ``x`` (per colour band) and its nonlinear parameters
``θ`` (scalars) exactly as ``reflab.reconstruction.scene.BRDF_PARAMS`` does, and gives ``g`` (the BRDF
times the cosine of incidence, one column per linear parameter) and ``dg/dθ`` analytically. All
terms are 0 where the light is below the surface (``n·l <= 0``). ``kd`` multiplies ``n·l``
itself (no 1/π), as in docs/formats.md.

Inputs are batches: ``theta`` (N, P), ``n``, ``l``, ``v`` (N, 3) unit vectors (normal, toward
the light, toward the viewer). Evaluate several lights by stacking them along N.
"""
from __future__ import annotations

import numpy as np

#: Below this, n·v is clamped: the viewer sits on the normal's side by construction of the trees,
#: and models whose lobes divide by n·v stay finite at grazing views.
_MIN_COS_VIEW = 1e-6


def _dot(a, b):
    return np.einsum("ij,ij->i", a, b)


def _half_cos(n, l, v):
    """n·h for the unit half vector h of l and v (0 where l = −v)."""
    h = l + v
    norm = np.linalg.norm(h, axis=1)
    return np.divide(_dot(n, h), norm, out=np.zeros(len(n)), where=norm > 0)


def power(base, exponent):
    """``base ** exponent`` for base in [0, 1] and exponent > 0, via exp(e·log b), underflow → 0.

    Returns
    -------
    value, log_base : ndarray
        The power, and ``log(base)`` with 0 where ``base <= 0`` (so ``value · log_base``, the
        derivative in the exponent, is finite and tends to its limit 0 at base 0 and base 1).
    """
    base = np.clip(base, 0.0, 1.0)
    pos = base > 0
    log_b = np.log(np.where(pos, base, 1.0))
    with np.errstate(under="ignore"):
        value = np.where(pos, np.exp(exponent * log_b), 0.0)
    return value, log_b


class Model:
    """A partially linear BRTDF: subclasses set the names and implement :meth:`_eval`."""

    name: str = ""
    linear: tuple[str, ...] = ()
    nonlinear: tuple[str, ...] = ()
    #: The linear slots whose g depends on θ (what an undetermined θ leaves undetermined).
    shaped: tuple[int, ...] = ()

    @property
    def n_linear(self) -> int:
        return len(self.linear)

    @property
    def n_nonlinear(self) -> int:
        return len(self.nonlinear)

    def _prepare(self, theta, n, l, v):
        n, l, v = (np.asarray(a, dtype=np.float64).reshape(-1, 3) for a in (n, l, v))
        theta = np.asarray(theta, dtype=np.float64)
        theta = np.broadcast_to(theta.reshape(-1, self.n_nonlinear) if theta.size else np.zeros((1, 0)),
                                (len(n), self.n_nonlinear))
        return theta, n, l, v

    def g(self, theta, n, l, v) -> np.ndarray:
        """g(θ; n, l, v) (N, L): radiance = intensity / d² · g · x."""
        return self._eval(*self._prepare(theta, n, l, v), grad=False)[0]

    def dg(self, theta, n, l, v) -> np.ndarray:
        """dg/dθ (N, L, P), analytic."""
        return self._eval(*self._prepare(theta, n, l, v), grad=True)[1]

    def g_and_dg(self, theta, n, l, v) -> tuple[np.ndarray, np.ndarray]:
        """Both g (N, L) and dg/dθ (N, L, P) in one pass."""
        return self._eval(*self._prepare(theta, n, l, v), grad=True)

    def theta_of(self, material) -> np.ndarray:
        """The nonlinear parameters of ``material`` as a (P,) float64 array."""
        return np.array([float(material[p]) for p in self.nonlinear], dtype=np.float64)

    def x_of(self, material) -> np.ndarray:
        """The linear parameters of ``material`` as a (3, L) array (band, parameter)."""
        return np.stack([np.broadcast_to(material[p], (3,)) for p in self.linear], axis=1).astype(np.float64)

    def _eval(self, theta, n, l, v, grad):  # pragma: no cover - abstract
        raise NotImplementedError


class Lambert(Model):
    """``g = [n·l]``."""

    name, linear, nonlinear = "lambert", ("kd",), ()

    def _eval(self, theta, n, l, v, grad):
        nl = np.maximum(_dot(n, l), 0.0)
        return nl[:, None], (np.zeros((len(n), 1, 0)) if grad else None)


class Phong(Model):
    """``g = [n·l, (n·h)^ns]`` (docs/formats.md: kd (n·l) + ks (n·h)^ns), h the half vector."""

    name, linear, nonlinear, shaped = "phong", ("kd", "ks"), ("ns",), (1,)

    def _eval(self, theta, n, l, v, grad):
        nl = _dot(n, l)
        lit = nl > 0
        spec, log_nh = power(np.where(lit, _half_cos(n, l, v), 0.0), theta[:, 0])
        g = np.stack([np.where(lit, nl, 0.0), spec], axis=1)
        if not grad:
            return g, None
        dg = np.zeros((len(n), 2, 1))
        dg[:, 1, 0] = spec * log_nh
        return g, dg


class Ward(Model):
    """Isotropic Ward: ``g = [n·l, n·l · exp(−tan²δ/α²) / (4π α² sqrt(n·l n·v))]``, δ = ∠(n, h)."""

    name, linear, nonlinear, shaped = "ward", ("kd", "ks"), ("alpha",), (1,)

    def _eval(self, theta, n, l, v, grad):
        nl = _dot(n, l)
        lit = nl > 0
        nl = np.where(lit, nl, 0.0)
        nv = np.maximum(_dot(n, v), _MIN_COS_VIEW)
        nh = np.clip(_half_cos(n, l, v), 0.0, 1.0)
        alpha = theta[:, 0]
        ok = lit & (nh > 0)
        nh2 = np.where(ok, nh * nh, 1.0)
        tan2 = (1.0 - nh2) / nh2
        with np.errstate(under="ignore"):
            lobe = np.where(ok, np.exp(-tan2 / alpha**2), 0.0)
        # n·l / sqrt(n·l n·v) = sqrt(n·l / n·v): no division by a vanishing n·l.
        spec = lobe * np.sqrt(nl / nv) / (4.0 * np.pi * alpha**2)
        g = np.stack([nl, spec], axis=1)
        if not grad:
            return g, None
        dg = np.zeros((len(n), 2, 1))
        dg[:, 1, 0] = spec * (2.0 * tan2 / alpha**3 - 2.0 / alpha)
        return g, dg


class OrenNayar(Model):
    """Qualitative Oren–Nayar: ``g = [n·l (A + B max(0, cos(φi−φo)) sin α tan β)]``, σ the roughness.

    ``A = 1 − σ²/(2(σ²+0.33))``, ``B = 0.45 σ²/(σ²+0.09)``, α = max(θi, θo), β = min(θi, θo).
    Computed without angles: ``max(0, cos Δφ) sin α tan β = max(0, l·v − (n·l)(n·v)) / max(n·l, n·v)``.
    """

    name, linear, nonlinear, shaped = "oren-nayar", ("kd",), ("sigma",), (0,)

    def _eval(self, theta, n, l, v, grad):
        nl = _dot(n, l)
        lit = nl > 0
        nl = np.where(lit, nl, 0.0)
        nv = np.maximum(_dot(n, v), _MIN_COS_VIEW)
        c = np.maximum(_dot(l, v) - nl * nv, 0.0) / np.maximum(np.maximum(nl, nv), _MIN_COS_VIEW)
        s2 = theta[:, 0] ** 2
        a = 1.0 - 0.5 * s2 / (s2 + 0.33)
        b = 0.45 * s2 / (s2 + 0.09)
        g = (nl * (a + b * c))[:, None]
        if not grad:
            return g, None
        sigma = theta[:, 0]
        da = -0.5 * 2.0 * sigma * 0.33 / (s2 + 0.33) ** 2
        db = 0.45 * 2.0 * sigma * 0.09 / (s2 + 0.09) ** 2
        return g, (nl * (da + db * c))[:, None, None]


MODELS: dict[str, Model] = {m.name: m for m in (Phong(), Lambert(), Ward(), OrenNayar())}

#: Largest number of linear / nonlinear parameters over the models (for zero-padded arrays).
MAX_LINEAR = max(m.n_linear for m in MODELS.values())
MAX_NONLINEAR = max(m.n_nonlinear for m in MODELS.values())


def get_model(name: str) -> Model:
    """The model called ``name`` (a ``brdf`` value of scene.json)."""
    try:
        return MODELS[name]
    except KeyError:
        raise ValueError(f"unknown BRTDF model {name!r}; expected one of {sorted(MODELS)}") from None
