"""Fit the non-Lambertian parameters from one image: F-TBO and NF-TBO (METHOD.md §3).

Both minimise the same objective, ``ε = Σ_c ‖A_c(θ) y_c(x, r, t) − b_c‖²`` over the used pixels
(:mod:`inverse.factorization`), normalised by ``Σ b²``, with bounds ``x ≥ 0`` and ``r, t ∈ [0, 1]``;
linear parameters are per band, θ is shared by the bands of a surface.

- **F-TBO**: for fixed θ, the Gram matrices ``G_c = A_cᵀA_c`` and ``h_c = A_cᵀb_c`` reduce the
  problem to the (few) monomial columns. There, ``x`` is the exact bounded least-squares solution
  for fixed r, t (NNLS), and each ``r_s`` / ``t_s`` the exact minimiser on [0, 1] of its
  polynomial, alternated to convergence. θ (shininess searched in log2) is optimised on top: a
  coarse global scan per θ (each candidate with the exact inner solve), then Levenberg–Marquardt
  with the envelope-theorem gradient and the variable-projection curvature.
- **NF-TBO**: every parameter at once by preconditioned Polak–Ribière nonlinear conjugate gradient
  on a bounded reparametrisation (``x = w²``, ``r = sin² φ``, ``log2 ns = lo + (hi − lo) sin² ψ``),
  with a diagonal (Gauss–Newton) preconditioner; every evaluation is a full pass over the nodes.

Parameters the image does not determine — no signal in their columns (a surface never seen, no
reflection or transmission through a surface), or a one-sigma uncertainty larger than
:data:`RESOLVE` of their scale (a hidden highlight, ks ≈ 0 leaving ns free) — are kept at their
initial value, out of the fit, and named in ``undetermined``; so are values the user gave
(``held``). The reported one-sigma uncertainties hold when the model is imperfect: the larger of
``σ² (JᵀJ)⁻¹`` (σ per band from the residual, never below :data:`NOISE_FLOOR` of the image
peak) and a cluster-robust sandwich over image tiles (:mod:`inverse.uncertainty`), and on
textured scenes from the pixels a free texture cannot explain (:func:`texture_absorbed`); a fitted
value whose σ spans its scale is reported undetermined too. Every value stays in its plausible
range (:mod:`inverse.ranges`); outlier pixels are left out and counted (:func:`outliers`).
:func:`diagnose` says in words whether the fitted model explains the image (``status``,
``warnings``). The stage on a workspace is :func:`inverse.fit_stage.fit_workspace`.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from hardware.images import clip_level
from hardware.task import Task, ensure
from hardware.workspace import WorkspaceError
from inverse.factorization import BANDS, Factorization, one_blas_thread
from inverse.ranges import at_bound, clip, linear_upper, theta_bounds

#: Nonlinear parameters searched in log2 (scale parameters spanning decades).
LOG2 = frozenset({"ns", "alpha"})
#: A parameter whose one-sigma exceeds this fraction of its scale (its value or initial value for
#: x, the range [0, 1] for r and t, a factor 2 for a log2 parameter) is undetermined.
RESOLVE = 1.0
#: A fitted shininess is reported undetermined when its final (robust) one-sigma exceeds this many
#: log2 units (a factor √2): the linearised σ of a log-scale parameter understates its long tail.
RESOLVE_THETA = 0.5
#: Noise assumed at least this fraction of the image peak: a noise-free float image still carries
#: rounding, so σ never reaches 0 and a parameter with vanishing signal stays undetermined.
NOISE_FLOOR = 1e-6
#: Within this (relative) distance of a bound a parameter counts as pinned there.
BOUND_TOL = 1e-3
#: Column signal below this fraction of the image peak counts as none.
SIGNAL_FLOOR = 1e-9
#: At least this many pixel values at the image maximum make a clipped (saturated) plateau.
PLATEAU = 3
#: Values per θ of F-TBO's coarse global scan, and sweeps over the θs.
SCAN_POINTS = 8
#: The scan's range in search units (log2 for LOG2 names; others scan their whole range). Shininess
#: below 2 is a lobe flat enough to pass for diffuse light: ks would trade with kd and fit noise.
SCAN_RANGE = {"ns": (1.0, 16.0), "alpha": (-8.0, 0.0)}
SCAN_SWEEPS = 2
#: Images with at least this many used pixels are scanned on every second pixel in x and y (a
#: quarter of the cost per candidate), the full image finishing from the basins found there.
COARSE_MIN_ROWS = 60_000
#: F-TBO stops once the undamped Gauss–Newton step on θ predicts a relative decrease of the error
#: below this: Levenberg–Marquardt otherwise creeps along a flat valley for dozens of iterations,
#: each gaining 1e-9 of the error (measured on the textured demo).
STOP_GAIN = 1e-8
#: A scan candidate must lower the squared error by this many times the image noise variance (per
#: band): far beyond what fitting noise with a band's linear parameters gains (≈ 1 each).
SCAN_GAIN = 25.0
METHODS = ("ftbo", "nftbo")
#: The diagnosis flags a pixel whose residual exceeds this many image-noise σ plus DIAG_FLOOR of the peak.
DIAG_SIGMAS = 6.0
DIAG_FLOOR = 1e-4
#: A pixel is an outlier, left out and the fit repeated, when its residual exceeds this many image-noise σ
#: (plus DIAG_FLOOR of the peak); only when such pixels are at most REJECT_SHARE of those used (more
#: is a misfit for the diagnosis, not outliers).
REJECT_SIGMAS = 6.0
REJECT_SHARE = 0.01
#: A pixel where directly seen texture carries at least this share of the light says nothing about
#: the other parameters once the texture is free (:func:`texture_absorbed`).
ABSORB_SHARE = 0.02
#: Passes of rejection and refit at most.
REJECT_PASSES = 4
#: fit.json's ``message`` when a method stops for ``max_seconds``.
BUDGET_MESSAGE = "stopped: wall-clock budget (max_seconds) spent before convergence"


# ---------------------------------------------------------------------- input checks
def check_image(image, width: int, height: int, path="input image") -> np.ndarray:
    """Validate the input photograph against the camera and return it as float64 (H, W, 3).

    Raises
    ------
    WorkspaceError
        Size different from camera.json, or not a photograph (:func:`hardware.images.check_radiance`:
        NaN, mostly negative, all black); noise-level negative values are kept.
    """
    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[:2] != (height, width):
        raise WorkspaceError(path, "size", f"{width}x{height} RGB as in camera.json",
                             got=f"{image.shape[1]}x{image.shape[0]}" if image.ndim >= 2 else image.shape)
    from hardware.images import check_radiance

    return check_radiance(image, path)


def saturated_pixels(image, level: float | None = None) -> np.ndarray:
    """Pixels (H*W,) bool with any band at the saturation level.

    Parameters
    ----------
    image : (H, W, 3) array_like
    level : float, optional
        Clipping level. By default the image maximum counts as clipped when at least
        :data:`PLATEAU` pixel values sit exactly on it (a sensor or 16-bit file clips to a plateau;
        a rendered or unclipped highlight has one brightest value).
    """
    flat = np.asarray(image, dtype=np.float64).reshape(-1, BANDS)
    if level is None:
        level = clip_level(flat, PLATEAU)
        if level is None:
            return np.zeros(len(flat), dtype=bool)
    return np.any(flat >= level, axis=1)


def image_noise(image, used=None) -> np.ndarray:
    """Gaussian noise σ per band estimated from one image (Immerkær 1996, median form).

    The 3×3 mask ``[1 −2 1; −2 4 −2; 1 −2 1]`` (a product of two second differences) cancels
    shading that is locally linear or quadratic along rows and columns, and sends white noise of
    σ to σ·6; the median of its absolute response over 0.6745 is robust to edges and highlights.

    Parameters
    ----------
    image : (H, W, 3) array_like
    used : (H, W) bool, optional
        Pixels to trust (e.g. not saturated); a mask response counts only where all 9 are used.

    Returns
    -------
    (3,) ndarray
        0 where no 3×3 window is available.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.shape[0] < 3 or img.shape[1] < 3:
        return np.zeros(BANDS)
    row = img[:, :-2] - 2.0 * img[:, 1:-1] + img[:, 2:]
    resp = row[:-2] - 2.0 * row[1:-1] + row[2:]  # (H-2, W-2, 3)
    ok = np.ones(resp.shape[:2], dtype=bool)
    if used is not None:
        u = np.asarray(used, dtype=bool)
        for dv in range(3):
            for du in range(3):  # 9 shifted views of the mask, not a pixel loop
                ok &= u[dv:dv + resp.shape[0], du:du + resp.shape[1]]
    if not ok.any():
        return np.zeros(BANDS)
    return np.median(np.abs(resp[ok]), axis=0) / (0.6745 * 6.0)


# ---------------------------------------------------------------------- parameters
@dataclass
class Params:
    """Flat parameters (layout of :class:`inverse.factorization.Layout`), natural units."""

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


class _Search:
    """θ ↔ search variable u (log2 for :data:`LOG2` names), with bounds."""

    def __init__(self, fac: Factorization):
        names = [name for _, name in fac.layout.theta_names]
        self.log = np.array([n in LOG2 for n in names], dtype=bool)
        lo, hi = theta_bounds(fac)
        self.lo = np.where(self.log, np.log2(np.maximum(lo, 1e-300)), lo)
        self.hi = np.where(self.log, np.log2(hi), hi)

    def to_u(self, theta):
        return np.clip(np.where(self.log, np.log2(np.maximum(theta, 1e-300)), theta), self.lo, self.hi)

    def to_theta(self, u):
        return np.where(self.log, np.exp2(u), u)

    def dtheta_du(self, theta):
        return np.where(self.log, theta * np.log(2.0), 1.0)


# ---------------------------------------------------------------------- the objective
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
        self.b = np.asarray(image, dtype=np.float64).reshape(-1, BANDS)[fac.rows].T.copy()  # (3, R)
        self.bb = np.einsum("cr,cr->c", self.b, self.b)
        self.norm = float(self.bb.sum()) or 1.0
        self.peak = float(self.b.max()) if self.b.size else 0.0
        used = np.zeros(fac.width * fac.height, dtype=bool)
        used[fac.rows] = True
        #: Noise σ per band estimated from the image alone, never below NOISE_FLOOR of the peak.
        self.noise = np.maximum(image_noise(image, used.reshape(fac.height, fac.width)), NOISE_FLOOR * self.peak)
        self.search = _Search(fac)
        names = [name for _, name in fac.layout.theta_names]
        self.scan_lo = np.array([SCAN_RANGE.get(n, (lo, hi))[0] for n, lo, hi in zip(names, self.search.lo, self.search.hi)])
        self.scan_hi = np.array([SCAN_RANGE.get(n, (lo, hi))[1] for n, lo, hi in zip(names, self.search.lo, self.search.hi)])
        self.onehot = np.zeros((fac.n_columns, fac.layout.n_x))
        self.onehot[np.arange(fac.n_columns), fac.col_x] = 1.0
        self.evaluations = 0
        #: Seconds per phase of :func:`fit` (fit.json ``phases_s``) and the scan's evaluations.
        self.phases = {"structure": 0.0, "scan": 0.0, "refinement": 0.0, "uncertainty": 0.0}
        self.scan_evaluations = 0
        #: The scan's gain threshold scales with this share of the full image's pixels (coarse scan).
        self.scan_share = 1.0
        #: perf_counter() time after which the methods stop (None: no wall-clock budget).
        self.deadline = None
        #: The stage's :class:`hardware.task.Task` (progress, pause, cancel, deadline).
        self.task = ensure(None)

    def out_of_time(self) -> bool:
        """True once the wall-clock budget of the fit (or the task's) is spent."""
        return (self.deadline is not None and time.perf_counter() > self.deadline) or self.task.out_of_time

    def step(self, done, total, message) -> None:
        """Report one outer iteration to the task; raises :class:`hardware.task.Cancelled`."""
        self.task.step(done, total, message)

    def residual(self, A, y) -> np.ndarray:
        """Model minus image (3, R)."""
        return np.stack([A[c] @ y[c] for c in range(BANDS)]) - self.b

    def rms(self, res) -> np.ndarray:
        """RMS residual per band over the used pixels."""
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


class _Inner:
    """F-TBO's inner problem for fixed θ, in monomial space: G_c, h_c per band."""

    def __init__(self, problem: Problem, A):
        self.pb = problem
        self.G = [(A[c].T @ A[c]).toarray() for c in range(BANDS)]
        self.h = [A[c].T @ problem.b[c] for c in range(BANDS)]

    def upper(self, p: Params) -> np.ndarray:
        """(X,) upper bounds of the linear parameters at ``p.theta`` (:mod:`inverse.ranges`)."""
        key = p.theta.tobytes()
        if getattr(self, "_ub_key", None) != key:
            self._ub_key, self._ub = key, linear_upper(self.pb.fac, p.theta)
        return self._ub

    def eps(self, c, y):
        return float(y @ self.G[c] @ y - 2.0 * self.h[c] @ y + self.pb.bb[c])

    def x_step(self, c, p: Params, free: Free):
        """Exact bounded (x ≥ 0) least squares of band c's free x for fixed r, t."""
        from scipy.optimize import nnls

        fx = free.x[:, c]
        if not fx.any():
            return
        T = self.pb.onehot * self.pb.fac.factor_products(p.s)[:, c:c + 1]
        Q = T.T @ self.G[c] @ T
        q = T.T @ self.h[c] - Q[:, ~fx] @ p.x[~fx, c]
        Qf, qf = Q[np.ix_(fx, fx)], q[fx]
        # ‖R x − d‖² = xᵀ Q x − 2 qᵀ x + const with R = √w Vᵀ, d = Vᵀq / √w (w > 0).
        w, V = np.linalg.eigh(Qf)
        keep = w > max(w.max(), 0.0) * 1e-14
        if not keep.any():
            return
        R = np.sqrt(w[keep])[:, None] * V[:, keep].T
        d = (V[:, keep].T @ qf) / np.sqrt(w[keep])
        x = nnls(R, d, maxiter=50 * len(qf) + 50)[0]
        ub = self.upper(p)[fx]
        if np.any(x > ub):  # a plausible range binds (inverse.ranges): bounded least squares
            from scipy.optimize import lsq_linear

            x = np.clip(lsq_linear(R, d, bounds=(0.0, ub), method="bvls", tol=1e-14).x, 0.0, ub)
        p.x[fx, c] = x

    def s_step(self, c, f, p: Params):
        """Exact minimiser on [0, 1] of band c's ε as a polynomial in factor f."""
        fac = self.pb.fac
        e = fac.exponents[:, f]
        u = p.x[fac.col_x, c] * fac.factor_products(p.s, skip=f)[:, c]
        G, h = self.G[c], self.h[c]
        top = int(e.max())
        # y(σ) = Σ_d σ^d U_d; ε(σ) = Σ_{d,d'} σ^{d+d'} U_dᵀ G U_d' − 2 Σ_d σ^d hᵀU_d + const.
        U = np.stack([np.where(e == d, u, 0.0) for d in range(top + 1)])  # (top+1, C)
        GU = U[1:] @ G  # rows d >= 1 (G symmetric)
        coef = np.zeros(2 * top + 1)  # ascending powers; the constant term does not move the minimiser
        cross = GU @ U.T  # (top, top+1): U_dᵀ G U_d' for d >= 1
        for d in range(1, top + 1):
            coef[d] += 2.0 * cross[d - 1, 0] - 2.0 * (h @ U[d])
            for d2 in range(1, top + 1):
                coef[d + d2] += cross[d - 1, d2]
        cand = [0.0, 1.0, p.s[f, c]]
        deriv = coef[1:] * np.arange(1, len(coef))
        if np.any(deriv[1:]):
            roots = np.polynomial.polynomial.polyroots(deriv)
            # A root within rounding of a bound is that bound (a t of 1e-23 would only trouble later stages).
            cand += [float(r.real) for r in roots if abs(r.imag) <= 1e-9 * (1 + abs(r.real)) and 1e-12 < r.real < 1.0 - 1e-12]
        cand = np.array(cand)
        vals = np.polynomial.polynomial.polyval(cand, coef)
        p.s[f, c] = cand[int(np.argmin(vals))]

    def joint_step(self, c, p: Params, free: Free) -> None:
        """One projected Gauss–Newton step on all free linear parameters of band c at once.

        Alternating exact block minimisers converges linearly when blocks are coupled (an albedo
        and the mirror that reflects it); this joint step, still in monomial space, is kept only
        when it lowers ε, so the alternation's exactness is preserved and its tail is cut short.
        """
        D, labels = self.pb.dy(p, c, free)
        if not labels:
            return
        fac = self.pb.fac
        y = fac.y(p.x, p.s)[c]
        g = D.T @ (self.G[c] @ y - self.h[c])
        H = D.T @ self.G[c] @ D
        z = np.array([p.x[i, c] if k == "x" else p.s[i, c] for k, i in labels])
        ub = self.upper(p)
        hi = np.array([ub[i] if k == "x" else 1.0 for k, i in labels])
        act = ((z <= 0.0) & (g > 0)) | ((z >= hi) & (g < 0))
        fr = ~act
        if not fr.any():
            return
        w, V = np.linalg.eigh(H[np.ix_(fr, fr)])
        keep = w > max(w.max(), 0.0) * 1e-13
        if not keep.any():
            return
        step = np.zeros_like(z)
        step[fr] = -(V[:, keep] / w[keep]) @ (V[:, keep].T @ g[fr])
        new = np.clip(z + step, 0.0, hi)
        # Within rounding of a bound is on it (a t of 1e-23 would only trouble later stages).
        new = np.where(new < 1e-12, 0.0, np.where(hi - new < 1e-12, hi, new))
        trial = p.copy()
        for (k, i), v in zip(labels, new):
            (trial.x if k == "x" else trial.s)[i, c] = v
        if self.eps(c, fac.y(trial.x, trial.s)[c]) < self.eps(c, y):
            p.x[:, c], p.s[:, c] = trial.x[:, c], trial.s[:, c]

    def solve(self, p: Params, free: Free, tol=1e-15, max_sweeps=200) -> int:
        """Alternate the exact x and factor steps per band until ε stops decreasing."""
        fac = self.pb.fac
        sweeps = 0
        for c in range(BANDS):
            last = self.eps(c, fac.y(p.x, p.s)[c])
            for sweep in range(max_sweeps):
                self.x_step(c, p, free)
                for f in np.flatnonzero(free.s[:, c]):
                    self.s_step(c, f, p)
                self.joint_step(c, p, free)
                now = self.eps(c, fac.y(p.x, p.s)[c])
                sweeps += 1
                if last - now <= tol * self.pb.bb[c] + 1e-300:
                    break
                last = now
        return sweeps


# ---------------------------------------------------------------------- results
@dataclass
class FitResult:
    """Everything ``fit.json`` reports (INTERFACES.md) plus diagnostics."""

    method: str
    params: Params
    free: Free
    materials: list
    sigma: Params
    rms: np.ndarray
    time_s: float
    trace: list
    undetermined: list
    rounds: int
    evaluations: int
    iterations: int
    message: str
    stats: dict = field(default_factory=dict)


def _step_message(what: str, trace: list) -> str:
    """The task's progress message: the iteration and the error so far (a GUI draws it live)."""
    return f"{what}, RMS per band [{', '.join(f'{v:.4g}' for v in trace[-1][1])}]" if trace else what


def _trace_point(t0, rms):
    return [round(time.perf_counter() - t0, 6), [float(v) for v in rms]]


def _ftbo(pb: Problem, p: Params, free: Free, t0, trace, maxiter=100, scan=True):
    """F-TBO: θ (search space) by Levenberg–Marquardt over the exact inner linear solution.

    With ``scan``, a coarse global step (:func:`_scan`) first picks each θ's basin.

    The profiled objective's gradient is the partial derivative at the inner optimum (envelope
    theorem); its Gauss–Newton curvature is the Schur complement of the full normal matrix on
    θ (variable projection), which costs a few monomial-space products per iteration.
    """
    srch = pb.search
    q = np.flatnonzero(free.theta)
    evaluate = _evaluator(pb, free, q)
    u = srch.to_u(p.theta)[q]
    E, g, cur, A, grad, res = evaluate(u, p)
    trace.append(_trace_point(t0, pb.rms(res)))
    if len(q) == 0:
        return cur, 0, "no nonlinear parameter to fit: one exact linear solve"
    coarse = _coarse(pb) if scan else None
    if coarse is not None:
        # The basins from a quarter of the pixels; the full image evaluates the chosen θ once.
        t_scan = time.perf_counter()
        ev = _evaluator(coarse, free, q)
        cu, cstate = _scan(coarse, q, u, ev(u, cur), ev, t0, [])
        if not np.array_equal(cu, u):
            u, (E, g, cur, A, grad, res) = cu, evaluate(cu, cstate[2])
            trace.append(_trace_point(t0, pb.rms(res)))
        pb.evaluations += coarse.evaluations
        pb.scan_evaluations += coarse.evaluations
        pb.phases["scan"] += time.perf_counter() - t_scan
    elif scan:
        u, (E, g, cur, A, grad, res) = _scan(pb, q, u, (E, g, cur, A, grad, res), evaluate, t0, trace)
    lam, message, it = 1e-3, f"stopped after {maxiter} iterations", 0
    lo, hi = srch.lo[q], srch.hi[q]
    for it in range(1, maxiter + 1):
        pb.step(it, maxiter, _step_message("F-TBO iteration", trace))
        if pb.out_of_time():
            it -= 1
            message = BUDGET_MESSAGE
            break
        S = _theta_curvature(pb, cur, free, A, grad) * np.outer(srch.dtheta_du(cur.theta)[q], srch.dtheta_du(cur.theta)[q])
        S = 2.0 * S / pb.norm
        if _predicted_gain(S, g, u, lo, hi) <= STOP_GAIN * E:
            message = "converged: the Gauss-Newton step predicts no further gain"
            break
        improved = False
        for _ in range(12):  # damping increases until a step lowers ε
            step = -np.linalg.solve(S + lam * np.diag(np.maximum(np.diag(S), 1e-300)), g)
            u_new = np.clip(u + step, lo, hi)
            trial = evaluate(u_new, cur)
            if trial[0] < E:
                improved = True
                break
            lam *= 4.0
        if not improved:
            message = "converged: no step lowers the error"
            break
        gain, moved = E - trial[0], float(np.max(np.abs(u_new - u)))
        u, (E, g, cur, A, grad, res) = u_new, trial
        lam = max(lam / 3.0, 1e-12)
        trace.append(_trace_point(t0, pb.rms(res)))
        if moved < 1e-10 or gain <= 1e-12 * (E + gain) or E == 0.0:
            message = "converged: step or error change below tolerance"
            break
    return cur, it, message


def _evaluator(pb: Problem, free: Free, q):
    """F-TBO's objective at θ search values ``u`` (the free θ ``q``), linear parameters solved exactly.

    Returns ``evaluate(u, start) -> (ε, dε/du, params, A, grad, residual)``; ``start`` warm-starts
    the inner solve.
    """
    fac, srch = pb.fac, pb.search

    def evaluate(u, start: Params):
        cur = start.copy()
        full = srch.to_u(cur.theta)
        full[q] = u
        cur.theta = srch.to_theta(full)
        A, grad = fac.matrices_and_grad(cur.theta)
        _Inner(pb, A).solve(cur, free)
        y = fac.y(cur.x, cur.s)
        res = pb.residual(A, y)
        pb.evaluations += 1
        E = float(np.sum(res * res)) / pb.norm
        g = 2.0 * grad(res, y)[q] * srch.dtheta_du(cur.theta)[q] / pb.norm
        return E, g, cur, A, grad, res

    return evaluate


def _coarse(pb: Problem):
    """The problem on every second used pixel in x and y, or None below :data:`COARSE_MIN_ROWS`.

    It keeps the full image's noise σ, deadline and task; its scan threshold scales with its
    share of the pixels, so that it keeps the candidates the full image would.
    """
    fac = pb.fac
    if fac.n_rows < COARSE_MIN_ROWS:
        return None
    x, y = fac.rows % fac.width, fac.rows // fac.width
    sub = fac.without(fac.rows[(x % 2 == 1) | (y % 2 == 1)])
    image = np.zeros((fac.width * fac.height, BANDS))
    image[fac.rows] = pb.b.T
    coarse = Problem(sub, image.reshape(fac.height, fac.width, BANDS), pb.transparent)
    coarse.noise, coarse.deadline, coarse.task = pb.noise, pb.deadline, pb.task
    coarse.scan_share = sub.n_rows / fac.n_rows
    return coarse


def _predicted_gain(S, g, u, lo, hi) -> float:
    """Decrease of ε that the undamped Gauss–Newton step on θ (kept within the bounds) predicts."""
    w, V = np.linalg.eigh(S)
    keep = w > max(w.max(), 0.0) * 1e-12
    if not keep.any():
        return np.inf
    d = np.clip(u - (V[:, keep] / w[keep]) @ (V[:, keep].T @ g), lo, hi) - u
    return float(-(g @ d + 0.5 * d @ S @ d))


def _scan(pb: Problem, q, u, state, evaluate, t0, trace):
    """Coarse coordinate-wise scan of each free θ over its whole search range (global step).

    The linear parameters are solved exactly for every candidate θ, so a handful of values per
    surface (:data:`SCAN_POINTS`, log2 for shininess) tells which basin holds the highlight: a
    start at ns = 2^14 sees flat highlights that a local method cannot leave. A candidate is kept
    only when it lowers ε by more than :data:`SCAN_GAIN` times the image noise variance per band,
    so a θ whose columns carry no signal (hidden highlight) is never moved by noise or rounding.
    """
    srch = pb.search
    gain_min = SCAN_GAIN * pb.scan_share * float(np.sum(pb.noise**2)) / pb.norm
    t_scan, n_scan = time.perf_counter(), pb.evaluations
    for _ in range(SCAN_SWEEPS):
        moved = False
        for k, qk in enumerate(q):  # coordinate-wise: one θ at a time, the others at their best so far
            best_u, best = None, state
            for value in np.linspace(pb.scan_lo[qk], pb.scan_hi[qk], SCAN_POINTS):
                if abs(value - u[k]) < 1e-12 or pb.out_of_time():
                    continue
                pb.task.check()
                trial_u = u.copy()
                trial_u[k] = value
                trial = evaluate(trial_u, state[2])
                if trial[0] < best[0] - gain_min:
                    best_u, best = trial_u, trial
            if best_u is not None:
                u, state, moved = best_u, best, True
                trace.append(_trace_point(t0, pb.rms(state[5])))
        if not moved:
            break
    pb.phases["scan"] += time.perf_counter() - t_scan
    pb.scan_evaluations += pb.evaluations - n_scan
    return u, state


def _theta_curvature(pb: Problem, p: Params, free: Free, A, grad) -> np.ndarray:
    """JᵀJ of θ with the linear parameters profiled out (Schur complement), natural units."""
    inner = Free(free.x & (p.x > 0), free.s & (p.s > 0) & (p.s < 1), free.theta)  # bounds active: held
    # :func:`_normal_matrix`'s blocks, in monomial space: (A D)ᵀ(A D) = Dᵀ(AᵀA)D and (A D)ᵀ img =
    # Dᵀ(Aᵀ img), so no (pixels × parameters) product is formed (640×480: 78 → 30 ms).
    q = np.flatnonzero(free.theta)
    img = grad.images(pb.fac.y(p.x, p.s))[q]  # (nq, 3, R)
    Hqq = np.einsum("qcr,pcr->qp", img, img)
    blocks, cross = [], []
    for c in range(BANDS):
        D, _ = pb.dy(p, c, inner)
        if D.shape[1]:
            blocks.append(D.T @ (A[c].T @ A[c]).toarray() @ D)
            cross.append(D.T @ np.asarray(A[c].T @ img[:, c, :].T))
    n_lin = sum(b.shape[0] for b in blocks)
    if n_lin == 0:
        return Hqq
    Hll = np.zeros((n_lin, n_lin))
    off = 0
    for b in blocks:
        Hll[off:off + len(b), off:off + len(b)] = b
        off += len(b)
    Hlq = np.concatenate(cross)
    w, V = np.linalg.eigh(Hll)
    keep = w > max(w.max(), 0.0) * 1e-13
    proj = V[:, keep].T @ Hlq
    return Hqq - proj.T @ (proj / w[keep][:, None])


class _NFMap:
    """NF-TBO's unconstrained variables z ↔ bounded parameters (free ones only)."""

    def __init__(self, pb: Problem, p: Params, free: Free):
        self.pb, self.base, self.free = pb, p, free
        self.q = np.flatnonzero(free.theta)
        srch = pb.search
        self.lo, self.hi = srch.lo[self.q], srch.hi[self.q]

    def to_z(self, p: Params) -> np.ndarray:
        w = np.sqrt(np.maximum(p.x[self.free.x], 0.0))
        phi = np.arcsin(np.sqrt(np.clip(p.s[self.free.s], 0.0, 1.0)))
        u = self.pb.search.to_u(p.theta)[self.q]
        span = np.maximum(self.hi - self.lo, 1e-300)
        psi = np.arcsin(np.sqrt(np.clip((u - self.lo) / span, 0.0, 1.0)))
        return np.concatenate([w, phi, psi])

    def to_params(self, z):
        """Parameters and dparam/dz (diagonal) of the free ones."""
        nx, ns = int(self.free.x.sum()), int(self.free.s.sum())
        w, phi, psi = z[:nx], z[nx:nx + ns], z[nx + ns:]
        p = self.base.copy()
        p.x[self.free.x] = w * w
        p.s[self.free.s] = np.sin(phi) ** 2
        span = self.hi - self.lo
        u = self.pb.search.to_u(p.theta)
        u[self.q] = self.lo + span * np.sin(psi) ** 2
        p.theta = self.pb.search.to_theta(u)
        d = np.concatenate([2.0 * w, np.sin(2.0 * phi), span * np.sin(2.0 * psi) * self.pb.search.dtheta_du(p.theta)[self.q]])
        return p, d


def _gradient(pb: Problem, p: Params, A, grad, res):
    """∂ε/∂(x, s, θ) (natural units, unnormalised halves excluded): full arrays."""
    fac = pb.fac
    y = fac.y(p.x, p.s)
    gy = 2.0 * np.stack([A[c].T @ res[c] for c in range(BANDS)])  # (3, C)
    prod = fac.factor_products(p.s)
    gx = np.stack([np.bincount(fac.col_x, weights=gy[c] * prod[:, c], minlength=fac.layout.n_x) for c in range(BANDS)], axis=1)
    gs = np.zeros_like(p.s)
    for f in np.flatnonzero(fac.exponents.any(axis=0)):  # factors: 2 per surface
        e = fac.exponents[:, f]
        rest = fac.factor_products(p.s, skip=f)
        d = np.where(e[:, None] > 0, e[:, None] * p.s[f][None, :] ** np.maximum(e[:, None] - 1, 0) * rest, 0.0)
        gs[f] = np.einsum("cm,mc->c", gy, p.x[fac.col_x] * d)
    gth = 2.0 * grad(res, y)
    return gx, gs, gth


def _nftbo(pb: Problem, p: Params, free: Free, t0, trace, maxiter=5000):
    """NF-TBO: preconditioned Polak–Ribière (PR+) conjugate gradient on all free parameters at once.

    Works on the bounded reparametrisation of :class:`_NFMap`. The preconditioner is the diagonal
    of the Gauss–Newton matrix, refreshed at every restart (every n iterations, or when the
    direction stops descending); the step length is the Gauss–Newton minimiser along the
    direction, backtracked until the error falls (Armijo).
    """
    fac = pb.fac
    m = _NFMap(pb, p, free)
    n = len(m.to_z(p))

    def evaluate(z):
        cur, d = m.to_params(z)
        A, grad = fac.matrices_and_grad(cur.theta)
        y = fac.y(cur.x, cur.s)
        res = pb.residual(A, y)
        pb.evaluations += 1
        gx, gs, gth = _gradient(pb, cur, A, grad, res)
        g = np.concatenate([gx[free.x], gs[free.s], gth[m.q]]) * d / pb.norm
        return {"z": z, "E": float(np.sum(res * res)) / pb.norm, "g": g, "p": cur, "d": d, "A": A, "grad": grad, "y": y, "res": res}

    st = evaluate(m.to_z(p))
    trace.append(_trace_point(t0, pb.rms(st["res"])))
    if n == 0:
        return st["p"], 0, "nothing to fit"
    cap_theta = np.where(pb.search.log[m.q], np.log(2.0) * st["p"].theta[m.q], 0.1 * (m.hi - m.lo))
    message, it, since_restart, direction, prev = f"stopped after {maxiter} iterations", 0, n, None, None
    stalls = 0
    for it in range(1, maxiter + 1):
        pb.step(it, maxiter, _step_message("NF-TBO iteration", trace))
        if pb.out_of_time():
            it -= 1
            message = BUDGET_MESSAGE
            break
        if since_restart >= n or direction is None:
            diag = _gn_diagonal(pb, m, st["z"])
            precond = 1.0 / np.maximum(diag, 1e-10 * max(diag.max(), 1e-300))
            since_restart, prev = 0, None
        s = precond * st["g"]
        cap = np.concatenate([np.maximum(st["p"].x[free.x], 0.1), np.full(int(free.s.sum()), 0.25),
                              np.where(pb.search.log[m.q], np.log(2.0) * st["p"].theta[m.q], cap_theta)])
        if prev is None:
            direction = -s
        else:
            beta = max(0.0, float(st["g"] @ (s - prev[1])) / max(float(prev[0] @ prev[1]), 1e-300))
            direction = -s + beta * direction
        slope = float(st["g"] @ direction)
        if slope >= 0:
            direction, slope = -s, float(-(st["g"] @ s))
        curv = 2.0 * float(np.sum(_directional(pb, st, m, direction) ** 2)) / pb.norm
        alpha = -slope / curv if curv > 0 else 1.0
        # Trust region: to first order no x moves by more than max(x, 0.1), no r or t by more
        # than 0.25, no log2 θ by more than 1 (flat valleys such as ks → ∞ with ns → ∞ stay shut).
        move = np.abs(direction * st["d"])
        alpha = min(alpha, float(np.min(cap / np.maximum(move, 1e-300))))
        new = None
        for _ in range(30):  # Armijo backtracking
            trial = evaluate(st["z"] + alpha * direction)
            if trial["E"] <= st["E"] + 1e-4 * alpha * slope:
                new = trial
                break
            alpha *= 0.25
        if new is None:
            if since_restart == 0:
                message = "converged: no descent step lowers the error"
                break
            direction = None  # restart along the preconditioned gradient
            continue
        gain = st["E"] - new["E"]
        prev = (st["g"], s)
        st = new
        since_restart += 1
        trace.append(_trace_point(t0, pb.rms(st["res"])))
        stalls = stalls + 1 if gain <= 1e-13 * (st["E"] + gain) else 0
        if st["E"] == 0.0 or stalls >= 3:
            message = "converged: error change below tolerance"
            break
    return st["p"], it, message


def _directional(pb: Problem, st: dict, m: "_NFMap", dz) -> np.ndarray:
    """Image change (3, R) along ``dz`` to first order (Gauss–Newton), z-space direction."""
    fac, free, p = pb.fac, m.free, st["p"]
    dpar = dz * st["d"]
    nx, ns = int(free.x.sum()), int(free.s.sum())
    dx, ds = np.zeros_like(p.x), np.zeros_like(p.s)
    dx[free.x], ds[free.s] = dpar[:nx], dpar[nx:nx + ns]
    dy = dx[fac.col_x] * fac.factor_products(p.s)
    for f in np.flatnonzero(free.s.any(axis=1)):
        e = fac.exponents[:, f]
        rest = fac.factor_products(p.s, skip=f)
        dy += np.where(e[:, None] > 0, e[:, None] * p.s[f][None, :] ** np.maximum(e[:, None] - 1, 0) * rest, 0.0) * p.x[fac.col_x] * ds[f][None, :]
    out = np.stack([st["A"][c] @ dy[:, c] for c in range(BANDS)])
    if len(m.q):
        img = st["grad"].images(st["y"])[m.q]
        out += np.einsum("q,qcr->cr", dpar[nx + ns:], img)
    return out


def _gn_diagonal(pb: Problem, m: _NFMap, z) -> np.ndarray:
    """Gauss–Newton curvature ‖∂B/∂z_i‖² / norm of each NF-TBO variable (z order)."""
    cur, d = m.to_params(z)
    H, labels = _normal_matrix(pb, cur, m.free, np.ones(BANDS))
    pos = {"x": np.full(m.free.x.shape, -1), "s": np.full(m.free.s.shape, -1)}
    nx, ns = int(m.free.x.sum()), int(m.free.s.sum())
    pos["x"][m.free.x] = np.arange(nx)
    pos["s"][m.free.s] = nx + np.arange(ns)
    theta_pos = {q: nx + ns + k for k, q in enumerate(m.q)}
    order = [pos[kind][i, c] if kind != "theta" else theta_pos[i] for kind, i, c in labels]
    diag = np.zeros(len(z))
    diag[order] = np.diag(H)
    return diag * d * d / pb.norm


def _normal_matrix(pb: Problem, p: Params, free: Free, weights, A=None, grad=None, res=None, tiles=None, keep=None):
    """JᵀWJ of the free parameters (natural units) with band weights; and the label of each row.

    ``A``, ``grad`` from ``fac.matrices_and_grad(p.theta)`` when the caller has them. With the
    residual ``res`` (3, R) and ``tiles`` = (tile of each used pixel, T), also the per-tile
    gradients ``g_t = Σ_{i∈t} J_iᵀ W r_i`` (n, T) of :func:`inverse.uncertainty.covariance`.
    ``keep`` (R,) bool: only these pixels inform (the others' rows count as zero).
    """
    fac = pb.fac
    if A is None:
        A, grad = fac.matrices_and_grad(p.theta)
    y = fac.y(p.x, p.s)
    q = np.flatnonzero(free.theta)
    img = grad.images(y)[q] if len(q) else np.zeros((0, BANDS, fac.n_rows))  # (nq, 3, R)
    if keep is not None:
        img = img * keep
        res = None if res is None else res * keep
    blocks, labels = [], []
    for c in range(BANDS):
        D, lab = pb.dy(p, c, free)
        blocks.append(D)
        labels += [(kind, i, c) for kind, i in lab]
    n_lin = sum(b.shape[1] for b in blocks)
    n = n_lin + len(q)
    H = np.zeros((n, n))
    scores = None
    if res is not None:
        from scipy.sparse import csr_matrix

        tile, n_tiles = tiles
        P = csr_matrix((np.ones(len(tile)), (np.arange(len(tile)), tile)), shape=(len(tile), n_tiles))
        wr = weights[:, None] * res  # (3, R)
        scores = np.zeros((n, n_tiles))
        if len(q):
            scores[n_lin:] = np.asarray((P.T @ np.einsum("qcr,cr->rq", img, wr)).T)
    off = 0
    for c in range(BANDS):
        D = blocks[c]
        k = D.shape[1]
        AD = A[c] @ D  # (R, k): image derivatives of band c's linear parameters
        if keep is not None:
            AD = AD * keep[:, None]
        if scores is not None and k:
            scores[off:off + k] = np.asarray((P.T @ (AD * wr[c][:, None])).T)
        H[off:off + k, off:off + k] = weights[c] * (AD.T @ AD)
        if len(q):
            cross = weights[c] * (AD.T @ img[:, c, :].T)
            H[off:off + k, n_lin:] = cross
            H[n_lin:, off:off + k] = cross.T
        off += k
    if len(q):
        H[n_lin:, n_lin:] = np.einsum("c,qcr,pcr->qp", weights, img, img)
    labels += [("theta", i, -1) for i in q]
    if res is not None:
        return H, labels, scores
    return H, labels


def uncertainty(pb: Problem, p: Params, free: Free, res, robust: bool = True, keep=None) -> Params:
    """One-sigma uncertainties (natural units) of the free parameters; inf where unconstrained.

    The noise of band c is estimated from its residual, but never below :data:`NOISE_FLOOR` of
    the image peak; the model-based covariance is ``(JᵀWJ)⁻¹`` with ``W = 1/σ_c²``. With
    ``robust`` each σ is the larger of that and the cluster-robust sandwich over image tiles
    (:mod:`inverse.uncertainty`), which holds when the model is imperfect. ``keep`` (R,) bool:
    only these pixels inform (:func:`texture_absorbed` leaves out what a free texture explains).
    Never NaN.
    """
    from inverse.uncertainty import COARSE_FACTOR, coarser, covariance, tile_index

    n_free = free.count()
    dof = max(BANDS * pb.fac.n_rows - n_free, 1)
    var = np.sum(res * res, axis=1) / max(dof / BANDS, 1.0)
    var = np.maximum(var, (NOISE_FLOOR * pb.peak) ** 2)
    sig = Params(np.full_like(p.x, np.inf), np.full_like(p.s, np.inf), np.full_like(p.theta, np.inf))
    if robust:
        tiles = tile_index(pb.fac.rows, pb.fac.width, pb.fac.height)
        H, labels, scores = _normal_matrix(pb, p, free, 1.0 / var, res=res, tiles=tiles, keep=keep)
    else:
        (H, labels), scores = _normal_matrix(pb, p, free, 1.0 / var, keep=keep), None
    if not labels:
        return sig
    model, sandwich = covariance(H, scores)
    if scores is not None:
        group, n_big = coarser(pb.fac.rows, pb.fac.width, pb.fac.height, COARSE_FACTOR)
        big = np.zeros((scores.shape[0], n_big))
        np.add.at(big.T, group, scores.T)
        sandwich = np.fmax(sandwich, covariance(H, big)[1])
    sd = np.fmax(model, sandwich)
    sd = np.where(np.isnan(sd), np.inf, sd)
    for (kind, i, c), v in zip(labels, sd):
        if kind == "x":
            sig.x[i, c] = v
        elif kind == "s":
            sig.s[i, c] = v
        else:
            sig.theta[i] = v
    return sig


def _structural_free(pb: Problem, p: Params) -> Free:
    """Parameters with signal in their columns (exact zeros left out).

    Signal counts at the initial θ or anywhere on the global scan's grid (:func:`_scan`): a start
    at ns = 2^14 hides every highlight that a broader lobe would show.
    """
    fac, lay, srch = pb.fac, pb.fac.layout, pb.search
    floor = SIGNAL_FLOOR * max(pb.peak, 1e-300)
    live = np.zeros((fac.n_columns, BANDS), dtype=bool)
    th_free = np.zeros(lay.n_theta, dtype=bool)
    u0 = srch.to_u(p.theta)
    for k in range(SCAN_POINTS + 1 if lay.n_theta else 1):  # the initial θ, then the scan grid
        u = u0 if k == 0 else pb.scan_lo + (pb.scan_hi - pb.scan_lo) * (k - 1) / (SCAN_POINTS - 1)
        A, grad = fac.matrices_and_grad(srch.to_theta(u))
        now = np.stack([abs(A[c]).max(axis=0).toarray().ravel() for c in range(BANDS)], axis=1) > floor  # (C, 3)
        live |= now
        if lay.n_theta:
            # θ acts through the columns of its surface's x: only those with signal count.
            img = grad.images(now.T.astype(np.float64))
            th_free |= np.abs(img).max(axis=(1, 2)) > floor
            if th_free.all() and k > 0:
                break
    x_free = np.zeros((lay.n_x, BANDS), dtype=bool)
    np.logical_or.at(x_free, fac.col_x, live)
    s_free = np.zeros((lay.n_factors, BANDS), dtype=bool)
    for f in np.flatnonzero(fac.exponents.any(axis=0)):
        s_free[f] = live[fac.exponents[:, f] > 0].any(axis=0)
    for i, transparent in enumerate(pb.transparent):
        if not transparent:
            s_free[2 * i + 1] = False
    return Free(x_free, s_free, th_free)


def _unresolved(pb: Problem, p: Params, init: Params, free: Free, sig: Params, A, theta_resolve=RESOLVE,
                bounds_hold: bool = True) -> Free:
    """Free parameters whose one-sigma exceeds :data:`RESOLVE` of their scale.

    ``A`` = ``fac.matrices(p.theta)``, the system at the fitted θ. With ``bounds_hold`` a value
    pinned at a bound counts as determined whatever its σ (the fit's rounds); without, it is
    judged by its σ like any other (the final report: ks = 0 ± 3000 is undetermined).
    """
    fac = pb.fac
    # Scale of x: its value, but at most 1 (albedo units) — a ks of 1e9 under a faint lobe tail
    # must not count as resolved relative to itself — and at least its initial value.
    xs = np.maximum(np.maximum(np.minimum(np.abs(p.x), 1.0), np.abs(init.x)), 1e-3)
    # A parameter pinned at a bound is held there by the data (moving inside would show), even
    # where the linearisation is blind to it (t² has zero slope at t = 0) — but only if its
    # columns show at the fitted θ (ks = 0 under a held ns = 2^14 is seen by no pixel).
    live = np.stack([abs(A[c]).max(axis=0).toarray().ravel() for c in range(BANDS)], axis=1) > SIGNAL_FLOOR * max(pb.peak, 1e-300)
    seen = np.zeros_like(free.x)
    np.logical_or.at(seen, fac.col_x, live)
    bad_x = free.x & ~(sig.x <= RESOLVE * xs) & ((p.x > BOUND_TOL * xs) | ~seen | (not bounds_hold))
    bad_s = free.s & ~(sig.s <= RESOLVE) & (((p.s > BOUND_TOL) & (p.s < 1.0 - BOUND_TOL)) | (not bounds_hold))
    # A shininess pinned at its lower bound is a lobe as broad as diffuse light: it trades with kd
    # and fits misfit, not a highlight (docs/fit.md).
    pinned = pb.search.log & (pb.search.to_u(p.theta) <= pb.search.lo + 1e-6)
    bad_t = free.theta & (~(_theta_resolution(pb, p, sig) <= theta_resolve) | pinned)
    return Free(bad_x, bad_s, bad_t)


def _theta_resolution(pb: Problem, p: Params, sig: Params) -> np.ndarray:
    """σ of each θ relative to its scale: in log2 units for :data:`LOG2` names, else of the range."""
    srch = pb.search
    return np.where(srch.log, sig.theta / np.maximum(p.theta * np.log(2.0), 1e-300),
                    sig.theta / np.maximum(srch.hi - srch.lo, 1e-300))


@one_blas_thread
def fit(fac: Factorization, image, materials, method: str = "ftbo", *, max_rounds: int | None = None,
        maxiter: int | None = None, max_seconds: float | None = None, textured=None,
        names=None, scan: bool = True, task: Task | None = None, held=None, reject: bool = True) -> FitResult:
    """Fit every determinable photometric parameter from one image.

    Parameters
    ----------
    fac : Factorization
        The scene's factorized system (its ``rows`` are the pixels used, e.g. saturated ones left out).
    image : (H, W, 3) array_like
        Linear radiance (validated with :func:`check_image`).
    materials : list of Material
        Initial values, one per surface (scene.json's, else METHOD.md §3's). Their ``ior`` says
        which surfaces are transparent.
    method : {"ftbo", "nftbo"}
    max_rounds : int, optional
        Fit → find unresolved parameters → fix them → refit, at most this many times (default:
        3 + the number of nonlinear parameters, as θ are held one per round).
    maxiter : int, optional
        Outer iteration cap (Levenberg–Marquardt for F-TBO, CG for NF-TBO).
    max_seconds : float, optional
        Wall-clock budget of the fit: the methods stop at their next iteration once it is spent
        (``message`` = :data:`BUDGET_MESSAGE`), and the uncertainties are computed where they stopped.
    textured : list of bool, optional
        Per surface: its albedo varies (scene.json ``textured``), so the diagnosis
        (:func:`diagnose`) excuses a residual up to its diffuse radiance. Default: none textured.
    names : list of str, optional
        Surface names for the diagnosis' warnings (default ``surface 0``, …).
    scan : bool
        F-TBO's coarse global scan of each θ before the local search (off when ``materials``
        already start near the answer, e.g. a refit).
    task : hardware.task.Task, optional
        Stepped once per outer iteration (raises ``Cancelled`` when cancelled); its deadline
        stops the methods like ``max_seconds``.
    held : list of set of str, optional
        Per surface, the parameter names the user gave (scene.json): held at their value, never
        fitted (default: none; :func:`fit_workspace` passes every name not ``defaulted``).
    reject : bool or int
        Passes (True: :data:`REJECT_PASSES`) in which outlier pixels (:func:`outliers`: residual beyond :data:`REJECT_SIGMAS` image-noise σ,
        at most :data:`REJECT_SHARE` of the used pixels) are left out and the fit repeated from
        where it stopped; ``stats["rejected"]`` counts and lists them.

    Returns
    -------
    FitResult
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if len(materials) != len(fac.models):
        raise ValueError(f"{len(materials)} materials for {len(fac.models)} surfaces")
    t0 = time.perf_counter()
    pb = Problem(fac, image, [m.transparent for m in materials])
    pb.task = ensure(task)
    if max_seconds is not None:
        pb.deadline = t0 + float(max_seconds)
    init = params_of(fac, materials)
    srch = pb.search
    init.theta = srch.to_theta(srch.to_u(init.theta))
    p = init.copy()
    free = _structural_free(pb, p)
    pb.phases["structure"] = time.perf_counter() - t0
    if held is not None:
        _hold(fac, free, held)
    trace, iterations, message = [], 0, ""
    rounds = 0
    kw = {} if maxiter is None else {"maxiter": maxiter}
    max_rounds = 3 + fac.layout.n_theta if max_rounds is None else max_rounds
    for rounds in range(1, max_rounds + 1):
        t_method = time.perf_counter()
        if method == "ftbo":
            # The global scan picks the basins once; later rounds only hold parameters.
            p, nit, message = _ftbo(pb, p, free, t0, trace, scan=scan and rounds == 1, **kw)
        else:
            p, nit, message = _nftbo(pb, p, free, t0, trace, **kw)
        pb.phases["refinement"] += time.perf_counter() - t_method
        clip(fac, p)  # NF-TBO's reparametrisation has no upper bounds (F-TBO stays inside)
        iterations += nit
        A = fac.matrices(p.theta)
        res = pb.residual(A, fac.y(p.x, p.s))
        # Which parameters to hold: the model-based σ (the data's own resolution); the robust σ
        # below also counts misfit, which holding a parameter at its start would not cure.
        sig = uncertainty(pb, p, free, res, robust=False)
        bad = _unresolved(pb, p, init, free, sig, A)
        if bad.count() == 0 or pb.out_of_time():
            break
        if bad.theta.any():
            # θ first: an unresolved shininess inflates its ks's σ; with θ held, ks is judged alone.
            # Only the worst θ per round: a misfit elsewhere (a hidden highlight still settling)
            # inflates every σ, and a two-pixel highlight resolves once the rest is refitted.
            worst = np.nanargmax(np.where(bad.theta, _theta_resolution(pb, p, sig), -np.inf))
            bad.theta[:] = False
            bad.theta[worst] = True
            bad.x[:], bad.s[:] = False, False
        # Hold the unresolved ones at their initial value and refit the rest from there.
        for name in ("x", "s", "theta"):
            cur, b0, fr = getattr(p, name), getattr(init, name), getattr(bad, name)
            cur[fr] = b0[fr]
            getattr(free, name)[fr] = False
        if rounds == max_rounds:
            A = fac.matrices(p.theta)
            res = pb.residual(A, fac.y(p.x, p.s))
    sig = uncertainty(pb, p, free, res)
    absorbed = texture_absorbed(fac, p, materials, textured)
    if absorbed.any():
        # A free texture explains every pixel where it is seen directly: σ from the others only
        # (kd of a textured surface is its texture's mean: its σ stays the one from every pixel).
        tex_kd = np.array([bool(textured[s]) and name == "kd" for s, name in fac.layout.x_names], dtype=bool)
        # The texture (its mean kd included) counts as known from the pixels that see it directly.
        sig_t = uncertainty(pb, p, Free(free.x & ~tex_kd[:, None], free.s, free.theta), res, keep=~absorbed)
        sig = Params(np.where(tex_kd[:, None], sig.x, np.fmax(sig.x, sig_t.x)), np.fmax(sig.s, sig_t.s),
                     np.fmax(sig.theta, sig_t.theta))
    # Fitted, but the robust σ spans its scale (a value on a bound included): reported undetermined.
    loose = _unresolved(pb, p, init, free, sig, A, theta_resolve=RESOLVE_THETA, bounds_hold=False)
    # A lobe's ks means nothing without its shininess: held or undetermined θ makes its ks so too.
    lay = fac.layout
    for k, (s, name) in enumerate(lay.x_names):
        th = slice(lay.theta_offset[s], lay.theta_offset[s + 1])
        if name != "kd" and (np.any(~free.theta[th]) or np.any(loose.theta[th])):
            loose.x[k] |= free.x[k]
    elapsed = time.perf_counter() - t0
    rms = pb.rms(res)
    trace.append(_trace_point(t0, rms))
    status, warnings = diagnose(pb, p, A, res, textured, names)
    elapsed = time.perf_counter() - t0
    pb.phases["refinement"] -= pb.phases["scan"]
    pb.phases["uncertainty"] = elapsed - sum(pb.phases.values())  # with the holding rounds and the diagnosis
    if message.startswith("stopped"):  # iteration cap or wall-clock budget
        warnings.insert(0, f"the fit did not converge ({message})")
        status = "not converged" if status == "ok" else status
    if int(reject) > 0 and not message.startswith("stopped"):
        bad = outliers(pb, p, A, res, textured)
        if 0 < len(bad) <= REJECT_SHARE * fac.n_rows:
            first = FitResult(method, p, free, materials_of(fac, p, materials), sig, rms, elapsed, trace, [], rounds,
                              pb.evaluations, iterations, message,
                              {"phases_s": dict(pb.phases), "scan_evaluations": pb.scan_evaluations})
            return _refit_without(first, fac, image, bad, method, maxiter=maxiter, textured=textured, names=names,
                                  task=task, held=held, t0=t0, passes=REJECT_PASSES if reject is True else int(reject),
                                  max_seconds=None if max_seconds is None else max_seconds - elapsed)
    return FitResult(method, p, free, materials_of(fac, p, materials), sig, rms, elapsed, trace,
                     _undetermined(fac, free, materials, loose), rounds, pb.evaluations, iterations, message,
                     {"used_pixels": int(fac.n_rows), "free_parameters": free.count(), "at_bound": at_bound(fac, p, free),
                      "noise": [float(v) for v in pb.noise], "status": status, "warnings": warnings,
                      "phases_s": {k: round(v, 6) for k, v in pb.phases.items()}, "scan_evaluations": pb.scan_evaluations,
                      "rejected": {"count": 0, "pixels": [], "threshold_sigmas": REJECT_SIGMAS}})


def texture_absorbed(fac: Factorization, p: Params, materials, textured) -> np.ndarray:
    """(R,) bool: used pixels where free texture carries at least :data:`ABSORB_SHARE` of the
    predicted light in some band.

    A texture free per texel (about one per pixel) can take up any residual where it shows — a
    highlight, a faint reflection — unless the same texel is pinned down elsewhere. Texture seen
    directly is free; texture seen only in a mirror or through glass (the demo box's back face) is
    free too; texture seen there AND directly (a floor in a mirror) is fixed by the direct view.
    So only pixels without free texture tell a specular term from albedo. Which points are seen
    directly: cells of twice the mean spacing of the surface's directly seen nodes.
    """
    if textured is None or not any(textured):
        return np.zeros(fac.n_rows, dtype=bool)
    from inverse.rendering import node_radiance

    tr = fac.trees
    surf, level, pts = np.asarray(tr.surface), np.asarray(tr.level), np.asarray(tr.point, dtype=np.float64)
    light = np.abs(node_radiance(tr, materials_of(fac, p, materials), fac._args[0]))
    tex = np.asarray(textured, dtype=bool)[surf]
    free_tex = tex & (level == 1)
    for s in np.flatnonzero(np.asarray(textured, dtype=bool)):
        direct, seen_else = (surf == s) & (level == 1), (surf == s) & (level > 1)
        if not seen_else.any():
            continue
        if not direct.any():
            free_tex |= seen_else
            continue
        ext = np.sort(np.ptp(pts[direct], axis=0))[::-1]
        cell = 2.0 * np.sqrt(max(ext[0] * ext[1], 1e-12) / direct.sum())
        key = np.floor(pts / cell).astype(np.int64)
        both = direct | seen_else
        lo = key[both].min(axis=0)
        span = key[both].max(axis=0) - lo + 1
        flat = np.ravel_multi_index(tuple((key - lo).clip(0).T), tuple(span), mode="clip")
        free_tex |= seen_else & ~np.isin(flat, flat[direct])
    npix = fac.width * fac.height
    out = np.zeros(fac.n_rows, dtype=bool)
    for c in range(BANDS):
        total = np.bincount(tr.pixel, weights=light[:, c], minlength=npix)[fac.rows]
        part = np.bincount(tr.pixel[free_tex], weights=light[free_tex, c], minlength=npix)[fac.rows]
        out |= part > ABSORB_SHARE * np.maximum(total, 1e-300)
    return out


def outliers(pb: Problem, p: Params, A, res, textured=None) -> np.ndarray:
    """Flat pixel indices whose residual exceeds :data:`REJECT_SIGMAS` σ in some band (σ the image
    noise or 1.4826 × the median absolute residual, the larger).

    The same test as :func:`diagnose`'s (plus :data:`DIAG_FLOOR` of the peak, plus on textured
    surfaces the diffuse radiance their homogeneous kd predicts), at a lower threshold.
    """
    fac = pb.fac
    textured = [False] * len(fac.models) if textured is None else [bool(t) for t in textured]
    # The scale: the image noise, or the residual's own robust spread when larger (an outlier that
    # pulled the fit leaves every pixel a little off, far below its own residual).
    spread = 1.4826 * np.median(np.abs(res), axis=1) if res.size else np.zeros(BANDS)
    tol = np.broadcast_to((REJECT_SIGMAS * np.maximum(pb.noise, spread) + DIAG_FLOOR * pb.peak)[:, None], res.shape).copy()
    diffuse = np.array([textured[s] and fac.layout.x_names[i][1] == "kd" for s, i in zip(fac.col_surface, fac.col_x)], dtype=bool)
    if diffuse.any() and fac.albedo is None:
        y = fac.y(p.x, p.s)
        tol += np.stack([A[c] @ np.where(diffuse, y[c], 0.0) for c in range(BANDS)])
    excess = np.max(np.abs(res) / tol, axis=0)
    over = excess > 1.0
    if over.sum() > REJECT_SHARE * fac.n_rows:
        # Too many to be outliers — unless a few strong ones pulled the fit so that the rest
        # misfit a little: take the worst (over half the largest excess) first, refit, repeat.
        over &= excess > 0.5 * excess.max()
    return fac.rows[over]


def _refit_without(first: FitResult, fac: Factorization, image, bad, method, *, t0, passes, **kw) -> FitResult:
    """Fit again from ``first`` with the pixels ``bad`` left out; traces, counts and time add up."""
    again = fit(fac.without(bad), image, first.materials, method, scan=False, reject=passes - 1, **kw)
    width = fac.width
    pixels = [[int(i % width), int(i // width)] for i in bad] + again.stats["rejected"]["pixels"]
    rejected = {"count": len(pixels), "pixels": pixels, "threshold_sigmas": REJECT_SIGMAS}
    bad = pixels
    warnings = [f"{len(bad)} outlier pixel(s) left out of the fit (residual above {REJECT_SIGMAS:g} times the image noise or the residual's robust spread; "
                "fit.json 'rejected' lists them as [x, y])"] + [w for w in again.stats.get("warnings", []) if "outlier" not in w]
    offset = first.time_s
    return dataclasses.replace(
        again, trace=first.trace + [[offset + t, r] for t, r in again.trace], time_s=time.perf_counter() - t0,
        evaluations=first.evaluations + again.evaluations, iterations=first.iterations + again.iterations,
        rounds=first.rounds + again.rounds, stats={**again.stats, "rejected": rejected, "warnings": warnings,
                                                   **_add_phases(first.stats, again.stats)})


def _add_phases(first: dict, again: dict) -> dict:
    """``phases_s`` and ``scan_evaluations`` of a fit and its refit, added up (each phase's total)."""
    return {"phases_s": {k: round(v + again["phases_s"].get(k, 0.0), 6) for k, v in first["phases_s"].items()},
            "scan_evaluations": first["scan_evaluations"] + again["scan_evaluations"]}


def _hold(fac: Factorization, free: Free, held) -> None:
    """Take the user-given parameters (per surface, a set of names) out of ``free`` in place."""
    lay = fac.layout
    for k, (s, name) in enumerate(lay.x_names):
        if name in held[s]:
            free.x[k] = False
    for q, (s, name) in enumerate(lay.theta_names):
        if name in held[s]:
            free.theta[q] = False
    for i in range(len(fac.models)):
        if "r" in held[i]:
            free.s[2 * i] = False
        if "t" in held[i]:
            free.s[2 * i + 1] = False


def diagnose(pb: Problem, p: Params, A, res, textured=None, names=None) -> tuple[str, list]:
    """Does the fitted model explain the image? A safety net for a wrong basin or a bad scene.

    A pixel is *unexplained* when its residual in some band exceeds :data:`DIAG_SIGMAS` times the
    noise σ estimated from the image itself (:func:`image_noise`) plus :data:`DIAG_FLOOR` of the
    peak, plus — on textured surfaces — the diffuse radiance that their homogeneous ``kd`` predicts
    there (albedo variation is the texture stage's job, not a misfit). With Gaussian noise no pixel
    gets there; a highlight left in the wrong place, a missing reflection or wrong geometry does.

    Parameters
    ----------
    pb : Problem
    p : Params
        The fitted parameters.
    A : list of CSR
        ``fac.matrices(p.theta)``.
    res : (3, R) ndarray
        Model minus image.
    textured : list of bool, optional
        Per surface (default: none).
    names : list of str, optional
        Surface names for the messages.

    Returns
    -------
    status : {"ok", "poor fit", "texture pending"}
        "texture pending" instead of "poor fit" when some surface is textured: its albedo may vary
        by more than the allowance, so only ``reflab texture`` can tell. :func:`fit` turns "ok"
        into "not converged" when a method stopped at its cap.
    warnings : list of str
        Plain-language diagnosis (empty when ``status == "ok"``).
    """
    fac = pb.fac
    n_surf = len(fac.models)
    textured = [False] * n_surf if textured is None else [bool(t) for t in textured]
    names = [f"surface {i}" for i in range(n_surf)] if names is None else list(names)
    tol = np.broadcast_to((DIAG_SIGMAS * pb.noise + DIAG_FLOOR * pb.peak)[:, None], res.shape).copy()
    diffuse = np.array([textured[s] and fac.layout.x_names[i][1] == "kd"
                        for s, i in zip(fac.col_surface, fac.col_x)], dtype=bool)
    if diffuse.any():
        y = fac.y(p.x, p.s)
        tol += np.stack([A[c] @ np.where(diffuse, y[c], 0.0) for c in range(BANDS)])
    bad = np.any(np.abs(res) > tol, axis=0)
    if not bad.any():
        return "ok", []
    # Which surface each unexplained pixel sees first (its primary hit).
    tr = fac.trees
    first = np.full(fac.width * fac.height, -1, dtype=np.int64)
    primary = np.asarray(tr.level) == 1
    first[np.asarray(tr.pixel)[primary]] = np.asarray(tr.surface)[primary]
    where = first[fac.rows[bad]]
    counts = np.bincount(where[where >= 0], minlength=n_surf)
    share = float(np.sum(res[:, bad] ** 2) / max(np.sum(res**2), 1e-300))
    parts = ", ".join(f"{names[i]} {int(counts[i])}" for i in np.argsort(-counts) if counts[i])
    rms = ", ".join(f"{v:.3g}" for v in pb.rms(res))
    noise = ", ".join(f"{v:.3g}" for v in pb.noise)
    pending = any(textured)
    return ("texture pending" if pending else "poor fit"), [
        f"the fitted {'homogeneous ' if pending and fac.albedo is None else ''}model"
        f"{' (with the recovered texture)' if fac.albedo is not None else ''} does not explain {int(bad.sum())} of {fac.n_rows} pixels (residual above "
        f"{DIAG_SIGMAS:g} times the image noise [{noise}]{' plus textured albedo' if diffuse.any() else ''}); "
        f"they hold {100 * share:.0f}% of the squared residual; first seen surface: {parts or 'none'}",
        f"RMS residual per band [{rms}]: "
        + ("texture (run reflab texture and compare its re-render), or " if pending else "")
        + "a wrong basin (try another starting shininess in scene.json), a wrong BRTDF model, "
        "or geometry, lights or camera that do not match the image"]


def _undetermined(fac: Factorization, free: Free, materials, loose: Free | None = None) -> list:
    """Per surface, the names of the parameters held at their initial value ("ks[2]" for one band),
    and of those fitted whose (robust) σ exceeds their scale (``loose``)."""
    lay, out = fac.layout, []
    if loose is None:
        loose = Free(np.zeros_like(free.x), np.zeros_like(free.s), np.zeros_like(free.theta))
    for i, (model, mat) in enumerate(zip(fac.models, materials)):
        names = []
        for j, name in enumerate(model.linear):
            k = lay.x_offset[i] + j
            names += _band_names(name, ~free.x[k] | loose.x[k])
        names += _band_names("r", ~free.s[2 * i] | loose.s[2 * i])
        names += _band_names("t", ~free.s[2 * i + 1] | loose.s[2 * i + 1])
        names += [name for j, name in enumerate(model.nonlinear)
                  if not free.theta[lay.theta_offset[i] + j] or loose.theta[lay.theta_offset[i] + j]]
        out.append(names)
    return out


def _band_names(name, held) -> list:
    if held.all():
        return [name]
    return [f"{name}[{c}]" for c in np.flatnonzero(held)]


def fit_json(result: FitResult, fac: Factorization, scene, depth: int, extra: dict | None = None) -> dict:
    """The fit.json object of INTERFACES.md (plus diagnostics)."""
    lay, surfaces = fac.layout, []
    bounds = result.stats.get("at_bound")
    for i, (surf, model, mat) in enumerate(zip(scene.surfaces, fac.models, result.materials)):
        sigma = {}
        for j, name in enumerate(model.linear):
            k = lay.x_offset[i] + j
            sigma[name] = _sigma_list(result.sigma.x[k], result.free.x[k])
        for j, name in enumerate(model.nonlinear):
            q = lay.theta_offset[i] + j
            sigma[name] = float(result.sigma.theta[q]) if result.free.theta[q] and np.isfinite(result.sigma.theta[q]) else None
        sigma["r"] = _sigma_list(result.sigma.s[2 * i], result.free.s[2 * i])
        sigma["t"] = _sigma_list(result.sigma.s[2 * i + 1], result.free.s[2 * i + 1])
        surfaces.append({"name": surf.name, "material": mat.to_json(), "sigma": sigma,
                         "undetermined": result.undetermined[i], "at_bound": bounds[i] if bounds else {}})
    out = {
        "method": result.method, "depth": int(depth), "time_s": round(result.time_s, 6),
        "rms": [float(v) for v in result.rms], "trace": result.trace, "surfaces": surfaces,
        "columns": {"used": int(fac.n_columns), "monomials": len(fac.monomials),
                    "dense_dissertation": fac.dense_columns, "names": fac.column_names()},
        "iterations": result.iterations, "evaluations": result.evaluations, "rounds": result.rounds,
        "message": result.message,
    }
    out.update({k: v for k, v in result.stats.items() if k != "at_bound"})
    out.update(extra or {})
    return _finite(out)


def _finite(obj):
    """``obj`` (JSON-like) with every NaN or infinite float replaced by None."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _sigma_list(sig, free) -> list:
    """Per-band sigma, None where the band is undetermined (JSON null, never NaN/inf)."""
    return [float(v) if f and np.isfinite(v) else None for v, f in zip(sig, free)]
