"""Surfaces of the scene: fitted to sparse points, modelled from marked corners, or imported.

Three sources, all in the workspace's world frame (metres, ground z = 0, +z up):

* sparse SfM points of textured surfaces: the ground plane by RANSAC plane segmentation (Open3D),
  then every cluster of points standing on it as a box resting on the ground, fitted to the
  points' distance from the box surface (robust least squares);
* corners marked in two or more registered shots (a marks file, docs/reconstruction.md), for what
  feature matching cannot see: mirrors and transparent sheets. Like Façade (Debevec 1996), a
  box's parameters (centre, rotation, edge lengths) are fitted to the marks' reprojection error;
  edge lengths that the marks cannot show (a sheet's thickness) are given in the file;
* a mesh from a scanner (PLY/OBJ).

A transparent surface (``ior`` set) must be closed: a marked sheet is a thin box, and an imported
open mesh with an ``ior`` is refused.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.calibration.camera import Camera
from reflab.calibration.rotations import nearest_rotation
from reflab.core.workspace import WorkspaceError, as_array, as_float, object_items, read_json
from reflab.reconstruction.scene import BRDF_PARAMS, Material, Mesh, Scene, Surface

#: Points within this distance of a box's side face count as that face's (metres).
SIDE_BAND = 0.004
#: How far (metres) a fitted footprint may reach beyond the box's outermost point on each axis.
REACH_MARGIN = 0.004
#: How far (metres) :func:`refine_box_edges` looks for a footprint edge in the shots, either way.
EDGE_SEARCH = 0.005
#: Boxes at least this tall have sides that carry points of their own (five bands: a tile's do not).
TALL = 5 * SIDE_BAND
#: Box corner labels in the order of :func:`box_mesh`'s vertices.
CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
#: Quads counter-clockwise seen from outside: -x, +x, -y, +y, -z, +z.
_QUADS = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]


@dataclass
class Modelled:
    """A surface made by this module: name, mesh, material fields and where it came from."""

    name: str
    mesh: Mesh
    brdf: str = "phong"
    ior: float | None = None
    textured: bool = True
    source: str = ""
    info: dict = field(default_factory=dict)


def box_mesh(center, R, size) -> Mesh:
    """A closed box (8 vertices, 12 outward triangles): corner k at ``center + R @ (CORNERS[k] * size / 2)``."""
    verts = (CORNERS * (0.5 * np.asarray(size, dtype=np.float64))) @ np.asarray(R).T + np.asarray(center)
    return Mesh(verts, [t for a, b, c, d in _QUADS for t in ((a, b, c), (a, c, d))])


def box_frame(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre (3,), rotation (3, 3) and edge lengths (3,) of a :func:`box_mesh` (its inverse)."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    axes = np.stack([v[4] - v[0], v[2] - v[0], v[1] - v[0]], axis=1)  # box_mesh's corner order
    size = np.linalg.norm(axes, axis=0)
    return v.mean(axis=0), axes / size, size


def quad_mesh(center, R, size) -> Mesh:
    """An open rectangle in the box frame's z = 0 plane (two-sided): corners ``center + R @ (±w/2, ±h/2, 0)``."""
    half = 0.5 * np.asarray(size, dtype=np.float64)[:2]
    local = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=np.float64) * np.r_[half, 0]
    return Mesh(local @ np.asarray(R).T + np.asarray(center), [[0, 1, 2], [0, 2, 3]])


def plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane of ``normal``, the first as close to world x as possible."""
    n = normal / np.linalg.norm(normal)
    e1 = np.array([1.0, 0, 0]) - n[0] * n
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.array([0, 1.0, 0]) - n[1] * n
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


# ---------------------------------------------------------------- fitted to sparse points
def fit_ground(points: np.ndarray, threshold: float = 0.002, up=(0.0, 0.0, 1.0), max_tilt_deg: float = 30.0):
    """The ground plane: the largest RANSAC plane whose normal is within ``max_tilt_deg`` of ``up``.

    Returns
    -------
    normal : (3,) ndarray
        Unit normal, on ``up``'s side.
    offset : float
        ``normal @ x + offset = 0`` on the plane.
    inliers : (N,) bool ndarray
    """
    from reflab.core.open3d_env import open3d
    o3d = open3d()

    points = np.asarray(points, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    remaining = np.arange(len(points))
    for _ in range(4):
        if len(remaining) < 50:
            break
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[remaining]))
        model, idx = cloud.segment_plane(distance_threshold=threshold, ransac_n=3, num_iterations=2000,
                                         probability=0.99999)
        n = np.asarray(model[:3], dtype=np.float64)
        if abs(n @ up) / np.linalg.norm(n) >= np.cos(np.radians(max_tilt_deg)):
            inl = remaining[np.asarray(idx)]
            # Least-squares refit on the inliers (RANSAC's plane passes through 3 noisy points).
            centre = points[inl].mean(axis=0)
            n = np.linalg.svd(points[inl] - centre)[2][-1]
            n = n if n @ up > 0 else -n
            d = -n @ centre
            inliers = np.abs(points @ n + d) < threshold
            return n, float(d), inliers
        remaining = np.delete(remaining, np.asarray(idx))
    raise WorkspaceError("sparse points", expected=f"a ground plane within {max_tilt_deg:g} deg of horizontal among "
                                                   "the sparse points (is the turntable's top textured?)",
                         got=f"{len(points)} points, no such plane")


def ground_mesh(points: np.ndarray, normal: np.ndarray, offset: float, margin: float = 0.0) -> Mesh:
    """A rectangle in the ground plane covering ``points`` (its inliers) plus ``margin``."""
    e1, e2 = plane_basis(normal)
    a, b = points @ e1, points @ e2
    lo, hi = np.array([a.min(), b.min()]) - margin, np.array([a.max(), b.max()]) + margin
    origin = -offset * normal
    corners = [origin + u * e1 + v * e2 for u, v in ((lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1]))]
    return Mesh(corners, [[0, 1, 2], [0, 2, 3]])


def view_ground_mesh(camera: Camera, margin: float = 0.05, far: float = 10.0) -> Mesh:
    """The world frame's ground plane z = 0 as a rectangle covering what ``camera`` sees of it, plus ``margin``.

    The image border's rays meet z = 0 where the view's footprint ends; rays that miss it (the
    horizon is in view) stop at ``far`` times the camera's height above the ground.
    """
    w, h = camera.width - 1.0, camera.height - 1.0
    s = np.linspace(0.0, 1.0, 17)
    border = np.concatenate([np.stack([s * w, 0 * s], 1), np.stack([s * w, 0 * s + h], 1),
                             np.stack([0 * s, s * h], 1), np.stack([0 * s + w, s * h], 1)])
    origin, d = camera.rays(border)
    height = origin[0, 2]
    if not height > 0:
        raise WorkspaceError("camera.json", expected="a camera above the ground plane z = 0", got=f"height {height:g} m")
    # Rays toward the ground stop there; the others (at or above the horizon) at `far` heights away.
    t = np.where(d[:, 2] < 0, height / np.maximum(-d[:, 2], 1e-12), np.inf)
    t = np.minimum(t, far * height)
    xy = origin[:, :2] + t[:, None] * d[:, :2]
    lo, hi = xy.min(axis=0) - margin, xy.max(axis=0) + margin
    return Mesh([[lo[0], lo[1], 0.0], [hi[0], lo[1], 0.0], [hi[0], hi[1], 0.0], [lo[0], hi[1], 0.0]], [[0, 1, 2], [0, 2, 3]])


def _box_sdf(local: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs(local) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def fit_resting_box(points: np.ndarray, normal: np.ndarray, offset: float,
                    ground: np.ndarray | None = None, outlier: float = 0.0025) -> tuple[Mesh, dict]:
    """A box standing on the ground plane, fitted to points on its visible faces.

    Footprint (centre, yaw, two edge lengths) and height minimise the robust (soft-L1, 0.5 mm)
    distance of the points from the box surface, started from the minimum-area rectangle of
    the top face's points seen from above; points farther than ``outlier`` from the first fit are
    dropped before the second. Points on a thin box's top face say little about its footprint,
    so ``ground`` points (seen on the ground, hence not under the box) push the footprint's
    edges out of them: each adds how deep inside the footprint it lies. A tall box's footprint
    is then refitted to its side faces' points where they carry some (:func:`_side_pose`), and
    each edge placed by its own side's points (:func:`_side_edges`).
    """
    import cv2
    from scipy.optimize import least_squares

    e1, e2 = plane_basis(normal)
    uvh = np.stack([points @ e1, points @ e2, points @ normal + offset], axis=1)
    top = float(np.percentile(uvh[:, 2], 98))
    # Start from the top face's points: mismatches at the occluding side edges lie below it.
    on_top = np.abs(uvh[:, 2] - np.median(uvh[uvh[:, 2] > top - outlier, 2])) < outlier
    (cu, cv), (w, l), ang = cv2.minAreaRect(uvh[on_top if on_top.sum() >= 5 else slice(None), :2].astype(np.float32))
    if ground is None:
        ground = np.zeros((0, 3))
    g2 = np.stack([ground @ e1, ground @ e2], axis=1)
    near = np.linalg.norm(g2 - [cu, cv], axis=1) < 0.5 * np.hypot(w, l) + 0.02
    g2 = g2[near]
    x0 = np.array([cu, cv, np.radians(ang), max(w, 1e-3), max(l, 1e-3), max(top, 1e-3)])

    def residual(x):
        c, s = np.cos(x[2]), np.sin(x[2])
        d = uvh[:, :2] - x[:2]
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], uvh[:, 2] - x[5] / 2], axis=1)
        half = np.abs(np.array([x[3], x[4], x[5]])) / 2
        dg = g2 - x[:2]
        gl = np.stack([c * dg[:, 0] + s * dg[:, 1], -s * dg[:, 0] + c * dg[:, 1]], axis=1)
        inside = np.maximum(-_box_sdf(np.c_[gl, np.zeros(len(gl))], np.r_[half[:2], 1.0]), 0.0)
        # Nothing else holds a footprint that only top-face points see (a still ground has no
        # points): it could grow freely (a 120 mm tile came out 296 mm wide in one run of two).
        reach = np.r_[local[:, :2].max(axis=0), -local[:, :2].min(axis=0)]  # each edge's outermost point
        beyond = np.maximum(np.r_[half[:2], half[:2]] - reach - REACH_MARGIN, 0.0)
        return np.concatenate([_box_sdf(local, half), 10.0 * inside, 10.0 * beyond])

    scale = np.r_[0.01, 0.01, 0.1, 0.01, 0.01, 0.01]
    sol = least_squares(residual, x0, loss="soft_l1", f_scale=5e-4, x_scale=scale)
    # Points far from the first box are mismatches (e.g. at occluding edges): drop them and refit.
    keep = np.abs(residual(sol.x)[: len(uvh)]) < outlier
    if keep.sum() >= 0.5 * len(uvh) and not keep.all():
        uvh = uvh[keep]
        sol = least_squares(residual, sol.x, loss="soft_l1", f_scale=5e-4, x_scale=scale)
    if abs(sol.x[5]) < TALL:
        sol.x = _low_box_yaw(uvh, sol.x, residual, scale, outlier)
    x, by_sides = _side_pose(uvh, sol.x)
    cu, cv, yaw, w, l, h = _side_edges(uvh, x, toward_top=not by_sides)
    w, l, h = abs(w), abs(l), abs(h)
    c, s = np.cos(yaw), np.sin(yaw)
    ax, ay = c * e1 + s * e2, -s * e1 + c * e2
    R = np.stack([ax, ay, normal], axis=1)
    center = cu * e1 + cv * e2 + (h / 2 - offset) * normal
    res = residual(sol.x)[: len(uvh)]
    return box_mesh(center, R, [w, l, h]), {"points": int(len(uvh)), "outliers": int(len(points) - len(uvh)),
                                             "size_m": [float(w), float(l), float(h)],
                                             "rms_mm": float(1e3 * np.sqrt(np.mean(res**2)))}


def _low_box_yaw(uvh: np.ndarray, x: np.ndarray, residual, scale: np.ndarray, outlier: float,
                 trim: int = 3, span_deg: float = 10.0, step_deg: float = 0.05) -> np.ndarray:
    """A low box's footprint at the yaw of the smallest rectangle around its top face's points.

    A box lower than :data:`TALL` (a tile) shows points on its top face only. Inside the
    footprint they lie on the top plane wherever the footprint's edges are, so the distance
    fit is flat in the yaw except for the few points just outside, which it turns toward while
    its edges grow (the simulated lab's tile, true yaw 20 degrees: 18.5 and 19.3 in two runs, a
    corner 3.6 mm off). What the top face's points do say is their outline: the yaw is the one
    (within ``span_deg`` of the fit's, in ``step_deg`` steps) whose rectangle, each edge at the
    ``trim``-th outermost point so that a stray match or two beyond an edge does not turn it, is
    smallest; it is held while the centre, edges and height are refitted.
    """
    from scipy.optimize import least_squares

    on_top = np.abs(uvh[:, 2] - abs(x[5])) < outlier
    if on_top.sum() < 4 * trim + 4:
        return x
    xy = uvh[on_top, :2] - uvh[on_top, :2].mean(axis=0)
    yaws = x[2] + np.radians(np.arange(-span_deg, span_deg + step_deg / 2, step_deg))
    c, s = np.cos(yaws)[:, None], np.sin(yaws)[:, None]
    u, v = c * xy[:, 0] + s * xy[:, 1], -s * xy[:, 0] + c * xy[:, 1]  # (yaws, points)
    k = trim - 1
    su, sv = np.sort(u, axis=1), np.sort(v, axis=1)
    area = (su[:, -1 - k] - su[:, k]) * (sv[:, -1 - k] - sv[:, k])
    yaw = float(yaws[int(np.argmin(area))])
    free = [0, 1, 3, 4, 5]
    fixed = lambda p: residual(np.insert(p, 2, yaw))  # noqa: E731
    sol = least_squares(fixed, x[free], loss="soft_l1", f_scale=5e-4, x_scale=scale[free])
    return np.insert(sol.x, 2, yaw)


def _side_pose(uvh: np.ndarray, x: np.ndarray, band: float = SIDE_BAND,
               min_points: int = 4) -> tuple[np.ndarray, bool]:
    """Footprint centre, yaw and size refitted to the side faces' points, when two adjacent sides carry some.

    The top face's points say nothing about the yaw unless near its edges, where they thin
    out, and the ground points that push the footprint out include some on the sides' feet:
    both bias the yaw (2 degrees on the simulated lab's 100 mm box). Points half-way up the
    sides lie on the footprint's outline; with ``min_points`` of them on each of two adjacent
    sides they fix it, while the top face's points only have to stay inside. Sides lower than
    :data:`TALL` (a tile) are left to the first fit: their few points there are mostly
    mismatches along the top face's edges.
    """
    from scipy.optimize import least_squares

    height = abs(x[5])
    if height < TALL:
        return x, False
    mid = (uvh[:, 2] > 0.15 * height) & (uvh[:, 2] < 0.85 * height)
    top = np.abs(uvh[:, 2] - height) < band

    def local(p, sel):
        c, s = np.cos(p[2]), np.sin(p[2])
        d = uvh[sel, :2] - p[:2]
        return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)

    loc, half = np.abs(local(x, mid)), np.abs(x[3:5]) / 2
    on = (np.abs(loc - half) < band) & (loc[:, ::-1] < half[::-1] - band)  # on a face, away from its corners
    if min(on[:, 0].sum(), on[:, 1].sum()) < min_points:
        return x, False

    def residual(p):
        half = np.abs(p[3:5]) / 2
        q = np.abs(local(p, mid)) - half
        outside = np.linalg.norm(np.maximum(np.abs(local(p, top)) - half, 0.0), axis=1)
        return np.concatenate([np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0), outside])

    sol = least_squares(residual, x[:5], loss="soft_l1", f_scale=5e-4, x_scale=np.r_[0.01, 0.01, 0.1, 0.01, 0.01])
    return np.r_[sol.x, x[5]], True


def _side_edges(uvh: np.ndarray, x: np.ndarray, band: float = SIDE_BAND, min_points: int = 6,
                toward_top: bool = True) -> np.ndarray:
    """Each footprint edge placed by the points of its own side face, else between two biased bounds.

    The least-squares footprint rests on indirect evidence where a side carries few points:
    ground points near the base (some of them on the box's foot) push an edge outward, while the
    top face's points thin out within a few pixels of its edges (features straddling an occluding
    edge do not match), so their reach falls short of it. A side face seen with ``min_points``
    points or more (within ``band`` of it, away from its top, bottom and vertical edges) places
    its edge as their median; otherwise, unless the side faces already placed the footprint
    (``toward_top`` False, :func:`_side_pose`), an edge that the fit put beyond the top face's
    reach (its third outermost point) moves halfway back toward it.
    """
    cu, cv, yaw, w, l, h = x
    c, s = np.cos(yaw), np.sin(yaw)
    d = uvh[:, :2] - [cu, cv]
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
    height = abs(h)
    middle = (uvh[:, 2] > 0.15 * height) & (uvh[:, 2] < 0.85 * height)
    top = np.abs(uvh[:, 2] - height) < band
    half = np.abs([w, l]) / 2
    edges = np.stack([-half, half])  # (sign, axis): edge coordinates in the box frame
    for a in (0, 1):
        b = 1 - a
        across = np.abs(local[:, b]) < half[b] - band
        for k, sign in enumerate((-1.0, 1.0)):
            on = middle & across & (np.abs(sign * local[:, a] - half[a]) < band)
            if on.sum() >= min_points:
                edges[k, a] = np.median(local[on, a])
            elif toward_top and (top & across).sum() >= 3:
                reach = np.sort(sign * local[top & across, a])[-3]
                edges[k, a] = sign * min(half[a], 0.5 * (half[a] + reach))
    mid = edges.mean(axis=0)
    size = edges[1] - edges[0]
    return np.array([cu + c * mid[0] - s * mid[1], cv + s * mid[0] + c * mid[1], yaw, size[0], size[1], h])


def fit_scene_points(points: np.ndarray, *, camera: Camera | None = None, ground_threshold: float = 0.002,
                     min_height: float = 0.003, cluster_eps: float = 0.012, min_points: int = 30,
                     adopt: float = 0.004, min_ground: int = 100) -> list[Modelled]:
    """The ground plane and the boxes standing on it, from sparse points in the world frame.

    Registration puts the ground at z = 0 of the world frame. A ground that turned with the
    objects carries sparse points and is fitted to them (RANSAC). A ground that stayed still
    (the turntable's top masked out with the table, as in the simulated lab's own sweep) carries
    fewer than ``min_ground`` points within ``ground_threshold`` of z = 0: given the ``camera``,
    it is then the plane z = 0 spanning the input view (:func:`view_ground_mesh`).
    """
    from reflab.core.open3d_env import open3d
    o3d = open3d()

    points = np.asarray(points, dtype=np.float64)
    on_frame_ground = np.abs(points[:, 2]) < ground_threshold
    if camera is not None and on_frame_ground.sum() < min_ground:
        n, d, inliers = np.array([0.0, 0.0, 1.0]), 0.0, on_frame_ground
        out = [Modelled("ground", view_ground_mesh(camera), "phong", None, True,
                        "plane z = 0 of the world frame over the input view (the ground did not turn: "
                        f"{int(inliers.sum())} sparse points on it)", {"points": int(inliers.sum())})]
    else:
        n, d, inliers = fit_ground(points, ground_threshold)
        out = [Modelled("ground", ground_mesh(points[inliers], n, d), "phong", None, True, "ground plane (RANSAC)",
                        {"points": int(inliers.sum()), "normal": n.tolist(), "offset_m": d,
                         "rms_mm": float(1e3 * np.sqrt(np.mean((points[inliers] @ n + d) ** 2)))})]
    above = points[(points @ n + d) > min_height]
    if len(above) >= min_points:
        labels = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(above)).cluster_dbscan(
            eps=cluster_eps, min_points=8))
        ids, counts = np.unique(labels[labels >= 0], return_counts=True)
        for k in ids[np.argsort(-counts)]:
            cluster = above[labels == k]
            if len(cluster) < min_points:
                continue
            mesh, info = fit_resting_box(cluster, n, d, points[inliers])
            # DBSCAN leaves a tall box's sparsely seen side faces as noise: take back those near it.
            near = (labels < 0) & (distance_to_mesh(mesh, above) < adopt)
            if near.any() and info["size_m"][2] >= TALL:
                mesh, info = fit_resting_box(np.concatenate([cluster, above[near]]), n, d, points[inliers])
                info["adopted"] = int(near.sum())
            out.append(Modelled(f"box{len(out) - 1}", mesh, "phong", None, True, "box on the ground (fitted)", info))
    return out


# ---------------------------------------------------------------- modelled from marks
@dataclass
class Views:
    """Registered shots: name -> world-to-camera pose, with the shared intrinsics."""

    camera: Camera
    poses: dict  # name -> (R, t)

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        return self.camera.undistort(np.asarray(uv, dtype=np.float64).reshape(-1, 2))

    def project(self, name: str, X: np.ndarray) -> np.ndarray:
        import cv2

        R, t = self.poses[name]
        uv, _ = cv2.projectPoints(np.asarray(X, dtype=np.float64).reshape(-1, 1, 3), cv2.Rodrigues(R)[0], t,
                                  self.camera.K, self.camera.dist)
        return uv.reshape(-1, 2)


def edge_gradients(images: dict) -> dict:
    """Per shot name, the grey image's derivatives along u and v ((H, W) float32 each), for :func:`refine_box_edges`."""
    import cv2

    out = {}
    for name, img in images.items():
        g = np.asarray(img, dtype=np.float32)
        g = g.mean(axis=2) if g.ndim == 3 else g
        out[name] = (cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8, cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8)
    return out


def refine_box_edges(mesh: Mesh, views: Views, gradients: dict, search: float = EDGE_SEARCH, step: float = 1e-4,
                     samples: int = 41, min_contrast: float = 3.0, check=None) -> tuple[Mesh, list]:
    """A box resting on the ground with each footprint edge moved to where the shots show its top edge.

    Sparse points stop short of a box's edges (features straddling an occluding edge do not
    match), so a footprint fitted to them is 1-3 mm short there (the lab's tile: 119.2 x 116.8
    mm for 120 x 120). The top edge of each side face is where the box's top meets its side or
    what lies behind it: an intensity step in every registered shot, wherever the box turned.
    Each of the four top edges is moved along its outward normal, within ``search`` metres in
    ``step`` steps, to where the image derivative across its projection, averaged over
    ``samples`` points of its middle 80 % (a straight step along the whole edge, not texture),
    summed over the shots, is largest; an edge whose best score is under ``min_contrast`` times
    the scores' median, or at the end of the range, stays. Returns the mesh and the four shifts
    (metres, outward positive; None where kept) in the order -x, +x, -y, +y of the box's frame.
    ``check`` (e.g. a task's), when given, is called before each edge.
    """
    from scipy.ndimage import map_coordinates

    centre, R, size = box_frame(mesh)
    deltas = np.arange(-search, search + step / 2, step)
    lo, hi = -size[:2] / 2, size[:2] / 2
    shifts = []
    for a in (0, 1):
        for sign in (-1.0, 1.0):
            n = sign * R[:, a]
            along = np.linspace(-0.4, 0.4, samples)[:, None] * size[1 - a] * R[:, 1 - a]
            P = centre + sign * size[a] / 2 * R[:, a] + size[2] / 2 * R[:, 2] + along
            if check is not None:
                check()
            score = np.zeros(len(deltas))
            for name, (gu, gv) in gradients.items():
                if name not in views.poses:
                    continue
                h, w = gu.shape
                uv = views.project(name, (P[None] + deltas[:, None, None] * n).reshape(-1, 3)).reshape(len(deltas), samples, 2)
                normal = views.project(name, P + 1e-3 * n) - uv[len(deltas) // 2]
                normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
                inside = (uv[..., 0] > 1) & (uv[..., 0] < w - 2) & (uv[..., 1] > 1) & (uv[..., 1] < h - 2)
                if not np.all(inside.mean(axis=1) >= 0.8):
                    continue
                du = map_coordinates(gu, [uv[..., 1].ravel(), uv[..., 0].ravel()], order=1, mode="nearest")
                dv = map_coordinates(gv, [uv[..., 1].ravel(), uv[..., 0].ravel()], order=1, mode="nearest")
                across = (du.reshape(uv.shape[:2]) * normal[:, 0] + dv.reshape(uv.shape[:2]) * normal[:, 1]) * inside
                score += np.abs(across.sum(axis=1) / np.maximum(inside.sum(axis=1), 1))
            k = int(np.argmax(score))
            if score[k] <= min_contrast * max(float(np.median(score)), 1e-12) or k in (0, len(deltas) - 1):
                shifts.append(None)
                continue
            shifts.append(float(deltas[k]))
            if sign < 0:
                lo[a] -= deltas[k]
            else:
                hi[a] += deltas[k]
    mid = (lo + hi) / 2
    return box_mesh(centre + R[:, :2] @ mid, R, [hi[0] - lo[0], hi[1] - lo[1], size[2]]), shifts


#: How far (metres) :func:`refine_marked_face` looks for a marked face's edge in the shots, each way.
MARKED_SEARCH = 0.003


def refine_marked_face(mesh: Mesh, views: Views, gradients: dict, face_axis: int, face_sign: float,
                       search: float = MARKED_SEARCH, step: float = 1e-4, samples: int = 41,
                       min_contrast: float = 1.5, ground: float = 0.003, check=None) -> tuple[Mesh, dict]:
    """A box from marked corners with its marked face's plane (and extent) moved to where the shots show its edges.

    A corner marked with 1 px noise puts a mirror's plane 0.2 degrees off (the lab's, 480x360), and a
    mirror doubles an angle error in what it shows. The face's edges, though, are steps in every shot
    that sees the face: where the frame ends against what lies behind or beside it. Its own texture
    is no help (a mirror shows reflections, which move from shot to shot and average out), and an
    edge standing on the ground (within ``ground`` metres of z = 0) is left out: there a mirror's
    reflection of the ground continues the ground. Each other edge of the face, as a straight line
    over its middle 80 % (``samples`` points), is moved in steps of ``step`` within ``search``
    metres along the face's normal and, independently, outward in the face's plane, to where the
    image derivative across its projection, summed over the shots that see the face's front, is
    largest (:func:`refine_box_edges`' score); an edge whose best score is under ``min_contrast``
    times the median, or at the end of either range, keeps the marks'. The face's plane is then
    the one through the found edges (offset, tilt and yaw from three edges; with fewer, the rest
    stay as marked) and each found edge's outward shift moves that edge in the plane; the box's
    thickness (``face_axis``, from the marks file) is kept. Returns the mesh and, per edge
    (name -> [normal, outward] shift in metres, or None where kept), what was found.
    """
    import itertools

    from scipy.ndimage import map_coordinates

    centre, R, size = box_frame(mesh)
    n = face_sign * R[:, face_axis]
    inplane = [a for a in range(3) if a != face_axis]
    face_centre = centre + face_sign * size[face_axis] / 2 * R[:, face_axis]
    deltas = np.arange(-search, search + step / 2, step)
    nd = len(deltas)
    # Shots that see the face's front (the camera on its outward side).
    shots = []
    for name in gradients:
        if name in views.poses:
            Rc, t = views.poses[name]
            if (-Rc.T @ t - face_centre) @ n > 0:
                shots.append(name)
    found, rows, rhs = {}, [], []
    lo, hi = -size[inplane] / 2, size[inplane] / 2
    for i, a in enumerate(inplane):
        b = inplane[1 - i]
        for sign in (-1.0, 1.0):
            label = f"{'-' if sign < 0 else '+'}{'xyz'[a]}"
            out = sign * R[:, a]
            along = np.linspace(-0.4, 0.4, samples)[:, None] * size[b] * R[:, b]
            P = face_centre + sign * size[a] / 2 * R[:, a] + along
            ends = face_centre + sign * size[a] / 2 * R[:, a] + np.array([[-0.5], [0.5]]) * size[b] * R[:, b]
            if np.all(np.abs(ends[:, 2]) < ground):
                found[label] = None  # on the ground: not a safe edge
                continue
            if check is not None:
                check()
            grid = deltas[:, None, None] * n + deltas[None, :, None] * out  # (normal, outward, 3)
            score = np.zeros((nd, nd))
            for name, Q in itertools.product(shots, (P, P - size[face_axis] * n)):  # the edge and its twin behind
                X = (Q[None, None] + grid[:, :, None]).reshape(-1, 3)
                gu, gv = gradients[name]
                h, w = gu.shape
                uv = views.project(name, X).reshape(nd, nd, samples, 2)
                e = views.project(name, np.stack([Q[0], Q[-1]]))
                d = e[1] - e[0]
                normal = np.array([-d[1], d[0]]) / max(np.linalg.norm(d), 1e-12)
                inside = (uv[..., 0] > 1) & (uv[..., 0] < w - 2) & (uv[..., 1] > 1) & (uv[..., 1] < h - 2)
                if not np.all(inside.mean(axis=2) >= 0.8):
                    continue
                coords = [uv[..., 1].ravel(), uv[..., 0].ravel()]
                du = map_coordinates(gu, coords, order=1, mode="nearest").reshape(inside.shape)
                dv = map_coordinates(gv, coords, order=1, mode="nearest").reshape(inside.shape)
                across = (du * normal[0] + dv * normal[1]) * inside
                score += np.abs(across.sum(axis=2) / np.maximum(inside.sum(axis=2), 1))
            k, j = np.unravel_index(int(np.argmax(score)), score.shape)
            if (score[k, j] <= min_contrast * max(float(np.median(score)), 1e-12) or k in (0, nd - 1)
                    or j in (0, nd - 1)):
                found[label] = None
                continue
            found[label] = [float(deltas[k]), float(deltas[j])]
            # The face's normal shift at the edge's middle, in the face's in-plane coordinates.
            rows.append([1.0, sign * size[a] / 2 if i == 0 else 0.0, sign * size[a] / 2 if i == 1 else 0.0])
            rhs.append(deltas[k])
            if sign < 0:
                lo[i] -= deltas[j]
            else:
                hi[i] += deltas[j]
    # Normal shift s(p) = c0 + c1 p0 + c2 p1 over the face: least squares, minimum norm where the
    # found edges leave it open (those components stay as marked).
    coef = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0] if rows else np.zeros(3)
    corners = []
    for p0 in (lo[0], hi[0]):
        for p1 in (lo[1], hi[1]):
            s = coef[0] + coef[1] * p0 + coef[2] * p1
            corners.append(face_centre + p0 * R[:, inplane[0]] + p1 * R[:, inplane[1]] + s * n)
    c = np.array(corners)  # (lo,lo), (lo,hi), (hi,lo), (hi,hi)
    ax0 = (c[2] + c[3] - c[0] - c[1]) / 2
    ax1 = (c[1] + c[3] - c[0] - c[2]) / 2
    cols = np.zeros((3, 3))
    cols[:, inplane[0]], cols[:, inplane[1]] = ax0, ax1
    cols[:, face_axis] = np.cross(cols[:, (face_axis + 1) % 3], cols[:, (face_axis + 2) % 3])
    cols[:, face_axis] *= np.sign(cols[:, face_axis] @ R[:, face_axis])
    R2 = nearest_rotation(cols / np.linalg.norm(cols, axis=0))
    new_size = size.copy()
    new_size[inplane] = [np.linalg.norm(ax0), np.linalg.norm(ax1)]
    new_centre = c.mean(axis=0) - face_sign * size[face_axis] / 2 * R2[:, face_axis]
    return box_mesh(new_centre, R2, new_size), found


def load_marks(path, obj: dict | None = None) -> list[dict]:
    """Read and validate a marks file (docs/reconstruction.md), or ``obj`` read from it; image names are checked later."""
    path = Path(path)
    obj = read_json(path) if obj is None else obj
    out = []
    for where, item in object_items(obj.get("surfaces"), path, "surfaces", "marked surfaces"):
        name = item.get("name")
        if not isinstance(name, str) or not name:
            raise WorkspaceError(path, f"{where}.name", "a non-empty string", got=name)
        shape = item.get("shape", "box")
        if shape not in ("box", "plane"):
            raise WorkspaceError(path, f"{where}.shape", "'box' or 'plane'", got=shape)
        brdf = item.get("brdf", "phong")
        if brdf not in BRDF_PARAMS:
            raise WorkspaceError(path, f"{where}.brdf", f"one of {sorted(BRDF_PARAMS)}", got=brdf)
        ior = item.get("ior")
        if ior is not None:
            ior = as_float(ior, path, f"{where}.ior", positive=True)
            if ior < 1:
                raise WorkspaceError(path, f"{where}.ior", "null (opaque) or a refraction index >= 1", got=ior)
            if shape == "plane":
                raise WorkspaceError(path, f"{where}.shape", "'box' for a transparent surface (a sheet is a thin box "
                                                             "and must be closed)", got=shape)
        dims = 3 if shape == "box" else 2
        size = item.get("size", [None] * dims)
        if not isinstance(size, list) or len(size) != dims:
            raise WorkspaceError(path, f"{where}.size", f"a list of {dims} edge lengths or nulls", got=size)
        size = [None if s is None else as_float(s, path, f"{where}.size[{k}]", positive=True) for k, s in enumerate(size)]
        corners = item.get("corners")
        if not isinstance(corners, list) or not corners:
            raise WorkspaceError(path, f"{where}.corners", "a non-empty list of marked corners", got=corners)
        parsed = []
        for j, c in enumerate(corners):
            cw = f"{where}.corners[{j}]"
            if not isinstance(c, dict):
                raise WorkspaceError(path, cw, "an object with 'corner' and 'marks'", got=c)
            label = as_array(c.get("corner"), (dims,), path, f"{cw}.corner")
            if not np.all(np.abs(label) == 1):
                raise WorkspaceError(path, f"{cw}.corner", f"{dims} values of -1 or +1", got=c.get("corner"))
            marks = c.get("marks")
            if not isinstance(marks, dict) or len(marks) < 2:
                raise WorkspaceError(path, f"{cw}.marks", "marks in at least two images ({image: [u, v]})",
                                     got=f"{0 if not isinstance(marks, dict) else len(marks)} image(s)")
            uv = {str(k): as_array(v, (2,), path, f"{cw}.marks[{k!r}]") for k, v in marks.items()}
            parsed.append((np.r_[label, [0.0] * (3 - dims)], uv))
        out.append({"name": name, "shape": shape, "brdf": brdf, "ior": ior, "size": size + [None] * (3 - dims),
                    "textured": bool(item.get("textured", ior is None)), "corners": parsed, "where": where,
                    "path": path})
    return out


def _triangulate_corner(views: Views, marks: dict) -> np.ndarray:
    from reflab.reconstruction.registration import triangulate

    names = list(marks)
    R = np.stack([views.poses[n][0] for n in names])
    t = np.stack([views.poses[n][1] for n in names])
    xy = np.stack([views.undistort(marks[n])[0] for n in names])[:, None]
    X, _ = triangulate(R, t, xy, np.ones((len(names), 1), bool))
    return X[0]


def box_from_marks(spec: dict, views: Views) -> Modelled:
    """A box (or an open rectangle) fitted to its corners marked in registered shots.

    Initial box: the corners are triangulated, then an affine map from corner labels to points
    gives centre, axes and edge lengths. Final box: centre, rotation and the free edge lengths
    minimise the marks' reprojection error (Façade's objective).
    """
    import cv2
    from scipy.optimize import least_squares

    path, where = spec["path"], spec["where"]
    for j, (_, marks) in enumerate(spec["corners"]):
        missing = [n for n in marks if n not in views.poses]
        if missing:
            raise WorkspaceError(path, f"{where}.corners[{j}].marks",
                                 f"images among the registered shots ({', '.join(sorted(views.poses)[:3])}, ...)",
                                 got=missing[0])
    labels = np.array([c for c, _ in spec["corners"]])
    P = np.array([_triangulate_corner(views, m) for _, m in spec["corners"]])
    dims = 3 if spec["shape"] == "box" else 2
    varying = [a for a in range(dims) if np.ptp(labels[:, a]) > 0]
    given = np.array([np.nan if s is None else s for s in spec["size"]], dtype=np.float64)
    for a in range(dims):
        if a not in varying and not np.isfinite(given[a]):
            raise WorkspaceError(path, f"{where}.size[{a}]", f"this edge length: the marked corners all lie on one "
                                                            f"face along axis {a}", got=None)
    if len(varying) < 2 or len(P) < len(varying) + 1:
        raise WorkspaceError(path, f"{where}.corners", "at least 3 marked corners spanning two axes of the box",
                             got=f"{len(P)} corners")
    # Affine fit P = c + M @ labels over the varying axes.
    A = np.concatenate([np.ones((len(P), 1)), labels[:, varying]], axis=1)
    sol, *_ = np.linalg.lstsq(A, P, rcond=None)
    cols = np.zeros((3, 3))
    for k, a in enumerate(varying):
        cols[:, a] = sol[1 + k]
    if len(varying) == 2:
        a = ({0, 1, 2} - set(varying)).pop()
        cols[:, a] = np.cross(cols[:, (a + 1) % 3], cols[:, (a + 2) % 3])
    R0 = nearest_rotation(cols / np.maximum(np.linalg.norm(cols, axis=0), 1e-12))
    half0 = np.where(np.isfinite(given), given / 2, np.linalg.norm(cols, axis=0))
    if dims == 2:
        half0[2] = 0.0
    centre0 = sol[0] - sum(labels[0, a] * half0[a] * R0[:, a] for a in range(3) if a not in varying)
    free = [a for a in range(dims) if not np.isfinite(given[a])]

    obs = [(k, n, uv) for k, (_, marks) in enumerate(spec["corners"]) for n, uv in marks.items()]

    def unpack(x):
        half = half0.copy()
        half[free] = np.abs(x[6:])
        return x[:3], cv2.Rodrigues(x[3:6])[0], half

    def residual(x):
        c, R, half = unpack(x)
        X = c + (labels * half) @ R.T
        return np.concatenate([views.project(n, X[k])[0] - uv for k, n, uv in obs])

    x0 = np.concatenate([centre0, cv2.Rodrigues(R0)[0].ravel(), half0[free]])
    fit = least_squares(residual, x0, x_scale=np.r_[[0.01] * 3, [0.1] * 3, [0.01] * len(free)])
    c, R, half = unpack(fit.x)
    rms = float(np.sqrt(np.mean(fit.fun**2)))
    mesh = box_mesh(c, R, 2 * half) if dims == 3 else quad_mesh(c, R, 2 * half)
    info = {"corners": int(len(P)), "marks": len(obs), "reprojection_px": rms, "size_m": (2 * half[:dims]).tolist()}
    face = None
    if dims == 3 and len(varying) == 2:  # the corners of one face: refine_marked_face can move it
        a = ({0, 1, 2} - set(varying)).pop()
        info["face"] = [a, float(labels[0, a])]
        face = (a, float(labels[0, a]))
    info["pose_sigma"] = marked_pose_sigma(fit, unpack, face if face is not None else (2, 0.0), len(free))
    return Modelled(spec["name"], mesh, spec["brdf"], spec["ior"], spec["textured"], "marked corners", info)


#: One-sigma floor of a marked corner's reprojection error (px): marks are clicked to about a pixel's
#: tenth at best, and the shots' registration adds its own (sfm.json's ``reprojection_px``).
MARK_FLOOR_PX = 0.3


def marked_pose_sigma(fit, unpack, face: tuple[int, float], n_free_sizes: int) -> dict:
    """The marked face's plane pose σ (scene.json's ``pose_sigma``, docs/formats.md) from the marks' fit.

    The fitted centre, rotation and sizes have covariance ``s² (JᵀJ)⁻¹`` (``J`` the marks'
    reprojection Jacobian at the optimum, ``s`` their residual RMS over the degrees of freedom,
    at least :data:`MARK_FLOOR_PX`): the marks' pixel error carried through the registered cameras
    to the corners in space. It is mapped to the face's tilt about its two in-plane axes and its
    offset along its normal at its centre, numerically (the plane's three degrees of freedom).
    """
    x = np.asarray(fit.x, dtype=np.float64)
    J = np.asarray(fit.jac, dtype=np.float64)
    dof = max(J.shape[0] - J.shape[1], 1)
    s2 = max(float(np.sum(fit.fun ** 2)) / dof, MARK_FLOOR_PX ** 2)
    cov = s2 * np.linalg.pinv(J.T @ J)
    a, sign = face
    inplane = [k for k in range(3) if k != a]

    def frame(v):
        c, R, half = unpack(v)
        return c + sign * half[a] * R[:, a], R

    centre, R0 = frame(x)
    n0 = R0[:, a]

    def plane(v):  # tilt about each in-plane axis, offset along the normal at the face's centre
        f, R = frame(v)
        dn = R[:, a] - n0
        return np.array([dn @ np.cross(R0[:, inplane[0]], n0), dn @ np.cross(R0[:, inplane[1]], n0), (f - centre) @ n0,
                         (f - centre) @ R0[:, inplane[0]], (f - centre) @ R0[:, inplane[1]]])

    G = np.zeros((5, len(x)))
    for k in range(len(x)):
        h = 1e-6 if k >= 3 else 1e-7
        e = np.zeros(len(x))
        e[k] = h
        G[:, k] = (plane(x + e) - plane(x - e)) / (2 * h)
    sd = np.sqrt(np.maximum(np.diag(G @ cov @ G.T), 0.0))
    return {"centre": centre.tolist(), "normal": n0.tolist(), "axes": [R0[:, k].tolist() for k in inplane],
            "tilt_rad": [float(sd[0]), float(sd[1])], "offset_m": float(sd[2]), "shift_m": [float(sd[3]), float(sd[4])],
            "from": f"marked corners ({np.sqrt(s2):.2f} px per mark)"}


#: One-sigma error of an edge :func:`refine_marked_face` found (m): the demo's mirror (480x360, about
#: 1 mm per pixel there) had its edges 0.15-0.3 mm from the truth, three search steps.
EDGE_SIGMA = 3e-4


def refined_pose_sigma(mesh: Mesh, face_axis: int, face_sign: float, found: dict, marked: dict,
                       edge: float = EDGE_SIGMA) -> dict:
    """The pose σ of a face :func:`refine_marked_face` moved to its edges in the shots.

    Each found edge fixes the face's normal shift at its middle to ``edge`` (one-sigma); with three
    or more edges spanning the plane, the offset and both tilts have the least-squares covariance
    ``edge² (RᵀR)⁻¹`` of the edges' rows, and an in-plane axis whose two edges were found the shift
    σ edge/√2. With fewer edges, ``marked`` (the marks' own, :func:`marked_pose_sigma`) is kept.
    """
    centre, R, size = box_frame(mesh)
    inplane = [a for a in range(3) if a != face_axis]
    rows = []
    for label, shift in found.items():
        if shift is None:
            continue
        sign, a = (-1.0 if label[0] == "-" else 1.0), "xyz".index(label[1])
        i = inplane.index(a)
        rows.append([1.0, sign * size[a] / 2 if i == 0 else 0.0, sign * size[a] / 2 if i == 1 else 0.0])
    rows = np.array(rows)
    if len(rows) < 3 or np.linalg.matrix_rank(rows) < 3:
        return marked
    sd = edge * np.sqrt(np.diag(np.linalg.inv(rows.T @ rows)))  # offset, slope along inplane[0], along inplane[1]
    n = face_sign * R[:, face_axis]
    out = {"centre": (centre + face_sign * size[face_axis] / 2 * R[:, face_axis]).tolist(), "normal": n.tolist(),
           "axes": [R[:, a].tolist() for a in inplane],
           # a slope along one in-plane axis is a tilt about the other
           "tilt_rad": [float(sd[2]), float(sd[1])], "offset_m": float(sd[0]),
           "from": f"{len(rows)} edges in the shots ({1e3 * edge:.1f} mm each)"}
    if marked.get("shift_m") is not None:  # an axis whose two edges were found: their mean, else the marks'
        both = [all(found.get(f"{sg}{'xyz'[a]}") is not None for sg in "-+") for a in inplane]
        out["shift_m"] = [edge / np.sqrt(2.0) if b else float(m) for b, m in zip(both, marked["shift_m"])]
    return out


# ---------------------------------------------------------------- imported
def import_mesh(name: str, path, ior: float | None = None, brdf: str = "phong") -> Modelled:
    """A scanner's mesh (PLY/OBJ, metres, world frame); refused when transparent but not closed."""
    mesh = Mesh.load(path)
    if ior is not None and not mesh.is_closed():
        raise WorkspaceError(path, expected=f"a closed mesh, because surface '{name}' is transparent (ior {ior}): "
                                            "every edge shared by exactly two triangles", got="an open mesh")
    return Modelled(name, mesh, brdf, ior, True, f"imported from {Path(path).name}")


# ---------------------------------------------------------------- output
def write_scene(root, modelled: list[Modelled], existing: Scene | None = None) -> Scene:
    """Write ``meshes/<name>.ply`` and scene.json: existing surfaces kept, same names replaced."""
    from reflab.core.workspace import Workspace

    ws = Workspace(root)
    root = ws.root
    surfaces = list(existing.surfaces) if existing is not None else []
    for m in modelled:
        if m.ior is not None and not m.mesh.is_closed():
            raise WorkspaceError(ws.mesh(m.name), expected=f"a closed mesh for transparent surface '{m.name}'",
                                 got="an open mesh")
        material = Material.from_json({"brdf": m.brdf, "ior": m.ior}, ws.scene, m.name)
        extra = {"source": m.source}
        if m.info and "pose_sigma" in m.info:  # the pose's one-sigma (inverse/fit/geometry_sigma.py)
            extra["pose_sigma"] = m.info["pose_sigma"]
        s = Surface(m.name, ws.mesh(m.name).relative_to(root).as_posix(), material, m.textured, m.mesh, extra)
        names = [x.name for x in surfaces]
        if m.name in names:
            surfaces[names.index(m.name)] = s
        else:
            surfaces.append(s)
    scene = Scene(surfaces, root)
    for s in surfaces:
        if s.mesh is not None:
            s.mesh.save(root / s.mesh_path)
    scene.save(ws.scene, write_meshes=False)
    return scene


# ---------------------------------------------------------------- measuring


def distance_to_mesh(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """Unsigned distance (N,) of points to a mesh's surface (Open3D ray-casting scene)."""
    from reflab.core.open3d_env import open3d
    o3d = open3d()

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy().astype(np.float64)
