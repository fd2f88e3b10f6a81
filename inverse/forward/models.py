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


class Model:
    """A partially linear BRTDF: subclasses set the names and implement :meth:`_geometry` (the
    θ-independent terms) and :meth:`_on` (g and dg/dθ from them)."""

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

    def geometry(self, n, l, v) -> tuple:
        """The θ-independent terms of ``g`` on fixed (n, l, v) (:meth:`g_and_dg_on`): a fit
        evaluates one surface's nodes at many θ, and these (dot products, the half vector, its
        logarithm) are most of a model's cost."""
        n, l, v = (np.asarray(a, dtype=np.float64).reshape(-1, 3) for a in (n, l, v))
        return self._geometry(n, l, v)

    def g_and_dg_on(self, theta, geometry, grad: bool = True):
        """``g`` (N, L) and, with ``grad``, ``dg/dθ`` (N, L, P) on a :meth:`geometry`; the same numbers
        as :meth:`g_and_dg` on its (n, l, v) (the same operations, in the same order)."""
        theta = np.asarray(theta, dtype=np.float64)
        theta = np.broadcast_to(theta.reshape(-1, self.n_nonlinear) if theta.size else np.zeros((1, 0)),
                                (len(geometry[0]), self.n_nonlinear))
        return self._on(theta, geometry, grad)

    def _eval(self, theta, n, l, v, grad):
        return self._on(theta, self._geometry(n, l, v), grad)

    def theta_of(self, material) -> np.ndarray:
        """The nonlinear parameters of ``material`` as a (P,) float64 array."""
        return np.array([float(material[p]) for p in self.nonlinear], dtype=np.float64)

    def x_of(self, material) -> np.ndarray:
        """The linear parameters of ``material`` as a (3, L) array (band, parameter)."""
        return np.stack([np.broadcast_to(material[p], (3,)) for p in self.linear], axis=1).astype(np.float64)

    def _geometry(self, n, l, v) -> tuple:  # pragma: no cover - abstract
        """The θ-independent terms, a tuple whose first item has one row per (n, l, v)."""
        raise NotImplementedError

    def _on(self, theta, geometry, grad):  # pragma: no cover - abstract
        raise NotImplementedError


class Lambert(Model):
    """``g = [n·l]``."""

    name, linear, nonlinear = "lambert", ("kd",), ()

    def _geometry(self, n, l, v):
        return (np.maximum(_dot(n, l), 0.0),)

    def _on(self, theta, geometry, grad):
        nl = geometry[0]
        return nl[:, None], (np.zeros((len(nl), 1, 0)) if grad else None)


class Phong(Model):
    """``g = [n·l, (n·h)^ns]`` (docs/formats.md: kd (n·l) + ks (n·h)^ns), h the half vector."""

    name, linear, nonlinear, shaped = "phong", ("kd", "ks"), ("ns",), (1,)

    def _geometry(self, n, l, v):
        nl = _dot(n, l)
        lit = nl > 0
        # (n·h)^ns = exp(ns · log n·h): the logarithm is θ-independent (0 where n·h is 0, the power then 0).
        base = np.clip(np.where(lit, _half_cos(n, l, v), 0.0), 0.0, 1.0)
        pos = base > 0
        return np.where(lit, nl, 0.0), pos, np.log(np.where(pos, base, 1.0))

    def _on(self, theta, geometry, grad):
        nl, pos, log_nh = geometry
        with np.errstate(under="ignore"):
            spec = np.where(pos, np.exp(theta[:, 0] * log_nh), 0.0)
        g = np.stack([nl, spec], axis=1)
        if not grad:
            return g, None
        dg = np.zeros((len(nl), 2, 1))
        dg[:, 1, 0] = spec * log_nh
        return g, dg


class Ward(Model):
    """Isotropic Ward: ``g = [n·l, n·l · exp(−tan²δ/α²) / (4π α² sqrt(n·l n·v))]``, δ = ∠(n, h)."""

    name, linear, nonlinear, shaped = "ward", ("kd", "ks"), ("alpha",), (1,)

    def _geometry(self, n, l, v):
        nl = _dot(n, l)
        lit = nl > 0
        nl = np.where(lit, nl, 0.0)
        nv = np.maximum(_dot(n, v), _MIN_COS_VIEW)
        nh = np.clip(_half_cos(n, l, v), 0.0, 1.0)
        ok = lit & (nh > 0)
        nh2 = np.where(ok, nh * nh, 1.0)
        # n·l / sqrt(n·l n·v) = sqrt(n·l / n·v): no division by a vanishing n·l.
        return nl, ok, (1.0 - nh2) / nh2, np.sqrt(nl / nv)

    def _on(self, theta, geometry, grad):
        nl, ok, tan2, root = geometry
        alpha = theta[:, 0]
        with np.errstate(under="ignore"):
            lobe = np.where(ok, np.exp(-tan2 / alpha**2), 0.0)
        spec = lobe * root / (4.0 * np.pi * alpha**2)
        g = np.stack([nl, spec], axis=1)
        if not grad:
            return g, None
        dg = np.zeros((len(nl), 2, 1))
        dg[:, 1, 0] = spec * (2.0 * tan2 / alpha**3 - 2.0 / alpha)
        return g, dg


class OrenNayar(Model):
    """Qualitative Oren–Nayar: ``g = [n·l (A + B max(0, cos(φi−φo)) sin α tan β)]``, σ the roughness.

    ``A = 1 − σ²/(2(σ²+0.33))``, ``B = 0.45 σ²/(σ²+0.09)``, α = max(θi, θo), β = min(θi, θo).
    Computed without angles: ``max(0, cos Δφ) sin α tan β = max(0, l·v − (n·l)(n·v)) / max(n·l, n·v)``.
    """

    name, linear, nonlinear, shaped = "oren-nayar", ("kd",), ("sigma",), (0,)

    def _geometry(self, n, l, v):
        nl = _dot(n, l)
        lit = nl > 0
        nl = np.where(lit, nl, 0.0)
        nv = np.maximum(_dot(n, v), _MIN_COS_VIEW)
        return nl, np.maximum(_dot(l, v) - nl * nv, 0.0) / np.maximum(np.maximum(nl, nv), _MIN_COS_VIEW)

    def _on(self, theta, geometry, grad):
        nl, c = geometry
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
