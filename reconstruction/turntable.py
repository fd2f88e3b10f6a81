"""Bundle adjustment under the turntable's own geometry: one axis, one angle per shot.

COLMAP gives every shot six free pose parameters. A turntable allows one: the camera stands
still and the objects turn about a fixed axis, so in the objects' frame every shot's pose is the
reference shot's pose turned about that axis,

    R_i = R_ref · Rot(u, φ_i),    t_i = t_ref + R_ref · (a − Rot(u, φ_i) · a),

with ``u`` the axis direction, ``a`` a point on it and ``φ_i`` the shot's angle. Where a shot sees
little of what turns (a mirror standing in front of the objects), its six free parameters trade
rotation against translation; its one angle is pinned by every other shot's view of the same
axis. The commanded angles are not used, so the recovered angles stay an independent check of
the turntable (:func:`reflab.reconstruction.registration.turntable_check`).

The reference pose is held, which fixes the similarity frame up to a scale about its camera
centre; one residual holds the axis' distance from that centre at its starting value for it.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from reflab.calibration.rotations import perpendicular_basis, rodrigues


@dataclass
class Observations:
    """Image measurements of the sparse points.

    Attributes
    ----------
    point : (K,) int ndarray
        Index of the observed point.
    image : (K,) int ndarray
        Index of the shot that observes it.
    xy : (K, 2) ndarray
        Undistorted normalised image coordinates (x/z, y/z in the camera frame).
    """

    point: np.ndarray
    image: np.ndarray
    xy: np.ndarray


def rotations(u: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations by angles ``phi`` (radians) about the unit axis ``u`` (Rodrigues)."""
    return rodrigues(np.asarray(phi, dtype=np.float64)[:, None] * np.asarray(u, dtype=np.float64))


#: Cap on :func:`refine`'s function evaluations. The simulated lab's sweep (36 shots, ~1 550 points
#: seen ~12 000 times) took 16-49 in five COLMAP runs and 60+ in one (COLMAP's multithreaded
#: mapping is not repeatable): a cap of 60 then stopped it mid-way at 1.0 px, the free poses were
#: kept, and the demo's novel view fell from 30.4 to 28.1 dB. An evaluation costs ~50 ms there.
MAX_EVALUATIONS = 300


def turntable_model(R: np.ndarray, t: np.ndarray, reference: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Starting axis direction, axis point and per-shot angles (radians) from free poses.

    Parameters
    ----------
    R, t : (N, 3, 3), (N, 3) ndarray
        World-to-camera poses; NaN rows for unregistered shots.
    reference : int
        The shot whose angle is 0.

    Returns
    -------
    u : (3,) ndarray
    a : (3,) ndarray
        A point of the axis (the centre of the circle the camera centres trace).
    phi : (N,) ndarray
        NaN for unregistered shots.
    """
    import cv2

    from reflab.reconstruction.registration import _fit_circle_axis, rotation_axis

    ok = np.all(np.isfinite(t), axis=1)
    u = rotation_axis(R, reference)
    C = -np.einsum("nji,nj->ni", R[ok], t[ok])
    if np.linalg.norm(C - C.mean(axis=0), axis=1).max() <= 1e-6 * max(np.linalg.norm(C.mean(axis=0)), 1.0):
        raise ValueError("the camera centres coincide: the camera lies on the turntable axis (no circle to fit)")
    a = _fit_circle_axis(C, u)
    phi = np.full(len(R), np.nan)
    for i in np.flatnonzero(ok):
        phi[i] = cv2.Rodrigues(R[reference].T @ R[i])[0].ravel() @ u
    return u, a, phi


def poses(R0: np.ndarray, t0: np.ndarray, u: np.ndarray, a: np.ndarray, phi: np.ndarray):
    """World-to-camera poses (N, 3, 3), (N, 3) of the shots at angles ``phi`` about the axis (u, a)."""
    Rot = rotations(u, phi)
    R = R0 @ Rot
    t = t0 + (a - Rot @ a) @ R0.T
    return R, t


def refine(R: np.ndarray, t: np.ndarray, points: np.ndarray, obs: Observations, reference: int,
           focal: float, *, loss_scale_px: float = 1.0, max_points: int = 3000, max_evaluations: int = MAX_EVALUATIONS,
           seed: int = 0) -> dict:
    """Bundle adjustment with every shot's pose on the turntable's circle.

    The turntable's few parameters are solved on a subset of the points, balanced over the shots
    (each shot keeps its share, so shots that see little keep all they see); then every point is
    re-triangulated with the refined poses.

    Parameters
    ----------
    R, t : (N, 3, 3), (N, 3) ndarray
        Free (COLMAP) world-to-camera poses in the reconstruction's frame; NaN where unregistered.
    points : (P, 3) ndarray
        Sparse points.
    obs : Observations
        Their measurements (observations in unregistered shots are ignored).
    reference : int
        Registered shot held fixed (angle 0).
    focal : float
        Focal length in pixels: residuals are reported in pixels.
    loss_scale_px : float
        Soft-L1 loss scale: mismatches further off than this count linearly, not squared.
    max_points : int
        Points used to solve for the axis and the angles.
    max_evaluations : int
        Cap on the solver's function evaluations.
    seed : int
        Seed of the subset's random choice (repeatable runs).

    Returns
    -------
    dict
        ``R``, ``t`` (constrained poses, NaN where unregistered), ``points``, ``point_error``
        (mean reprojection per point, pixels), ``axis``, ``axis_point``, ``angles_deg`` (NaN where
        unregistered), and ``report``: ``rms_px_free`` / ``rms_px`` (reprojection RMS of all
        observations with the free poses and with the turntable model), ``max_shot_rms_px``,
        ``observations``, ``points``, ``points_solved``, ``evaluations``, ``converged``, ``time_s``.
    """
    t_start = time.perf_counter()
    n, P = len(R), len(points)
    ok = np.all(np.isfinite(t), axis=1)
    if not ok[reference]:
        raise ValueError("refine: the reference shot is not registered")
    keep = ok[obs.image]
    pi, ii, xy = obs.point[keep], obs.image[keep], obs.xy[keep]
    r_free = _reprojection(R, t, points, pi, ii, xy, focal)
    sub = _balanced_subset(pi, ii, n, P, max_points, np.random.default_rng(seed))
    in_sub = np.zeros(P, bool)
    in_sub[sub] = True
    renumber = np.cumsum(in_sub) - 1
    o = in_sub[pi]
    u, a, phi, Xs, sol = _solve(R, t, points[sub], renumber[pi[o]], ii[o], xy[o], reference, focal, ok,
                                loss_scale_px, max_evaluations)
    Rs, ts = poses(R[reference], t[reference], u, a, phi)
    Rs[~ok], ts[~ok] = np.nan, np.nan
    X = points.copy()
    X[sub] = Xs
    X = triangulate_points(Rs, ts, X, pi, ii, xy)
    r = _reprojection(Rs, ts, X, pi, ii, xy, focal)
    per_point = np.bincount(pi, weights=r, minlength=P) / np.maximum(np.bincount(pi, minlength=P), 1)
    per_shot = np.sqrt(np.bincount(ii, weights=r**2, minlength=n) / np.maximum(np.bincount(ii, minlength=n), 1))
    angles = np.degrees(phi)
    angles[~ok] = np.nan
    report = {"model": "one axis, one angle per shot (reference shot held)",
              "observations": int(len(pi)), "points": int(P), "points_solved": int(len(sub)),
              "rms_px_free": float(np.sqrt(np.mean(r_free**2))), "rms_px": float(np.sqrt(np.mean(r**2))),
              "max_shot_rms_px": float(per_shot[ok].max()),
              "evaluations": int(sol.nfev), "converged": bool(sol.status > 0),
              "time_s": round(time.perf_counter() - t_start, 3)}
    return {"R": Rs, "t": ts, "points": X, "point_error": per_point, "axis": u, "axis_point": a,
            "angles_deg": angles, "report": report}


def _balanced_subset(pi, ii, n, P, max_points, rng) -> np.ndarray:
    """Indices of at most about ``max_points`` points: each shot contributes its share, at random."""
    if P <= max_points:
        return np.arange(P)
    share = max(1, max_points // max(n, 1))
    order = np.lexsort((rng.random(len(pi)), ii))  # by shot, shuffled within each
    first = np.searchsorted(ii[order], np.arange(n))
    rank = np.arange(len(order)) - first[ii[order]]
    return np.unique(pi[order[rank < share]])


def _solve(R, t, X0, pi, ii, xy, reference, focal, ok, loss_scale_px, max_evaluations):
    """Least squares over (axis direction 2, axis point 2, angles, points) on the given observations."""
    from scipy.optimize import least_squares
    from scipy.sparse import coo_matrix

    n, P = len(R), len(X0)
    u0, a0, phi0 = turntable_model(R, t, reference)
    e1, e2 = perpendicular_basis(u0)
    R0, t0 = R[reference], t[reference]
    C0 = -R0.T @ t0
    d0 = np.linalg.norm((C0 - a0) - ((C0 - a0) @ u0) * u0)
    if not np.isfinite(d0) or d0 <= 1e-9 * max(np.linalg.norm(C0 - a0), 1e-300):
        raise ValueError("the reference camera lies on the turntable axis (its centre traces no circle)")
    shots = np.flatnonzero(ok & (np.arange(n) != reference))
    slot = np.full(n, -1)
    slot[shots] = np.arange(len(shots))
    n_phi = len(shots)

    def unpack(p):
        u = u0 + p[0] * e1 + p[1] * e2
        u = u / np.linalg.norm(u)
        a = a0 + p[2] * e1 + p[3] * e2
        phi = np.zeros(n)
        phi[shots] = p[4:4 + n_phi]
        return u, a, phi, p[4 + n_phi:].reshape(P, 3)

    def residuals(p):
        u, a, phi, X = unpack(p)
        Rs, ts = poses(R0, t0, u, a, phi)
        c = np.einsum("kij,kj->ki", Rs[ii], X[pi]) + ts[ii]
        z = np.where(np.abs(c[:, 2]) > 1e-12, c[:, 2], 1e-12)
        r = focal * (c[:, :2] / z[:, None] - xy)
        d = np.linalg.norm((C0 - a) - ((C0 - a) @ u) * u)
        return np.concatenate([r.ravel(), [1e3 * (d - d0) / d0]])

    # Each observation's two rows depend on the axis (not for the reference shot), its shot's
    # angle and its point's three coordinates; the gauge row on the axis alone.
    K = len(pi)
    obs_rows = np.arange(2 * K)
    moving = np.repeat(ii != reference, 2)
    has_phi = np.repeat(slot[ii] >= 0, 2)
    rows = [np.tile(obs_rows[moving], 4), obs_rows[has_phi], np.tile(obs_rows, 3), np.full(4, 2 * K)]
    cols = [np.repeat(np.arange(4), moving.sum()), 4 + np.repeat(slot[ii], 2)[has_phi],
            (4 + n_phi + 3 * np.repeat(pi, 2)[None, :] + np.arange(3)[:, None]).ravel(), np.arange(4)]
    rr, cc = np.concatenate(rows), np.concatenate(cols)
    sparsity = coo_matrix((np.ones(len(rr)), (rr, cc)), shape=(2 * K + 1, 4 + n_phi + 3 * P)).tocsr()
    x0 = np.concatenate([np.zeros(4), phi0[shots], X0.ravel()])
    sol = least_squares(residuals, x0, jac_sparsity=sparsity, method="trf", tr_solver="lsmr", x_scale="jac",
                        loss="soft_l1", f_scale=loss_scale_px, max_nfev=max_evaluations)
    u, a, phi, X = unpack(sol.x)
    return u, a, phi, X, sol


def triangulate_points(R, t, X, pi, ii, xy, iterations: int = 5) -> np.ndarray:
    """Gauss–Newton on each point's reprojection error with the poses fixed, all points at once.

    Parameters
    ----------
    R, t : (N, 3, 3), (N, 3) ndarray
        World-to-camera poses.
    X : (P, 3) ndarray
        Starting points.
    pi, ii : (K,) int ndarray
        Point and shot of each observation.
    xy : (K, 2) ndarray
        Normalised image coordinates.

    Returns
    -------
    (P, 3) ndarray
        Points; a point whose 3×3 normal matrix is singular (seen from one direction) is left as given.
    """
    X = np.array(X, dtype=np.float64)
    P = len(X)
    Rk = R[ii]
    for _ in range(iterations):
        c = np.einsum("kij,kj->ki", Rk, X[pi]) + t[ii]
        z = c[:, 2]
        r = c[:, :2] / z[:, None] - xy
        # d(x/z, y/z)/dc = [[1/z, 0, -x/z²], [0, 1/z, -y/z²]]; dc/dX = R.
        dp = np.zeros((len(pi), 2, 3))
        dp[:, 0, 0] = dp[:, 1, 1] = 1.0 / z
        dp[:, :, 2] = -c[:, :2] / (z**2)[:, None]
        J = dp @ Rk  # (K, 2, 3)
        JtJ = np.zeros((P, 3, 3))
        Jtr = np.zeros((P, 3))
        np.add.at(JtJ, pi, np.einsum("kai,kaj->kij", J, J))
        np.add.at(Jtr, pi, np.einsum("kai,ka->ki", J, r))
        good = np.abs(np.linalg.det(JtJ)) > 1e-12 * np.maximum(np.einsum("pii->p", JtJ), 1e-300) ** 3
        step = np.zeros((P, 3))
        step[good] = np.linalg.solve(JtJ[good], -Jtr[good][:, :, None])[:, :, 0]
        X += step
        if np.abs(step).max(initial=0.0) < 1e-12:
            break
    return X


def explains(report: dict) -> bool:
    """Whether one axis explains the shots about as well as free poses (:func:`refine`'s report).

    A rigid turntable costs a little reprojection (its shots lose five parameters each: 0.42
    against 0.39 px RMS on the simulated lab's sweep); a table that tilts 1.5 degrees back and
    forth as it turns doubles it.
    """
    return bool(report["rms_px"] <= 1.25 * report["rms_px_free"] + 0.1)


def refine_if_rigid(R, t, points, obs: Observations, reference: int, focal: float, **kw) -> dict:
    """:func:`refine`, with the report's ``used`` saying whether to take its poses.

    ``used`` is False, with a ``warning``, when one axis does not explain the shots
    (:func:`explains`: a turntable that wobbles or slips) or cannot be fitted at all (the camera
    on the axis); the caller then keeps the free poses. Otherwise as :func:`refine`.
    """
    try:
        out = refine(R, t, points, obs, reference, focal, **kw)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return {"report": {"used": False, "warning": f"one turntable axis could not be fitted ({exc}): "
                                                      "kept the free poses"}}
    rr = out["report"]
    rr["used"] = explains(rr)
    if not rr["used"]:
        why = (f"its fit stopped unconverged after {rr['evaluations']} evaluations" if not rr["converged"]
               else "does the turntable wobble?")
        rr["warning"] = (f"one turntable axis explains the shots at {rr['rms_px']:.2f} px RMS against "
                         f"{rr['rms_px_free']:.2f} px with free poses: kept the free poses ({why})")
    return out


def _reprojection(R, t, X, pi, ii, xy, focal) -> np.ndarray:
    """(K,) reprojection error of each observation, pixels."""
    c = np.einsum("kij,kj->ki", R[ii], X[pi]) + t[ii]
    return focal * np.linalg.norm(c[:, :2] / c[:, 2:3] - xy, axis=1)
