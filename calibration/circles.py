"""Circle-grid target detection with sub-pixel ellipse centres, and the ellipse-centre bias.

A circle seen in perspective is an ellipse whose centre is *not* the image of the circle's centre
(Heikkilä 2000; OpenCV issue 7312): the offset grows with the circle's size and the target's
tilt. :func:`detect_grid` returns measured ellipse centres (intensity-weighted area centroids,
exact for an ellipse, sub-pixel through the anti-aliased edge); :func:`ellipse_centres` predicts
where those centres are for a given pose, so the calibration (:mod:`reflab.calibration.tsai`) fits the
measured centres with the predicted *ellipse* centres instead of the projected circle centres:
Heikkilä's correction, inside the refinement rather than as a separate pre-correction.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class GridDetection:
    """One image's detection.

    Attributes
    ----------
    found : bool
        True when all ``cols * rows`` circles were found and ordered.
    centres : (N, 2) ndarray or None
        Sub-pixel ellipse centres, row by row (see :func:`reflab.calibration.target.target_points`).
    areas : (N,) ndarray or None
        Ellipse areas in px² (used to estimate the printed circles' radius).
    n_blobs : int
        Dark blobs the blob detector saw (a hint when the grid size is wrong).
    reason : str
        Why the grid was not accepted (empty when found).
    """

    found: bool
    centres: np.ndarray | None
    areas: np.ndarray | None
    n_blobs: int
    reason: str = ""


def parse_grid(text: str, option: str = "grid") -> tuple[int, int]:
    """``"COLSxROWS"`` -> (cols, rows), each ≥ 2; an OptionError naming ``option`` otherwise."""
    from reflab.core.workspace import OptionError

    parts = str(text).lower().split("x")
    try:
        cols, rows = (int(p) for p in parts)
    except ValueError:
        raise OptionError(option, f"expected COLSxROWS such as 11x8, got {text!r}") from None
    if cols < 2 or rows < 2:
        raise OptionError(option, f"need at least 2 circles per row and column, got {text!r}")
    return cols, rows


def _grey(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, dtype=np.float64)
    return img.mean(axis=2) if img.ndim == 3 else img


def _blob_detector(shape, min_area: float = 12.0, max_area: float | None = None):
    import cv2

    p = cv2.SimpleBlobDetector_Params()
    p.filterByColor, p.blobColor = True, 0
    p.filterByArea, p.minArea = True, float(min_area)
    p.maxArea = float(shape[0] * shape[1]) / 8 if max_area is None else float(max_area)
    p.filterByCircularity = False
    p.filterByInertia, p.minInertiaRatio = True, 0.08
    p.filterByConvexity, p.minConvexity = True, 0.8
    return cv2.SimpleBlobDetector_create(p)


def _canonical_order(centres: np.ndarray, cols: int, rows: int) -> np.ndarray:
    """Reorder OpenCV's grid so the target frame is right-handed with +z toward the camera.

    Of the orderings of the same grid (180° turn; mirror; 90° turns when square), keep those where
    the image of +x (along a row) crossed with the image of -y (down the columns) is positive, as
    for a camera above the plane, then the one whose rows run most to the right and downward.
    """
    grid = centres.reshape(rows, cols, 2)
    candidates = [grid, grid[::-1], grid[:, ::-1], grid[::-1, ::-1]]
    if cols == rows:
        candidates += [np.swapaxes(g, 0, 1) for g in candidates]
    best, best_score = None, -np.inf
    for g in candidates:
        a = g[0, -1] - g[0, 0]
        b = g[-1, 0] - g[0, 0]
        if a[0] * b[1] - a[1] * b[0] <= 0:
            continue
        score = a[0] / np.linalg.norm(a) + b[1] / np.linalg.norm(b)
        if score > best_score:
            best, best_score = g, score
    return best.reshape(-1, 2)


def detect_grid(image: np.ndarray, cols: int, rows: int) -> GridDetection:
    """Find a symmetric grid of dark circles on a light target, with sub-pixel ellipse centres.

    OpenCV's ``findCirclesGrid`` finds and orders the grid; each centre is then re-measured as the
    intensity-weighted centroid of its blob: weights ``(bg - I) / (bg - ink)`` clipped to [0, 1],
    with ``bg`` the local paper level (grey dilation) and ``ink`` the blob's darkest level, so the
    partially covered edge pixels count by their coverage.

    Parameters
    ----------
    image : (H, W, 3) or (H, W) ndarray
        Linear image.
    cols, rows : int
        Circles per row and per column.
    """
    import cv2

    g = _grey(image)
    lo, hi = np.percentile(g, [0.5, 99.5])
    g8 = np.clip(255 * (g - lo) / max(hi - lo, 1e-12), 0, 255).astype(np.uint8)
    detector = _blob_detector(g.shape)
    blobs = np.array([k.pt for k in detector.detect(g8)], dtype=np.float64).reshape(-1, 2)
    n_blobs = len(blobs)
    found, centres = cv2.findCirclesGrid(g8, (cols, rows), flags=cv2.CALIB_CB_SYMMETRIC_GRID,
                                         blobDetector=detector)
    if (not found or centres is None) and n_blobs > cols * rows:
        # Clutter (a textured table's dark grain) confuses the grid search: keep only blobs of
        # about the size of the target's circles (the cols x rows largest ones), and retry with
        # OpenCV's clustering search, which tolerates a few stray blobs.
        sizes = np.sort([k.size for k in detector.detect(g8)])[::-1][: cols * rows]
        area = np.pi * (np.median(sizes) / 2) ** 2
        found, centres = cv2.findCirclesGrid(g8, (cols, rows), flags=cv2.CALIB_CB_SYMMETRIC_GRID | cv2.CALIB_CB_CLUSTERING,
                                             blobDetector=_blob_detector(g.shape, area / 4, area * 4))
    if not found or centres is None or len(centres) != cols * rows:
        return GridDetection(False, None, None, n_blobs, f"no {cols}x{rows} grid among {n_blobs} dark blobs")
    centres = _canonical_order(centres.reshape(-1, 2).astype(np.float64), cols, rows)
    # findCirclesGrid happily returns a sub-grid of a larger target: look for circles that
    # continue the grid's rows or columns one step beyond its border.
    j, i = np.mgrid[0:rows, 0:cols]
    Hg, _ = cv2.findHomography(np.stack([i.ravel(), j.ravel()], 1).astype(np.float64), centres)
    if Hg is not None and n_blobs > cols * rows:
        q = np.column_stack([blobs, np.ones(n_blobs)]) @ np.linalg.inv(Hg).T
        q = q[:, :2] / q[:, 2:3]
        near = np.all(np.abs(q - np.round(q)) < 0.2, axis=1)
        qi, qj = np.round(q[:, 0]), np.round(q[:, 1])
        outside = (qi < 0) | (qi >= cols) | (qj < 0) | (qj >= rows)
        adjacent = (qi >= -1) & (qi <= cols) & (qj >= -1) & (qj <= rows)
        extra = int(np.sum(near & outside & adjacent))
        if extra:
            return GridDetection(False, None, None, n_blobs,
                                 f"the target continues beyond a {cols}x{rows} grid ({extra} more circles "
                                 "in line with it): the grid size is wrong")

    # Local paper level: grey dilation wider than the largest circle removes the dark discs.
    step = np.median(np.linalg.norm(np.diff(centres.reshape(rows, cols, 2), axis=1), axis=2))
    k = int(2 * np.ceil(step) + 1)
    bg = cv2.dilate(g.astype(np.float32), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))).astype(np.float64)
    # Blobs: connected components of "darker than half-way", grown by 2 px to take in the edge.
    dark = (g < 0.5 * (bg + np.percentile(g, 1))).astype(np.uint8)
    n_lab, labels = cv2.connectedComponents(dark, connectivity=8)
    ij = np.round(centres).astype(int)
    ij[:, 0] = ij[:, 0].clip(0, g.shape[1] - 1)
    ij[:, 1] = ij[:, 1].clip(0, g.shape[0] - 1)
    ids = labels[ij[:, 1], ij[:, 0]]
    if np.any(ids == 0) or len(np.unique(ids)) != len(ids):
        return GridDetection(False, None, None, n_blobs, "circles touch each other or the border")
    lut = np.zeros(n_lab, np.float32)
    lut[ids] = np.arange(1, len(ids) + 1)
    grown = cv2.dilate(lut[labels], np.ones((5, 5), np.uint8)).astype(np.int64)  # 0 = none, k+1 = circle k
    ink = np.full(len(ids) + 1, np.inf)
    np.minimum.at(ink, grown.ravel(), g.ravel())
    v, u = np.mgrid[0 : g.shape[0], 0 : g.shape[1]]
    paper = _paper_level(g, lut[labels], grown, centres, u, v)
    w = np.clip((paper - g) / np.maximum(paper - ink[grown], 1e-9), 0.0, 1.0)
    w[grown == 0] = 0.0
    m00 = np.bincount(grown.ravel(), w.ravel(), len(ids) + 1)[1:]
    mu = np.bincount(grown.ravel(), (w * u).ravel(), len(ids) + 1)[1:] / np.maximum(m00, 1e-12)
    mv = np.bincount(grown.ravel(), (w * v).ravel(), len(ids) + 1)[1:] / np.maximum(m00, 1e-12)
    if np.any(m00 < 3):
        return GridDetection(False, None, None, n_blobs, "circles too small (< 3 px²)")
    return GridDetection(True, np.stack([mu, mv], axis=1), m00, n_blobs)


def _paper_level(g: np.ndarray, circle: np.ndarray, grown: np.ndarray, centres: np.ndarray,
                 u: np.ndarray, v: np.ndarray, width: int = 3) -> np.ndarray:
    """The paper's level under each circle: a plane fitted to the ring of paper around it.

    The ring is the ``width`` pixels just outside the circle's grown blob (``grown``: 0 outside,
    k+1 for circle k). A plane, not a constant, because the lamps shade the paper across a circle:
    a level too high on one side gives that side's paper pixels weight in the centroid and pulls
    it there. Only the paper next to the circle counts, so what lies beyond the target's edge
    (the table, its grain, a brighter sheet) does not (a wide window's maximum shifted the
    circles of the row nearest the edge by 0.2 px). Ring pixels more than 3 robust sigma from the
    first plane (a speck, the target's edge) are left out of the second. Returns (H, W); 0
    outside the grown blobs.
    """
    import cv2

    n = len(centres)
    k = 2 * (2 + width) + 1
    outer = cv2.dilate(circle, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))).astype(np.int64)
    ring = (outer > 0) & (grown == 0)
    lab, gr = outer[ring], g[ring]
    du, dv = u[ring] - centres[lab - 1, 0], v[ring] - centres[lab - 1, 1]
    X = np.stack([np.ones_like(du), du, dv], axis=1)
    mean = np.bincount(lab, gr, n + 1) / np.maximum(np.bincount(lab, minlength=n + 1), 1)
    by_circle = np.argsort(lab, kind="stable")
    splits = np.searchsorted(lab[by_circle], np.arange(1, n + 1))

    def planes(keep):
        # Per circle, least squares of its kept ring pixels; the ring's mean where fewer than 8.
        XtX = np.zeros((n + 1, 3, 3))
        np.add.at(XtX, lab[keep], X[keep, :, None] * X[keep, None, :])
        Xtg = np.zeros((n + 1, 3))
        np.add.at(Xtg, lab[keep], X[keep] * gr[keep, None])
        ok = np.bincount(lab[keep], minlength=n + 1) >= 8
        coef = np.zeros((n + 1, 3))
        coef[ok] = np.linalg.solve(XtX[ok] + 1e-9 * np.eye(3), Xtg[ok][..., None])[..., 0]
        coef[~ok, 0] = mean[~ok]
        return coef

    coef = planes(np.ones(len(lab), bool))
    r = gr - (X * coef[lab]).sum(1)
    mad = np.zeros(n + 1)
    mad[1:] = [np.median(np.abs(a)) if len(a) else 0.0 for a in np.split(r[by_circle], splits)[1:]]
    coef = planes(np.abs(r) <= 3 * 1.4826 * np.maximum(mad[lab], 1e-12))
    idx = grown.ravel()
    cu = np.concatenate([[0.0], centres[:, 0]])[idx]
    cv_ = np.concatenate([[0.0], centres[:, 1]])[idx]
    c = coef[idx]
    level = c[:, 0] + c[:, 1] * (u.ravel() - cu) + c[:, 2] * (v.ravel() - cv_)
    return np.where(idx > 0, level, 0.0).reshape(g.shape)


def _image_conics(Hinv: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """(V, N, 3, 3) image conics ``Hinv^T Q Hinv`` of circles of ``radius`` at plane ``points``.

    The circle's conic factors as ``Q = T^T diag(1, 1, -radius^2) T`` with ``T`` the translation
    to its centre, so ``C = g0 g0^T + g1 g1^T - radius^2 g2 g2^T`` with ``g = T Hinv`` row by row.
    """
    h0, h1, h2 = (Hinv[:, None, k, :] for k in range(3))
    g0 = h0 - points[None, :, 0, None] * h2
    g1 = h1 - points[None, :, 1, None] * h2
    g2 = np.broadcast_to(h2, g0.shape)
    outer = lambda g: g[..., :, None] * g[..., None, :]  # noqa: E731
    return outer(g0) + outer(g1) - radius**2 * outer(g2)


def ellipse_centres(R: np.ndarray, t: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """Normalised (undistorted) image coordinates of the centres of the imaged circles.

    The plane-to-image homography ``H = [r1 r2 t]`` maps the circle's conic ``Q`` to
    ``C = H^-T Q H^-1``; the ellipse centre is ``-C[:2,:2]^-1 C[:2,2]``. With ``radius = 0`` this
    is the projected circle centre.

    Parameters
    ----------
    R, t : (3, 3), (3,) ndarray, or (V, 3, 3), (V, 3) for V views at once
        Target-to-camera pose(s).
    points : (N, 3) ndarray
        Circle centres on the target plane z = 0.
    radius : float
        Printed circle radius, same unit as ``points`` and ``t``.

    Returns
    -------
    (N, 2) or (V, N, 2) ndarray
    """
    R, t = np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64)
    single = R.ndim == 2
    H = np.concatenate([np.atleast_3d(R.reshape(-1, 3, 3))[:, :, :2], t.reshape(-1, 3, 1)], axis=2)
    if radius == 0:
        p = np.einsum("vij,nj->vni", H, np.column_stack([points[:, 0], points[:, 1], np.ones(len(points))]))
        out = p[..., :2] / p[..., 2:3]
    else:
        C = _image_conics(np.linalg.inv(H), points, radius)
        A, b = C[..., :2, :2], C[..., :2, 2]
        det = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
        # -A^-1 b for symmetric 2x2 A, written out (fast for many small systems).
        out = -np.stack([A[..., 1, 1] * b[..., 0] - A[..., 0, 1] * b[..., 1],
                         A[..., 0, 0] * b[..., 1] - A[..., 1, 0] * b[..., 0]], axis=-1) / det[..., None]
    return out[0] if single else out


def ellipse_boundaries(R: np.ndarray, t: np.ndarray, points: np.ndarray, radius: float,
                       samples: int = 16) -> np.ndarray:
    """Points on the imaged circles' boundaries, normalised undistorted coordinates.

    Evenly spaced in the ellipse's parametric angle, so a polygon through them keeps the ellipse's
    centre and, once mapped through the lens distortion, gives the distorted disc's centroid
    (:func:`polygon_centroids`), which is what :func:`detect_grid` measures.

    Returns
    -------
    (V, N, samples, 2) ndarray (V = 1 for a single pose)
    """
    R, t = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3), np.asarray(t, dtype=np.float64).reshape(-1, 3)
    H = np.concatenate([R[:, :, :2], t[:, :, None]], axis=2)
    C = _image_conics(np.linalg.inv(H), points, radius)
    A, b, c = C[..., :2, :2], C[..., :2, 2], C[..., 2, 2]
    e = -np.linalg.solve(A, b[..., None])[..., 0]
    k = -(c + (b * e).sum(-1))  # (x - e)^T A (x - e) = k on the boundary
    L = np.linalg.cholesky(np.linalg.inv(A) * k[..., None, None])
    a = np.linspace(0, 2 * np.pi, samples, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a)], axis=1)
    return e[:, :, None, :] + np.swapaxes(L @ ring.T, -1, -2)


def polygon_centroids(poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroids (..., 2) and areas (...) of closed polygons (..., S, 2) (shoelace formula)."""
    x, y = poly[..., 0], poly[..., 1]
    x1, y1 = np.roll(x, -1, axis=-1), np.roll(y, -1, axis=-1)
    cross = x * y1 - x1 * y
    area = cross.sum(-1) / 2
    cx = ((x + x1) * cross).sum(-1) / (6 * area)
    cy = ((y + y1) * cross).sum(-1) / (6 * area)
    return np.stack([cx, cy], axis=-1), np.abs(area)
