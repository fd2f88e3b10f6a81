"""Registration of a structure-from-motion reconstruction into the workspace's world frame.

SfM knows the scene up to a similarity (scale, rotation, translation). Two ways fix it:

* the calibration target lying on the ground plane (turning with the objects): its circle centres
  are found in the shots, triangulated with the recovered poses, and matched to their known
  positions (:func:`reflab.calibration.target.target_points`) by Umeyama's closed-form similarity;
* the input view and the turntable axis: the shot taken at the input view's angle must have
  camera.json's pose, which fixes everything but the scale; the camera centres circle the
  turntable axis, whose place on the ground (x, y) then gives the scale.

Either way the recovered turntable rotations are checked against the commanded angles (the axis'
tilt from the ground normal, and per-shot angle errors), and the registered pose of the input
shot against camera.json.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reflab.calibration.camera import Camera
from reflab.calibration.rotations import perpendicular_basis
from reflab.core.workspace import WorkspaceError


@dataclass
class Similarity:
    """``X_world = scale * R @ X_sfm + T``."""

    scale: float
    R: np.ndarray
    T: np.ndarray

    def points(self, X: np.ndarray) -> np.ndarray:
        """Map (N, 3) points into the world frame."""
        return self.scale * np.asarray(X, dtype=np.float64) @ self.R.T + self.T

    def poses(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map world-to-camera poses (N, 3, 3), (N, 3) into metric world-frame poses."""
        Rw = R @ self.R.T
        tw = self.scale * t - np.einsum("nij,j->ni", Rw, self.T)
        return Rw, tw


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """Least-squares similarity taking ``src`` (N, 3) onto ``dst`` (N, 3) (Umeyama 1991)."""
    src, dst = np.asarray(src, dtype=np.float64), np.asarray(dst, dtype=np.float64)
    if len(src) < 3:
        raise ValueError(f"umeyama: need at least 3 point pairs, got {len(src)}")
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    var = (a**2).sum() / len(src)
    if var <= 0:
        raise ValueError("umeyama: the source points coincide")
    scale = float(np.trace(np.diag(S) @ D) / var)
    return Similarity(scale, R, md - scale * R @ ms)


def triangulate(R: np.ndarray, t: np.ndarray, xy: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear (DLT) triangulation of M points seen in V views, batched.

    Parameters
    ----------
    R, t : (V, 3, 3), (V, 3) ndarray
        World-to-camera poses.
    xy : (V, M, 2) ndarray
        Normalised (undistorted) image coordinates.
    valid : (V, M) bool ndarray
        Which view sees which point.

    Returns
    -------
    X : (M, 3) ndarray
        Points (NaN where fewer than two views see the point).
    n_views : (M,) ndarray
    """
    P = np.concatenate([R, t[:, :, None]], axis=2)  # (V, 3, 4)
    rows_x = xy[:, :, 0, None] * P[:, None, 2] - P[:, None, 0]  # (V, M, 4)
    rows_y = xy[:, :, 1, None] * P[:, None, 2] - P[:, None, 1]
    w = valid[:, :, None].astype(np.float64)
    A = np.concatenate([rows_x * w, rows_y * w], axis=0).transpose(1, 0, 2)  # (M, 2V, 4)
    _, _, Vt = np.linalg.svd(A)
    h = Vt[:, -1]
    n_views = valid.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        X = h[:, :3] / h[:, 3:]
    X[(n_views < 2) | (np.abs(h[:, 3]) < 1e-12)] = np.nan
    return X, n_views


def _project_norm(R, t, X):
    c = np.einsum("vij,mj->vmi", R, X) + t[:, None]
    return c[..., :2] / c[..., 2:3], c[..., 2]


def find_target(image: np.ndarray, cols: int, rows: int):
    """Circle-grid detection that also works on a textured turntable.

    The printed target is the brightest large region; everything outside its filled outline is
    painted at the paper's level so that the texture around it cannot confuse the grid finder.

    Returns
    -------
    (cols*rows, 2) ndarray or None
        Pixel centres in :func:`reflab.calibration.circles.detect_grid`'s order, or None.
    """
    import cv2

    from reflab.calibration.circles import detect_grid

    d = detect_grid(image, cols, rows)
    if d.found:
        return d.centres
    g = np.asarray(image, dtype=np.float64)
    g = g.mean(axis=2) if g.ndim == 3 else g
    bright = (g > 0.7 * np.percentile(g, 99.5)).astype(np.uint8)
    bright = cv2.morphologyEx(bright, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bright, connectivity=8)
    for k in (np.argsort(-stats[1:, cv2.CC_STAT_AREA]) + 1)[:3]:
        if stats[k, cv2.CC_STAT_AREA] < 4 * cols * rows:
            break
        region = (labels == k).astype(np.uint8)
        contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        filled = np.zeros_like(region)
        cv2.drawContours(filled, contours, -1, 1, thickness=cv2.FILLED)
        filled = cv2.erode(filled, np.ones((3, 3), np.uint8))
        d = detect_grid(np.where(filled > 0, g, np.median(g[region > 0])), cols, rows)
        if d.found:
            return d.centres
    return None


def _relabellings(cols: int, rows: int) -> list[np.ndarray]:
    """Index permutations of a symmetric grid that look the same (180° turn; 90° when square)."""
    idx = np.arange(cols * rows).reshape(rows, cols)
    out = [idx, idx[::-1, ::-1]]
    if cols == rows:
        out += [np.rot90(idx), np.rot90(idx, 3)]
    return [o.ravel() for o in out]


def register_target(images: list, R: np.ndarray, t: np.ndarray, camera: Camera, grid: tuple[int, int],
                    spacing: float, reference: int, name: str = "captures/turntable") -> tuple[Similarity, dict]:
    """Similarity from the circle target on the ground plane, seen in two or more shots.

    A symmetric grid reads the same turned by 180°, so each view's labelling is chosen to agree
    with the others (smallest triangulation residual), and the whole target's by the labelling
    that puts the reference shot nearest camera.json's pose.

    Parameters
    ----------
    images : list of (H, W, 3) ndarray
        The shots (linear).
    R, t : (N, 3, 3), (N, 3) ndarray
        SfM poses (NaN for unregistered shots).
    camera : Camera
        camera.json: intrinsics, and the reference pose.
    grid : (cols, rows)
    spacing : float
        Circle spacing in metres.
    reference : int
        Index of the shot taken from the input view at the reference angle.

    Returns
    -------
    Similarity, dict
        The report has ``method``, ``views`` (shots where the target was found), ``rms_mm``
        (triangulated centres against their known places) and ``max_mm``.
    """
    from reflab.calibration.target import target_points

    cols, rows = grid
    ok = np.all(np.isfinite(t), axis=1)
    views, uv = [], []
    for i in np.flatnonzero(ok):
        c = find_target(images[i], cols, rows)
        if c is not None:
            views.append(i)
            uv.append(c)
    if len(views) < 2:
        raise WorkspaceError(name, expected=f"the {cols}x{rows} circle target found in at least 2 registered shots "
                                            "(it must lie on the turntable, unoccluded in some shots; or give "
                                            "--turntable-centre instead)", got=f"found in {len(views)}")
    views = np.array(views)
    xy = np.stack([camera.undistort(u) for u in uv])  # (V, M, 2)
    Rv, tv = R[views], t[views]
    perms = _relabellings(cols, rows)
    # Each view's labelling: the one that triangulates best with the first view.
    for k in range(1, len(views)):
        errs = []
        for p in perms:
            pair = np.stack([xy[0], xy[k][p]])
            X, _ = triangulate(Rv[[0, k]], tv[[0, k]], pair, np.ones(pair.shape[:2], bool))
            proj, _ = _project_norm(Rv[[0, k]], tv[[0, k]], X)
            errs.append(np.nanmean(np.linalg.norm(proj - pair, axis=2)))
        xy[k] = xy[k][perms[int(np.argmin(errs))]]
    X, _ = triangulate(Rv, tv, xy, np.ones(xy.shape[:2], bool))
    known = target_points(cols, rows, spacing)
    best = None
    for p in perms:
        sim = umeyama(X[p], known)
        Rw, tw = sim.poses(R[reference:reference + 1], t[reference:reference + 1])
        miss = np.linalg.norm(-Rw[0].T @ tw[0] - camera.center)
        if best is None or miss < best[0]:
            best = (miss, sim, p)
    _, sim, p = best
    res = np.linalg.norm(sim.points(X[p]) - known, axis=1)
    report = {"method": "target", "views": [int(v) for v in views], "points": int(len(known)),
              "rms_mm": float(1e3 * np.sqrt(np.mean(res**2))), "max_mm": float(1e3 * res.max())}
    return sim, report


def _fit_circle_axis(C: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Centre of the circle that points ``C`` (N, 3) trace about ``axis`` (least squares, in its plane)."""
    e1, e2 = perpendicular_basis(axis)
    p = np.stack([C @ e1, C @ e2], axis=1)
    A = np.concatenate([2 * p, np.ones((len(p), 1))], axis=1)
    sol, *_ = np.linalg.lstsq(A, (p**2).sum(axis=1), rcond=None)
    return sol[0] * e1 + sol[1] * e2 + np.mean(C @ axis) * axis


def rotation_axis(R: np.ndarray, reference: int) -> np.ndarray:
    """Unit turntable axis in the frame of ``R``: the mean axis of the rotations relative to the reference shot."""
    import cv2

    ok = np.all(np.isfinite(R.reshape(len(R), -1)), axis=1)
    rel = [R[reference].T @ R[i] for i in np.flatnonzero(ok) if i != reference]
    vecs = np.array([cv2.Rodrigues(r)[0].ravel() for r in rel])
    # Rotation vectors of near-180° turns flip sign arbitrarily: align them before averaging.
    main = vecs[np.argmax(np.linalg.norm(vecs, axis=1))]
    vecs *= np.where(vecs @ main < 0, -1.0, 1.0)[:, None]
    a = vecs.sum(axis=0)
    return a / np.linalg.norm(a)


def register_axis(R: np.ndarray, t: np.ndarray, camera: Camera, reference: int,
                  centre_xy) -> tuple[Similarity, dict]:
    """Similarity from the input view's pose (camera.json) and the turntable axis' place on the ground.

    The reference shot's pose fixes rotation and translation for any scale; the axis, the centre
    of the circle the camera centres trace, must then stand on the ground at ``centre_xy``.
    """
    ok = np.all(np.isfinite(t), axis=1)
    axis = rotation_axis(R, reference)
    C = -np.einsum("nji,nj->ni", R[ok], t[ok])
    A = _fit_circle_axis(C, axis)
    rot = camera.R.T @ R[reference]  # world-from-sfm rotation
    C0 = -R[reference].T @ t[reference]
    v = (rot @ (A - C0))[:2]
    want = np.asarray(centre_xy, dtype=np.float64) - camera.center[:2]
    scale = float(v @ want / (v @ v))
    if not np.isfinite(scale) or scale <= 0:
        raise WorkspaceError("captures/turntable", expected="a turntable axis on the camera's side of the scene",
                             got=f"scale {scale}")
    sim = Similarity(scale, rot, camera.center - scale * rot @ C0)
    miss = np.linalg.norm(scale * v - want)
    return sim, {"method": "axis", "axis_centre_miss_mm": float(1e3 * miss)}


def turntable_check(R: np.ndarray, angles: np.ndarray, reference: int, up=(0.0, 0.0, 1.0)) -> dict:
    """Recovered turntable rotations against the commanded angles.

    Parameters
    ----------
    R : (N, 3, 3) ndarray
        World-frame (registered) world-to-camera rotations; NaN for unregistered shots.
    angles : (N,) ndarray
        Commanded turntable angles in degrees.
    reference : int
        The shot the angles are relative to.
    up : (3,) array_like
        The ground normal the axis should follow.

    Returns
    -------
    dict
        ``axis`` (unit, world frame), ``axis_tilt_deg`` (angle to ``up``), ``direction`` (+1 when a
        positive command turns counter-clockwise about ``up``), ``angle_error_deg`` per shot (None
        where unregistered), ``max_angle_error_deg`` and ``rms_angle_error_deg``.
    """
    import cv2

    up = np.asarray(up, dtype=np.float64)
    axis = rotation_axis(R, reference)
    if axis @ up < 0:
        axis = -axis
    tilt = float(np.degrees(np.arccos(np.clip(axis @ up, -1, 1))))
    ok = np.all(np.isfinite(R.reshape(len(R), -1)), axis=1)
    measured = np.full(len(R), np.nan)
    for i in np.flatnonzero(ok):
        # Object turned by +a about the axis: camera-from-object rotation R_ref @ Rot(a).
        rvec = cv2.Rodrigues(R[reference].T @ R[i])[0].ravel()
        measured[i] = np.degrees(rvec @ axis)
    commanded = np.asarray(angles, dtype=np.float64) - angles[reference]

    def wrap(x):
        return (x + 180.0) % 360.0 - 180.0

    errs = {s: wrap(measured - s * commanded) for s in (1.0, -1.0)}
    direction = min(errs, key=lambda s: np.nanmax(np.abs(errs[s])))
    err = errs[direction]
    return {"axis": axis.tolist(), "axis_tilt_deg": tilt, "direction": int(direction),
            "angle_error_deg": [None if not np.isfinite(e) else float(e) for e in err],
            "max_angle_error_deg": float(np.nanmax(np.abs(err))),
            "rms_angle_error_deg": float(np.sqrt(np.nanmean(err**2)))}


def reference_check(R: np.ndarray, t: np.ndarray, camera: Camera, reference: int) -> dict:
    """How far the registered reference shot is from camera.json's pose (centre mm, rotation deg)."""
    import cv2

    C = -R[reference].T @ t[reference]
    dR = cv2.Rodrigues(R[reference] @ camera.R.T)[0].ravel()
    return {"centre_mm": float(1e3 * np.linalg.norm(C - camera.center)),
            "rotation_deg": float(np.degrees(np.linalg.norm(dR)))}
