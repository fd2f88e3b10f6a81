"""F-TBO: θ over the exact bounded linear solution (docs/method.md §3).

For fixed θ, the Gram matrices ``G_c = A_cᵀA_c`` and ``h_c = A_cᵀb_c`` reduce the problem to the
(few) monomial columns. There, ``x`` is the exact bounded least-squares solution for fixed r, t
(NNLS), and each ``r_s`` / ``t_s`` the exact minimiser on [0, 1] of its polynomial, alternated to
convergence. θ (shininess searched in log2) is optimised on top: a coarse global scan per θ (each
candidate with the exact inner solve), then Levenberg–Marquardt with the envelope-theorem gradient
and the variable-projection curvature, corrected by secant information where a fit creeps.
"""
from __future__ import annotations

import time

import numpy as np

from reflab.inverse.forward.factorization import BANDS, gram
from reflab.inverse.fit.problem import BUDGET_MESSAGE, SCAN_POINTS, Free, Params, Problem, step_message, trace_point
from reflab.inverse.fit.ranges import linear_upper
from reflab.inverse.fit.uncertainty import normal_matrix


#: Sweeps of the scan over the θs at most.
SCAN_SWEEPS = 2
#: Images with at least this many used pixels are scanned on a subsample (every s-th pixel in x
#: and y), the full image finishing from the basins found there.
COARSE_MIN_ROWS = 60_000
#: The subsample's stride s is the largest (at least 2) that leaves this many used pixels: about
#: a 160x120 image, on which the full-image scan finds its basins (320x240: every second pixel;
#: 480x360: every third; 640x480: every fourth, a sixteenth of the cost per candidate).
COARSE_ROWS = 15_000
#: F-TBO stops once the undamped Gauss–Newton step on θ predicts a relative decrease of the error
#: below this: Levenberg–Marquardt otherwise creeps along a flat valley for dozens of iterations,
#: each gaining 1e-9 of the error (measured on the textured demo).
STOP_GAIN = 1e-8
#: The same for a fit that only seeds another (a textured scene's homogeneous start and early
#: texture rounds, refitted against a new texture): its last iterations on a large-residual
#: problem each gain half the one before (GN's curvature lacks the residual's second-order term).
SEED_STOP_GAIN = 1e-6
#: Past this many iterations, Levenberg–Marquardt's model learns the curvature that Gauss–Newton
#: misses from its trials (:func:`_secant_curvature`); a fit that converges sooner keeps the plain
#: Gauss–Newton path. A textured zoo scene's pilot (homogeneous fit, noise estimate at the floor)
#: otherwise crept for 100 iterations (187 evaluations); it now converges in 32 (56), lower.
CREEP_ITERATIONS = 20
#: ... or below this share of the image's squared norm, whatever ε is: the inner solve's rounding.
#: At a noise-free fit's exact solution (ε ≈ 1e-22) a flat θ (a lobe with no signal) otherwise
#: chases "gains" of 1e-23 for a hundred iterations, each lowering ε by its own rounding. Where
#: it stops a noise-free fit short of the rounding, :func:`_polish` finishes it.
STOP_FLOOR = 1e-20
#: A scan candidate must lower the squared error by this many times the image noise variance (per
#: band): far beyond what fitting noise with a band's linear parameters gains (≈ 1 each).
SCAN_GAIN = 25.0
#: A fit whose squared error is below this share of the image noise's (σ² per used pixel and
#: band) is noise-free to its model: the data then fix the parameters to the rounding, far beyond
#: where the stopping rules above leave θ (the inner solve's Gram-form ε cannot see gains below
#: ~1e-16 of Σ b², which pollutes the envelope gradient), so :func:`_polish` finishes it.
POLISH_BELOW = 1e-6
#: Joint Gauss–Newton steps of the polish at most; it stops at the first that does not halve ε
#: (at zero residual Gauss–Newton converges quadratically: a slower step is at the rounding floor).
POLISH_STEPS = 8


def ftbo(pb: Problem, p: Params, free: Free, t0, trace, maxiter=100, scan=True, stop_gain=STOP_GAIN):
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
    E, g, cur, A, grad, res = evaluate(u, p, gradient=len(q) > 0)  # no θ: the linear solve alone
    trace.append(trace_point(t0, pb.rms(res)))
    if len(q) == 0:
        return cur, 0, "no nonlinear parameter to fit: one exact linear solve"
    coarse = coarse_problem(pb) if scan else None
    if coarse is not None:
        # The basins from a subsample of the pixels; the full image evaluates the chosen θ once.
        t_scan = time.perf_counter()
        ev = _evaluator(coarse, free, q)
        cu, cstate = _scan(coarse, q, u, ev(u, cur), ev, t0, [])
        if not np.array_equal(cu, u):
            u, (E, g, cur, A, grad, res) = cu, evaluate(cu, cstate[2])
            trace.append(trace_point(t0, pb.rms(res)))
        pb.evaluations += coarse.evaluations
        pb.scan_evaluations += coarse.evaluations
        pb.phases["scan"] += time.perf_counter() - t_scan
    elif scan:
        u, (E, g, cur, A, grad, res) = _scan(pb, q, u, (E, g, cur, A, grad, res), evaluate, t0, trace)
    lam, message, it = 1e-3, f"stopped after {maxiter} iterations", 0
    lo, hi = srch.lo[q], srch.hi[q]
    B = np.zeros((len(q), len(q)))  # the curvature Gauss–Newton misses, learnt from the trials
    for it in range(1, maxiter + 1):
        pb.step(it, maxiter, step_message("F-TBO iteration", trace))
        if pb.out_of_time():
            it -= 1
            message = BUDGET_MESSAGE
            break
        S = _theta_curvature(pb, cur, free, A, grad) * np.outer(srch.dtheta_du(cur.theta)[q], srch.dtheta_du(cur.theta)[q])
        S = 2.0 * S / pb.norm + B
        if _predicted_gain(S, g, u, lo, hi) <= stop_gain * E + STOP_FLOOR:
            message = "converged: the Gauss-Newton step predicts no further gain"
            break
        improved, tried, losses = False, [], []
        for _ in range(12):  # damping increases until a step lowers ε
            step = -np.linalg.solve(S + lam * np.diag(np.maximum(np.diag(S), 1e-300)), g)
            u_new = np.clip(u + step, lo, hi)
            if any(np.array_equal(u_new, v) for v in tried):  # clipped onto a point already tried
                lam *= 4.0
                continue
            trial = evaluate(u_new, cur, gradient=False)  # its gradient only if it is kept
            if it > CREEP_ITERATIONS:
                B_d = _secant_curvature(S, g, u_new - u, trial[0] - E)
                B, S = B + B_d, S + B_d
            if trial[0] < E:
                improved = True
                break
            tried.append(u_new)
            losses.append((trial[0] - E, float(np.max(np.abs(u_new - u)))))
            if _slope_fails(losses):
                break
            lam *= 4.0
        if not improved:
            message = "converged: no step lowers the error"
            break
        gain, moved = E - trial[0], float(np.max(np.abs(u_new - u)))
        u, (E, g, cur, A, grad, res) = u_new, evaluate.gradient(trial)
        lam = max(lam / 3.0, 1e-12)
        trace.append(trace_point(t0, pb.rms(res)))
        if moved < 1e-10 or gain <= 1e-12 * (E + gain) or E == 0.0:
            message = "converged: step or error change below tolerance"
            break
    if E * pb.norm < POLISH_BELOW * pb.fac.n_rows * float(np.sum(pb.noise**2)) and not message.startswith("stopped"):
        cur = _polish(pb, cur, free, A, grad, res, t0, trace)
    return cur, it, message


def _polish(pb: Problem, p: Params, free: Free, A, grad, res, t0, trace) -> Params:
    """Joint Gauss–Newton steps on the free linear parameters and θ from the residual itself.

    The gradient ``Jᵀr`` is formed from the residual ``r = A y − b`` (not from the Gram form
    ``yᵀGy − 2hᵀy + bᵀb``, whose rounding is ~1e-16 of ``bᵀb``): iterative refinement, which takes
    a noise-free fit to the rounding of its residual whatever the BLAS kernel's own rounding left
    (F-TBO's end point otherwise depended on the CPU: a mirror's ks 1.3e-4 off on one, exact on
    another). Parameters on a bound stay there; a step is kept only when it lowers ε.
    """
    fac, srch = pb.fac, pb.search
    q = np.flatnonzero(free.theta)
    E = float(np.sum(res * res))
    for _ in range(POLISH_STEPS):
        if E == 0.0 or pb.out_of_time():
            break
        ub = linear_upper(fac, p.theta)[:, None]
        inner = Free(free.x & (p.x > 0) & (p.x < ub), free.s & (p.s > 0) & (p.s < 1), free.theta)
        H, labels = normal_matrix(pb, p, inner, np.ones(BANDS), A, grad)
        if not labels:
            break
        y = fac.y(p.x, p.s)
        g = np.concatenate([pb.dy(p, c, inner)[0].T @ (A[c].T @ res[c]) for c in range(BANDS)] + [grad(res, y)[q]])
        dg = np.sqrt(np.maximum(np.diag(H), 0.0))
        ok = dg > 0
        if not ok.any():
            break
        w, V = np.linalg.eigh(H[np.ix_(ok, ok)] / np.outer(dg[ok], dg[ok]))
        keep = w > max(w.max(), 0.0) * 1e-12
        step = np.zeros(len(labels))
        step[ok] = -(V[:, keep] @ ((V[:, keep].T @ (g[ok] / dg[ok])) / w[keep])) / dg[ok]
        new = p.copy()
        for (kind, i, c), d in zip(labels, step):
            if kind == "x":
                new.x[i, c] += d
            elif kind == "s":
                new.s[i, c] += d
            else:
                new.theta[i] += d
        new.theta = np.where(free.theta, srch.to_theta(srch.to_u(new.theta)), p.theta)
        new.x = np.where(inner.x, np.clip(new.x, 0.0, linear_upper(fac, new.theta)[:, None]), p.x)
        new.s = np.where(inner.s, np.clip(new.s, 0.0, 1.0), p.s)
        A_new, grad_new = fac.matrices_and_grad(new.theta)
        res_new = pb.residual(A_new, fac.y(new.x, new.s))
        pb.evaluations += 1
        E_new = float(np.sum(res_new * res_new))
        if not E_new < E:
            break
        p, A, grad, res, halved, E = new, A_new, grad_new, res_new, E_new <= 0.5 * E, E_new
        trace.append(trace_point(t0, pb.rms(res)))
        if not halved:
            break
    return p


class _Inner:
    """F-TBO's inner problem for fixed θ, in monomial space: G_c, h_c per band."""

    def __init__(self, problem: Problem, A):
        self.pb = problem
        self.G = [gram(A, c) for c in range(BANDS)]
        self.h = [A[c].T @ problem.b[c] for c in range(BANDS)]
        fac = problem.fac
        self._index = fac._factor_index  # each column's factors, by degree (Factorization.factor_products)
        self._used = fac._used
        self._where = {}  # factor -> its masks e == d per degree d (the factor step's polynomial)

    def products(self, s_c, skip=None) -> np.ndarray:
        """Band c's factor product of each column (C,) from its factors ``s_c`` (F,), leaving out the
        factors ``skip`` (a list: then (len(skip), C), one row per factor left out); the numbers
        of ``Factorization.factor_products`` (the same products, in the same order)."""
        used, idx = self._used, self._index
        if skip is None:
            ext = np.ones(len(used) + 1)
            ext[:-1] = s_c[used]
            out = ext[idx[:, 0]]
            for k in range(1, idx.shape[1]):
                out *= ext[idx[:, k]]
            return out
        ext = np.ones((len(skip), len(used) + 1))
        ext[:, :-1] = s_c[used]
        ext[:, :-1][used[None, :] == np.asarray(skip)[:, None]] = 1.0
        out = ext[:, idx[:, 0]]
        for k in range(1, idx.shape[1]):
            out *= ext[:, idx[:, k]]
        return out

    def y(self, p: Params, c: int) -> np.ndarray:
        """Band c's monomial values (C,)."""
        return p.x[self.pb.fac.col_x, c] * self.products(p.s[:, c])

    def dy(self, p: Params, c: int, free: Free) -> tuple[np.ndarray, list]:
        """:meth:`Problem.dy` (the same numbers), its factor columns formed together."""
        fac = self.pb.fac
        fx, fs = np.flatnonzero(free.x[:, c]), np.flatnonzero(free.s[:, c])
        labels = [("x", i) for i in fx] + [("s", f) for f in fs]
        if not labels:
            return np.zeros((fac.n_columns, 0)), labels
        parts = [self.pb.onehot[:, fx] * self.products(p.s[:, c])[:, None]]
        if len(fs):
            e = fac.exponents[:, fs].T  # (n_s, C)
            rest = self.products(p.s[:, c], list(fs))
            with np.errstate(divide="ignore", invalid="ignore"):
                d = np.where(e > 0, e * p.s[fs, c][:, None] ** np.maximum(e - 1, 0) * rest, 0.0)
            parts.append((p.x[fac.col_x, c] * d).T)
        return np.concatenate(parts, axis=1), labels

    def upper(self, p: Params) -> np.ndarray:
        """(X,) upper bounds of the linear parameters at ``p.theta`` (:mod:`reflab.inverse.fit.ranges`)."""
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
        T = self.pb.onehot * self.products(p.s[:, c])[:, None]
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
        ub = self.upper(p)[fx]
        if keep.all():  # strictly convex: the previous sweep's bounds, where still optimal, give the one minimiser
            x = _on_bounds(R, d, p.x[fx, c], ub)
            if x is not None:
                p.x[fx, c] = x
                return
        x = nnls(R, d, maxiter=50 * len(qf) + 50)[0]
        if np.any(x > ub):  # a plausible range binds (reflab.inverse.fit.ranges): bounded least squares
            from scipy.optimize import lsq_linear

            x = np.clip(lsq_linear(R, d, bounds=(0.0, ub), method="bvls", tol=1e-14).x, 0.0, ub)
        p.x[fx, c] = x

    def s_step(self, c, f, p: Params):
        """Exact minimiser on [0, 1] of band c's ε as a polynomial in factor f."""
        fac = self.pb.fac
        if f not in self._where:
            e = fac.exponents[:, f]
            self._where[f] = np.stack([e == d for d in range(int(e.max()) + 1)])
        where = self._where[f]
        u = p.x[fac.col_x, c] * self.products(p.s[:, c], [f])[0]
        G, h = self.G[c], self.h[c]
        top = len(where) - 1
        # y(σ) = Σ_d σ^d U_d; ε(σ) = Σ_{d,d'} σ^{d+d'} U_dᵀ G U_d' − 2 Σ_d σ^d hᵀU_d + const.
        U = np.where(where, u, 0.0)  # (top+1, C)
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
            # A linear derivative (the factor of degree 1 everywhere, the usual case) has one root:
            # numpy's polyroots computes the same quotient, after a tenth of a millisecond of checks.
            roots = [-deriv[0] / deriv[1]] if len(deriv) == 2 else np.polynomial.polynomial.polyroots(deriv)
            # A root within rounding of a bound is that bound (a t of 1e-23 would only trouble later stages).
            cand += [float(r.real) for r in roots if abs(r.imag) <= 1e-9 * (1 + abs(r.real)) and 1e-12 < r.real < 1.0 - 1e-12]
        cand = np.array(cand)
        vals = coef[-1] + cand * 0.0  # Horner, as numpy's polyval
        for d in range(2, len(coef) + 1):
            vals = coef[-d] + vals * cand
        p.s[f, c] = cand[int(np.argmin(vals))]

    def joint_step(self, c, p: Params, free: Free) -> None:
        """One projected Gauss–Newton step on all free linear parameters of band c at once.

        Alternating exact block minimisers converges linearly when blocks are coupled (an albedo
        and the mirror that reflects it); this joint step, still in monomial space, is kept only
        when it lowers ε, so the alternation's exactness is preserved and its tail is cut short.
        """
        D, labels = self.dy(p, c, free)
        if not labels:
            return
        y = self.y(p, c)
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
        if self.eps(c, self.y(trial, c)) < self.eps(c, y):
            p.x[:, c], p.s[:, c] = trial.x[:, c], trial.s[:, c]

    def solve(self, p: Params, free: Free, tol=1e-15, max_sweeps=200) -> int:
        """Alternate the exact x and factor steps per band until ε stops decreasing."""
        sweeps = 0
        for c in range(BANDS):
            last = self.eps(c, self.y(p, c))
            for sweep in range(max_sweeps):
                self.x_step(c, p, free)
                for f in np.flatnonzero(free.s[:, c]):
                    self.s_step(c, f, p)
                self.joint_step(c, p, free)
                now = self.eps(c, self.y(p, c))
                sweeps += 1
                if last - now <= tol * self.pb.bb[c] + 1e-300:
                    break
                last = now
        return sweeps


def _on_bounds(R, d, x0, ub):
    """The minimiser of ‖R x − d‖² on 0 ≤ x ≤ ub (R square, full rank) if its binding bounds are
    those ``x0`` sits on, else None (the caller then searches them: NNLS, BVLS).

    From one sweep to the next the bounds that bind rarely change, so one least-squares solve on
    the others and a check of the optimality conditions (each variable inside its range, the
    gradient pointing out of the bound each bound one sits on) replaces the active-set search.
    """
    lo, hi = x0 <= 0.0, (x0 >= ub) & (x0 > 0.0)
    free = ~(lo | hi)
    x = np.where(hi, ub, 0.0)
    if free.any():
        x[free] = np.linalg.lstsq(R[:, free], d - R[:, hi] @ ub[hi], rcond=None)[0]
        if not (np.all(x[free] > 0.0) and np.all(x[free] < ub[free])):
            return None
    g = R.T @ (R @ x - d)  # half the gradient of ‖R x − d‖²
    if np.any(g[lo] < 0.0) or np.any(g[hi] > 0.0):
        return None
    return x


def _evaluator(pb: Problem, free: Free, q):
    """F-TBO's objective at θ search values ``u`` (the free θ ``q``), linear parameters solved exactly.

    Returns ``evaluate(u, start, gradient=True) -> (ε, dε/du, params, A, grad, residual)``;
    ``start`` warm-starts the inner solve. With ``gradient=False`` dε/du is None until
    ``evaluate.gradient(state)`` forms it (the same numbers): the scan's candidates and the
    rejected trials need ε alone, and the gradient is a tenth of an evaluation.
    """
    fac, srch = pb.fac, pb.search

    def evaluate(u, start: Params, gradient: bool = True):
        cur = start.copy()
        full = srch.to_u(cur.theta)
        full[q] = u
        cur.theta = srch.to_theta(full)
        A, grad = fac.matrices_and_grad(cur.theta)
        _Inner(pb, A).solve(cur, free)
        res = pb.residual(A, fac.y(cur.x, cur.s))
        pb.evaluations += 1
        state = (float(np.sum(res * res)) / pb.norm, None, cur, A, grad, res)
        return with_gradient(state) if gradient else state

    def with_gradient(state):
        E, g, cur, A, grad, res = state
        if g is None:
            g = 2.0 * grad(res, fac.y(cur.x, cur.s))[q] * srch.dtheta_du(cur.theta)[q] / pb.norm
            g = g + _bound_slope(pb, cur, free, q, A, res)
        return E, g, cur, A, grad, res

    evaluate.gradient = with_gradient
    return evaluate


def _bound_slope(pb: Problem, p: Params, free: Free, q, A, res) -> np.ndarray:
    """dε/du through the linear parameters held on their θ-dependent upper bound (a Phong ks at 1/L(ns)).

    The envelope theorem's partial derivative holds for bounds that do not move with θ; a ks
    pressed against ``ub(ns)`` follows it, adding ``∂ε/∂ks · dub/du`` (∂ε/∂ks < 0 there). Without
    it the gradient points where ε rises (lowering ns lowers the bound) and every damped step
    fails: Levenberg–Marquardt spent a dozen evaluations per such call to conclude so.
    """
    fac, srch = pb.fac, pb.search
    ub = linear_upper(fac, p.theta)
    on = free.x & (p.x >= ub[:, None] * (1.0 - 1e-12)) & (ub[:, None] > 0)
    out = np.zeros(len(q))
    if not on.any():
        return out
    prod = fac.factor_products(p.s)  # (C, 3)
    M = np.stack([A[c].T @ res[c] for c in range(BANDS)], axis=1)  # ½ ∂ε·norm/∂y per band
    dx = np.minimum(2.0 * (pb.onehot.T @ (prod * M)) / pb.norm, 0.0)  # ∂ε/∂x, pressing outward only
    u = srch.to_u(p.theta)
    for k, qk in enumerate(q):
        h = 1e-6 * max(1.0, abs(u[qk]))
        up, dn = u.copy(), u.copy()
        up[qk], dn[qk] = min(u[qk] + h, srch.hi[qk]), max(u[qk] - h, srch.lo[qk])
        if up[qk] == dn[qk]:
            continue
        dub = (linear_upper(fac, srch.to_theta(up)) - linear_upper(fac, srch.to_theta(dn))) / (up[qk] - dn[qk])
        out[k] = float(np.sum(np.where(on, dx * dub[:, None], 0.0)))
    return out


def coarse_stride(n_rows: int) -> int:
    """The coarse scan's stride in x and y: the largest (at least 2) leaving :data:`COARSE_ROWS` pixels."""
    return max(2, int(np.sqrt(n_rows / COARSE_ROWS)))


def coarse_problem(pb: Problem):
    """The problem on every s-th used pixel in x and y (:data:`COARSE_ROWS`), or None below :data:`COARSE_MIN_ROWS`.

    It keeps the full image's noise σ, deadline and task; its scan threshold scales with its
    share of the pixels, so that it keeps the candidates the full image would.
    """
    fac = pb.fac
    if fac.n_rows < COARSE_MIN_ROWS:
        return None
    x, y = fac.rows % fac.width, fac.rows // fac.width
    stride = coarse_stride(fac.n_rows)
    sub = fac.without(fac.rows[(x % stride != 0) | (y % stride != 0)])
    image = np.zeros((fac.width * fac.height, BANDS))
    # The photograph itself: ``b`` carries a sample's row weights, which ``sub`` applies again
    # (weighed twice, its data would no longer match its model; docs/fit.md, "Sampling").
    data = pb.b if pb.scale is None else np.divide(pb.b, pb.scale, out=np.zeros_like(pb.b), where=pb.scale > 0)
    image[fac.rows] = data.T
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


def _slope_fails(losses) -> bool:
    """True when the last three failed trials (rise of ε, step length) shrank the step at least
    twofold each and ε rose in proportion to it: the rise is the first-order term, so the envelope
    gradient's slope along the damped direction is wrong (a kink of the profiled ε) and no shorter
    step lowers ε; the last trials of a "no step lowers the error" end are spared."""
    if len(losses) < 3:
        return False
    (e0, d0), (e1, d1), (e2, d2) = losses[-3:]
    if not (d1 <= 0.5 * d0 and d2 <= 0.5 * d1 and e2 > 0.0):
        return False
    return abs(e2 / d2 - e1 / d1) <= 0.25 * (e1 / d1) and abs(e1 / d1 - e0 / d0) <= 0.5 * (e0 / d0)


def _secant_curvature(S, g, d, dE) -> np.ndarray:
    """Rank-one correction that gives the model ``gᵀd + ½ dᵀSd`` the observed change ``dE`` along ``d``.

    Gauss–Newton's curvature lacks the residual's second-order term, which dominates on a large-
    residual fit (a textured scene's homogeneous start) along a θ with little signal: its model then
    sees a flat valley where ε rises steeply, proposes a long step to a bound, and Levenberg–
    Marquardt's one damping, raised until that direction stops failing, also freezes the well-
    determined θ (a pilot fit took 100 iterations, each moving them by 1e-3). Only added curvature
    is learnt (the correction stays positive semi-definite).
    """
    dd = float(d @ d)
    if not dd > 0.0:
        return np.zeros_like(S)
    alpha = 2.0 * (dE - float(g @ d)) - float(d @ S @ d)
    if not alpha > 0.0 or not np.isfinite(alpha):
        return np.zeros_like(S)
    return alpha * np.outer(d, d) / dd**2


def _scan(pb: Problem, q, u, state, evaluate, t0, trace):
    """Coarse coordinate-wise scan of each free θ over its whole search range (global step).

    The linear parameters are solved exactly for every candidate θ, so a handful of values per
    surface (:data:`SCAN_POINTS`, log2 for shininess) tells which basin holds the highlight: a
    start at ns = 2^14 sees flat highlights that a local method cannot leave. A candidate is kept
    only when it lowers ε by more than :data:`SCAN_GAIN` times the image noise variance per band,
    so a θ whose columns carry no signal (hidden highlight) is never moved by noise or rounding.

    A θ is scanned again (the next sweep) only when another θ moved since its last scan: with the
    others where they were, its candidates would be compared with the value it chose then (or
    kept) under the same rule, which none beat by the gain (zoo seed 8 at 640x480: 78 → 55
    evaluations, the same basins).
    """
    srch = pb.search
    gain_min = SCAN_GAIN * pb.scan_share * float(np.sum(pb.noise**2)) / pb.norm
    t_scan, n_scan = time.perf_counter(), pb.evaluations
    moves, scanned_at = 0, np.full(len(q), -1)  # moves so far; their count when each θ was last scanned
    for _ in range(SCAN_SWEEPS):
        moved = False
        for k, qk in enumerate(q):  # coordinate-wise: one θ at a time, the others at their best so far
            if scanned_at[k] == moves:
                continue  # nothing moved since its last scan
            best_u, best = None, state
            for value in np.linspace(pb.scan_lo[qk], pb.scan_hi[qk], SCAN_POINTS):
                if abs(value - u[k]) < 1e-12 or pb.out_of_time():
                    continue
                pb.task.check()
                trial_u = u.copy()
                trial_u[k] = value
                trial = evaluate(trial_u, state[2], gradient=False)
                if trial[0] < best[0] - gain_min:
                    best_u, best = trial_u, trial
            if best_u is not None:
                u, state, moved = best_u, best, True
                moves += 1
                trace.append(trace_point(t0, pb.rms(state[5])))
            scanned_at[k] = moves
        if not moved:
            break
    pb.phases["scan"] += time.perf_counter() - t_scan
    pb.scan_evaluations += pb.evaluations - n_scan
    return u, evaluate.gradient(state)


def _theta_curvature(pb: Problem, p: Params, free: Free, A, grad) -> np.ndarray:
    """JᵀJ of θ with the linear parameters profiled out (Schur complement), natural units.

    The blocks are :func:`reflab.inverse.fit.uncertainty.normal_matrix`'s (unit band weights), formed in
    monomial space: no (pixels × parameters) product.
    """
    inner = Free(free.x & (p.x > 0), free.s & (p.s > 0) & (p.s < 1), free.theta)  # bounds active: held
    H, _ = normal_matrix(pb, p, inner, np.ones(BANDS), A, grad)
    n_lin = H.shape[0] - int(np.count_nonzero(free.theta))
    Hqq = H[n_lin:, n_lin:]
    if n_lin == 0:
        return Hqq
    w, V = np.linalg.eigh(H[:n_lin, :n_lin])
    keep = w > max(w.max(), 0.0) * 1e-13
    proj = V[:, keep].T @ H[:n_lin, n_lin:]
    return Hqq - proj.T @ (proj / w[keep][:, None])
