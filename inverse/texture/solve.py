"""Diffuse texture recovery (docs/method.md §4, dissertation §2.3): the sparse system E z = b − Q.

With every non-Lambertian parameter fixed, a tree node ``n`` on a textured surface adds
``P_n · basis_n[kd] · ρ(p_n)`` to its pixel (docs/architecture.md; ``P_n`` the product of r and t
along its path, ``basis_n[kd]`` the Fresnel-weighted irradiance times the model's diffuse factor).
``ρ(p)`` is the bilinear blend of four texels of the surface's atlas (:mod:`reflab.inverse.texture.texels`), so
each pixel and band is one sparse row over the texels of every surface it sees, directly, in
mirrors or through transparent sheets (eq. 2.13). ``Q`` is everything else the trees predict
(specular lobes, untextured surfaces at their homogeneous ``kd``).

Solving (docs/texture.md): conjugate gradient on the normal
equations without forming them, Jacobi-scaled, warm started from each texel's ratio of observed to
predicted radiance; it converges in 15–20 iterations where bounded solvers take minutes. The
unknowns are split into the connected components of the system (scipy.sparse.csgraph) and
numbered component by component, so that one set of sparse products per iteration serves every
component while each keeps its own step sizes and stopping test (exactly separate solves).
Bounds are then enforced by a short active-set loop (fix the violators at their bound, re-solve
the rest) and a final projection.

A weak prior pulls each texel toward the surface's homogeneous ``kd`` (the fitted value) with a
weight relative to the texel's own data (``prior``, dimensionless): it fixes the directions the
image does not determine — two textured layers seen through one transparent sheet — and barely
moves determined texels (by about ``prior`` times their deviation). An optional smoothness term
ties neighbouring texels. Texels that no lit, unsaturated pixel sees are left out and masked.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from reflab.core.images import clip_level
from reflab.core.workspace import Workspace, WorkspaceError, atomic_write, read_json, write_json
from reflab.inverse.texture.texels import TexelMap, build_texel_map, choose_texel_size, pixel_footprint

#: Flag bits of the per-texel diagnostics.
AMPLIFIED, SATURATED, CLIPPED, GUESSED = 1, 2, 4, 8
#: Nodes (or entries of E) per chunk of the passes that would otherwise make temporaries as large
#: as E itself (a 12 MP photograph: 150 M entries, 1.2 GB per float64 array).
CHUNK = 1 << 21
#: Up to this many connected components the conjugate gradient works on each one's slice.
FEW_COMPONENTS = 64
#: Threads writing textures/' images (the EXR and PNG writers release the GIL). Two: at a load of
#: 1.9 the 3 MP texture's files took 1.20–1.28 s against 1.73–1.75 s in one (the same CPU time).
#: Not used for E's products (two threads over blocks of rows were slower at loads of 2–4 on this
#: shared 2-core machine: memory-bound) nor for the assembly's chunks (8 % faster, +0.1 GB of
#: peak memory at half the 3 MP system: the threads' malloc arenas).
THREADS = 2


def _in_threads(jobs) -> list:
    """Run the callables ``jobs`` in :data:`THREADS` threads; their results in order (the first
    error raised once all are done)."""
    if THREADS <= 1 or len(jobs) <= 1:
        return [job() for job in jobs]
    with ThreadPoolExecutor(THREADS) as pool:
        return [f.result() for f in [pool.submit(job) for job in jobs]]


@dataclass
class SolverOptions:
    """Settings of the texture stage.

    Attributes
    ----------
    texel_scale : float
        Texel size as a multiple of the pixel footprint on the surface.
    texel_size : float or None
        Texel size in metres for every surface (overrides ``texel_scale``).
    texel_quantile : float
        Which quantile of a surface's node footprints sets its texel size.
    prior : float
        Relative weight of the prior toward the homogeneous ``kd`` (0 disables it; null-space
        directions then keep the warm start's values, each texel's observed/predicted ratio).
    smoothness : float
        Relative weight of the first-difference term between neighbouring texels (0 = off).
    bounds : (float, float)
        Albedo bounds.
    saturation : float or None
        Pixel values at or above this are dropped (per band). None: detect a clipped plateau
        (the image maximum shared by several pixels).
    min_coverage : float
        A texel is known when the bilinear weights of the lit, unsaturated nodes on it sum to
        at least this (in pixels).
    amplification_limit : float
        Flag texels whose observations are attenuated by more than this (faint reflections).
    tol : float
        Conjugate gradient stops, per connected component, when its normal-equation residual is
        this fraction of the residual at the homogeneous ``kd`` (so a warm start counts).
    max_iter : int
        Iteration cap per conjugate-gradient call.
    """

    texel_scale: float = 1.0
    texel_size: float | None = None
    texel_quantile: float = 0.5
    prior: float = 1e-3
    smoothness: float = 0.01
    bounds: tuple[float, float] = (0.0, 1.0)
    saturation: float | None = None
    min_coverage: float = 0.1
    amplification_limit: float = 10.0
    tol: float = 3e-4
    max_iter: int = 3000

    def validate(self) -> None:
        """Raise ValueError naming the first bad setting."""
        checks = [("texel_scale", self.texel_scale > 0), ("prior", self.prior >= 0),
                  ("smoothness", self.smoothness >= 0), ("min_coverage", self.min_coverage > 0),
                  ("amplification_limit", self.amplification_limit > 1), ("tol", self.tol > 0),
                  ("max_iter", self.max_iter >= 1),
                  ("texel_quantile", 0 < self.texel_quantile <= 1),
                  ("bounds", len(self.bounds) == 2 and self.bounds[0] < self.bounds[1]),
                  ("texel_size", self.texel_size is None or self.texel_size > 0),
                  ("saturation", self.saturation is None or self.saturation > 0)]
        for name, ok in checks:
            value = getattr(self, name)
            if not ok or not np.all(np.isfinite(np.asarray(value if value is not None else 0.0, dtype=float))):
                raise ValueError(f"texture option {name}: invalid value {value!r}")


@dataclass
class TextureSolution:
    """Recovered textures, per textured surface index (arrays are atlas-shaped, (H, W, …)).

    ``kd`` holds the homogeneous value where ``mask`` is False; ``weight`` is the observation
    weight per band (bilinear weight × Fresnel × r/t products, in pixels seen directly);
    ``amplification`` is coverage / weight (1 for direct views, 1/r for a reflection);
    ``flags`` has the bits :data:`AMPLIFIED`, :data:`SATURATED`, :data:`CLIPPED`.
    """

    maps: dict[int, TexelMap]
    kd: dict[int, np.ndarray]
    mask: dict[int, np.ndarray]
    weight: dict[int, np.ndarray]
    amplification: dict[int, np.ndarray]
    flags: dict[int, np.ndarray]
    stats: dict = field(default_factory=dict)
    #: ``kd`` again, solved with the same system from the photograph plus ``perturb``
    #: (:func:`recover_texture`); empty without it.
    perturbed: dict[int, np.ndarray] = field(default_factory=dict)


# ---------------------------------------------------------------------- inputs
def load_materials(workspace, scene) -> tuple[list, str]:
    """Materials in surface order: fit.json's when it exists, else scene.json's.

    fit.json's r and t are taken at the value a view renders them with (:func:`_render_values`):
    a loose one shrinks toward 0, the posterior mean under the field's prior (docs/fit.md,
    "Rendering a loose value").

    Returns
    -------
    materials : list of Material
    source : str
        ``"fit.json"`` or ``"scene.json"``.
    """
    from reflab.reconstruction.scene import Material

    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    materials = [s.material for s in scene]
    if not ws.fit.exists():
        return materials, "scene.json"
    fit = read_json(ws.fit)
    items = fit.get("surfaces")
    if not isinstance(items, list):
        raise WorkspaceError(ws.fit, "surfaces", "a list of fitted surfaces", got=items)
    for i, item in enumerate(items):
        if not isinstance(item, dict) or "material" not in item:
            raise WorkspaceError(ws.fit, f"surfaces[{i}]", "an object with 'name' and 'material'", got=item)
        name = item.get("name", scene[i].name if i < len(scene) else None)  # by name, else by position
        if name not in scene.names:
            raise WorkspaceError(ws.fit, f"surfaces[{i}].name", f"one of the scene's surfaces {scene.names}", got=name)
        material = Material.from_json(item["material"], ws.fit, f"surfaces[{i}].material")
        materials[scene.index(name)] = _render_values(material, item.get("sigma"), scene[scene.index(name)].material.given)
    return materials, "fit.json"


def _render_values(material, sigma, given):
    """``material`` with each fitted r and t at the value a view renders it with
    (:func:`reflab.inverse.fit.ranges.render_value`: a loose one near 0 shrinks toward it);
    given values, and values without a finite σ, unchanged."""
    import dataclasses

    from reflab.inverse.fit.ranges import render_value

    if not isinstance(sigma, dict):
        return material
    params = dict(material.params)
    for name in ("r", "t"):
        sig = sigma.get(name)
        if name in given or name not in params or not isinstance(sig, list) or len(sig) != np.size(params[name]):
            continue
        sig = np.array([np.inf if e is None else e for e in sig], dtype=np.float64)
        params[name] = render_value(np.asarray(params[name], dtype=np.float64).reshape(-1), sig).reshape(np.shape(params[name]))
    return dataclasses.replace(material, params=params)


class Uncertainty(NamedTuple):
    """What fit.json says the photograph did not pin down (:func:`load_uncertainty`)."""

    #: Per surface, the names fit.json calls undetermined (``"ks"``, ``"r[2]"``).
    undetermined: list
    #: Per surface, fit.json's ``sigma`` of the values it determined: name -> per-band list (None
    #: in the bands it calls undetermined) or a float; undetermined names are left out.
    sigma: list
    #: (3,) the photograph's noise σ per band as a fraction of its peak (fit.json's ``noise`` over
    #: ``image.peak``); None without them.
    noise: np.ndarray | None


def load_uncertainty(workspace, scene) -> Uncertainty:
    """What fit.json says the photograph did not pin down, per surface, less what scene.json gives
    (a given value is known); empty without fit.json (the user gave the materials)."""
    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    undetermined, sigma = [set() for _ in scene], [{} for _ in scene]
    if not ws.fit.exists():
        return Uncertainty(undetermined, sigma, None)
    fit = read_json(ws.fit)
    for item in fit.get("surfaces", []):
        if not (isinstance(item, dict) and item.get("name") in scene.names):
            continue
        s = scene.index(item["name"])
        given = scene[s].material.given
        loose = set(item.get("undetermined", []))
        undetermined[s] = {n for n in loose if n.partition("[")[0] not in given}
        for name, v in (item.get("sigma") if isinstance(item.get("sigma"), dict) else {}).items():
            if name in given or name in loose:
                continue
            sigma[s][name] = [None if f"{name}[{c}]" in loose else e for c, e in enumerate(v)] if isinstance(v, list) else v
    noise, peak = fit.get("noise"), (fit.get("image") or {}).get("peak")
    ok = isinstance(noise, list) and len(noise) == 3 and isinstance(peak, (int, float)) and peak > 0
    return Uncertainty(undetermined, sigma, np.asarray(noise, dtype=np.float64) / peak if ok else None)


def build_maps(scene, trees, options: SolverOptions, crop: bool = False) -> dict[int, TexelMap]:
    """A texel atlas for each textured surface that some node lies on, sized from its footprint.

    ``crop``: planar charts cover only what the trees' nodes span (a map that only these trees'
    nodes will be looked up in, such as the fit's texture rounds'; a written texture is not
    cropped: other views see more of the surface).
    """
    footprints, regions = {}, {}
    for s, surf in enumerate(scene):
        sel = np.nonzero(trees.surface == s)[0]
        if not surf.textured or len(sel) == 0:
            continue
        footprints[s] = None if options.texel_size is not None else node_footprints(trees, sel)
        if crop:
            regions[s] = (trees.triangle[sel], trees.point[sel])
    return maps_from_footprints(scene, footprints, options, max(trees.width, trees.height), regions)


def node_footprints(trees, sel) -> np.ndarray:
    """Pixel footprints of the nodes ``sel`` that set their surface's texel size: the reference
    photograph's when some lie in it (several photographs: texels as fine as the reference sees
    the surface; further views, farther or more oblique, would coarsen them for every view)."""
    ref = trees.stats.get("reference_pixels") if isinstance(trees.stats, dict) else None
    if ref and np.any(trees.pixel[sel] < ref):
        sel = sel[trees.pixel[sel] < ref]
    return pixel_footprint(trees.pixel[sel], trees.path[sel], trees.point[sel], trees.width)


def maps_from_footprints(scene, footprints: dict, options: SolverOptions, image_size: int,
                         regions: dict | None = None) -> dict[int, TexelMap]:
    """The texel atlas of each surface in ``footprints`` (surface -> its nodes' footprints, None
    with ``options.texel_size``); ``image_size`` the image's larger side (a surface seen in isolated
    single pixels only gets about one texel per pixel); ``regions`` as :func:`build_maps`' crop."""
    maps = {}
    for s, fp in footprints.items():
        surf = scene[s]
        size = options.texel_size
        if size is None:
            size = choose_texel_size(fp, options.texel_scale, options.texel_quantile)
        if size is None:  # isolated single-pixel sightings only: one texel per pixel-ish
            size = float(np.ptp(surf.mesh.vertices, axis=0).max()) / image_size
        maps[s] = build_texel_map(s, surf.name, surf.mesh, size, region=(regions or {}).get(s))
    return maps


# ---------------------------------------------------------------------- the system
@dataclass
class _System:
    E: object  # scipy.sparse.csr_matrix, rows = (band, pixel), cols = (band, texel) compressed
    rhs: np.ndarray
    row_pixel: np.ndarray  # (R,) pixel of each row
    row_band: np.ndarray  # (R,) int8
    col_global: np.ndarray  # (C,) band * n_texels + global texel index, increasing until solve() renumbers
    prior: np.ndarray  # (C,) homogeneous kd of each column
    coverage: np.ndarray  # (3 * n_texels,) over all texels
    weight: np.ndarray
    saturated_touch: np.ndarray  # (3 * n_texels,) bool
    offsets: dict  # surface -> global texel offset
    n_texels: int
    n_saturated: int
    n_unmodelled: int  # pixel-band rows dropped: their textured node's texels are unsupported
    #: The three bands have the same rows, columns and entries (none saturated or unlit in one band
    #: alone: the usual case); only E's values differ.
    shared: bool = False


def _compress(keys: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The sorted distinct values of ``keys`` (in ``[0, size)``) and each key's rank among them.

    A mark-and-cumsum in O(size): much faster than ``np.unique`` for dense key ranges.
    """
    used = np.zeros(size, dtype=bool)
    used[keys] = True
    return np.flatnonzero(used), (np.cumsum(used) - 1)[keys]


@dataclass
class TexturedNodes:
    """What the texture's system needs of the tree nodes on textured surfaces, in pixel order.

    A tile's trees are reduced to this (:func:`textured_nodes`) and released: about 90 bytes a
    node against the trees' 2 KB a pixel. Tiles in row order concatenate (:meth:`concatenate`)
    to the whole photograph's, node for node.
    """

    pixel: np.ndarray  # (n,) int64, the photograph's pixel index
    surface: np.ndarray  # (n,) int32
    triangle: np.ndarray  # (n,) int64
    barycentric: np.ndarray  # (n, 2)
    coef: np.ndarray  # (3, n) E's value per unit bilinear weight
    seen: np.ndarray  # (3, n) attenuation between camera and node

    def __len__(self) -> int:
        return len(self.pixel)

    @classmethod
    def concatenate(cls, parts: list) -> "TexturedNodes":
        """The parts in order, one field at a time; each part's field is released once copied, so
        the peak is the whole plus one field, not twice the whole."""
        fields = {}
        for k in ("pixel", "surface", "triangle", "barycentric", "coef", "seen"):
            fields[k] = np.concatenate([getattr(p, k) for p in parts], axis=-1 if k in ("coef", "seen") else 0)
            for p in parts:
                setattr(p, k, None)
        return cls(**fields)


def textured_nodes(trees, materials, intensities, textured_surfaces, *, pixel_map=None,
                   keep=None) -> tuple[TexturedNodes, np.ndarray]:
    """The trees' nodes on ``textured_surfaces`` and the rest of each pixel's predicted light.

    Parameters
    ----------
    textured_surfaces : iterable of int
        The surfaces whose kd is unknown (their nodes are E's entries; others go to ``Q``).
    pixel_map : (H·W,) int64, optional
        The photograph's (or stacked image's) pixel index of each of the trees' pixels (a tile's);
        default the trees' own.
    keep : (N,) bool, optional
        Nodes to reduce (a tile built with an extra row for the footprints keeps its own rows').

    Returns
    -------
    nodes : TexturedNodes
    Q : (H·W, 3) float64
        Per pixel of the trees, the light of every node but the textured ones (their kd 0).
    """
    from reflab.inverse.forward.models import get_model
    from reflab.inverse.forward.rendering import linear_basis, path_products, surface_parameters

    npix = trees.width * trees.height
    basis = linear_basis(trees, materials, intensities)  # (N, 3, L), kd is slot 0
    textured = np.isin(trees.surface, list(textured_surfaces))
    # Q from the nodes that can carry light only: a textured surface's kd is E's, so a textured
    # Lambertian node (most of a tile: a matte ground) adds exactly 0, and so does a node no lamp
    # lights (its basis is 0: the inside of a glass). The others' values are node_radiance's.
    x_table, _ = surface_parameters(materials, np.flatnonzero(np.bincount(trees.surface, minlength=len(materials))))
    beyond_kd = np.array([get_model(m.brdf).n_linear > 1 for m in materials])
    carry = (~textured | beyond_kd[trees.surface]) & trees.visible.any(axis=1)
    if keep is not None:
        keep = np.asarray(keep, dtype=bool)
        carry &= keep
        textured &= keep
    carry = np.flatnonzero(carry)
    x = x_table[trees.surface[carry]]
    x[textured[carry], :, 0] = 0.0
    per_path = path_products(trees, materials, per_path=True)
    q_nodes = per_path[trees.path[carry]] * np.einsum("ncl,ncl->nc", basis[carry], x)
    del x
    Q = np.stack([np.bincount(trees.pixel[carry], weights=q_nodes[:, c], minlength=npix) for c in range(3)], axis=1)
    # Textured nodes in pixel order, so that E's entries come out sorted by row.
    nodes = np.flatnonzero(textured)
    pix = trees.pixel[nodes]
    if np.any(pix[1:] < pix[:-1]):
        nodes = nodes[np.argsort(pix, kind="stable")]
    pix = trees.pixel[nodes].astype(np.int64)
    atten = per_path[trees.path[nodes]]  # (n, 3)
    out = TexturedNodes(pix if pixel_map is None else np.asarray(pixel_map)[pix], trees.surface[nodes],
                        trees.triangle[nodes], trees.barycentric[nodes],
                        (atten * basis[nodes, :, 0]).T, (trees.fresnel[nodes, None] * atten).T)
    return out, Q


def build_system(trees, materials, intensities, image, maps, options: SolverOptions, exclude=None) -> _System:
    """Assemble E, b − Q and the per-texel coverage / weight (:func:`textured_nodes`, then
    :func:`assemble_system`).

    ``exclude`` (H*W bool, optional): pixels left out of the system, as saturated ones are (but
    not flagged as saturated).
    """
    nodes, Q = textured_nodes(trees, materials, intensities, list(maps))
    return assemble_system(nodes, Q, image, materials, maps, options, exclude)


def assemble_system(nodes: TexturedNodes, Q, image, materials, maps, options: SolverOptions, exclude=None, *,
                    release: bool = False) -> _System:
    """E, b − Q and the per-texel coverage / weight from the textured nodes of every pixel.

    ``Q`` (H·W, 3): each pixel's light from everything but the textured nodes; ``image`` the
    photograph (H, W, 3) or (H·W, 3). Vectorised over (node, bilinear corner, band) entries: no
    Python loop beyond one per textured surface (its bilinear lookup) and one per chunk of
    :data:`CHUNK` nodes where E's arrays are filled, so that no temporary holds every entry.
    ``release``: the caller hands ``nodes`` over, whose fields are dropped once used (a 12 MP
    texture's triangles and barycentric points: 0.35 GB less at the peak).
    """
    import scipy.sparse as sp

    img = np.asarray(image, dtype=np.float64).reshape(-1, 3)
    npix = len(img)
    sat_level = options.saturation if options.saturation is not None else clip_level(img)
    saturated = img >= sat_level if sat_level is not None else np.zeros_like(img, dtype=bool)
    offsets, total = {}, 0
    for s, m in maps.items():
        offsets[s], total = total, total + m.n_texels
    kd_table = np.stack([np.broadcast_to(mat["kd"], (3,)) for mat in materials]).astype(np.float64)

    # An excluded pixel's nodes only flag the texels a saturated pixel touches: the others are dropped here.
    excluded = None
    if exclude is not None:
        excluded = np.asarray(exclude, dtype=bool).reshape(npix)
        keep = ~excluded[nodes.pixel] | saturated[nodes.pixel].any(axis=1)
        nodes = TexturedNodes(nodes.pixel[keep], nodes.surface[keep], nodes.triangle[keep], nodes.barycentric[keep],
                              nodes.coef[:, keep], nodes.seen[:, keep])
    pix, surface = nodes.pixel, nodes.surface
    n = len(pix)
    idx = np.zeros((n, 4), dtype=np.int64)
    w = np.zeros((n, 4))
    for s, m in maps.items():
        sel = np.flatnonzero(surface == s)
        for a in range(0, len(sel), CHUNK):  # the lookup's temporaries are a dozen arrays a node
            part = sel[a:a + CHUNK]
            i, ww = m.bilinear(nodes.triangle[part], nodes.barycentric[part])
            idx[part], w[part] = i + offsets[s], ww
    del surface
    if release:
        nodes.triangle = nodes.barycentric = nodes.surface = None
    coef, seen = nodes.coef, nodes.seen
    lit = coef > 0
    ok = lit & ~saturated[pix].T  # (3, n)
    if excluded is not None:
        ok &= ~excluded[pix][None, :]

    # E band by band (rows band * npix + pixel, columns band * total + texel, both in increasing
    # order). When every band keeps the same nodes (none saturated or unlit in one band alone: the
    # usual case) the entries' structure is the same in each band: worked out once, each band
    # taking its own values (640x480 textured scene: 0.55 -> 0.25 s).
    shared = bool(np.array_equal(ok[0], ok[1]) and np.array_equal(ok[0], ok[2]))
    bands = [_band_structure(ok[0], idx, w, pix, total, options.min_coverage)]
    bands += [bands[0]] * 2 if shared else [_band_structure(ok[b], idx, w, pix, total, options.min_coverage)
                                            for b in (1, 2)]
    del w
    # E's arrays filled in place, chunk by chunk, 32-bit indices (as scipy keeps them).
    band_at = np.concatenate([[0], np.cumsum([int(e.row_nnz.sum()) for e in bands])])
    band_col = np.concatenate([[0], np.cumsum([len(e.col_texels) for e in bands])])
    nnz, n_rows, n_cols = int(band_at[-1]), sum(len(e.row_pixels) for e in bands), int(band_col[-1])
    data, indices = np.empty(nnz), np.empty(nnz, dtype=np.int32)
    indptr = np.zeros(n_rows + 1, dtype=np.int32 if nnz < 2**31 else np.int64)
    row_ids, col_global = np.empty(n_rows, dtype=np.int64), np.empty(n_cols, dtype=np.int64)
    coverage, weight = np.zeros(3 * total), np.zeros(3 * total)
    row = 0
    for b, e in enumerate(bands):
        r, k, col = len(e.row_pixels), len(e.col_texels), band_col[b]
        indptr[row + 1:row + r + 1] = np.cumsum(e.row_nnz) + band_at[b]
        row_ids[row:row + r], col_global[col:col + k] = e.row_pixels + b * npix, e.col_texels + b * total
        row += r
    # Entries a chunk of nodes at a time, each chunk's structure worked out once for the bands
    # that share it.
    for e in {id(e): e for e in bands}.values():
        same = [b for b in range(3) if bands[b] is e]
        at = 0
        for a in range(0, n, CHUNK):
            wk = e.wk[a:a + CHUNK].ravel()
            flat = np.flatnonzero(wk)  # node (pixel order), then corner: row order
            m, node, wv = len(flat), flat // 4 + a, wk[flat]
            cols = e.col_rank[idx[a:a + CHUNK].ravel()[flat]]
            for b in same:
                o = band_at[b] + at
                np.multiply(coef[b][node], wv, out=data[o:o + m])
                np.add(cols, band_col[b], out=indices[o:o + m], casting="unsafe")
            at += m
    # Per texel, each band's coverage (Σ weights) and observation weight (Σ weight × seen), summed
    # into place (entries with zero weight add nothing, so the sums over every corner are those
    # over the entries); a band sharing the previous one's structure copies its coverage.
    for b, e in enumerate(bands):
        if b and bands[b] is bands[b - 1]:
            coverage[b * total:(b + 1) * total] = coverage[(b - 1) * total:b * total]
        else:
            _corner_sums(idx, e.wk, None, coverage[b * total:(b + 1) * total])
        _corner_sums(idx, e.wk, seen[b], weight[b * total:(b + 1) * total])
    n_bad = sum(e.n_bad for e in bands)
    del bands
    saturated_touch = np.zeros(3 * total, dtype=bool)
    band, node = np.nonzero(lit & saturated[pix].T)
    saturated_touch[(idx[node] + (band * total)[:, None]).ravel()] = True
    del idx
    E = sp.csr_matrix((data, indices, indptr), shape=(n_rows, n_cols))
    E.sum_duplicates()  # a pixel seeing one texel twice (two paths) gets one entry
    row_band, row_pixel = (row_ids // npix).astype(np.int8), row_ids % npix
    del row_ids
    rhs = img[row_pixel, row_band] - Q[row_pixel, row_band]

    surf_of = np.zeros(total, dtype=np.int64)
    for s, m in maps.items():
        surf_of[offsets[s]: offsets[s] + m.n_texels] = s
    prior = kd_table[surf_of[col_global % max(total, 1)], col_global // max(total, 1)]
    return _System(E, rhs, row_pixel, row_band, col_global, prior, coverage, weight,
                   saturated_touch, offsets, total, int(np.count_nonzero(saturated)), n_bad, shared)


def _corner_sums(idx, wk, factor, out: np.ndarray) -> np.ndarray:
    """Add to ``out`` (one value per texel) the corner weights ``wk`` (n, 4) at ``idx`` (n, 4),
    each times its node's ``factor`` ((n,), None for 1); returns ``out``.

    The sums are ``np.bincount(idx.ravel(), weights=(wk * factor[:, None]).ravel())``'s bit for
    bit (scipy's kernel adds the same products in the same order) without the weight temporary
    (32 bytes a node: 0.47 GB at 12 MP) nor bincount's output copy; three such bincounts per band
    took 1.1 s of the 3 MP assembly.
    """
    from scipy.sparse import _sparsetools

    n, step = len(idx), max(1, CHUNK // 4)
    ind = np.ascontiguousarray(idx).ravel()
    for a in range(0, n, step):
        b = min(a + step, n)
        x = np.ones(b - a) if factor is None else np.ascontiguousarray(factor[a:b], dtype=np.float64)
        ptr = np.arange(0, 4 * (b - a) + 1, 4, dtype=ind.dtype)
        _sparsetools.csc_matvec(len(out), b - a, ptr, ind[4 * a:4 * b], np.ascontiguousarray(wk[a:b]).ravel(), x, out)
    return out


class _BandStructure(NamedTuple):
    """One band's entries of E (:func:`_band_structure`)."""

    wk: np.ndarray  # (n, 4) each node's renormalised bilinear weights; 0 where no entry
    col_texels: np.ndarray  # distinct texels of the entries, increasing
    col_rank: np.ndarray  # (total,) each texel's rank among them (-1: none)
    row_pixels: np.ndarray  # distinct pixels of the rows, increasing (two nodes of one pixel share a row)
    row_nnz: np.ndarray  # entries per row
    n_bad: int  # pixels dropped: their node keeps less than half its weight


def _band_structure(ok, idx, w, pix, total: int, min_coverage: float) -> _BandStructure:
    """One band's entries of E: the nodes ``ok`` keeps (in pixel order), their bilinear texels
    ``idx`` and weights ``w`` (n, 4).

    Texels that carry less than ``min_coverage`` pixels of weight are not modelled: each node's
    weights are renormalised over its supported texels, and a pixel whose node keeps less than
    half its weight is dropped. This removes the near-null columns at the edges of what the image
    sees, which would otherwise dominate the solver's iterations. Node-sized arrays only: E's
    entries are written from ``wk`` chunk by chunk (:func:`assemble_system`).
    """
    wk = np.where(ok[:, None] & (w > 0), w, 0.0)
    supported = _corner_sums(idx, wk, None, np.zeros(total)) >= min_coverage
    wk *= supported[idx]
    kept = wk.sum(axis=1)
    bad_pixel = np.zeros(int(pix.max()) + 1 if len(pix) else 0, dtype=bool)
    bad_pixel[pix[ok & (kept < 0.5)]] = True
    good = ok & ~bad_pixel[pix]
    wk *= np.where(good, 1.0 / np.maximum(kept, 1e-300), 0.0)[:, None]
    entry = wk != 0
    used = np.zeros(total, dtype=bool)
    for a in range(0, len(pix), CHUNK):
        used[idx[a:a + CHUNK][entry[a:a + CHUNK]]] = True
    col_rank = np.cumsum(used) - 1
    count = entry.sum(axis=1)
    has = count > 0
    keys = pix[has]
    first = np.ones(len(keys), dtype=bool)
    first[1:] = keys[1:] != keys[:-1]
    starts = np.flatnonzero(first)
    row_nnz = np.add.reduceat(count[has], starts) if len(starts) else np.zeros(0, dtype=np.int64)
    return _BandStructure(wk, np.flatnonzero(used), col_rank, keys[starts], row_nnz, int(np.count_nonzero(bad_pixel)))


def _smoothness_pairs(system: _System, maps, kind: bool = False) -> tuple[np.ndarray, ...]:
    """Column pairs (i, j), i < j, of horizontally or vertically adjacent texels, both in the
    system; with ``kind``, also (n,) bool: the pair is vertical.

    Bands that share their structure: band 0's pairs, repeated for bands 1 and 2 (each column's
    pairs in the same order as when found over every band, so sums over them are the same)."""
    if system.shared and len(system.col_global) % 3 == 0:
        c1 = len(system.col_global) // 3
        pi, pj, vertical = _adjacent(system.col_global[:c1], system, maps)
        out = (np.concatenate([pi + b * c1 for b in range(3)]), np.concatenate([pj + b * c1 for b in range(3)]),
               np.tile(vertical, 3))
    else:
        out = _adjacent(system.col_global, system, maps)
    return out if kind else out[:2]


def _adjacent(col_global, system: _System, maps) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs (i, j) among the columns ``col_global`` (band * n_texels + texel) of adjacent texels,
    and whether each is vertical."""
    total = system.n_texels
    texel = col_global % total
    starts = np.array(sorted(system.offsets.values()))
    by_start = {system.offsets[s]: m for s, m in maps.items()}
    which = np.searchsorted(starts, texel, side="right") - 1
    width = np.array([by_start[o].width for o in starts])[which]
    count = np.array([by_start[o].n_texels for o in starts])[which]
    local = texel - starts[which]
    bands = int(col_global[-1]) // total + 1 if len(col_global) else 1  # increasing: the last is the largest
    position = np.full(bands * total + 1, -1, dtype=np.int64)  # column of each (band, texel); -1: none
    position[col_global] = np.arange(len(col_global))
    pairs_i, pairs_j = [], []
    for step, inside in ((1, local % width != width - 1), (width, local < count - width)):
        cand = np.flatnonzero(inside)
        j = position[col_global[cand] + (step if np.isscalar(step) else step[cand])]
        pairs_i.append(cand[j >= 0])
        pairs_j.append(j[j >= 0])
    vertical = np.zeros(len(pairs_i[0]) + len(pairs_i[1]), dtype=bool)
    vertical[len(pairs_i[0]):] = True
    return np.concatenate(pairs_i), np.concatenate(pairs_j), vertical


# ---------------------------------------------------------------------- the solver
def _cg(apply, b, x, free, sizes, stop, max_iter, check=None, trace=None) -> tuple[np.ndarray, int]:
    """Conjugate gradient on N x = b over the free unknowns, one independent solve per component.

    ``apply(p)`` computes N p; the unknowns are ordered by connected component, ``sizes`` giving
    each component's count. Every component gets its own step sizes and its own stopping test
    (squared residual ≤ ``stop[component]``), exactly as if it were solved alone, while one set
    of sparse products per iteration serves them all. ``free`` (0/1 per unknown, or None for
    all free): fixed unknowns keep their value. ``check()``, when given, is called every
    iteration (a task's cancellation). ``trace``, when given, gets (perf_counter, squared residual
    summed over the components) after every iteration. Returns (x, iterations of the slowest component).
    """
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    # A few components (the usual case: a handful per band) are taken slice by slice: sums in
    # float64 by pairwise summation and per-component factors in place, without reduceat's
    # sequential float64 loop or np.repeat's unknown-sized factor arrays (a quarter of the
    # iteration's time at 3 MP besides the sparse products).
    few = len(sizes) <= FEW_COMPONENTS
    spans = list(zip(starts.tolist(), (starts + sizes).tolist()))

    def seg(v):
        """Per-component sums of ``v``, float64."""
        if few:
            return np.array([np.add.reduce(v[a:b], dtype=np.float64) for a, b in spans])
        return np.add.reduceat(v, starts, dtype=np.float64)

    def scale(v, f):
        """``v`` times each component's factor ``f`` (float32), in place."""
        if few:
            for (a, b), fk in zip(spans, f):
                v[a:b] *= fk
        else:
            v *= np.repeat(f, sizes)

    dtype = x.dtype
    r = b - apply(x)
    if free is not None:
        r *= free
    work = r * r  # the products summed below, one buffer for every iteration
    gamma = seg(work)
    active = gamma > stop
    p = r.copy()
    scale(p, active.astype(dtype))
    it = 0
    while it < max_iter and active.any():
        if check is not None:
            check()
        q = apply(p)
        if free is not None:
            q *= free
        delta = seg(np.multiply(p, q, out=work))
        alpha = np.divide(gamma, delta, out=np.zeros_like(gamma), where=active & (delta > 0)).astype(dtype)
        scale(q, alpha)  # alpha q, then x += alpha p by the same factors
        if few:
            for (a, b), ak in zip(spans, alpha):
                if ak:
                    x[a:b] += np.multiply(p[a:b], ak, out=work[a:b])
        else:
            x += np.multiply(p, np.repeat(alpha, sizes), out=work)
        r -= q
        new = seg(np.multiply(r, r, out=work))
        if trace is not None:
            trace.append((time.perf_counter(), float(new.sum())))
        active &= (new > stop) & (delta > 0)
        scale(p, np.divide(new, gamma, out=np.zeros_like(gamma), where=active).astype(dtype))
        if active.all():
            p += r
        elif few:
            for (a, b), on in zip(spans, active):
                if on:
                    p[a:b] += r[a:b]
        else:
            p += r * np.repeat(active, sizes).astype(dtype)
        gamma = new
        it += 1
    return x, it


#: A column's place in :class:`_Grid`'s code: (key · 2²¹ + row) · 2²¹ + column.
_SHIFT = 1 << 21


class _Grid(NamedTuple):
    """Where each column of E lies in its atlas (:func:`_grid`), to tell which columns the
    smoothness pairs already join."""

    code: np.ndarray  # (C,) int64 (key · 2²¹ + y) · 2²¹ + x, key = band · surfaces + the atlas' slot
    glob: np.ndarray  # (C,) band * n_texels + texel (``col_global``)
    width: np.ndarray  # (C,) the atlas' width
    present: np.ndarray  # (bands · n_texels,) bool: which (band, texel) is a column


def _grid(col_global, system: _System, maps) -> _Grid | None:
    """:class:`_Grid` of the columns ``col_global`` (band * n_texels + texel, increasing); None
    for an atlas too large for its code."""
    total = system.n_texels
    texel, band = col_global % total, col_global // total
    starts = np.array(sorted(system.offsets.values()))
    by_start = {system.offsets[s]: m for s, m in maps.items()}
    if any(m.width >= _SHIFT or m.height >= _SHIFT for m in maps.values()):
        return None
    which = np.searchsorted(starts, texel, side="right") - 1
    width = np.array([by_start[o].width for o in starts])[which]
    local = texel - starts[which]
    # every (band, texel) of the bands present: a diagonal's shared neighbours are texels of its band
    present = np.zeros((int(col_global[-1]) // total + 1) * total if len(col_global) else 0, dtype=bool)
    present[col_global] = True
    code = ((band * len(starts) + which) * _SHIFT + local // width) * _SHIFT + local % width
    return _Grid(code, col_global, width, present)


def _joined(u, v, grid: _Grid) -> np.ndarray:
    """(n,) bool: column pairs (u, v) that the smoothness pairs join already: 4-neighbours in one
    atlas and band, or diagonal neighbours one of whose two shared neighbours is a column.

    Codes of one atlas and band differ by ``dy · 2²¹ + dx``; of two, by at least 2²¹ · (2²¹ − 1).
    """
    d = grid.code[v] - grid.code[u]
    ad = np.abs(d)
    joined = (ad == 1) | (ad == _SHIFT)
    diag = np.flatnonzero((ad == _SHIFT - 1) | (ad == _SHIFT + 1))
    dd, ud = d[diag], u[diag]
    dy = np.where(dd > 0, 1, -1)
    dx = dd - dy * _SHIFT
    g = grid.glob[ud]
    joined[diag] = grid.present[g + dx] | grid.present[g + dy * grid.width[ud]]
    return joined


def _components(E, pi, pj, grid: _Grid | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of the unknowns: texels sharing a row of E or a smoothness pair.

    Returns (label per unknown, numbered 0… in the order of each component's first column,
    unknowns per component). The graph is over the columns: the pairs ``(pi, pj)`` and each row's
    entries chained (an entry to the row's next). With ``grid`` (every pair of adjacent columns
    being among the pairs), the chained entries the pairs join already are left out: a pixel's
    bilinear texels are neighbours, so what is left is a few hundred thousand edges between
    surfaces or paths, and the graph is a third of E's size. (Until 2026-11-27 the graph was the
    bipartite pixel–texel one built from E's arrays: scipy's float64 copy and transpose of it took
    1.6–2.2 s of the 3 MP texture's CPU time, against 0.x s now.)
    """
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    C, nnz, ptr, ind = E.shape[1], E.nnz, E.indptr, E.indices
    first = np.zeros(nnz + 1, dtype=bool)
    first[ptr] = True  # an entry that begins its row (and the end)
    us, vs = [pi], [pj]
    for a in range(1, nnz, CHUNK):
        k = np.arange(a, min(a + CHUNK, nnz))
        k = k[~first[k]]
        u, v = ind[k - 1], ind[k]
        if grid is not None:
            keep = ~_joined(u, v, grid)
            u, v = u[keep], v[keep]
        us.append(u)
        vs.append(v)
    del first
    i, j = np.concatenate(us), np.concatenate(vs)
    del us, vs
    graph = csr_matrix((np.ones(len(i), np.int8), (i, j)), shape=(C, C))
    del i, j
    _, label = connected_components(graph, directed=False)
    return label, np.bincount(label)


def _band_components(system: _System, maps, pi, pj) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_components`, computed on one band when the three bands have the same structure
    (``pi``, ``pj`` every adjacent pair of columns, or none).

    Rows and columns are band-major; when nothing saturates and every node is lit in every
    band, bands 1 and 2 repeat band 0's pixels, texels and sparsity, and so its components.
    """
    E = system.E
    (R, C), nnz = E.shape, E.nnz
    if R % 3 or C % 3 or nnz % 3:
        return _components(E, pi, pj, _grid(system.col_global, system, maps) if len(pi) else None)
    R1, C1, n1 = R // 3, C // 3, nnz // 3
    texel = system.col_global % max(system.n_texels, 1)
    alike = system.shared or (np.array_equal(system.row_band, np.repeat(np.arange(3), R1))
             and np.array_equal(system.col_global // max(system.n_texels, 1), np.repeat(np.arange(3), C1))
             and np.all(system.row_pixel.reshape(3, R1) == system.row_pixel[:R1])
             and np.all(texel.reshape(3, C1) == texel[:C1])
             and np.all(np.diff(E.indptr).reshape(3, R1) == np.diff(E.indptr[: R1 + 1]))
             and np.all(E.indices.reshape(3, n1) - (np.arange(3) * C1)[:, None] == E.indices[:n1]))
    if not alike:
        return _components(E, pi, pj, _grid(system.col_global, system, maps) if len(pi) else None)
    from scipy.sparse import csr_matrix

    first = pi < C1  # smoothness pairs never cross bands
    label, sizes = _components(csr_matrix((E.data[:n1], E.indices[:n1], E.indptr[: R1 + 1]), shape=(R1, C1)),
                               pi[first], pj[first], _grid(system.col_global[:C1], system, maps) if len(pi) else None)
    return np.concatenate([label, label + len(sizes), label + 2 * len(sizes)]), np.tile(sizes, 3)


def _renumber_columns(system: _System, order: np.ndarray) -> np.ndarray:
    """Renumber the system's columns in place, new column ``k`` being old column ``order[k]``:
    E's column indices rewritten a chunk at a time (no second copy of E), ``col_global`` and
    ``prior`` permuted with them. Returns each old column's new number."""
    E = system.E
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    rank_i, ind = rank.astype(E.indices.dtype), E.indices
    for a in range(0, len(ind), CHUNK):
        ind[a:a + CHUNK] = rank_i[ind[a:a + CHUNK]]
    E.has_sorted_indices = False  # and so not canonical: scipy must not trust its cached flags
    system.col_global, system.prior = system.col_global[order], system.prior[order]
    return rank


def _products(E, cols=(), through=()) -> tuple[np.ndarray, np.ndarray]:
    """Column sums of E's squared values and several products with E, all in float64 in one pass
    over E's entries, a block of rows at a time.

    Returns ``(sq, P)``: ``sq`` (C,) the squared column norms, ``P`` (C, m + k) whose columns are
    ``Eᵀ w`` for each (R,) vector ``w`` in ``cols``, then ``Eᵀ(E v)`` for each (C,) vector ``v`` in
    ``through``. A block's ``E v`` is taken and used at once (``Eᵀ(E v)`` sums the blocks'
    ``E_blockᵀ(E_block v)``), so no (R,) product is kept, and E's indices and values are read once
    for every vector instead of twice per vector (the solve's set-up took eight passes over E:
    a 12 MP system's 147 M entries, 1.8 GB each time). The sums run over E's rows in order, as
    ``E.T @ w`` sums them.
    """
    from scipy.sparse import _sparsetools

    (R, C), ptr, ind = E.shape, E.indptr, E.indices
    m, k = len(cols), len(through)
    if ptr.dtype != ind.dtype:  # scipy's kernels take one index type
        return _products_scipy(E, cols, through)
    step = max(1, CHUNK // max(1, E.nnz // max(R, 1)))  # rows of about CHUNK entries
    V = np.ascontiguousarray(np.stack(through, axis=1), dtype=np.float64) if k else None
    out, sq = np.zeros((C, m + k)), np.zeros(C)
    W = np.empty((min(step, R), m + k))
    Y = np.empty((min(step, R), k))
    for a in range(0, R, step):
        b = min(a + step, R)
        n, lo, hi = b - a, int(ptr[a]), int(ptr[b])
        p, j = ptr[a:b + 1] - ptr[a], ind[lo:hi]
        data = E.data[lo:hi].astype(np.float64, copy=False)
        w = W[:n]
        for i, v in enumerate(cols):
            w[:, i] = v[a:b]
        if k:
            y = Y[:n]
            y.fill(0.0)
            _sparsetools.csr_matvecs(n, C, k, p, j, data, V.ravel(), y.ravel())
            w[:, m:] = y
        _sparsetools.csc_matvecs(C, n, m + k, p, j, data, w.ravel(), out.ravel())
        _sparsetools.csc_matvec(C, n, p, j, np.square(data), np.ones(n), sq)
    return sq, out


def _products_scipy(E, cols, through) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_products` by scipy's operators, one vector at a time (E with mixed index types)."""
    ET = E.T
    out = [ET @ np.asarray(v, dtype=np.float64) for v in cols] + [ET @ (E @ np.asarray(v, dtype=np.float64))
                                                                    for v in through]
    sq = np.zeros(E.shape[1])
    for a in range(0, E.nnz, CHUNK):
        sq += np.bincount(E.indices[a:a + CHUNK], weights=np.square(E.data[a:a + CHUNK], dtype=np.float64),
                          minlength=E.shape[1])
    return sq, np.stack(out, axis=1) if out else np.zeros((E.shape[1], 0))


class _Normal:
    """The scaled normal-equation product ``s·Eᵀ(E(s·p)) + d·p + P p`` (``P`` the smoothness pairs),
    written into buffers kept from one iteration to the next.

    Its values are scipy's ``s * (E.T @ (E @ (s * p))) + d * p + P @ p`` bit for bit (the same
    kernels in the same order); only the arrays are reused: at 12 MP a product's row vector is
    144 MB and a column vector 64 MB, and fresh ones every iteration cost their pages' faults
    (system time) each time. The returned array is overwritten by the next call.
    """

    def __init__(self, E, s, d, pairs):
        self.E, self.s, self.d, self.pairs = E, s, d, pairs
        rows, cols = E.shape
        # scipy's kernels with our outputs when the index types agree (else its own products)
        self.kernels = E.indptr.dtype == E.indices.dtype and pairs.indptr.dtype == pairs.indices.dtype
        self.rows, self.c1, self.out = np.empty(rows, E.dtype), np.empty(cols, E.dtype), np.empty(cols, E.dtype)

    def __call__(self, p):
        E, pairs, c1, out = self.E, self.pairs, self.c1, self.out
        if not self.kernels:
            return self.s * (E.T @ (E @ (self.s * p))) + self.d * p + pairs @ p
        from scipy.sparse import _sparsetools

        R, C = E.shape
        np.multiply(self.s, p, out=c1)
        self.rows.fill(0)
        _sparsetools.csr_matvec(R, C, E.indptr, E.indices, E.data, c1, self.rows)  # E (s p)
        c1.fill(0)
        _sparsetools.csc_matvec(C, R, E.indptr, E.indices, E.data, self.rows, c1)  # Eᵀ(...), E's CSC view
        np.multiply(self.s, c1, out=out)
        np.multiply(self.d, p, out=c1)
        out += c1
        c1.fill(0)
        _sparsetools.csr_matvec(C, C, pairs.indptr, pairs.indices, pairs.data, p, c1)
        out += c1
        return out


def _symmetric(pi, pj, vertical, off, n: int):
    """The (n, n) CSR matrix with ``off`` at (pi, pj) and at (pj, pi), as scipy's
    ``coo_matrix(...).tocsr()`` makes it (indices sorted in each row), from a table of each
    column's four neighbours.

    ``(pi, pj)`` are :func:`_smoothness_pairs` (``vertical`` their kind) after the columns were
    renumbered by component: the renumbering keeps the order within a component, and a pair never
    leaves one, so a column's neighbours still come in the order up, left, right, down. Filling
    that (n, 4) table and reading it row by row is the CSR without a sort (coo → csr took 0.9 s of
    the 3 MP set-up: its index checks and conversions, then a counting sort over 4·pairs indices).
    """
    from scipy.sparse import csr_matrix

    idx = np.int32 if max(n, 2 * len(pi)) < 2**31 else np.int64
    table, values = np.full((n, 4), -1, dtype=idx), np.zeros((n, 4), dtype=off.dtype)
    h = ~vertical
    # slots: 0 up, 1 left, 2 right, 3 down (each column's neighbours in increasing column order)
    for slot_i, slot_j, sel in ((2, 1, h), (3, 0, vertical)):
        i, j = pi[sel], pj[sel]
        table[i, slot_i], table[j, slot_j] = j, i
        values[i, slot_i] = values[j, slot_j] = off[sel]
    has = table >= 0
    ptr = np.zeros(n + 1, dtype=idx)
    np.cumsum(np.count_nonzero(has, axis=1), out=ptr[1:])
    out = csr_matrix((values[has], table[has], ptr), shape=(n, n))
    out.has_sorted_indices = True
    return out


def _to_float32(E) -> None:
    """E's values as float32, in place of the float64 ones (the iteration's matrix: one copy of E)."""
    data = np.empty(E.nnz, dtype=np.float32)
    for a in range(0, E.nnz, CHUNK):
        data[a:a + CHUNK] = E.data[a:a + CHUNK]
    E.data = data


def solve(system: _System, maps, options: SolverOptions, task=None, also=None,
          on_guess=None) -> tuple[np.ndarray, dict]:
    """Solve the bounded, regularised system by connected components; returns (z per column, stats).

    Minimises ``|E z − rhs|² + Σ w_j (z_j − kd_j)² + Σ μ_ab (z_a − z_b)²`` within the bounds by
    conjugate gradient on the normal equations ``(EᵀE + L) z = Eᵀ rhs + w kd`` (``L`` the
    smoothness Laplacian plus the prior's diagonal), never formed: each iteration is ``Eᵀ(E p)
    + L p``. Jacobi scaling (unit diagonal), a warm start from each texel's ratio of observed to
    predicted radiance, per-component step sizes and stopping; then up to four active-set rounds
    (violators fixed at their bound, the rest re-solved warm) and a final projection. ``task``
    (:class:`reflab.core.task.Task`, optional) is checked every CG iteration. ``also`` (per row,
    optional): a second right-hand side solved with the same setup, warm from the first's
    solution and to a 10x looser gradient (a perturbed photograph:
    :func:`recover_texture`'s ``perturb``); its solution is ``stats["also"]``. ``on_guess`` ((R,)
    bool, optional; E's entries positive): ``stats["guessed"]`` is then :func:`_guessed_columns`,
    in the renumbered order, taken in the set-up's pass over E.

    The system is changed in place, so that a photograph's E exists once: its columns are
    renumbered component by component (``col_global`` and ``prior`` follow; ``z`` is in that
    order) and its values become float32.
    """

    E, ncol = system.E, system.E.shape[1]
    t0 = time.perf_counter()
    if ncol == 0:
        return np.zeros(0), {"components": 0, "largest_component": 0, "iterations": 0, "active_set_rounds": 0,
                             "solve_s": 0.0}
    pi, pj, vertical = (_smoothness_pairs(system, maps, kind=True) if options.smoothness > 0 else
                        (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, dtype=bool)))
    label, sizes = _band_components(system, maps, pi, pj)
    # Unknowns renumbered component by component: per-component sums become contiguous segments.
    order = np.argsort(label, kind="stable")
    del label
    rank = _renumber_columns(system, order)
    pi, pj = rank[pi], rank[pj]
    del rank
    prior = system.prior

    # Every float64 product the set-up needs, in one pass over E before it turns float32: the
    # column norms, the right-hand sides, the warm start's denominator Eᵀ(E 1) and the stopping
    # level's Eᵀ(E kd); with ``on_guess``, the guessed texels' two sums (E's entries are positive).
    cols = [system.rhs] + ([np.asarray(also, dtype=np.float64)] if also is not None else [])
    if on_guess is not None:
        cols += [np.asarray(on_guess, dtype=np.float64), np.ones(E.shape[0])]
    colnorm2, P = _products(E, cols, [np.ones(ncol), prior])
    del cols
    Etrhs, ETE1, ETEkd = P[:, 0], P[:, -2], P[:, -1]
    guessed = None
    if on_guess is not None:
        guessed = P[:, -4] > 0.5 * P[:, -3]
    # The prior's weight is relative to the data a texel would have if seen directly: a texel seen
    # only through an attenuation a gets (1/a)² times more, so faint reflections and sheets lean
    # on the homogeneous kd instead of making the system ill-conditioned.
    cov, wt = system.coverage[system.col_global], system.weight[system.col_global]
    amp = np.divide(cov, wt, out=np.ones(ncol), where=wt > 0)
    del cov, wt
    prior_w = options.prior * np.maximum(amp, 1.0) ** 2 * colnorm2
    del amp
    # Smoothness rows sqrt(μ c_a c_b) (z_a − z_b): relative to the two texels' data (c² = column norm²).
    mu = options.smoothness * np.sqrt(colnorm2[pi] * colnorm2[pj])
    lap_diag = prior_w + np.bincount(pi, mu, minlength=ncol) + np.bincount(pj, mu, minlength=ncol)
    scale = 1.0 / np.sqrt(np.maximum(colnorm2 + lap_diag, 1e-300))
    del colnorm2
    # Jacobi: unknowns y = z / scale, so that the normal matrix has a unit diagonal; the scaling
    # is applied to the vectors, E keeps its values (one copy of it, not a scaled second one).
    # L's diagonal as a vector, its off-diagonal (the smoothness pairs, both ways) as a matrix.
    diag = lap_diag * scale * scale
    off = -mu * scale[pi] * scale[pj]
    pairs = _symmetric(pi, pj, vertical, off, ncol)
    del off, mu, lap_diag, pi, pj, vertical
    Etrhs = scale * Etrhs
    b = Etrhs + scale * prior_w * prior
    b_also = scale * P[:, 1] + scale * prior_w * prior if also is not None else None
    del prior_w
    # Warm start: each texel's data-weighted ratio of observed to predicted radiance.
    den = scale * ETE1
    ratio = np.divide(Etrhs, den, out=prior.copy(), where=den > 0)
    del den, Etrhs
    lo, hi = options.bounds
    # Stop when the gradient is ``tol`` times its value at the homogeneous kd, per component.
    r0 = b - (scale * ETEkd + diag * (prior / scale) + pairs @ (prior / scale))
    del P, ETE1, ETEkd
    stop = np.add.reduceat(r0 * r0, np.concatenate([[0], np.cumsum(sizes)[:-1]])) * options.tol**2
    g0 = max(float(r0 @ r0), 1e-300)
    del r0
    # The iteration runs in float32 (half the memory traffic of its sparse products), its
    # scalars in float64: the albedo agrees with a float64 run within 5e-5 (RMS 1e-6, measured
    # at 320x240 and 640x480), far below the stopping level's effect.
    F = np.float32
    _to_float32(E)
    apply = _Normal(E, scale.astype(F), diag.astype(F), pairs.astype(F))

    def bounded(b, y, stop, steps):
        """CG, then up to four active-set rounds (violators fixed at their bound, the rest re-solved warm)."""
        free, iters, rounds = None, 0, 0
        for rounds in range(5):
            if task is not None:
                task.step(rounds, 5, f"texture: conjugate gradient, active-set round {rounds + 1}")
            y, it = _cg(apply, b.astype(F), y.astype(F), None if free is None else free.astype(F), sizes, stop,
                        options.max_iter, None if task is None else task.check, steps)
            y = y.astype(np.float64)
            iters += it
            z = y * scale
            viol = ((z < lo) | (z > hi)) & (True if free is None else free > 0)
            if not viol.any():
                break
            y = np.where(viol, np.clip(z, lo, hi) / scale, y)
            free = np.where(viol, 0.0, 1.0) if free is None else np.where(viol, 0.0, free)
        return np.clip(y * scale, lo, hi), iters, rounds

    steps = []  # (perf_counter, squared normal-equation residual) per CG iteration, every round
    solved, iters, rounds = bounded(b, np.clip(ratio, lo, hi) / scale, stop, steps)
    stats = {"components": int(len(sizes)), "largest_component": int(sizes.max()), "iterations": iters,
             "active_set_rounds": rounds, "solve_s": time.perf_counter() - t0,
             # The CG's error against its run time (the report's error-vs-time plot): seconds since
             # the solve began, normal-equation residual relative to the homogeneous kd's (tol's scale).
             "trace": [[round(t - t0, 6), float(np.sqrt(g / g0))] for t, g in steps],
             "trace_quantity": "relative residual"}
    if b_also is not None:
        stats["also"] = bounded(b_also, solved / scale, stop * 100.0, [])[0]
    if guessed is not None:
        stats["guessed"] = guessed
    return solved, stats


def recover_texture(scene, trees, materials, intensities, image, options: SolverOptions | None = None,
                    exclude=None, guess=None, task=None, maps=None, perturb=None) -> TextureSolution:
    """Recover the diffuse texture of every textured surface the trees reach.

    Parameters
    ----------
    scene : reflab.reconstruction.scene.Scene
        Surfaces with meshes; ``textured`` says which get a texture.
    trees : reflab.inverse.forward.trees.Trees
        Trees of the input camera and lights.
    materials : list of Material
        Fixed non-Lambertian parameters (and the homogeneous ``kd``), surface order.
    intensities : (K, 3) array_like
        Light intensities.
    image : (H, W, 3) array_like
        The linear input image (same size as the trees).
    options : SolverOptions, optional
    exclude : (H, W) or (H*W,) bool array_like, optional
        Pixels to leave out (their texels are then known only from other pixels, or not at all).
    guess : (H, W) or (H*W,) bool array_like, optional
        Pixels whose light rests on parameters the fit left undetermined
        (:func:`reflab.inverse.forward.rendering.undetermined_pixels`): a texel that draws most of its weight from
        them is a guess, flagged :data:`GUESSED` (kept: it is the best guess the fit allows).
    task : reflab.core.task.Task, optional
        Progress and cancellation, checked every conjugate-gradient iteration.
    maps : dict, optional
        The texel maps of an earlier call with the same scene, trees and options
        (``TextureSolution.maps``), instead of building them again.
    perturb : (H, W, 3) array_like, optional
        Added to the photograph for a second solve of the same system (noise, to see what the
        texels make of it: :func:`reflab.inverse.fit.texture_aware.deattenuated`); its texels are
        ``TextureSolution.perturbed``.

    Returns
    -------
    TextureSolution
    """
    options = options or SolverOptions()
    options.validate()
    image = np.asarray(image, dtype=np.float64)
    if image.shape != (trees.height, trees.width, 3):
        raise ValueError(f"image: expected shape ({trees.height}, {trees.width}, 3) like the trees, got {image.shape}")
    if not np.all(np.isfinite(image)):
        raise ValueError("image: NaN or inf pixel values")
    t0 = time.perf_counter()
    maps = build_maps(scene, trees, options) if maps is None else maps
    t_maps = time.perf_counter()
    system = build_system(trees, materials, intensities, image, maps, options, exclude)
    return solve_texture(system, maps, materials, options, guess=guess, task=task, perturb=perturb,
                         times=(t0, t_maps, time.perf_counter()))


def _guessed_columns(E, on_guess) -> np.ndarray:
    """(C,) bool: columns of E with more than half their weight (|E|) in the rows ``on_guess``
    ((R,) bool), summed in float64.

    E's entries are positive (a lit node's coefficient times a bilinear weight), so the weights
    are two products with E's transpose (one pass over E each); a chunked sum of ``|E|`` is
    kept for a matrix with negative values.
    """
    R, C = E.shape
    if E.dtype == np.float64 and (E.nnz == 0 or E.data.min() >= 0):
        return E.T @ on_guess.astype(np.float64) > 0.5 * (E.T @ np.ones(R))
    guessed, whole = np.zeros(C), np.zeros(C)
    step = max(1, CHUNK // 4)
    for a in range(0, R, step):
        r1 = min(a + step, R)
        lo, hi = E.indptr[a], E.indptr[r1]
        cols, v = E.indices[lo:hi], np.abs(E.data[lo:hi], dtype=np.float64)
        flag = np.repeat(on_guess[a:r1], np.diff(E.indptr[a:r1 + 1]))
        guessed += np.bincount(cols, weights=np.where(flag, v, 0.0), minlength=C)
        whole += np.bincount(cols, weights=v, minlength=C)
    return guessed > 0.5 * whole


def solve_texture(system: _System, maps, materials, options: SolverOptions, *, guess=None, task=None, perturb=None,
                  times=None) -> TextureSolution:
    """Solve an assembled system (:func:`build_system`, :func:`assemble_system`) into the
    per-surface textures; ``guess``, ``task`` and ``perturb`` as for :func:`recover_texture`,
    ``times`` the (start, maps done, system done) perf_counter instants for the stats."""
    t0, t_maps, t_sys = times if times is not None else (time.perf_counter(),) * 3
    also = None
    if perturb is not None:
        also = system.rhs + np.asarray(perturb, dtype=np.float64).reshape(-1, 3)[system.row_pixel, system.row_band]
    total = system.n_texels
    # Guessed texels need E's float64 values and columns as assembled: before the solve changes them.
    guessed3, on_guess = np.zeros(3 * total, dtype=bool), None
    if guess is not None and system.E.shape[1]:
        on_guess = np.asarray(guess, dtype=bool).reshape(-1)[system.row_pixel]
        if system.E.dtype != np.float64 or system.E.data.min() < 0:  # else the solve's set-up sums them
            guessed3[system.col_global] = _guessed_columns(system.E, on_guess)
            on_guess = None
    z, stats = solve(system, maps, options, task, also=also, on_guess=on_guess)
    z_perturbed = stats.pop("also", None)
    if on_guess is not None:
        guessed3[system.col_global] = stats.pop("guessed")  # col_global in the solve's order
    guessed3 = guessed3.reshape(3, total)

    resid = system.E @ z.astype(system.E.dtype) - system.rhs if len(z) else np.zeros(0)
    count = np.bincount(system.row_band, minlength=3)
    rms = np.sqrt(np.bincount(system.row_band, weights=resid * resid, minlength=3) / np.maximum(count, 1)).tolist()
    # Per-texel arrays as (band, texel) views: each surface is a contiguous slice of texels.
    full = np.full(3 * total, np.nan)
    full[system.col_global] = z
    full_perturbed = None
    if z_perturbed is not None:
        full_perturbed = np.full(3 * total, np.nan)
        full_perturbed[system.col_global] = z_perturbed
        full_perturbed = full_perturbed.reshape(3, total)
    lo, hi = options.bounds
    clipped = np.zeros(3 * total, dtype=bool)
    clipped[system.col_global] = (z <= lo) | (z >= hi)
    known3 = (system.coverage >= options.min_coverage).reshape(3, total)
    weight3, coverage3 = system.weight.reshape(3, total), system.coverage.reshape(3, total)
    full, clipped, saturated3 = full.reshape(3, total), clipped.reshape(3, total), system.saturated_touch.reshape(3, total)

    result = TextureSolution(maps, {}, {}, {}, {}, {}, {})
    column_texel = system.col_global % max(total, 1)
    for s, m in maps.items():
        off, n = system.offsets[s], m.n_texels
        sl = slice(off, off + n)
        # Known, amplified, clipped and guessed texels are columns of the system, saturated ones
        # touch a saturated pixel: the rest keep the defaults. A map can be far larger than what
        # the image sees (a floor under a small view: 1.4 M texels, 56 k known).
        act = saturated3[:, sl].any(axis=0)
        act[column_texel[(column_texel >= off) & (column_texel < off + n)] - off] = True
        act = np.flatnonzero(act)
        kn3, w3 = known3[:, sl][:, act], weight3[:, sl]
        known = kn3.all(axis=0)
        mean = np.asarray(materials[s]["kd"], float)

        def texels(solved):
            """(n, 3) the surface's albedo from one solve: the homogeneous kd where unknown."""
            values = np.nan_to_num(solved[:, sl][:, act], nan=0.0)
            kd = np.empty((n, 3))
            kd[:] = mean
            kd[act] = np.where(known, values, mean[:, None]).T
            return kd

        kd = texels(full)
        if full_perturbed is not None:
            result.perturbed[s] = texels(full_perturbed).reshape(m.height, m.width, 3)
        w3a = w3[:, act]
        amp_act = np.divide(coverage3[:, sl][:, act], w3a, out=np.zeros(w3a.shape), where=kn3 & (w3a > 0))
        amp_act[kn3 & (w3a <= 0)] = np.inf
        amp = np.zeros((n, 3))
        amp[act] = amp_act.T
        flags, mask = np.zeros(n, dtype=np.uint8), np.zeros(n, dtype=bool)
        flags[act] = (np.where((amp_act > options.amplification_limit).any(0) & known, AMPLIFIED, 0)
                      | np.where(saturated3[:, sl][:, act].any(0), SATURATED, 0)
                      | np.where(clipped[:, sl][:, act].any(0) & known, CLIPPED, 0)
                      | np.where(guessed3[:, sl][:, act].any(0) & known, GUESSED, 0))
        mask[act] = known
        shape = (m.height, m.width)
        result.kd[s] = kd.reshape(*shape, 3)
        result.mask[s] = mask.reshape(shape)
        result.weight[s] = w3.T.reshape(*shape, 3)
        result.amplification[s] = amp.reshape(*shape, 3)
        result.flags[s] = flags.reshape(shape)
    stats.update(
        rows=int(system.E.shape[0]), unknowns=int(system.E.shape[1]), nonzeros=int(system.E.nnz),
        residual_rms=rms, saturated_values=system.n_saturated,
        texels_known=int(sum(int(v.sum()) for v in result.mask.values())),
        texels_amplified=int(sum(int(np.count_nonzero(f & AMPLIFIED)) for f in result.flags.values())),
        texels_clipped=int(sum(int(np.count_nonzero(f & CLIPPED)) for f in result.flags.values())),
        texels_guessed=int(sum(int(np.count_nonzero(f & GUESSED)) for f in result.flags.values())),
        maps_s=t_maps - t0, system_s=t_sys - t_maps, total_s=time.perf_counter() - t0,
    )
    result.stats = stats
    return result


# ---------------------------------------------------------------------- files
def write_textures(workspace, scene, result: TextureSolution, extra: dict | None = None) -> list:
    """Write textures/<surface>.exr, _mask.png, _diag.exr (and _uv.npy for UV atlases), then
    textures/index.json last, so the index never names a missing file. Returns the paths."""
    from reflab.core.images import write_image

    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    jobs, entries = [], []
    for s, m in result.maps.items():
        name = scene[s].name
        files = {"kd": f"{name}.exr", "mask": f"{name}_mask.png", "diag": f"{name}_diag.exr"}
        jobs.append(lambda s=s, path=ws.textures / files["kd"]: write_image(path, result.kd[s]))
        jobs.append(lambda s=s, path=ws.textures / files["mask"]: write_image(path, result.mask[s].astype(np.float32)))
        jobs.append(lambda s=s, path=ws.textures / files["diag"]: write_image(path, np.stack(
            [result.weight[s].min(axis=2), result.amplification[s].max(axis=2), result.flags[s].astype(np.float32)],
            axis=2)))
        if m.kind == "uvatlas":
            files["uv"] = f"{name}_uv.npy"
            jobs.append(lambda m=m, path=ws.textures / files["uv"]: _write_npy(path, m.tri_uv.astype(np.float64)))
        entry = m.to_json()
        entry.update(files=files, texels_known=int(result.mask[s].sum()),
                     texels_amplified=int(np.count_nonzero(result.flags[s] & AMPLIFIED)),
                     texels_guessed=int(np.count_nonzero(result.flags[s] & GUESSED)))
        entries.append(entry)
    written = _in_threads(jobs)  # a failed write raises here, before index.json could name its file
    index = {"surfaces": entries, "stats": result.stats, **(extra or {})}
    written.append(write_json(ws.texture_index, index))
    return written


def _write_npy(path, array):
    """``array`` to ``path`` (.npy), atomically; returns the path."""
    with atomic_write(path, "wb") as f:
        np.save(f, array)
    return path


def load_texture_maps(workspace, scene) -> dict[int, tuple[TexelMap, np.ndarray, np.ndarray]]:
    """Read textures/index.json: surface index -> (map, kd (H, W, 3), mask (H, W) bool)."""
    from reflab.core.images import read_image

    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    path = ws.require(ws.texture_index, "reflab texture")
    index = read_json(path)
    items = index.get("surfaces")
    if not isinstance(items, list):
        raise WorkspaceError(path, "surfaces", "a list of texture entries", got=items)
    out = {}
    for i, item in enumerate(items):
        where = f"surfaces[{i}]"
        if not isinstance(item, dict) or item.get("surface") not in scene.names:
            raise WorkspaceError(path, f"{where}.surface", f"one of the scene's surfaces {scene.names}", got=item.get("surface") if isinstance(item, dict) else item)
        s = scene.index(item["surface"])
        files = item.get("files", {})
        tri_uv = None
        if item.get("kind") == "uvatlas":
            uv_path = ws.textures / str(files.get("uv", ""))
            if not uv_path.is_file():
                raise WorkspaceError(path, f"{where}.files.uv", "an existing .npy of per-corner texel coordinates", got=str(uv_path))
            tri_uv = np.load(uv_path, allow_pickle=False)
        m = TexelMap.from_json(item, s, scene[s].mesh, path, where, tri_uv)
        kd = read_image(ws.textures / str(files.get("kd", "")))
        mask = read_image(ws.textures / str(files.get("mask", "")))[:, :, 0] > 0.5
        if kd.shape[:2] != (m.height, m.width) or mask.shape != (m.height, m.width):
            raise WorkspaceError(path, f"{where}.files", f"images of {m.height}x{m.width} texels", got=[kd.shape, mask.shape])
        out[s] = (m, kd.astype(np.float64), mask)
    return out


def sample_texture(texel_map: TexelMap, kd: np.ndarray, mask: np.ndarray, triangle, barycentric) -> np.ndarray:
    """Albedo (N, 3) at points on one surface (triangle and Open3D barycentric coordinates).

    Bilinear over the known texels, weights renormalised over them; NaN where the known texels
    carry less than half the weight (beyond what the input saw).
    """
    idx, w = texel_map.bilinear(triangle, barycentric)
    w = w * mask.ravel()[idx]
    wsum = w.sum(axis=1)
    val = np.einsum("nj,njc->nc", w, kd.reshape(-1, 3)[idx]) / np.maximum(wsum, 1e-300)[:, None]
    return np.where((wsum >= 0.5)[:, None], val, np.nan)


def albedo_nodes(workspace, scene, trees, textures=None) -> np.ndarray:
    """Recovered diffuse albedo (N, 3) at every tree node; NaN where it is unknown.

    Textured surfaces: bilinear blend of their known texels (weights renormalised over the known
    ones; NaN when the known ones carry less than half the weight, e.g. beyond the region the
    input saw). Untextured surfaces: their homogeneous ``kd`` (fit.json, else scene.json).
    Textured surfaces that the texture stage never saw: NaN. ``textures``: the workspace's
    :func:`load_texture_maps`, when the caller has read them already.
    """
    textures = load_texture_maps(workspace, scene) if textures is None else textures
    materials, _ = load_materials(workspace, scene)
    out = np.full((len(trees), 3), np.nan)
    for s, surf in enumerate(scene):
        sel = np.nonzero(trees.surface == s)[0]
        if len(sel) == 0:
            continue
        if not surf.textured:
            out[sel] = materials[s]["kd"]
        elif s in textures:
            out[sel] = sample_texture(*textures[s], trees.triangle[sel], trees.barycentric[sel])
    return out


def guessed_flags(workspace, scene, textures=None) -> dict:
    """Surface index -> (H, W, 3) float64, 1 on the texels the texture stage flagged
    :data:`GUESSED` (read from each diagnostics image once; :func:`guessed_nodes` samples it)."""
    from reflab.core.images import read_image

    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    entries = {item.get("surface"): item for item in read_json(ws.texture_index).get("surfaces", [])
               if isinstance(item, dict)}
    out = {}
    for s in (load_texture_maps(ws, scene) if textures is None else textures):
        diag = ws.textures / str(entries[scene[s].name].get("files", {}).get("diag", ""))
        if diag.is_file():
            flag = (read_image(diag)[:, :, 2].astype(np.int64) & GUESSED) > 0
            out[s] = np.repeat(flag[:, :, None], 3, axis=2).astype(np.float64)
    return out


def guessed_nodes(workspace, scene, trees, textures=None, flags=None) -> np.ndarray:
    """(N,) bool: nodes on texels the texture stage flagged :data:`GUESSED` (bilinear weight ≥ ½);
    ``textures`` as for :func:`albedo_nodes`, ``flags`` :func:`guessed_flags` when the caller
    has read them already (a render tile by tile)."""
    textures = load_texture_maps(workspace, scene) if textures is None else textures
    flags = guessed_flags(workspace, scene, textures) if flags is None else flags
    out = np.zeros(len(trees), dtype=bool)
    for s, (m, _, mask) in textures.items():
        sel = np.nonzero(trees.surface == s)[0]
        if s not in flags or len(sel) == 0:
            continue
        value = sample_texture(m, flags[s], mask, trees.triangle[sel], trees.barycentric[sel])[:, 0]
        out[sel] = np.nan_to_num(value, nan=0.0) >= 0.5
    return out
