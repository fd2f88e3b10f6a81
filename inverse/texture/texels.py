"""Texel parameterization of each surface: where a surface point's diffuse albedo is stored.

Every textured surface gets a 2D texel grid (an *atlas*). A point on the surface maps to
continuous texel coordinates ``(col, row)`` (texel centres at integers) through the triangle it
lies on: each triangle corner carries texel coordinates (``tri_uv``), the point's barycentric
coordinates interpolate them, and the albedo at the point is the bilinear blend of the four
surrounding texels (docs/method.md §4; the dissertation's novel views use bilinear texture too).

Two kinds of map:

- ``planar``: the mesh is a few planes (a ground plane, a tile, the six faces of a box). Each
  plane becomes one rectangular *chart* with an orthonormal in-plane frame chosen as the
  minimum-area bounding rectangle, so a box face is a texel-aligned rectangle. Texel
  ``(col, row)`` of a chart has its centre at
  ``origin + ((col - offset[0]) * axis_u + (row - offset[1]) * axis_v) * texel_size``.
- ``uvatlas``: a general mesh, parameterized by Open3D's UV atlas (Zhou et al. 2004).

Charts are packed on shelves with a gutter of :data:`PAD` texels, so that the bilinear
footprint of a point on a chart's edge never reaches another chart.

The texel size comes from the input image's pixel footprint on the surface (measured between
neighbouring pixels' tree nodes, :func:`pixel_footprint`), times a configurable scale.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from reflab.core.workspace import WorkspaceError

#: Gutter around each chart, in texels (≥ 1 keeps bilinear footprints inside their chart).
PAD = 2
#: A mesh with more coplanar groups than this is parameterized by the UV atlas.
MAX_PLANAR_CHARTS = 64
#: Upper bound on the texels of one surface; a finer request is coarsened to fit.
MAX_TEXELS = 8_000_000


@dataclass
class Chart:
    """One planar chart: a plane's frame and where its texels sit in the atlas."""

    origin: np.ndarray  # (3,) world point of texel (offset[0], offset[1])'s centre
    axis_u: np.ndarray  # (3,) unit, along texel columns
    axis_v: np.ndarray  # (3,) unit, along texel rows
    offset: np.ndarray  # (2,) atlas texel coordinates (col, row) of origin
    shape: tuple[int, int]  # (rows, cols) of the chart's block, gutter included

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.axis_u, self.axis_v)

    def to_json(self) -> dict:
        return {"origin": self.origin, "axis_u": self.axis_u, "axis_v": self.axis_v,
                "offset": self.offset, "shape": list(self.shape)}


@dataclass
class TexelMap:
    """The texel atlas of one surface.

    Attributes
    ----------
    surface : int
        Index into ``scene.surfaces``.
    name : str
        The surface's name.
    kind : {"planar", "uvatlas"}
    texel_size : float
        Texel edge in metres (for the UV atlas: the mean edge, the atlas stretches a little).
    width, height : int
        Atlas size in texels.
    tri_uv : (T, 3, 2) ndarray
        Texel coordinates (col, row) of each triangle corner, float64.
    charts : list of Chart
        Planar charts (empty for the UV atlas).
    """

    surface: int
    name: str
    kind: str
    texel_size: float
    width: int
    height: int
    tri_uv: np.ndarray
    charts: list[Chart] = field(default_factory=list)
    vertices: np.ndarray | None = None
    triangles: np.ndarray | None = None

    @property
    def n_texels(self) -> int:
        return self.width * self.height

    # ------------------------------------------------------------------ lookup
    def coords_at(self, triangle: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
        """Continuous atlas coordinates (N, 2) = (col, row) of points given by triangle and
        Open3D barycentric ``(u, v)`` (point = (1-u-v) v0 + u v1 + v v2), as the trees store them."""
        uv = np.asarray(barycentric, dtype=np.float64).reshape(-1, 2)
        t = self.tri_uv[np.asarray(triangle, np.int64)]
        u, v = uv[:, :1], uv[:, 1:]
        # Spelled out: einsum("nk,nkc->nc") took 4x longer (a 12 MP texture: 9 s of lookups).
        return (1.0 - u - v) * t[:, 0] + u * t[:, 1] + v * t[:, 2]

    def texel_coords(self, points: np.ndarray) -> np.ndarray:
        """Continuous atlas coordinates (N, 2) of arbitrary points (N, 3), via the nearest triangle."""
        tri, bary = locate(self.vertices, self.triangles, points)
        return self.coords_at(tri, bary[:, 1:])

    def bilinear(self, triangle: np.ndarray, barycentric: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinear texel indices and weights of points given as in :meth:`coords_at`.

        Returns
        -------
        index : (N, 4) int64
            Flat texel index ``row * width + col`` of the four texels around each point.
        weight : (N, 4) float64
            Bilinear weights, summing to 1 per point.
        """
        return bilinear_weights(self.coords_at(triangle, barycentric), self.width, self.height)

    def texel_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World position of every planar-chart texel centre: ``(flat_index (M,), points (M, 3))``."""
        idx, pts = [], []
        for c in self.charts:
            rows, cols = np.mgrid[0 : c.shape[0], 0 : c.shape[1]]
            col = cols.ravel() + int(c.offset[0]) - PAD
            row = rows.ravel() + int(c.offset[1]) - PAD
            du, dv = (col - c.offset[0]) * self.texel_size, (row - c.offset[1]) * self.texel_size
            idx.append(row * self.width + col)
            pts.append(c.origin + du[:, None] * c.axis_u + dv[:, None] * c.axis_v)
        if not idx:
            return np.zeros(0, np.int64), np.zeros((0, 3))
        return np.concatenate(idx).astype(np.int64), np.concatenate(pts)

    # ------------------------------------------------------------------ file format
    def to_json(self) -> dict:
        """The index entry (the UV atlas's per-corner coordinates go to a side file)."""
        return {"surface": self.name, "kind": self.kind, "texel_size": self.texel_size,
                "width": self.width, "height": self.height, "triangles": int(len(self.tri_uv)),
                "charts": [c.to_json() for c in self.charts]}

    @classmethod
    def from_json(cls, obj: dict, surface: int, mesh, path, where: str, tri_uv: np.ndarray | None = None) -> "TexelMap":
        """Rebuild a map from its index entry and the surface's mesh (``tri_uv`` for the UV atlas)."""
        try:
            kind, size = obj["kind"], float(obj["texel_size"])
            width, height, ntri = int(obj["width"]), int(obj["height"]), int(obj["triangles"])
            charts = [Chart(np.asarray(c["origin"], float), np.asarray(c["axis_u"], float),
                            np.asarray(c["axis_v"], float), np.asarray(c["offset"], float),
                            (int(c["shape"][0]), int(c["shape"][1]))) for c in obj.get("charts", [])]
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise WorkspaceError(path, where, "a texel map entry (kind, texel_size, width, height, triangles, charts)", got=str(exc)) from None
        if kind not in ("planar", "uvatlas") or not size > 0 or width <= 0 or height <= 0:
            raise WorkspaceError(path, where, "kind planar|uvatlas, positive texel_size and size", got=obj)
        if ntri != len(mesh.triangles):
            raise WorkspaceError(path, f"{where}.triangles", f"{len(mesh.triangles)} (the surface's mesh changed since `reflab texture`; run it again)", got=ntri)
        if kind == "planar":
            tri_uv = _planar_tri_uv(mesh.vertices, mesh.triangles, charts, size, path, where)
        elif tri_uv is None or tri_uv.shape != (ntri, 3, 2):
            raise WorkspaceError(path, f"{where}.uv", f"per-corner texel coordinates of shape ({ntri}, 3, 2)", got=None if tri_uv is None else tri_uv.shape)
        return cls(surface, obj["surface"], kind, size, width, height, np.asarray(tri_uv, np.float64),
                   charts, mesh.vertices, mesh.triangles)


# ---------------------------------------------------------------------- geometry helpers
def bilinear_weights(coords: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Four texel indices and bilinear weights for continuous coordinates (N, 2) = (col, row).

    Coordinates are clamped to the atlas so that every index is valid.
    """
    c = np.clip(coords[:, 0], 0.0, width - 1.0)
    r = np.clip(coords[:, 1], 0.0, height - 1.0)
    c0 = np.minimum(np.floor(c), max(width - 2, 0))
    r0 = np.minimum(np.floor(r), max(height - 2, 0))
    fc, fr = c - c0, r - r0
    c0, r0 = c0.astype(np.int64), r0.astype(np.int64)
    # Written into the outputs' columns (no stacked temporaries); a 1-texel-wide atlas repeats its texel.
    index, weight = np.empty((len(c), 4), dtype=np.int64), np.empty((len(c), 4))
    right, down = (c0 + 1 <= width - 1), width * (r0 + 1 <= height - 1)
    np.add(r0 * width, c0, out=index[:, 0])
    np.add(index[:, 0], right, out=index[:, 1])
    np.add(index[:, 0], down, out=index[:, 2])
    np.add(index[:, 2], right, out=index[:, 3])
    gc, gr = 1 - fc, 1 - fr
    np.multiply(gc, gr, out=weight[:, 0])
    np.multiply(fc, gr, out=weight[:, 1])
    np.multiply(gc, fr, out=weight[:, 2])
    np.multiply(fc, fr, out=weight[:, 3])
    return index, weight


def locate(vertices: np.ndarray, triangles: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangle and barycentric coordinates (float64) of the surface point nearest each point.

    Open3D's closest-point query (float32) picks the triangle; the barycentric coordinates are
    recomputed in float64 and clamped to the triangle.
    """
    from reflab.core.open3d_env import open3d
    o3d = open3d()

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    ans = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    tri = ans["primitive_ids"].numpy().astype(np.int64)
    a, b, c = (vertices[triangles[tri, i]] for i in range(3))
    e1, e2, d = b - a, c - a, points - a
    d11, d12, d22 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    p1, p2 = (d * e1).sum(1), (d * e2).sum(1)
    den = d11 * d22 - d12 * d12
    den = np.where(np.abs(den) > 1e-300, den, 1e-300)  # degenerate triangles: land on a corner
    w1, w2 = (d22 * p1 - d12 * p2) / den, (d11 * p2 - d12 * p1) / den
    bary = np.clip(np.stack([1 - w1 - w2, w1, w2], axis=1), 0.0, None)
    bary /= np.maximum(bary.sum(1, keepdims=True), 1e-300)
    return tri, bary


def _canonical_planes(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-triangle canonical unit normal (sign fixed) and plane offset, and the group label."""
    v = vertices[triangles]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    # The sign makes the first clearly non-zero component positive: both windings share a plane.
    lead = np.argmax(np.abs(n) > 1e-6, axis=1)
    n *= np.where(n[np.arange(len(n)), lead] < 0, -1.0, 1.0)[:, None]
    d = (n * v[:, 0]).sum(1)
    scale = max(float(np.ptp(vertices, axis=0).max()), 1e-9)
    key = np.concatenate([np.round(n * 200), np.round(d / scale * 2e4)[:, None]], axis=1)
    _, label = np.unique(key, axis=0, return_inverse=True)
    return n, d, label.ravel()


def _min_area_frame(points2: np.ndarray, edges2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction (2,) among candidate edge directions giving the smallest bounding rectangle."""
    lens = np.linalg.norm(edges2, axis=1)
    cand = edges2[lens > 1e-12] / lens[lens > 1e-12, None]
    if len(cand) == 0:
        cand = np.array([[1.0, 0.0]])
    cand = cand[:: max(1, len(cand) // 256)]
    perp = np.stack([-cand[:, 1], cand[:, 0]], axis=1)
    pu, pv = points2 @ cand.T, points2 @ perp.T
    area = np.ptp(pu, axis=0) * np.ptp(pv, axis=0)
    best = int(np.argmin(area))
    return cand[best], perp[best]


#: A cropped chart (``region``) reaches this many texels beyond the outermost point it must hold.
CROP_MARGIN = 2


def _planar_charts(vertices, triangles, texel_size, region=None) -> tuple[list[Chart], np.ndarray, int, int]:
    """Charts of a piecewise-planar mesh, shelf-packed: (charts, tri_chart, width, height).

    ``region`` = (triangle (M,), points (M, 3)): each chart covers only the part of its plane
    these points span (plus :data:`CROP_MARGIN` texels), on the same texel lattice as the whole
    chart; a chart with none of them keeps a single texel. Points elsewhere on the mesh fall
    outside their chart's block.
    """
    n, d, label = _canonical_planes(vertices, triangles)
    frames = []
    for g in range(label.max() + 1):
        tris = triangles[label == g]
        normal = n[label == g][0]
        helper = np.eye(3)[np.argmin(np.abs(normal))]
        e0 = np.cross(normal, helper)
        e0 /= np.linalg.norm(e0)
        e1 = np.cross(normal, e0)
        pts = vertices[np.unique(tris)]
        p2 = np.stack([pts @ e0, pts @ e1], axis=1)
        ev = vertices[tris[:, [1, 2, 0]]] - vertices[tris]
        edges2 = np.stack([ev.reshape(-1, 3) @ e0, ev.reshape(-1, 3) @ e1], axis=1)
        du, dv = _min_area_frame(p2, edges2)
        axis_u, axis_v = du[0] * e0 + du[1] * e1, dv[0] * e0 + dv[1] * e1
        cu, cv = pts @ axis_u, pts @ axis_v
        lo, hi = np.array([cu.min(), cv.min()]), np.array([cu.max(), cv.max()])
        if region is not None:
            inside = region[1][label[region[0]] == g]
            if len(inside):
                ru, rv = inside @ axis_u, inside @ axis_v
                first = np.floor((np.array([ru.min(), rv.min()]) - lo) / texel_size) - CROP_MARGIN
                lo = lo + np.maximum(first, 0.0) * texel_size  # the same lattice, moved by whole texels
                hi = np.maximum(np.minimum(hi, np.array([ru.max(), rv.max()]) + CROP_MARGIN * texel_size), lo)
            else:
                hi = lo
        ext = hi - lo
        cols, rows = (np.ceil(ext / texel_size).astype(int) + 1 + 2 * PAD)
        origin = lo[0] * axis_u + lo[1] * axis_v + (normal @ pts[0]) * normal
        frames.append((origin, axis_u, axis_v, rows, cols))
    sizes = [(f[3], f[4]) for f in frames]
    total = sum(r * c for r, c in sizes)
    widest = max(c for _, c in sizes)
    # Try a few atlas widths, keep the smallest area.
    widths = {widest, sum(c for _, c in sizes)} | {max(widest, int(np.ceil(np.sqrt(total) * k))) for k in (1.0, 1.2, 1.5)}
    width, pos, height = min(((w, *_shelf_pack(sizes, w)) for w in widths), key=lambda t: t[0] * t[2])
    charts = [Chart(origin, au, av, np.array([x + PAD, y + PAD], float), (rows, cols))
              for (origin, au, av, rows, cols), (x, y) in zip(frames, pos)]
    return charts, label, width, height


def _shelf_pack(sizes: list[tuple[int, int]], width: int) -> tuple[list[tuple[int, int]], int]:
    """Shelf packing, tallest first: the (x, y) corner of each (rows, cols) block, and the height."""
    pos: list[tuple[int, int]] = [(0, 0)] * len(sizes)
    x = y = shelf = 0
    for i in sorted(range(len(sizes)), key=lambda i: -sizes[i][0]):
        rows, cols = sizes[i]
        if x + cols > width:
            x, y, shelf = 0, y + shelf, 0
        pos[i] = (x, y)
        x, shelf = x + cols, max(shelf, rows)
    return pos, y + shelf


def _planar_tri_uv(vertices, triangles, charts, texel_size, path="", where="") -> np.ndarray:
    """Texel coordinates of each triangle corner: the chart whose plane holds the triangle."""
    v = vertices[triangles]
    normals = np.stack([c.normal for c in charts])
    origins = np.stack([c.origin for c in charts])
    # Distance of each triangle's corners to each chart plane, plus normal agreement.
    dist = np.abs(np.einsum("tkx,cx->tkc", v, normals) - (normals * origins).sum(1)).max(1)
    n, _, _ = _canonical_planes(vertices, triangles)
    align = np.abs(n @ normals.T)
    scale = max(float(np.ptp(vertices, axis=0).max()), 1e-9)
    ok = (align > 1 - 1e-4) & (dist < 1e-5 * scale + 1e-9)
    if not np.all(ok.any(1)):
        raise WorkspaceError(path, where, "charts covering every triangle of the mesh (the mesh changed; run `reflab texture` again)")
    chart = np.argmax(ok, axis=1)
    axes_u = np.stack([c.axis_u for c in charts])[chart]
    axes_v = np.stack([c.axis_v for c in charts])[chart]
    rel = v - origins[chart][:, None, :]
    offs = np.stack([c.offset for c in charts])[chart]
    uv = np.stack([(rel * axes_u[:, None]).sum(2), (rel * axes_v[:, None]).sum(2)], axis=2) / texel_size
    return uv + offs[:, None, :]


def _uvatlas(vertices, triangles, texel_size) -> tuple[np.ndarray, int, float]:
    """Open3D UV atlas sized so that a texel is about ``texel_size``: (tri_uv, side, texel_size)."""
    from reflab.core.open3d_env import open3d
    o3d = open3d()

    v = vertices[triangles]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()
    # UV atlases fill about 60% of their square; aim for that many texels of the requested size.
    side = int(np.clip(np.ceil(np.sqrt(area / 0.6) / texel_size), 16, np.sqrt(MAX_TEXELS)))
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(vertices.astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(triangles.astype(np.int32))
    mesh.compute_uvatlas(size=side, gutter=float(PAD + 1))
    uv = mesh.triangle.texture_uvs.numpy().astype(np.float64).reshape(-1, 3, 2)
    # Open3D's uv: [0, 1] over the atlas, texel centres at (i + 0.5) / side.
    tri_uv = uv * side - 0.5
    tri_uv[..., 1] = (side - 1) - tri_uv[..., 1]  # v up in Open3D, rows down here
    return tri_uv, side, float(np.sqrt(area / 0.6) / side)


def build_texel_map(surface: int, name: str, mesh, texel_size: float, *, max_planar_charts: int = MAX_PLANAR_CHARTS,
                    region=None) -> TexelMap:
    """The texel atlas of one surface's mesh at ``texel_size`` metres per texel.

    Piecewise-planar meshes (at most ``max_planar_charts`` planes) get planar charts, others the
    UV atlas. A request beyond :data:`MAX_TEXELS` texels is coarsened to fit. ``region`` =
    (triangle (M,), points (M, 3)) crops planar charts to what those points span
    (:func:`_planar_charts`): for a map only those points will ever be looked up in.
    """
    if not (np.isfinite(texel_size) and texel_size > 0):
        raise ValueError(f"surface {name!r}: texel size must be a positive number, got {texel_size!r}")
    vertices, triangles = mesh.vertices, mesh.triangles
    _, _, label = _canonical_planes(vertices, triangles)
    if label.max() + 1 <= max_planar_charts:
        for _ in range(8):
            charts, _, width, height = _planar_charts(vertices, triangles, texel_size, region)
            if width * height <= MAX_TEXELS:
                break
            texel_size *= np.sqrt(width * height / MAX_TEXELS) * 1.05
        tri_uv = _planar_tri_uv(vertices, triangles, charts, texel_size)
        return TexelMap(surface, name, "planar", float(texel_size), int(width), int(height), tri_uv,
                        charts, vertices, triangles)
    tri_uv, side, size = _uvatlas(vertices, triangles, texel_size)
    return TexelMap(surface, name, "uvatlas", size, side, side, tri_uv, [], vertices, triangles)


def pixel_footprint(pixel: np.ndarray, path: np.ndarray, point: np.ndarray, width: int) -> np.ndarray:
    """Footprint (metres) of each tree node: the square root of the area one pixel covers there.

    A node is identified by (pixel, path); the neighbours to the right and below that followed
    the same sequence of ideal interactions land on the same surface region, so the hit-point
    offsets ``a`` (right) and ``b`` (below) span the pixel's parallelogram there, mirrors and
    refractions included: the footprint is ``sqrt(|a × b|)``. An oblique view stretches a pixel
    along one axis only; the area, not the shorter side, says how many pixels see a texel.
    Where only one neighbour has such a node, that offset's length is used; NaN where neither.
    """
    pixel = np.asarray(pixel, np.int64)
    path = np.asarray(path, np.int64)
    point = np.asarray(point, np.float64)
    if len(pixel) == 0:
        return np.zeros(0)
    # Dense table (pixel, path rank) -> node: one node per pixel and path, O(N) lookups.
    used = np.zeros(int(path.max()) + 1, dtype=bool)
    used[path] = True
    npath = int(used.sum())
    # Pixels counted from the surface's first: the table spans its rows of the image, not all of them.
    key = (pixel - int(pixel.min())) * npath + (np.cumsum(used) - 1)[path]
    table = np.full((int(pixel.max() - pixel.min()) + width + 2) * npath, -1, dtype=np.int64)
    table[key] = np.arange(len(key))
    offsets = []
    for step in (1, width):
        j = table[key + step * npath]
        hit = j >= 0
        if step == 1:
            hit &= (pixel % width) != width - 1
        off = np.full(point.shape, np.nan)
        off[hit] = point[j[hit]] - point[hit]
        offsets.append(off)
    right, down = offsets
    out = np.sqrt(np.linalg.norm(np.cross(right, down), axis=1))
    # One neighbour only (an edge of what the path sees): that offset's length, measured for those
    # nodes alone (the same floats as over every node).
    edge = np.flatnonzero(np.isnan(out))
    no_right = np.isnan(right[edge, 0])
    out[edge] = np.where(no_right, np.linalg.norm(down[edge], axis=1), np.linalg.norm(right[edge], axis=1))
    return out


def choose_texel_size(footprints: np.ndarray, scale: float = 1.0, quantile: float = 0.25) -> float | None:
    """Texel size from node footprints on one surface: their ``quantile`` times ``scale``.

    A low quantile resolves the part of the surface the image sees finest (usually the direct
    view); parts seen coarser (in mirrors, at grazing angles) are tied together by the
    bilinear weights and the prior. None when no footprint is finite.
    """
    f = footprints[np.isfinite(footprints) & (footprints > 0)]
    if len(f) == 0:
        return None
    return float(np.quantile(f, quantile) * scale)
