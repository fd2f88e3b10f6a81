"""Point-lamp positions from rod shadows (docs/method.md §5), marks.json, and lamp power.

A rod of known height ``h`` stands on the ground plane z = 0; in each image (one lamp on) the
rod's foot and its shadow's tip are marked. Both back-project onto the ground; the rod's top is
``foot + h z``, and the line from the shadow tip through the top points at the lamp. The lamp is
first the least-squares intersection of those lines, then refined by minimising the marks'
reprojection error over the lamp and every foot position (the tip is where the line
lamp -> top meets the ground), which weighs each mark by what it actually constrains. The
covariance comes from that fit's Jacobian; marks whose residual stands far out are dropped and
named as outliers.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.calibration.camera import Camera
from reflab.core.workspace import WorkspaceError, as_array, as_float, field as req, object_items, read_json, write_json


@dataclass
class Mark:
    """One rod placement: image, lamp index, pixel of the rod's foot and of its shadow's tip."""

    image: str
    light: int
    base: np.ndarray
    tip: np.ndarray

    def __post_init__(self):
        self.base = np.asarray(self.base, dtype=np.float64).reshape(2)
        self.tip = np.asarray(self.tip, dtype=np.float64).reshape(2)


def read_marks(path, rod_height: float | None = None) -> tuple[float, list[Mark]]:
    """Read marks.json (docs/formats.md): ``(rod_height, marks)``, validated field by field.

    A file without ``rod_height`` (marks made before the rod was measured) takes ``rod_height``
    when it is given (``--rod-height``); the field is required otherwise.
    """
    obj = read_json(path)
    if "rod_height" in obj:
        height = as_float(obj["rod_height"], path, "rod_height", positive=True)
    elif rod_height is None:
        raise WorkspaceError(path, "rod_height", "the rod's height in metres (in this file, or --rod-height)",
                             got="missing")
    else:
        height = rod_height
    marks = []
    for where, item in object_items(req(obj, "marks", path), path, "marks", "marks",
                                    "an object with image, light, base, tip"):
        light = req(item, "light", path, where)
        if isinstance(light, bool) or not isinstance(light, int) or light < 0:
            raise WorkspaceError(path, f"{where}.light", "a lamp index (integer >= 0)", got=light)
        image = req(item, "image", path, where)
        if not isinstance(image, str):
            raise WorkspaceError(path, f"{where}.image", "an image path (string)", got=image)
        base = as_array(req(item, "base", path, where), (2,), path, f"{where}.base")
        tip = as_array(req(item, "tip", path, where), (2,), path, f"{where}.tip")
        marks.append(Mark(image, light, base, tip))
    return height, marks


def write_marks(path, rod_height: float, marks: list[Mark]) -> Path:
    """Write marks.json atomically; what else the file holds (the surfaces' corner marks) is kept."""
    obj = read_json(path) if Path(path).exists() else {}
    obj.update({"rod_height": float(rod_height), "marks": [
        {"image": m.image, "light": int(m.light), "base": m.base, "tip": m.tip} for m in marks]})
    return write_json(path, obj)


def ground_points(camera: Camera, uv: np.ndarray, where: str = "marks") -> np.ndarray:
    """Back-project pixels (N, 2) onto the ground plane z = 0 (world frame)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    o, d = camera.rays(uv)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[:, 2] / d[:, 2]
    bad = ~(np.isfinite(s) & (s > 0))
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueError(f"{where}[{i}]: pixel {uv[i].tolist()} does not see the ground plane z = 0 "
                         "(above the horizon or behind the camera); check the mark and camera.json")
    return o + s[:, None] * d


def intersect_lines(points: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Least-squares point closest to lines ``points + s dirs`` (the plain intersection)."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    return np.linalg.solve(P.sum(axis=0), np.einsum("nij,nj->i", P, points))


@dataclass
class LampFit:
    """One lamp's position from its marks.

    Attributes
    ----------
    position : (3,) ndarray
        Refined lamp position (metres, world frame).
    covariance : (3, 3) ndarray
        Its covariance, from the fit's Jacobian and the marks' noise level.
    intersection : (3,) ndarray
        The plain least-squares line intersection (the starting point).
    sigma_px : float
        Mark noise level used for the covariance (given, or estimated from the residuals).
    residuals : (M, 2) ndarray
        Foot and tip reprojection errors (px) of every input mark, outliers included.
    outliers : list of int
        Indices (into this lamp's marks) left out of the final fit.
    """

    light: int
    position: np.ndarray
    covariance: np.ndarray
    intersection: np.ndarray
    sigma_px: float
    residuals: np.ndarray
    outliers: list = field(default_factory=list)

    def report(self) -> dict:
        return {"light": self.light, "position": self.position, "sigma_position": self.covariance,
                "sigma_xyz_m": np.sqrt(np.diag(self.covariance)), "line_intersection": self.intersection,
                "mark_sigma_px": self.sigma_px, "outliers": self.outliers,
                "mark_errors_px": np.linalg.norm(self.residuals, axis=2)}


def _predict(x, camera, h):
    """Pixels of feet and tips for parameters x = [lamp (3), feet xy (2M)]."""
    L, feet = x[:3], x[3:].reshape(-1, 2)
    base = np.column_stack([feet, np.zeros(len(feet))])
    top = base + [0.0, 0.0, h]
    s = L[2] / (L[2] - h)
    tips = L + s * (top - L)
    return camera.project(np.concatenate([base, tips])).reshape(2, -1, 2)


def _fit(camera, base_uv, tip_uv, h, L0):
    from scipy.optimize import least_squares

    feet = ground_points(camera, base_uv)[:, :2]
    obs = np.stack([base_uv, tip_uv])
    fun = lambda x: (_predict(x, camera, h) - obs).ravel()  # noqa: E731
    lo = np.full(3 + feet.size, -np.inf)
    lo[2] = h * (1 + 1e-6)  # the lamp is above the rod's top, or no shadow tip exists
    x0 = np.concatenate([np.maximum(L0, lo[:3] + [0, 0, 1e-3]), feet.ravel()])
    sol = least_squares(fun, x0, bounds=(lo, np.inf), x_scale="jac", xtol=1e-12, ftol=1e-12)
    return sol.x, fun(sol.x), sol.jac


def locate_lamp(camera: Camera, base_uv: np.ndarray, tip_uv: np.ndarray, rod_height: float, *,
                light: int = 0, mark_sigma: float | None = None, outlier_sigmas: float = 4.0,
                min_outlier_px: float = 2.0) -> LampFit:
    """Locate one lamp from its rod placements.

    Parameters
    ----------
    camera : Camera
        Calibrated camera that took the rod images (world frame: ground z = 0).
    base_uv, tip_uv : (M, 2) ndarray
        Pixels of the rod's foot and of its shadow's tip, M >= 2 placements.
    rod_height : float
        Rod height (metres).
    mark_sigma : float, optional
        Known marking noise (px); estimated from the residuals when None.
    outlier_sigmas, min_outlier_px : float
        A mark is an outlier when one of its errors exceeds both this many robust standard
        deviations and ``min_outlier_px``; the worst is dropped and the fit repeated.
    """
    base_uv = np.asarray(base_uv, dtype=np.float64).reshape(-1, 2)
    tip_uv = np.asarray(tip_uv, dtype=np.float64).reshape(-1, 2)
    if not (rod_height > 0 and np.isfinite(rod_height)):
        raise ValueError(f"rod height must be a positive number of metres, got {rod_height!r}")
    if len(base_uv) < 2 or len(base_uv) != len(tip_uv):
        raise ValueError(f"lamp {light}: need at least 2 rod placements (foot and tip each), got {len(base_uv)}")
    feet = ground_points(camera, base_uv, f"lamp {light} marks (foot)")
    tips = ground_points(camera, tip_uv, f"lamp {light} marks (tip)")
    tops = feet + [0.0, 0.0, rod_height]
    dirs = tops - tips
    if np.linalg.matrix_rank(np.column_stack([dirs / np.linalg.norm(dirs, axis=1, keepdims=True)]), tol=1e-3) < 2:
        raise ValueError(f"lamp {light}: all shadow lines are parallel; place the rod at more varied positions")
    L0 = intersect_lines(tips, dirs)

    keep = np.arange(len(base_uv))
    outliers: list[int] = []
    while True:
        x, res, J = _fit(camera, base_uv[keep], tip_uv[keep], rod_height, L0)
        comps = np.abs(res)
        robust = 1.4826 * np.median(comps) * np.sqrt(len(res) / max(len(res) - len(x), 1))
        per_mark = np.abs(res.reshape(2, -1, 2)).max(axis=(0, 2))
        worst = int(np.argmax(per_mark))
        if len(keep) <= 3 or per_mark[worst] <= max(outlier_sigmas * robust, min_outlier_px):
            break
        outliers.append(int(keep[worst]))
        keep = np.delete(keep, worst)
    dof = max(len(res) - len(x), 1)
    sigma = float(mark_sigma) if mark_sigma else float(np.sqrt(res @ res / dof))
    cov = sigma**2 * np.linalg.pinv(J.T @ J)[:3, :3]
    # Errors of every input mark (outliers too) against the final lamp, feet re-fitted per mark.
    all_feet = ground_points(camera, base_uv)[:, :2]
    all_res = _predict(np.concatenate([x[:3], all_feet.ravel()]), camera, rod_height) - np.stack([base_uv, tip_uv])
    all_res[:, keep] = res.reshape(2, -1, 2)
    return LampFit(light, x[:3].copy(), cov, L0, sigma, np.swapaxes(all_res, 0, 1), sorted(outliers))


def locate_lamps(camera: Camera, marks: list[Mark], rod_height: float, **kw) -> list[LampFit]:
    """One :class:`LampFit` per lamp index present in ``marks``, in index order."""
    out = []
    for k in sorted({m.light for m in marks}):
        mk = [m for m in marks if m.light == k]
        out.append(locate_lamp(camera, np.array([m.base for m in mk]), np.array([m.tip for m in mk]),
                               rod_height, light=k, **kw))
    return out


def _line(points: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted centroid and principal direction of pixel positions (N, 2)."""
    w = weights / weights.sum()
    c = w @ points
    d = points - c
    cov = (d * w[:, None]).T @ d
    return c, np.linalg.eigh(cov)[1][:, -1]


def detect_rod_marks(image: np.ndarray, *, room: np.ndarray | None = None, red_ratio: float = 1.8,
                     shadow_level: float = 0.5, min_pixels: int = 15) -> tuple[np.ndarray, np.ndarray]:
    """Find the rod's foot and its shadow's tip in one image (a red rod, one lamp on).

    The rod is the largest red blob (red channel ``red_ratio`` times green and blue); the shadow
    the largest blob darker than ``shadow_level`` times the local ground level (grey closing, which
    erases thin dark structures). Each is reduced to its principal line; the foot is where the two
    lines cross (both pass through it), the tip the shadow's far end along its line.

    ``room``: a lamps-off frame of the same view (the room light alone). The shadow is then found
    in the lamp's light relative to the room light, ``(image - room) / room``, in which the
    ground's texture cancels: a shadow falling across dark wood and white paper is one even strip.

    Returns
    -------
    base, tip : (2,) ndarray
        Pixel positions.

    Raises
    ------
    ValueError
        When the rod or its shadow is not found.
    """
    import cv2

    img = np.asarray(image, dtype=np.float64)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    lum = img.mean(axis=2)
    if room is not None:
        base = np.asarray(room, dtype=np.float64).mean(axis=2)
        lum = np.clip(lum - base, 0.0, None) / np.maximum(base, 1e-6 * max(float(base.max()), 1e-12))
    rod = (r > red_ratio * np.maximum(g, b)) & (r > 1e-6)

    def largest(mask):
        n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
        if n < 2:
            return None
        k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        return lab == k if stats[k, cv2.CC_STAT_AREA] >= min_pixels else None

    rod = largest(rod)
    if rod is None:
        raise ValueError("rod not found (no red blob); is the rod red and in view?")
    k = 41
    ground = cv2.morphologyEx(lum.astype(np.float32), cv2.MORPH_CLOSE,
                              cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))).astype(np.float64)
    near_rod = cv2.dilate(rod.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    shadow = largest((lum < shadow_level * ground) & ~near_rod)
    if shadow is None:
        raise ValueError("shadow not found (no dark strip beside the rod); is the lamp on?")
    vr, ur = np.nonzero(rod)
    vs, us = np.nonzero(shadow)
    pr = np.column_stack([ur, vr]).astype(np.float64)
    ps = np.column_stack([us, vs]).astype(np.float64)
    cr, dr = _line(pr, np.ones(len(pr)))
    cs, ds = _line(ps, np.clip(1 - lum[vs, us] / ground[vs, us], 0, 1) + 1e-6)
    # Foot: crossing of the rod's and the shadow's lines; when nearly collinear, the rod end
    # nearest the shadow.
    A = np.column_stack([dr, -ds])
    if abs(np.linalg.det(A)) > np.sin(np.radians(8)):
        foot = cr + dr * np.linalg.solve(A, cs - cr)[0]
    else:
        t = (pr - cr) @ dr
        end = np.sign((cs - cr) @ dr) or 1.0
        foot = cr + dr * (t.max() if end > 0 else t.min())
    if (cs - foot) @ ds < 0:
        ds = -ds
    # The shadow ends in the round shadow of the rod's top disc, centred on the true tip: step
    # back from the far end by the strip's half-width there (coverage-weighted, just before the end).
    t_end = ((ps - foot) @ ds).max()
    end = ps[np.argmax((ps - foot) @ ds)]
    if end.min() < 1 or end[0] > lum.shape[1] - 2 or end[1] > lum.shape[0] - 2:
        raise ValueError("the shadow runs out of the image; move the rod or mark the tip by hand")
    v, u = np.mgrid[0 : lum.shape[0], 0 : lum.shape[1]]
    rel = np.stack([u - foot[0], v - foot[1]], axis=-1)
    along, across = rel @ ds, np.abs(rel @ np.array([-ds[1], ds[0]]))
    dark = np.clip(1 - lum / np.maximum(ground, 1e-12), 0, None)
    coverage = np.clip(dark / np.median(dark[vs, us]), 0, 1)
    band = (along > t_end - 10) & (along < t_end - 4) & (across < 8) & ~near_rod
    half_width = coverage[band].sum() / 6 / 2 if band.any() else 0.0
    return foot, foot + ds * (t_end - half_width)


def lamp_intensity(image: np.ndarray, camera: Camera, lamp: np.ndarray, kd, *, region=None,
                   min_cos: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Radiant intensity of a lamp from an image of a ground-plane surface of known ``kd``.

    Lambertian ground z = 0 (``kd`` as in scene.json: radiance = kd (n·l) I / d²), so per pixel
    ``I = B d² / (kd cos)``; the median over the pixels that see ``region`` is robust to shadows
    and glints. For a paper of hemispherical reflectance rho, ``kd = rho / pi``.

    Parameters
    ----------
    image : (H, W, 3) ndarray
        Linear image, the lamp alone on.
    lamp : (3,) ndarray
        Lamp position.
    kd : float or (3,)
        The surface's diffuse coefficient per band.
    region : (xmin, xmax, ymin, ymax), optional
        The surface's extent on the ground (metres); the whole visible ground when None.

    Returns
    -------
    intensity : (3,) ndarray
    spread : (3,) ndarray
        Robust relative spread (1.4826 MAD / median) of the per-pixel estimates.
    """
    kd = np.broadcast_to(np.asarray(kd, dtype=np.float64), (3,))
    if np.any(kd <= 0):
        raise ValueError(f"kd must be positive, got {kd.tolist()}")
    img = np.asarray(image, dtype=np.float64).reshape(-1, 3)
    if img.shape[0] != camera.width * camera.height:
        raise ValueError(f"image is not {camera.width}x{camera.height} like the camera")
    o, d = camera.pixel_rays()
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[:, 2] / d[:, 2]
    ok = np.isfinite(s) & (s > 0)
    p = o + np.where(ok, s, 0)[:, None] * d
    to_lamp = np.asarray(lamp, dtype=np.float64) - p
    d2 = np.einsum("ij,ij->i", to_lamp, to_lamp)
    cos = to_lamp[:, 2] / np.sqrt(np.maximum(d2, 1e-300))
    ok &= cos > min_cos
    if region is not None:
        xmin, xmax, ymin, ymax = region
        ok &= (p[:, 0] >= xmin) & (p[:, 0] <= xmax) & (p[:, 1] >= ymin) & (p[:, 1] <= ymax)
    if ok.sum() < 50:
        raise ValueError(f"only {int(ok.sum())} pixels see the reference surface lit by the lamp; "
                         "check the region and the lamp position")
    est = img[ok] * (d2[ok] / cos[ok])[:, None] / kd
    med = np.median(est, axis=0)
    spread = 1.4826 * np.median(np.abs(est - med), axis=0) / np.maximum(np.abs(med), 1e-300)
    return med, spread
