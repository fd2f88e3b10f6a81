"""Pixel-intensity computation trees (docs/method.md §1, docs/architecture.md): built once by ray casting.

:func:`build_trees` casts one primary ray per pixel centre and follows ideal mirror reflections
and Snell refractions up to ``depth`` internal nodes per path, level by level, with Open3D's
``RaycastingScene`` (Embree, float32). Each node stores what the renderer needs to evaluate the
pixel's radiance for any photometric parameters without casting a ray again: the point, shading
normal, view and light directions, squared light distances, light visibility, the product of
the known Fresnel factors and the sequence of ideal interactions (its *path*).

Robustness against float32 ray casting: hit points are recomputed in float64 on the hit
triangle's plane, and every secondary or shadow ray starts a scene-scaled ``eps`` off the
surface, on the side it leaves to.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.core.workspace import WorkspaceError, atomic_write
from reflab.inverse.forward.optics import fresnel, normalize, reflect, refract

#: Kinds of ideal interaction in a path.
REFLECTION, TRANSMISSION = 0, 1

_ARRAYS = ("pixel", "surface", "point", "normal", "view", "level", "fresnel", "path",
           "light_dir", "light_dist2", "visible", "parent", "triangle", "barycentric")


@dataclass
class Trees:
    """The flat node table of every pixel's tree (fields as in docs/architecture.md).

    Besides the documented fields: ``parent`` (N,) int64, index of the parent node (−1 for
    primary hits); ``triangle`` (N,) int64, index of the hit triangle in its surface's mesh;
    ``barycentric`` (N, 2) f64, Open3D's (u, v) in it (point = (1−u−v) v0 + u v1 + v v2);
    ``key``, a fingerprint of the inputs (see :func:`trees_key`) for caching.
    """

    width: int
    height: int
    depth: int
    pixel: np.ndarray
    surface: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    view: np.ndarray
    level: np.ndarray
    fresnel: np.ndarray
    path: np.ndarray
    paths: list[tuple[tuple[int, int], ...]]
    light_dir: np.ndarray
    light_dist2: np.ndarray
    visible: np.ndarray
    parent: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    stats: dict = field(default_factory=dict)
    key: str = ""

    def __len__(self) -> int:
        return len(self.pixel)

    @property
    def n_lights(self) -> int:
        return self.light_dist2.shape[1]

    def of_pixels(self, pixels) -> "Trees":
        """The trees of the pixels where ``pixels`` (H*W,) bool is True: their nodes alone, every
        pixel index and the image size unchanged (``parent`` renumbered)."""
        keep = np.asarray(pixels, dtype=bool).reshape(-1)[np.asarray(self.pixel, dtype=np.int64)]
        renumber = np.cumsum(keep) - 1
        parent = np.asarray(self.parent, dtype=np.int64)[keep]
        arrays = {name: np.asarray(getattr(self, name))[keep] for name in _ARRAYS if name != "parent"}
        arrays["parent"] = np.where(parent >= 0, renumber[np.maximum(parent, 0)], -1)
        key = hashlib.sha1(self.key.encode() + np.packbits(np.asarray(pixels, dtype=bool)).tobytes()).hexdigest()
        return Trees(self.width, self.height, self.depth, paths=self.paths, stats=dict(self.stats), key=key, **arrays)

    def save(self, path) -> Path:
        """Write the trees to an ``.npz`` file, atomically."""
        flat = [item for p in self.paths for item in p]
        arrays = {name: getattr(self, name) for name in _ARRAYS}
        arrays.update(
            shape=np.array([self.width, self.height, self.depth]),
            paths_len=np.array([len(p) for p in self.paths], dtype=np.int64),
            paths_flat=np.array(flat, dtype=np.int64).reshape(-1, 2),
            stats=np.array(json.dumps(self.stats)),
            key=np.array(self.key),
        )
        with atomic_write(path, "wb") as f:
            np.savez(f, **arrays)
        return Path(path)

    @classmethod
    def load(cls, path) -> "Trees":
        """Read trees written by :meth:`save`; a missing or malformed file raises WorkspaceError."""
        path = Path(path)
        if not path.exists():
            raise WorkspaceError(path, expected="a trees file written by Trees.save", got="missing")
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise WorkspaceError(path, expected=f"an .npz trees file ({exc})") from None
        for name in (*_ARRAYS, "shape", "paths_len", "paths_flat", "stats", "key"):
            if name not in data:
                raise WorkspaceError(path, name, "this array", got="missing")
        ends = np.cumsum(data["paths_len"])
        flat = [tuple(int(x) for x in row) for row in data["paths_flat"]]
        paths = [tuple(flat[e - n:e]) for n, e in zip(data["paths_len"], ends)]
        width, height, depth = (int(x) for x in data["shape"])
        arrays = {name: data[name] for name in _ARRAYS}
        trees = cls(width, height, depth, paths=paths, stats=json.loads(str(data["stats"])),
                    key=str(data["key"]), **arrays)
        n = len(trees)
        if any(len(a) != n for a in arrays.values()) or (n and trees.path.max() >= len(paths)):
            raise WorkspaceError(path, expected="arrays of one length and path indices within 'paths'")
        return trees


#: Bumped whenever :func:`build_trees` changes what it stores, so older cache files are not reused.
TREES_VERSION = 1
#: Cached trees files kept per workspace (novel views and relightings add their own); oldest go first.
CACHE_KEEP = 4


def derived(trees, name: str, key: tuple, compute):
    """A value derived from ``trees`` alone, computed once per ``name`` while ``key`` holds.

    A fit asks for the same derived values many times (the nodes grouped by surface, each
    surface's per-(node, light) geometry, the nodes whose texture no direct view pins): they are
    kept on the trees object itself, so they live and die with it. ``key`` names what the value
    depends on: arrays by identity (a field replaced by another array computes anew), the rest by
    equality.
    """
    memo = trees.__dict__.setdefault("_derived", {})
    hit = memo.get(name)
    if hit is not None and len(hit[0]) == len(key) and all(
            (a is b) if isinstance(b, np.ndarray) else (a == b) for a, b in zip(hit[0], key)):
        return hit[1]
    value = compute()
    memo[name] = (key, value)
    return value


def trees_key(scene, camera, lights, depth: int, prune_tol: float) -> str:
    """SHA-1 of everything the trees depend on: camera, light positions, meshes, iors, r/t zeros."""
    h = hashlib.sha1()
    h.update(f"trees v{TREES_VERSION}".encode())
    for a in (camera.K, camera.dist, camera.R, camera.t, lights.positions):
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    h.update(repr((camera.width, camera.height, int(depth), float(prune_tol))).encode())
    for s in scene.surfaces:
        m = s.mesh
        h.update(np.ascontiguousarray(m.vertices).tobytes() + np.ascontiguousarray(m.triangles).tobytes())
        if m.normals is not None:
            h.update(np.ascontiguousarray(m.normals).tobytes())
        h.update(repr((s.material.ior, _given_zero(s.material, "r"), _given_zero(s.material, "t"))).encode())
    return h.hexdigest()


#: Cache files being written by a background thread (:func:`trees_for_workspace` with
#: ``background``): path → thread. Read again only after :func:`wait_for_saves`.
_SAVING: dict = {}
_SAVING_LOCK = threading.Lock()


def wait_for_saves(path=None) -> None:
    """Return once the background cache writes (of ``path`` alone, if given) have ended."""
    with _SAVING_LOCK:
        threads = [t for p, t in _SAVING.items() if path is None or p == Path(path)]
    for t in threads:
        t.join()


def _save_in_background(trees: Trees, path: Path, log) -> None:
    """Write the cache file on a thread (most of it file I/O and fsync, off the GIL): the fit
    goes on meanwhile (640x480: 0.2–0.35 s of wall, 80 MB). The log line comes when it is written."""
    def run():
        try:
            trees.save(path)
        except OSError as exc:
            if log is not None:
                log(f"trees: built in {trees.stats['build_s']:.2f} s ({len(trees)} nodes), not cached ({exc.strerror})")
            return
        finally:
            with _SAVING_LOCK:
                _SAVING.pop(path, None)
        _prune_cache(path.parent, keep=CACHE_KEEP)
        if log is not None:
            log(f"trees: built in {trees.stats['build_s']:.2f} s ({len(trees)} nodes), cached as {path.name}")

    thread = threading.Thread(target=run, name=f"save {path.name}")
    with _SAVING_LOCK:
        _SAVING[path] = thread
    thread.start()


def trees_for_workspace(workspace, scene, camera, lights, depth: int = 3, *, prune_tol: float = 1e-4,
                        log=None, task=None, background: bool = False) -> Trees:
    """The trees of a workspace's scene, from its cache when nothing they depend on has changed.

    The cache file (``Workspace.trees_cache(key)``, ``cache/trees-<key>.npz``) is named by
    :func:`trees_key`, a hash of the camera, the light positions, every mesh's vertices,
    triangles and normals, the iors, which r / t scene.json gives as 0, ``depth`` and
    ``prune_tol``: any change to one of them names another file, so a stale file is never read.
    A cache file that cannot be read (truncated, older format) is rebuilt and replaced. At most
    :data:`CACHE_KEEP` files are kept (a novel view or a relighting adds one), the least recently
    used deleted first.

    Parameters
    ----------
    workspace : path-like or reflab.core.workspace.Workspace
    scene, camera, lights, depth, prune_tol
        As for :func:`build_trees`.
    log : callable, optional
        Called with one line: ``"trees: reused cache <file> (N nodes, X s)"`` or
        ``"trees: built in X s (N nodes), cached as <file>"``.
    task : reflab.core.task.Task, optional
        Checked between levels of a build (pause, cancel); a cancelled build writes nothing.
    background : bool
        Write a built cache file on a thread and return at once (its log line comes when it is
        written); :func:`wait_for_saves` waits for it. A caller that returns to its own caller
        waits first (:func:`reflab.inverse.fit.workspace_fit.fit_workspace`).

    Returns
    -------
    Trees
        ``stats["cache"]`` is ``"reused"`` or ``"built"``, ``stats["load_s"]`` the seconds to read
        a reused file.
    """
    from reflab.core.workspace import Workspace

    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    key = trees_key(scene, camera, lights, depth, prune_tol)
    path = ws.trees_cache(key)
    wait_for_saves(path)  # a file still being written is read once whole
    if path.exists():
        t0 = time.perf_counter()
        try:
            trees = Trees.load(path)
        except WorkspaceError:
            trees = None
        if trees is not None and trees.key == key and (trees.width, trees.height) == (camera.width, camera.height):
            trees.stats["cache"] = "reused"
            with contextlib.suppress(OSError):  # least recently used goes first (a read-only workspace: no matter)
                os.utime(path)
            trees.stats["load_s"] = time.perf_counter() - t0
            if log is not None:
                log(f"trees: reused cache {path.name} ({len(trees)} nodes, {trees.stats['load_s']:.2f} s)")
            return trees
    trees = build_trees(scene, camera, lights, depth, prune_tol=prune_tol, task=task)
    trees.stats["cache"] = "built"
    if background:
        _save_in_background(trees, path, log)
        return trees
    try:
        trees.save(path)
    except OSError as exc:  # a read-only workspace still renders (reflab render -o elsewhere)
        if log is not None:
            log(f"trees: built in {trees.stats['build_s']:.2f} s ({len(trees)} nodes), not cached ({exc.strerror})")
        return trees
    _prune_cache(path.parent, keep=CACHE_KEEP)
    if log is not None:
        log(f"trees: built in {trees.stats['build_s']:.2f} s ({len(trees)} nodes), cached as {path.name}")
    return trees


def _prune_cache(folder: Path, keep: int) -> None:
    """Delete all but the ``keep`` most recently written or reused trees files in ``folder``."""
    files = sorted(folder.glob("trees-*.npz"), key=lambda f: f.stat().st_mtime, reverse=True)
    for old in files[keep:]:
        old.unlink(missing_ok=True)


def _given_zero(material, name: str) -> bool:
    """True where the user stated the attenuation ``name`` to be exactly 0 (not a default)."""
    return name not in material.defaulted and bool(np.all(np.asarray(material[name]) == 0))


class _Caster:
    """The scene in an Open3D RaycastingScene plus the float64 mesh data to refine its hits."""

    def __init__(self, scene):
        from reflab.core.open3d_env import open3d
        o3d = open3d()

        self.o3d = o3d
        self.rc = o3d.t.geometry.RaycastingScene()
        n = len(scene.surfaces)
        self.gid_to_surface = {}
        verts, tris, vnormals, offsets = [], [], [], [0]
        self.has_vnormals = np.zeros(n, dtype=bool)
        for i, s in enumerate(scene.surfaces):
            m = s.mesh
            if m is None or len(m.triangles) == 0:
                raise ValueError(f"surface {s.name!r} has no loaded mesh with triangles")
            if not np.all(np.isfinite(m.vertices)):
                raise ValueError(f"surface {s.name!r}: mesh vertices are not all finite")
            gid = self.rc.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)),
                                        o3d.core.Tensor(m.triangles.astype(np.uint32)))
            self.gid_to_surface[gid] = i
            base = sum(len(v) for v in verts)
            verts.append(m.vertices)
            tris.append(m.triangles + base)
            offsets.append(offsets[-1] + len(m.triangles))
            self.has_vnormals[i] = m.normals is not None and len(m.normals) == len(m.vertices)
            vnormals.append(m.normals if self.has_vnormals[i] else np.zeros_like(m.vertices))
        self.vertices = np.concatenate(verts)
        self.triangles = np.concatenate(tris)
        self.vnormals = np.concatenate(vnormals)
        self.tri_offset = np.array(offsets[:-1], dtype=np.int64)
        v = self.vertices[self.triangles]
        self.face_normals = normalize(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]))
        lut = np.full(max(self.gid_to_surface) + 1, -1, dtype=np.int64)
        for gid, i in self.gid_to_surface.items():
            lut[gid] = i
        self.lut = lut

    def cast(self, origin: np.ndarray, direction: np.ndarray, offset: np.ndarray | None = None, eps: float = 0.0):
        """First hits of unit rays: (hit mask, surface, global triangle, barycentric, float64 point).

        ``offset`` (M, 3) moves the origins handed to Embree only (off the surface they leave);
        hit points are intersected in float64 from the true ``origin``, so the offset leaves
        no trace in them.
        """
        rays = np.empty((len(origin), 6), dtype=np.float32)  # filled in place: no float64 (M, 6) copy
        if offset is None:
            rays[:, :3] = origin
        else:
            np.add(origin, offset, out=rays[:, :3], casting="same_kind")
        rays[:, 3:] = direction
        ans = self.rc.cast_rays(self.o3d.core.Tensor(rays))
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        hit = gid != self.rc.INVALID_ID
        gid = np.where(hit, gid, 0)
        surface = self.lut[np.minimum(gid, len(self.lut) - 1)]
        tri = self.tri_offset[surface] + ans["primitive_ids"].numpy().astype(np.int64) * hit
        uv = ans["primitive_uvs"].numpy().astype(np.float64)
        t32 = np.where(hit, ans["t_hit"].numpy().astype(np.float64), 0.0)
        # float64 distance to the hit triangle's plane; keep Embree's where the ray grazes it.
        ng = self.face_normals[tri]
        den = np.einsum("ij,ij->i", direction, ng)
        num = np.einsum("ij,ij->i", self.vertices[self.triangles[tri, 0]] - origin, ng)
        steep = hit & (np.abs(den) > 1e-6)
        t64 = np.divide(num, den, out=t32.copy(), where=steep)
        slack = 1e-4 * (1.0 + np.abs(t32)) + np.divide(2.0 * eps, np.abs(den), out=np.zeros_like(den), where=steep)
        good = steep & np.isfinite(t64) & (np.abs(t64 - t32) <= slack)
        t = np.where(good, t64, t32)
        point = origin + t[:, None] * direction
        return hit, surface, tri, uv, point

    def lit(self, origin: np.ndarray, cand: np.ndarray, lights: np.ndarray) -> np.ndarray:
        """(M, K) bool: whether the segment from each ``origin`` (M, 3) to each light (K, 3) hits
        no surface, tested where ``cand`` (M, K) only (False elsewhere). The rays are filled one
        light at a time (float32, the direction rounded from the float64 difference): no (M·K, 3)
        gathers of origins and light positions."""
        vis = np.zeros(cand.shape, dtype=bool)
        sel = [np.flatnonzero(cand[:, k]) for k in range(cand.shape[1])]
        rays = np.empty((sum(len(i) for i in sel), 6), dtype=np.float32)
        start = 0
        for k, i in enumerate(sel):
            o = origin[i]
            rays[start:start + len(i), :3] = o
            np.subtract(lights[k], o, out=rays[start:start + len(i), 3:], casting="same_kind")
            start += len(i)
        if len(rays) == 0:
            return vis
        occ = self.rc.test_occlusions(self.o3d.core.Tensor(rays), tnear=0.0, tfar=1.0).numpy()
        start = 0
        for k, i in enumerate(sel):
            vis[i, k] = occ[start:start + len(i)] == 0
            start += len(i)
        return vis

    def shading_normal(self, tri, uv, surface):
        """Interpolated vertex normals where the mesh has them, else the geometric normal."""
        n = self.face_normals[tri].copy()
        smooth = self.has_vnormals[surface]
        if np.any(smooth):
            t, w = tri[smooth], uv[smooth]
            vn = self.vnormals[self.triangles[t]]
            interp = (1 - w[:, :1] - w[:, 1:]) * vn[:, 0] + w[:, :1] * vn[:, 1] + w[:, 1:] * vn[:, 2]
            interp = normalize(interp)
            # keep the winding's side; a degenerate interpolation falls back to the face normal
            interp *= np.sign(np.einsum("ij,ij->i", interp, n) + 1e-300)[:, None]
            n[smooth] = np.where((np.linalg.norm(interp, axis=1) > 0.5)[:, None], interp, n[smooth])
        return n


def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)


def build_trees(scene, camera, lights, depth: int = 3, *, prune_tol: float = 1e-4, task=None,
                rows: tuple[int, int] | None = None, pixels=None) -> Trees:
    """Cast the pixel-intensity trees of ``scene`` seen by ``camera`` under point ``lights``.

    Parameters
    ----------
    scene : reflab.reconstruction.scene.Scene
        Surfaces with loaded meshes; only geometry, ``ior`` and r/t given as exactly 0 are used.
    camera : reflab.calibration.camera.Camera
    lights : reflab.calibration.lights.Lights
    depth : int
        Maximum number of internal nodes on a path (1 = direct lighting only).
    prune_tol : float
        A branch whose largest possible weight (product of Fresnel factors, r and t being <= 1)
        is below this is not followed.
    task : reflab.core.task.Task, optional
        Told after each level (``step``: pause, cancel).
    rows : (int, int), optional
        Image rows ``[r0, r1)`` only (a tile of a large photograph): the trees are those rows'
        own, as a ``width`` x ``r1 - r0`` image whose pixel ``(v - r0) * width + u`` is the
        photograph's ``v * width + u``; each node is the same as in the whole photograph's trees.
    pixels : (N,) int array_like, optional
        Only these pixels (indices in the image, or in the tile of ``rows``): their trees as the
        whole image's, the other pixels left without any (the pose sensitivities of
        :mod:`reflab.inverse.fit.geometry_sigma`, which need a surface's pixels only).

    Returns
    -------
    Trees
    """
    if int(depth) < 1:
        raise ValueError(f"depth must be >= 1, got {depth!r}")
    if not prune_tol >= 0:
        raise ValueError(f"prune_tol must be >= 0, got {prune_tol!r}")
    depth = int(depth)
    start = time.perf_counter()
    caster = _Caster(scene)
    mats = [s.material for s in scene.surfaces]
    transparent = np.array([m.transparent for m in mats])
    ior = np.array([m.ior if m.transparent else 1.0 for m in mats], dtype=np.float64)
    follow_r = np.array([not _given_zero(m, "r") for m in mats])
    follow_t = transparent & np.array([not _given_zero(m, "t") for m in mats])

    light_pos = lights.positions
    n_lights = len(light_pos)
    # Secondary and shadow rays start on the geometry, so its size sets float32's rounding there
    # (~6e-8 relative); eps sits far above it and far below any feature a scene models.
    scale = float(np.max(np.ptp(caster.vertices, axis=0))) + float(np.max(np.abs(caster.vertices)))
    eps = 1e-5 * scale

    stats = {
        "rays": {"primary": 0, "shadow": 0, "reflection": 0, "refraction": 0},
        "nodes_per_level": [],
        "pruned": {"r_zero": 0, "t_zero": 0, "weight": 0, "depth": 0},
        "total_internal_reflections": 0,
        "escaped": 0,
        "lights_too_close": 0,
        "eps": eps,
    }
    paths: list[tuple] = [()]
    path_id = {(): 0}

    r0, r1 = (0, camera.height) if rows is None else (int(rows[0]), int(rows[1]))
    if not 0 <= r0 < r1 <= camera.height:
        raise ValueError(f"rows must lie within [0, {camera.height}] with r0 < r1, got {rows!r}")
    if pixels is not None:  # only these pixels' rays (pixel_rays' per pixel)
        ray_pixel = np.unique(np.asarray(pixels, dtype=np.int64))
        v, u = np.divmod(ray_pixel, camera.width)
        origin, direction = camera.rays(np.stack([u, v + r0], axis=1).astype(np.float64))
    elif rows is None:
        origin, direction = camera.pixel_rays()
    else:  # the same rays as pixel_rays' rows r0..r1-1
        origin, direction = camera.pixel_rays(rows=(r0, r1))
    offset = None
    if pixels is None:
        ray_pixel = np.arange(len(origin), dtype=np.int64)
    n_pix = len(origin)
    ray_path = np.zeros(n_pix, dtype=np.int64)
    ray_fresnel = np.ones(n_pix)
    ray_parent = np.full(n_pix, -1, dtype=np.int64)
    stats["rays"]["primary"] = n_pix
    levels = []
    n_before = 0

    for level in range(1, depth + 1):
        if task is not None:
            task.step(level - 1, depth, f"trees: level {level} of {depth}")
        if len(origin) == 0:
            break
        hit, surf, tri, uv, point = caster.cast(origin, direction, offset, eps)
        if level > 1:
            stats["escaped"] += int(np.count_nonzero(~hit))
        d = direction[hit]
        surf, tri, uv, point = surf[hit], tri[hit], uv[hit], point[hit]
        node = dict(pixel=ray_pixel[hit], path=ray_path[hit], fresnel=ray_fresnel[hit],
                    parent=ray_parent[hit], surface=surf, point=point, triangle=tri - caster.tri_offset[surf],
                    barycentric=uv, level=np.full(len(d), level, dtype=np.int8), view=-d)
        m = len(d)
        stats["nodes_per_level"].append(m)

        # Orient normals toward the incoming ray (the viewer's side); the winding gives "outside".
        ng = caster.face_normals[tri]
        cos_g = _dot(d, ng)
        entering = cos_g < 0
        side = np.where(entering, 1.0, -1.0)[:, None]
        ngf = ng * side
        ns = caster.shading_normal(tri, uv, surf) * side
        ns = np.where((_dot(ns, -d) > 0)[:, None], ns, ngf)
        node["normal"] = ns

        # Direct lighting: light on the viewer's side of the shading normal and segment unoccluded.
        to_light = light_pos[None] - point[:, None]
        dist2 = np.sum(to_light**2, axis=2)
        # normalize()'s floats from the squares just summed (np.linalg.norm sums the same squares)
        norm = np.sqrt(dist2)[:, :, None]
        ldir = np.divide(to_light, norm, out=np.zeros_like(to_light), where=norm > 0)
        del to_light, norm
        close = dist2 <= eps**2
        stats["lights_too_close"] += int(np.count_nonzero(close))
        cand = (_dot(ldir, ns[:, None]) > 0) & ~close
        stats["rays"]["shadow"] += int(np.count_nonzero(cand))
        vis = caster.lit(point + eps * ngf, cand, light_pos)
        node.update(light_dir=ldir, light_dist2=np.maximum(dist2, eps**2), visible=vis)
        levels.append(node)

        # Ideal branches.
        s_t = transparent[surf]
        want_r, want_t = follow_r[surf], follow_t[surf]
        stats["pruned"]["r_zero"] += int(np.count_nonzero(~want_r))
        stats["pruned"]["t_zero"] += int(np.count_nonzero(s_t & ~want_t))
        if level == depth:
            stats["pruned"]["depth"] += int(np.count_nonzero(want_r) + np.count_nonzero(want_t))
            break
        # Fresnel, reflection and refraction of the nodes that branch only (most nodes are a
        # matte ground's, with neither branch): each node's values are the same floats either way.
        tr = np.flatnonzero(s_t)
        F = np.ones(m)
        F[tr] = fresnel(_dot(-d[tr], ns[tr]), np.where(entering[tr], 1.0, ior[surf[tr]]),
                        np.where(entering[tr], ior[surf[tr]], 1.0))
        w_r = node["fresnel"] * F
        w_t = node["fresnel"] * (1.0 - F)
        ir = np.flatnonzero(want_r)
        refl = reflect(d[ir], ns[ir])
        bad = _dot(refl, ngf[ir]) <= 0  # a shading normal must not send the ray into its own surface
        refl[bad] = reflect(d[ir][bad], ngf[ir][bad])
        it = np.flatnonzero(want_t)
        d_t, ngf_t = d[it], ngf[it]
        eta = np.where(entering[it], 1.0, ior[surf[it]]) / np.where(entering[it], ior[surf[it]], 1.0)
        trans, tir = refract(d_t, ns[it], eta)
        bad = ~tir & (_dot(trans, ngf_t) >= 0)
        if np.any(bad):
            trans[bad], tir_bad = refract(d_t[bad], ngf_t[bad], eta[bad])
            tir[bad] |= tir_bad
        stats["total_internal_reflections"] += int(np.count_nonzero(tir))
        take_r = w_r[ir] >= prune_tol
        take_t = ~tir & (w_t[it] >= prune_tol)
        stats["pruned"]["weight"] += int(np.count_nonzero(~take_r) + np.count_nonzero(~tir & ~take_t))
        stats["rays"]["reflection"] += int(np.count_nonzero(take_r))
        stats["rays"]["refraction"] += int(np.count_nonzero(take_t))

        refl, trans = refl[take_r], trans[take_t]
        ir, it = ir[take_r], it[take_t]
        idx = np.concatenate([ir, it])
        kind = np.concatenate([np.full(len(ir), REFLECTION), np.full(len(it), TRANSMISSION)])
        origin = point[idx]
        offset = eps * np.concatenate([ngf[ir], -ngf[it]])
        direction = np.concatenate([refl, trans])
        ray_fresnel = np.concatenate([w_r[ir], w_t[it]])
        ray_pixel = node["pixel"][idx]
        ray_parent = n_before + idx
        ray_path = _child_paths(node["path"][idx], surf[idx], kind, paths, path_id)
        n_before += m

    # nothing in view gives an empty, well-formed table
    nodes = {k: np.concatenate([lv[k] for lv in levels]) for k in _ARRAYS} if levels else _empty_nodes(n_lights)
    stats["build_s"] = time.perf_counter() - start
    key = trees_key(scene, camera, lights, depth, prune_tol)
    if rows is not None:
        stats["rows"] = [r0, r1]
        key = hashlib.sha1(f"{key} rows {r0} {r1}".encode()).hexdigest()
    return Trees(
        camera.width, r1 - r0, depth,
        pixel=nodes["pixel"].astype(np.int64), surface=nodes["surface"].astype(np.int32),
        point=nodes["point"], normal=nodes["normal"], view=nodes["view"],
        level=nodes["level"].astype(np.int8), fresnel=nodes["fresnel"],
        path=nodes["path"].astype(np.int32), paths=paths, light_dir=nodes["light_dir"],
        light_dist2=nodes["light_dist2"], visible=nodes["visible"], parent=nodes["parent"].astype(np.int64),
        triangle=nodes["triangle"].astype(np.int64), barycentric=nodes["barycentric"],
        stats=stats, key=key,
    )


class _Pixels:
    """A camera through some of its pixels only: :func:`build_trees` casts their rays as a one-row image."""

    def __init__(self, camera, pixels):
        self.camera, self.pixels = camera, np.asarray(pixels, dtype=np.int64)
        self.width, self.height = len(self.pixels), 1
        # trees_key reads these
        self.K, self.dist, self.R, self.t = camera.K, camera.dist, camera.R, camera.t

    def pixel_rays(self):
        v, u = np.divmod(self.pixels, int(self.camera.width))
        return self.camera.rays(np.stack([u, v], axis=1).astype(np.float64))


def trees_of_pixels(scene, camera, lights, pixels, depth: int = 3, task=None):
    """The trees of ``camera``'s flat pixel indices ``pixels`` alone, each through its own centre;
    the trees' image is the camera's (``width``, ``height``), pixel indices the camera's."""
    pixels = np.unique(np.asarray(pixels, dtype=np.int64))
    trees = build_trees(scene, _Pixels(camera, pixels), lights, depth=depth, task=task)
    trees.stats["cache"] = "built"  # never cached: the pixels read change with the fit
    trees.pixel = pixels[np.asarray(trees.pixel, dtype=np.int64)]
    trees.width, trees.height = int(camera.width), int(camera.height)
    return trees


def seen_first(trees, npix: int | None = None) -> np.ndarray:
    """(H·W,) int64: the surface each pixel's tree sees first, its level-1 node's (−1: none);
    ``npix`` pixels where given, else the trees' ``width`` × ``height``."""
    out = np.full(int(trees.width) * int(trees.height) if npix is None else int(npix), -1, dtype=np.int64)
    top = np.asarray(trees.level) == 1
    out[np.asarray(trees.pixel)[top]] = np.asarray(trees.surface)[top]
    return out


def first_surfaces(scene, camera) -> np.ndarray:
    """(H·W,) int64: the surface each of ``camera``'s pixels sees first (−1: none), the level-1
    nodes' of :func:`build_trees` without the rest of its work (no shadow rays, no deeper levels)."""
    caster = _Caster(scene)
    origin, direction = camera.pixel_rays()
    hit, surface, *_ = caster.cast(origin, direction)
    return np.where(hit, surface, -1).astype(np.int64)


def tile_rows(height: int, width: int, tile_pixels: int) -> list[tuple[int, int]]:
    """Row ranges ``[r0, r1)`` of at most ``tile_pixels`` pixels each (one row at least): the tiles
    a large photograph's trees are built in (``build_trees(rows=)``)."""
    step = max(1, int(tile_pixels) // max(int(width), 1))
    return [(r, min(r + step, int(height))) for r in range(0, int(height), step)]


class TileTask:
    """The task one tile's :func:`build_trees` sees: its levels report as a fraction of tile
    ``done`` of ``total``, under ``label``; pause and cancel are the stage's task's."""

    def __init__(self, task, done: int, total: int, label: str):
        self.task, self.done, self.total, self.label = task, done, total, label

    def check(self) -> None:
        self.task.check()

    def step(self, done: float, total: float, message: str = "") -> None:
        self.task.step(self.done + (done / total if total else 0.0), self.total, f"{self.label}: {message}")


def _child_paths(parent_path, surface, kind, paths, path_id) -> np.ndarray:
    """Path index of each child ray: its parent's path extended by (surface, kind)."""
    if len(parent_path) == 0:
        return np.zeros(0, dtype=np.int64)
    n_surf = int(surface.max()) + 1
    key = (parent_path * n_surf + surface) * 2 + kind
    uniq, inverse = np.unique(key, return_inverse=True)
    ids = np.empty(len(uniq), dtype=np.int64)
    for j, k in enumerate(uniq):  # one iteration per distinct path, not per ray
        p, rest = divmod(int(k), 2 * n_surf)
        new = paths[p] + ((rest // 2, rest % 2),)
        if new not in path_id:
            path_id[new] = len(paths)
            paths.append(new)
        ids[j] = path_id[new]
    return ids[inverse]


def _empty_nodes(n_lights: int) -> dict:
    z3 = np.zeros((0, 3))
    return dict(pixel=np.zeros(0, np.int64), surface=np.zeros(0, np.int32), point=z3, normal=z3, view=z3,
                level=np.zeros(0, np.int8), fresnel=np.zeros(0), path=np.zeros(0, np.int32),
                light_dir=np.zeros((0, n_lights, 3)), light_dist2=np.zeros((0, n_lights)),
                visible=np.zeros((0, n_lights), bool), parent=np.zeros(0, np.int64),
                triangle=np.zeros(0, np.int64), barycentric=np.zeros((0, 2)))
