"""NF-TBO: every parameter at once by nonlinear conjugate gradient (docs/method.md §3).

Preconditioned Polak–Ribière on a bounded reparametrisation (``x = w²``, ``r = sin² φ``,
``log2 ns = lo + (hi − lo) sin² ψ``), with a diagonal (Gauss–Newton) preconditioner; every
evaluation is a full pass over the nodes.
"""
from __future__ import annotations

import numpy as np

from reflab.inverse.forward.factorization import BANDS
from reflab.inverse.fit.problem import BUDGET_MESSAGE, Free, Params, Problem, step_message, trace_point
from reflab.inverse.fit.uncertainty import normal_matrix


def nftbo(pb: Problem, p: Params, free: Free, t0, trace, maxiter=5000):
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
    trace.append(trace_point(t0, pb.rms(st["res"])))
    if n == 0:
        return st["p"], 0, "nothing to fit"
    cap_theta = np.where(pb.search.log[m.q], np.log(2.0) * st["p"].theta[m.q], 0.1 * (m.hi - m.lo))
    message, it, since_restart, direction, prev = f"stopped after {maxiter} iterations", 0, n, None, None
    stalls = 0
    for it in range(1, maxiter + 1):
        pb.step(it, maxiter, step_message("NF-TBO iteration", trace))
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
        trace.append(trace_point(t0, pb.rms(st["res"])))
        stalls = stalls + 1 if gain <= 1e-13 * (st["E"] + gain) else 0
        if st["E"] == 0.0 or stalls >= 3:
            message = "converged: error change below tolerance"
            break
    return st["p"], it, message


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
        img = st["grad"].images(st["y"], m.q)
        out += np.einsum("q,qcr->cr", dpar[nx + ns:], img)
    return out


def _gn_diagonal(pb: Problem, m: _NFMap, z) -> np.ndarray:
    """Gauss–Newton curvature ‖∂B/∂z_i‖² / norm of each NF-TBO variable (z order)."""
    cur, d = m.to_params(z)
    H, labels = normal_matrix(pb, cur, m.free, np.ones(BANDS))
    pos = {"x": np.full(m.free.x.shape, -1), "s": np.full(m.free.s.shape, -1)}
    nx, ns = int(m.free.x.sum()), int(m.free.s.sum())
    pos["x"][m.free.x] = np.arange(nx)
    pos["s"][m.free.s] = nx + np.arange(ns)
    theta_pos = {q: nx + ns + k for k, q in enumerate(m.q)}
    order = [pos[kind][i, c] if kind != "theta" else theta_pos[i] for kind, i, c in labels]
    diag = np.zeros(len(z))
    diag[order] = np.diag(H)
    return diag * d * d / pb.norm
