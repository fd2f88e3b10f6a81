"""Tsai's camera calibration (1986/87) from a planar circle target, several views, uncertainties.

Stages (Tsai 1987, coplanar case; several views share one set of intrinsics):

1-2. The start: Zhang's, through ``cv2.calibrateCamera`` (intrinsics from the homographies of all
   views at once, then every pose), so that no single view decides it. Tsai's own per-view start
   is the fallback when OpenCV cannot start (:func:`_tsai_start`): the radial alignment
   constraint (RAC) with the image centre at the image's middle, ``sx = 1``, a homogeneous
   linear system for ``[r1 r2 Tx r4 r5 Ty]`` up to scale, the scale from orthonormality, the sign
   from the point farthest from the centre, R completed by orthonormality; ``f`` and ``Tz``
   linearly (flipping R's third column/row when ``f < 0``); then nonlinear ``f, Tz, kappa1``. It
   cannot separate ``f`` from ``Tz`` for a fronto-parallel view.
3. All views together: ``f, kappa1, Cx, Cy, sx`` and every pose (Tsai's "full optimisation").
4. The same data in OpenCV form (``fx, fy, cx, cy, k1, k2``; ``p1 = p2 = k3 = 0``), started from
   stage 3 with ``k1 = -kappa1 f^2`` and ``k2 = 3 (kappa1 f^2)^2`` (the series inverse of Tsai's
   distorted->undistorted model, in normalised units). camera.json carries this form; its
   ``tsai`` block carries stage 3's parameters.

After stage 3 a view reprojecting far worse than the others is left out and the rest restarted;
the reference view far worse is a refusal (:func:`calibrate`).

Tsai's distortion maps distorted to undistorted sensor coordinates, ``X_u = X_d (1 + kappa1 r_d^2)``
(millimetres, ``r_d`` the distorted radius); projection therefore inverts it with Newton steps.
OpenCV's maps undistorted normalised coordinates to distorted ones.

Observations are the centroids of the imaged discs. With ``bias_correction`` the model predicts
exactly those: the perspective ellipse of each circle (Heikkilä 2000), sampled as a 16-gon, sent
through the lens distortion, its area centroid taken. Without it the model predicts projected
circle centres, which is what OpenCV's circle-grid calibration does.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from reflab.calibration.camera import Camera
from reflab.calibration.circles import ellipse_boundaries, ellipse_centres, polygon_centroids
from reflab.calibration.rotations import nearest_rotation, rodrigues, rotation_vector


class CalibrationError(ValueError):
    """The views cannot determine the camera (too few, degenerate, inconsistent).

    ``view``: index of the observation at fault, when one is.
    """

    def __init__(self, message: str, view: int | None = None):
        super().__init__(message)
        self.view = view


# ------------------------------------------------------------------ the two camera models
def tsai_distort(xu: np.ndarray, yu: np.ndarray, kappa1: float) -> tuple[np.ndarray, np.ndarray]:
    """Distorted sensor coordinates from undistorted ones under ``X_u = X_d (1 + kappa1 r_d^2)``."""
    ru = np.hypot(xu, yu)
    rd = ru.copy()
    for _ in range(6):  # Newton on rd + kappa1 rd^3 = ru, from rd = ru (quadratic convergence)
        rd = rd - (rd + kappa1 * rd**3 - ru) / np.maximum(1 + 3 * kappa1 * rd**2, 0.1)
    scale = np.where(ru > 1e-15, rd / np.maximum(ru, 1e-15), 1.0)
    return xu * scale, yu * scale


def tsai_pixels(xn, yn, f, kappa1, Cx, Cy, sx, dx, dy):
    """Pixels of normalised undistorted coordinates under Tsai's model (f, dx, dy in mm)."""
    xd, yd = tsai_distort(f * xn, f * yn, kappa1)
    return np.stack([sx * xd / dx + Cx, yd / dy + Cy], axis=-1)


def opencv_pixels(xn, yn, fx, fy, cx, cy, k1, k2, k3=0.0):
    """Pixels of normalised undistorted coordinates under OpenCV's radial model."""
    r2 = xn**2 + yn**2
    fac = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return np.stack([fx * xn * fac + cx, fy * yn * fac + cy], axis=-1)


# ------------------------------------------------------------------ stage 1 and 2: one view
def tsai_linear(plane_xy: np.ndarray, uv: np.ndarray, Cx: float, Cy: float, dx: float, dy: float,
                sx: float = 1.0) -> tuple[np.ndarray, np.ndarray, float]:
    """Tsai's closed form for one coplanar view (stage 1): R, t and f (mm), distortion ignored."""
    Xd = (uv[:, 0] - Cx) * dx / sx
    Yd = (uv[:, 1] - Cy) * dy
    xw, yw = plane_xy[:, 0], plane_xy[:, 1]
    # RAC: Yd (r1 xw + r2 yw + Tx) - Xd (r4 xw + r5 yw + Ty) = 0, homogeneous in 6 unknowns.
    A = np.column_stack([Yd * xw, Yd * yw, Yd, -Xd * xw, -Xd * yw, -Xd])
    n = np.linalg.svd(A)[2][-1]
    r1, r2, _, r4, r5, _ = n
    Sr = r1**2 + r2**2 + r4**2 + r5**2
    det = r1 * r5 - r4 * r2
    scale2 = 1 / Sr if abs(det) < 1e-9 * Sr else (Sr - np.sqrt(max(Sr**2 - 4 * det**2, 0))) / (2 * det**2)
    n = n * np.sqrt(scale2)
    far = np.argmax(np.abs(Xd) + np.abs(Yd))
    x = n[0] * xw[far] + n[1] * yw[far] + n[2]
    y = n[3] * xw[far] + n[4] * yw[far] + n[5]
    if np.sign(x) != np.sign(Xd[far]) or np.sign(y) != np.sign(Yd[far]):
        n = -n
    r1, r2, Tx, r4, r5, Ty = n
    r3 = np.sqrt(max(1 - r1**2 - r2**2, 0.0))
    r6 = -np.sign(r1 * r4 + r2 * r5) * np.sqrt(max(1 - r4**2 - r5**2, 0.0))

    def f_tz(R):
        w = R[2, 0] * xw + R[2, 1] * yw
        xc = R[0, 0] * xw + R[0, 1] * yw + Tx
        yc = R[1, 0] * xw + R[1, 1] * yw + Ty
        M = np.concatenate([np.column_stack([xc, -Xd]), np.column_stack([yc, -Yd])])
        rhs = np.concatenate([w * Xd, w * Yd])
        return np.linalg.lstsq(M, rhs, rcond=None)[0]

    def rot(r3, r6):
        a, b = np.array([r1, r2, r3]), np.array([r4, r5, r6])
        return nearest_rotation(np.stack([a, b, np.cross(a, b)]))

    R = rot(r3, r6)
    f, Tz = f_tz(R)
    if f < 0:  # Tsai's flip of r3, r6 (and so r7, r8 through the cross product)
        R = rot(-r3, -r6)
        f, Tz = f_tz(R)
    return R, np.array([Tx, Ty, Tz]), float(f)


# ------------------------------------------------------------------ results
@dataclass
class CalibrationResult:
    """A multi-view calibration.

    Attributes
    ----------
    camera : Camera
        OpenCV intrinsics and distortion with the reference view's pose, plus the Tsai block.
    poses : list of (R, t)
        Target-to-camera pose of every used view.
    rms, worst : (V,) ndarray
        RMS and largest reprojection error (px) per used view.
    views : list of int
        The used views (indices into the observations given), in the order of ``poses``.
    rejected : dict
        Views left out because they reprojected far worse than the others: index -> RMS (px).
    sigma : dict
        One-standard-deviation uncertainty of every intrinsic (OpenCV and Tsai names).
    crosscheck : dict
        ``cv2.calibrateCamera`` on the same detections, and its differences from ours.
    radius : float
        Printed circle radius used for the bias correction (metres).
    residuals : (V, N, 2) ndarray, optional
        Model minus measured centre (px) of every circle in every used view.
    observations : (V, N, 2) ndarray, optional
        The measured centres.
    """

    camera: Camera
    poses: list
    rms: np.ndarray
    worst: np.ndarray
    sigma: dict
    crosscheck: dict
    radius: float
    bias_correction: bool
    time_s: float = 0.0
    stages: dict = field(default_factory=dict)
    views: list = field(default_factory=list)
    rejected: dict = field(default_factory=dict)
    residuals: np.ndarray | None = None
    observations: np.ndarray | None = None
    warnings: list = field(default_factory=list)

    @property
    def rms_all(self) -> float:
        return float(np.sqrt(np.mean(self.rms**2)))

    def report(self, names=None) -> dict:
        """JSON-ready summary (written beside camera.json by the CLI).

        ``names``: one per observation given to :func:`calibrate` (rejected views included).
        """
        views = self.views or list(range(len(self.rms)))
        names = names or [f"view {i}" for i in range(max(views + list(self.rejected), default=-1) + 1)]
        K, d = self.camera.K, self.camera.dist
        return {
            "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "k1": d[0], "k2": d[1],
            "tsai": self.camera.tsai, "sigma": self.sigma, "rms_px": self.rms_all,
            "views": [{"image": str(names[i]), "rms_px": float(r), "worst_px": float(w)}
                      for i, r, w in zip(views, self.rms, self.worst)],
            "rejected": [{"image": str(names[i]), "rms_px": r} for i, r in self.rejected.items()],
            "warnings": list(self.warnings),
            "bias_correction": self.bias_correction, "circle_radius_m": self.radius,
            "opencv_crosscheck": self.crosscheck, "stages": self.stages, "time_s": self.time_s,
            # Per view, [u, v, du, dv] of each circle: measured centre and model minus measured
            # (the report's residual vector field), 0.1 mpx resolution.
            "residuals_px": [] if self.residuals is None else
            np.round(np.concatenate([self.observations, self.residuals], axis=2), 4).tolist(),
        }


# ------------------------------------------------------------------ joint refinement
def _refine(pixels, intr0, poses, obs, points, radius, check=None):
    """Least squares over shared intrinsics and per-view poses; returns (intr, poses, res, cov).

    ``pixels(intr, xn, yn)`` maps normalised undistorted coordinates to pixels; ``check()``, when
    given, is called at every evaluation (a task's pause and cancel).
    """
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    ni, nv, npt = len(intr0), len(poses), len(points)
    obs = np.asarray(obs)
    x0 = np.concatenate([intr0] + [np.concatenate([rotation_vector(R), t]) for R, t in poses])

    def residuals(x):
        if check is not None:
            check()
        p = x[ni:].reshape(nv, 6)
        return (_centres(pixels, x[:ni], rodrigues(p[:, :3]), p[:, 3:], points, radius)[0] - obs).ravel()

    sparsity = lil_matrix((2 * npt * nv, len(x0)), dtype=int)
    sparsity[:, :ni] = 1
    for v in range(nv):
        sparsity[2 * npt * v : 2 * npt * (v + 1), ni + 6 * v : ni + 6 * v + 6] = 1
    sol = least_squares(residuals, x0, jac_sparsity=sparsity, x_scale="jac", method="trf",
                        xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=100)
    res = residuals(sol.x)
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    dof = max(len(res) - len(x0), 1)
    s2 = float(res @ res) / dof
    cov = s2 * np.linalg.pinv(J.T @ J)
    poses = [(rodrigues(sol.x[ni + 6 * v : ni + 6 * v + 3]), sol.x[ni + 6 * v + 3 : ni + 6 * v + 6].copy())
             for v in range(nv)]
    return sol.x[:ni].copy(), poses, res.reshape(nv, npt, 2), cov[:ni, :ni]


def _centres(pixels, intr, R, t, points, radius):
    """Predicted measured centres (V, N, 2) and disc areas (V, N) in pixels.

    ``radius = 0``: projected circle centres (areas 0). Otherwise the centroid of each disc's
    image through the lens: a 16-gon on the perspective ellipse, distorted vertex by vertex, which
    carries both the perspective bias and the (same-sized) bias distortion adds.
    """
    if radius == 0:
        e = ellipse_centres(R, t, points, 0.0)
        return pixels(intr, e[..., 0], e[..., 1]), np.zeros(e.shape[:-1])
    b = ellipse_boundaries(R, t, points, radius)
    return polygon_centroids(pixels(intr, b[..., 0], b[..., 1]))


def _opencv_calibration(obs, points, size):
    """``cv2.calibrateCamera`` (k1, k2; no tangential terms) on projected circle centres.

    Its start is Zhang's: intrinsics from the homographies of all views at once, so no single view
    (a frontal one, where Tsai's per-view closed form cannot separate f from the distance) decides
    it. Returns (rms, K, dist, poses).
    """
    import cv2

    objp = [points.astype(np.float32)] * len(obs)
    imgp = [o.reshape(-1, 1, 2).astype(np.float32) for o in obs]
    flags = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    # One OpenCV thread: with its thread pool the same centres gave focal lengths 1e-5 apart run to
    # run, and this is the start of the refinement below, so the camera (and the chain after it)
    # was not repeatable.
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objp, imgp, size, None, None, flags=flags)
    finally:
        cv2.setNumThreads(threads)
    poses = [(rodrigues(np.asarray(r, dtype=np.float64).ravel()), np.asarray(t, dtype=np.float64).ravel())
             for r, t in zip(rvecs, tvecs)]
    return float(rms), np.asarray(K, dtype=np.float64), np.asarray(dist, dtype=np.float64).ravel(), poses


def _crosscheck(cv, ours: Camera) -> dict:
    rms, K, dist, _ = cv
    return {
        "rms_px": rms, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
        "k1": dist[0], "k2": dist[1],
        "minus_ours": {"fx": K[0, 0] - ours.K[0, 0], "fy": K[1, 1] - ours.K[1, 1], "cx": K[0, 2] - ours.K[0, 2],
                       "cy": K[1, 2] - ours.K[1, 2], "k1": dist[0] - ours.dist[0], "k2": dist[1] - ours.dist[1]},
    }


def _tsai_start(obs, points, Cx0, Cy0, dx, dy):
    """Tsai's stages 1-2 per view: poses and the median f, kappa1 (the fallback start)."""
    from scipy.optimize import least_squares

    poses, fs, kappas = [], [], []
    for o in obs:
        R, t, f = tsai_linear(points, o, Cx0, Cy0, dx, dy)

        def res(p, R=R, t=t, o=o):
            xn = (R[0, :2] @ points[:, :2].T + t[0]) / (R[2, :2] @ points[:, :2].T + p[1])
            yn = (R[1, :2] @ points[:, :2].T + t[1]) / (R[2, :2] @ points[:, :2].T + p[1])
            return (tsai_pixels(xn, yn, p[0], p[2], Cx0, Cy0, 1.0, dx, dy) - o).ravel()

        p = least_squares(res, [f, t[2], 0.0], x_scale="jac").x
        poses.append((R, np.array([t[0], t[1], p[1]])))
        fs.append(p[0])
        kappas.append(p[2])
    return np.array([np.median(fs), np.median(kappas), Cx0, Cy0, 1.0]), poses


def _view_rms(res) -> np.ndarray:
    return np.sqrt(np.mean(np.sum(res**2, axis=2), axis=1))


def _worst_view(rms: np.ndarray, ratio: float, floor_px: float) -> int | None:
    """Index of the view that reprojects far worse than the others (else None)."""
    k = int(np.argmax(rms))
    others = np.delete(rms, k)
    limit = max(ratio * float(np.median(others)), floor_px) if len(others) else np.inf
    return k if rms[k] > limit else None


def calibrate(observations: list[np.ndarray], points: np.ndarray, size: tuple[int, int], *,
              radius: float | None = None, pixel_size: float = 0.005, reference: int = 0,
              bias_correction: bool = True, areas: list[np.ndarray] | None = None,
              min_views: int = 3, min_spread_deg: float = 5.0, bad_view_ratio: float = 3.0,
              bad_view_px: float = 0.5, max_focal_sigma: float = 0.002, check=None) -> CalibrationResult:
    """Calibrate one camera from several views of a planar circle grid.

    Parameters
    ----------
    observations : list of (N, 2) ndarray
        Measured ellipse centres per view, ordered like ``points``.
    points : (N, 3) ndarray
        Circle centres on the target plane z = 0 (metres).
    size : (width, height)
        Image size.
    radius : float, optional
        Printed circle radius (metres); estimated from ``areas`` when None (else 0.3 × spacing).
    pixel_size : float
        Sensor element size dx = dy in millimetres (only scales Tsai's f and kappa1).
    reference : int
        Index (into ``observations``) of the view whose pose camera.json gets.
    bias_correction : bool
        Model the perspective bias of ellipse centres (else fit projected circle centres).
    areas : list of (N,) ndarray, optional
        Measured ellipse areas (px²) per view, to estimate ``radius``.
    bad_view_ratio, bad_view_px : float
        A view whose RMS reprojection error exceeds both ``bad_view_ratio`` × the median of the
        others and ``bad_view_px`` is left out (named in ``rejected``) and the rest recalibrated;
        when it is the reference view the calibration is refused.
    max_focal_sigma : float
        A one-sigma uncertainty of fx or fy above this fraction of it adds a warning (views too
        alike: near-parallel target planes).
    check : callable, optional
        Called at every evaluation of the least squares (a task's ``check``: pause and cancel).

    Raises
    ------
    CalibrationError
        Fewer than ``min_views`` views, all target orientations within ``min_spread_deg``, or the
        reference view far worse than the others.
    """
    t0 = time.perf_counter()
    W, H = size
    nv = len(observations)
    if nv < min_views:
        raise CalibrationError(f"{nv} usable view(s) of the target; need at least {min_views} "
                               "(tilted differently) to determine focal length, image centre and distortion")
    if not 0 <= reference < nv:
        raise CalibrationError(f"reference view {reference} out of range 0..{nv - 1}")
    obs_all = [np.asarray(o, dtype=np.float64).reshape(-1, 2) for o in observations]
    points = np.asarray(points, dtype=np.float64)
    dx = dy = float(pixel_size)
    Cx0, Cy0 = (W - 1) / 2, (H - 1) / 2
    spacing = np.median(np.linalg.norm(np.diff(points[:, :2], axis=0), axis=1))
    tsai_model = lambda x, xn, yn: tsai_pixels(xn, yn, x[0], x[1], x[2], x[3], x[4], dx, dy)  # noqa: E731
    keep, rejected = list(range(nv)), {}
    while True:
        obs = [obs_all[i] for i in keep]
        if len(obs) < min_views:
            raise CalibrationError(f"only {len(obs)} view(s) left after leaving out {len(rejected)} that reproject "
                                   f"far worse than the others; need at least {min_views}")
        # Start: Zhang's (every view's homography at once) through cv2.calibrateCamera, so no single
        # view decides it; Tsai's per-view closed form only when OpenCV cannot start.
        try:
            cv = _opencv_calibration(obs, points, (W, H))
            _, K0, d0, poses = cv
            f0 = K0[1, 1] * dy
            x0, start = np.array([f0, -d0[0] / f0**2, K0[0, 2], K0[1, 2], K0[0, 0] / K0[1, 1]]), "zhang"
        except Exception:  # noqa: BLE001 - cv2.error and numerical failures alike
            cv = None
            x0, poses = _tsai_start(obs, points, Cx0, Cy0, dx, dy)
            start = "tsai"
        if not np.all(np.isfinite(x0)) or x0[0] <= 0:
            raise CalibrationError("no starting camera fits these views (are they of one planar target?)")
        normals = np.array([R[:, 2] for R, _ in poses])
        spread = np.degrees(np.arccos(np.clip(normals @ normals.T, -1, 1))).max()
        if spread < min_spread_deg:
            raise CalibrationError(f"all {len(obs)} views hold the target within {spread:.1f} deg of the same "
                                   f"orientation (degenerate: focal length and distance trade off); tilt it "
                                   f"differently between views (at least {min_spread_deg:.0f} deg apart, 20-45 deg "
                                   "is good)")
        # Stage 3: Tsai's full optimisation over all views (radius from the data when unknown).
        rad = float(radius) if radius else 0.3 * spacing
        r_fit = rad if bias_correction else 0.0
        x_t, poses, res_t, cov_t = _refine(tsai_model, x0, poses, obs, points, r_fit, check)
        if bias_correction and radius is None and areas is not None:
            pred = _centres(tsai_model, x_t, np.array([R for R, _ in poses]), np.array([t for _, t in poses]),
                            points, rad)[1]
            rad *= float(np.sqrt(np.median(np.asarray([areas[i] for i in keep]) / pred)))
            x_t, poses, res_t, cov_t = _refine(tsai_model, x_t, poses, obs, points, rad, check)
        rms_t = _view_rms(res_t)
        bad = _worst_view(rms_t, bad_view_ratio, bad_view_px)
        if bad is None:
            break
        others = float(np.median(np.delete(rms_t, bad)))
        if keep[bad] == reference:
            raise CalibrationError(f"the reference view reprojects at {rms_t[bad]:.2f} px RMS, the other views at "
                                   f"{others:.2f} px: its circles do not fit the camera the others agree on (other "
                                   "zoom or focus, target moved, blur); retake it, its pose is the one camera.json "
                                   "needs", view=reference)
        rejected[keep[bad]] = float(rms_t[bad])
        keep.pop(bad)
    f, kappa1, Cx, Cy, sx = x_t
    tsai = {"f": f, "kappa1": kappa1, "sx": sx, "Cx": Cx, "Cy": Cy, "dx": dx, "dy": dy}
    stages = {"start": start, "orientation_spread_deg": float(spread),
              "tsai_rms_px": float(np.sqrt(np.mean(rms_t**2))),
              "rejected_views": {str(k): v for k, v in rejected.items()}}

    # Stage 4: OpenCV form.
    kn = kappa1 * f**2
    cv_model = lambda x, xn, yn: opencv_pixels(xn, yn, *x)  # noqa: E731
    x_c, poses, res_c, cov_c = _refine(cv_model, np.array([sx * f / dx, f / dy, Cx, Cy, -kn, 3 * kn**2]),
                                       poses, obs, points, rad if bias_correction else 0.0, check)
    fx, fy, cx, cy, k1, k2 = x_c
    sig_c, sig_t = np.sqrt(np.diag(cov_c)), np.sqrt(np.diag(cov_t))
    sigma = dict(zip(["fx", "fy", "cx", "cy", "k1", "k2"], sig_c.tolist()))
    sigma["tsai"] = dict(zip(["f", "kappa1", "Cx", "Cy", "sx"], sig_t.tolist()))

    warnings = []
    rel = max(sigma["fx"] / abs(fx), sigma["fy"] / abs(fy))
    if rel > max_focal_sigma:
        warnings.append(f"focal length poorly determined: one sigma is {100 * rel:.2f}% of it (views within "
                        f"{spread:.0f} deg of each other); tilt the target more between views (20-45 deg)")
    R_ref, t_ref = poses[keep.index(reference)]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    camera = Camera(W, H, K, np.array([k1, k2, 0, 0, 0.0]), R_ref, t_ref, tsai=tsai)
    err = np.linalg.norm(res_c, axis=2)
    crosscheck = _crosscheck(cv if cv is not None else _opencv_calibration(obs, points, (W, H)), camera)
    return CalibrationResult(camera, poses, np.sqrt(np.mean(err**2, axis=1)), err.max(axis=1), sigma,
                             crosscheck, rad, bias_correction, time.perf_counter() - t0, stages, keep, rejected,
                             residuals=np.asarray(res_c), observations=np.asarray(obs), warnings=warnings)
