"""The fit's parameters and objective, shared by F-TBO (:mod:`reflab.inverse.fit.ftbo`) and NF-TBO (:mod:`reflab.inverse.fit.nftbo`).

Both minimise ``ε = Σ_c ‖A_c(θ) y_c(x, r, t) − b_c‖²`` over the used pixels
(:mod:`reflab.inverse.forward.factorization`), normalised by ``Σ b²``, with bounds ``x ≥ 0`` and ``r, t ∈ [0, 1]``;
linear parameters are per band, θ is shared by the bands of a surface.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from reflab.core.task import ensure
from reflab.inverse.forward.factorization import BANDS, Factorization
from reflab.inverse.fit.photograph import image_noise, known_noise
from reflab.inverse.fit.ranges import theta_bounds


#: Nonlinear parameters searched in log2 (scale parameters spanning decades).
LOG2 = frozenset({"ns", "alpha"})
#: Shape parameters whose lobe widens as they grow (Ward's α; a Phong lobe widens as ns falls).
WIDER_UP = frozenset({"alpha"})
#: Noise assumed at least this fraction of the image peak: a noise-free float image still carries
#: rounding, so σ never reaches 0 and a parameter with vanishing signal stays undetermined.
NOISE_FLOOR = 1e-6
#: Values per θ of F-TBO's coarse global scan (:mod:`reflab.inverse.fit.ftbo`), also where a θ's signal is sought.
SCAN_POINTS = 8
#: The scan's range in search units (log2 for LOG2 names; others scan their whole range). Shininess
#: below 2 is a lobe flat enough to pass for diffuse light: ks would trade with kd and fit noise.
SCAN_RANGE = {"ns": (1.0, 16.0), "alpha": (-8.0, 0.0)}
#: fit.json's ``message`` when a method stops for ``max_seconds``.
BUDGET_MESSAGE = "stopped: wall-clock budget (max_seconds) spent before convergence"


@dataclass
class Params:
    """Flat parameters (layout of :class:`reflab.inverse.forward.factorization.Layout`), natural units."""

    x: np.ndarray  # (X, 3)
    s: np.ndarray  # (F, 3): r_s at 2s, t_s at 2s+1
    theta: np.ndarray  # (Q,)

    def copy(self) -> "Params":
        return Params(self.x.copy(), self.s.copy(), self.theta.copy())


@dataclass
class Free:
    """Which parameters are fitted (True) or held at their initial value (False)."""

    x: np.ndarray
    s: np.ndarray
    theta: np.ndarray

    def count(self) -> int:
        return int(self.x.sum() + self.s.sum() + self.theta.sum())

    def copy(self) -> "Free":
        return Free(self.x.copy(), self.s.copy(), self.theta.copy())

    def __and__(self, other: "Free") -> "Free":
        return Free(self.x & other.x, self.s & other.s, self.theta & other.theta)

    def __or__(self, other: "Free") -> "Free":
        return Free(self.x | other.x, self.s | other.s, self.theta | other.theta)

    def __invert__(self) -> "Free":
        return Free(~self.x, ~self.s, ~self.theta)


def params_of(fac: Factorization, materials) -> Params:
    """Flat parameters from a list of materials (surface order)."""
    lay = fac.layout
    x, s, th = np.zeros((lay.n_x, BANDS)), np.zeros((lay.n_factors, BANDS)), np.zeros(lay.n_theta)
    for i, (model, mat) in enumerate(zip(fac.models, materials)):
        for j, name in enumerate(model.linear):
            x[lay.x_offset[i] + j] = mat[name]
        for j, name in enumerate(model.nonlinear):
            th[lay.theta_offset[i] + j] = float(mat[name])
        s[2 * i] = mat["r"]
        s[2 * i + 1] = mat["t"] if mat.transparent else 0.0
    return Params(x, np.clip(s, 0.0, 1.0), th)


def materials_of(fac: Factorization, p: Params, templates) -> list:
    """Materials (copies of ``templates``) carrying the parameters ``p``."""
    lay, out = fac.layout, []
    for i, (model, mat) in enumerate(zip(fac.models, templates)):
        m = mat.copy()
        for j, name in enumerate(model.linear):
            m.params[name] = p.x[lay.x_offset[i] + j].copy()
        for j, name in enumerate(model.nonlinear):
            m.params[name] = np.float64(p.theta[lay.theta_offset[i] + j])
        m.params["r"] = p.s[2 * i].copy()
        m.params["t"] = p.s[2 * i + 1].copy() if m.transparent else np.zeros(BANDS)
        out.append(m)
    return out


class Search:
    """θ ↔ search variable u (log2 for :data:`LOG2` names), with bounds."""

    def __init__(self, fac: Factorization):
        names = [name for _, name in fac.layout.theta_names]
        self.log = np.array([n in LOG2 for n in names], dtype=bool)
        self.wider_up = np.array([n in WIDER_UP for n in names], dtype=bool)
        lo, hi = theta_bounds(fac)
        self.lo = np.where(self.log, np.log2(np.maximum(lo, 1e-300)), lo)
        self.hi = np.where(self.log, np.log2(hi), hi)

    def to_u(self, theta):
        return np.clip(np.where(self.log, np.log2(np.maximum(theta, 1e-300)), theta), self.lo, self.hi)

    def to_theta(self, u):
        return np.where(self.log, np.exp2(u), u)

    def dtheta_du(self, theta):
        return np.where(self.log, theta * np.log(2.0), 1.0)


class Problem:
    """The data and the factorized model of one fit.

    Parameters
    ----------
    fac : Factorization
    image : (H, W, 3) array_like
        Linear radiance; only ``fac.rows`` are used.
    transparent : list of bool
        Per surface: has a refracted branch (``t`` is a parameter); else ``t`` = 0.
    """

    def __init__(self, fac: Factorization, image, transparent):
        self.fac = fac
        self.transparent = [bool(t) for t in transparent]
        data = np.asarray(image, dtype=np.float64).reshape(-1, BANDS)[fac.rows].T  # (3, R)
        #: sqrt of each row's weight (a sample's, :mod:`reflab.inverse.fit.sampling`; None: 1), applied
        #: to ``b`` as the factorization applies it to A's rows: residuals are weighted residuals.
        #: (``b`` is weighted: a Problem made from it on a weighted system would weigh it twice.)
        self.scale = getattr(fac, "row_scale", None)
        self.b = (data * self.scale if self.scale is not None else data).copy()
        self.bb = np.einsum("cr,cr->c", self.b, self.b)
        self.norm = float(self.bb.sum()) or 1.0
        self.peak = float(data.max()) if data.size else 0.0
        used = np.zeros(fac.width * fac.height, dtype=bool)
        used[fac.rows] = True
        #: Noise σ per band estimated from the image alone (over its usable pixels when the stage
        #: said which: remember_noise), never below NOISE_FLOOR of the peak.
        known = known_noise(image)
        self.noise = np.maximum(image_noise(image, used.reshape(fac.height, fac.width)) if known is None else known,
                                NOISE_FLOOR * self.peak)
        self.search = Search(fac)
        names = [name for _, name in fac.layout.theta_names]
        self.scan_lo = np.array([SCAN_RANGE.get(n, (lo, hi))[0] for n, lo, hi in zip(names, self.search.lo, self.search.hi)])
        self.scan_hi = np.array([SCAN_RANGE.get(n, (lo, hi))[1] for n, lo, hi in zip(names, self.search.lo, self.search.hi)])
        self.onehot = np.zeros((fac.n_columns, fac.layout.n_x))
        self.onehot[np.arange(fac.n_columns), fac.col_x] = 1.0
        self.evaluations = 0
        #: Seconds per phase of :func:`reflab.inverse.fit.rounds.fit` (fit.json ``phases_s``) and the scan's evaluations.
        self.phases = {"structure": 0.0, "scan": 0.0, "refinement": 0.0, "uncertainty": 0.0}
        self.scan_evaluations = 0
        #: The scan's gain threshold scales with this share of the full image's pixels (coarse scan).
        self.scan_share = 1.0
        #: perf_counter() time after which the methods stop (None: no wall-clock budget).
        self.deadline = None
        #: The stage's :class:`reflab.core.task.Task` (progress, pause, cancel, deadline).
        self.task = ensure(None)

    def out_of_time(self) -> bool:
        """True once the wall-clock budget of the fit (or the task's) is spent."""
        return (self.deadline is not None and time.perf_counter() > self.deadline) or self.task.out_of_time

    def step(self, done, total, message) -> None:
        """Report one outer iteration to the task; raises :class:`reflab.core.task.Cancelled`."""
        self.task.step(done, total, message)

    def residual(self, A, y) -> np.ndarray:
        """Model minus image (3, R)."""
        return np.stack([A[c] @ y[c] for c in range(BANDS)]) - self.b

    def unweighted(self, A, res):
        """``A`` (per band) and the residual ``res`` (3, R) with the row weights taken out: what a
        pixel's own residual is, for tests against the image noise (outliers, the diagnosis)."""
        if self.scale is None:
            return A, res
        from scipy.sparse import diags

        inv = np.divide(1.0, self.scale, out=np.zeros_like(self.scale), where=self.scale > 0)
        return [(diags(inv) @ a).tocsr() for a in A], res * inv

    def rms(self, res) -> np.ndarray:
        """RMS residual per band over the used pixels (weighted: the rows' weights average 1, so
        with weights it estimates the RMS over every pixel the sample stands for)."""
        return np.sqrt(np.mean(res * res, axis=1)) if res.shape[1] else np.zeros(BANDS)

    def dy(self, p: Params, c: int, free: Free) -> tuple[np.ndarray, list]:
        """∂y_c/∂(free linear parameters of band c): (C, n) and their (kind, index) labels."""
        fac = self.fac
        prod = fac.factor_products(p.s)[:, c]
        cols, labels = [], []
        for i in np.flatnonzero(free.x[:, c]):
            cols.append(np.where(fac.col_x == i, prod, 0.0))
            labels.append(("x", i))
        for f in np.flatnonzero(free.s[:, c]):
            e = fac.exponents[:, f]
            rest = fac.factor_products(p.s, skip=f)[:, c]
            with np.errstate(divide="ignore", invalid="ignore"):
                d = np.where(e > 0, e * p.s[f, c] ** np.maximum(e - 1, 0) * rest, 0.0)
            cols.append(p.x[fac.col_x, c] * d)
            labels.append(("s", f))
        return (np.stack(cols, axis=1) if cols else np.zeros((fac.n_columns, 0))), labels


def step_message(what: str, trace: list) -> str:
    """The task's progress message: the iteration and the error so far (a GUI draws it live)."""
    return f"{what}, RMS per band [{', '.join(f'{v:.4g}' for v in trace[-1][1])}]" if trace else what


def trace_point(t0, rms):
    return [round(time.perf_counter() - t0, 6), [float(v) for v in rms]]
