"""A textured surface's own lobe from colour: the dichromatic reflection model (docs/fit.md).

A free texture takes up a highlight seen once pixel for pixel: three bands, three albedos, one
pixel. But a textured dielectric (print, laminate, glaze) reflects its highlight at the surface,
before the light meets the pigment, so the highlight has the lamp's colour (the neutral interface,
Shafer's dichromatic model; the lamps' colour is in the intensities, so ks is one grey height);
and a texture printed or dyed with few colourants has its albedo on a **line** (two inks) or a
**plane** (three) in RGB. Where the lamp's colour is off that set, the part of each pixel off it
is the lobe's alone, which one photograph then determines — thousands of pixels for two numbers,
ks and the shininess, each pixel's position along the set free.

Per textured surface with a grey lobe of one shape parameter (Phong ns, Ward α):

1. the pixels where it is seen directly and alone among textured surfaces; the rest of the
   model's light (other surfaces, reflections) subtracted at the fitted values;
2. the texture's colour set: principal axes of the lobe-free albedo ``(I − ks g) / e``, a line if
   it leaves no more than the photograph's noise off it (or the fit's residual, and not much more
   than a plane leaves), else a plane; else none (a full-colour texture gives no handle, and the
   lobe stays undetermined);
3. the profiled objective: per pixel the albedo ``μ + D w`` (w free, μ shared), projected off
   ``e∘D``; linear in (μ, own r, ks) for each θ, ks within its plausible range; a scan over
   log θ (on a pixel subsample, then walked down the full objective), then Brent;
4. the σ of ks and θ from the Gauss–Newton normal matrix of that objective, the larger of the
   model's and the cluster-robust sandwich over image tiles (as :mod:`reflab.inverse.fit.uncertainty`).

What would fool it: a texture whose colours are on a line everywhere but under the highlight, or
a highlight whose colour lies in the texture's set (the demo's box: purple and lilac inks whose
plane holds white): the σ then says undetermined.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from reflab.inverse.forward.models import get_model
from reflab.inverse.fit.problem import NOISE_FLOOR
from reflab.inverse.fit.ranges import FIT_RANGE, ks_upper
from reflab.inverse.forward.rendering import basis_on, linear_basis, model_geometry, node_geometry, node_radiance, path_products
from reflab.inverse.fit.uncertainty import robust_sd, tile_index

#: A colour set is accepted when its misfit per degree of freedom is at most this many times what
#: the photograph's noise (or the fit's residual, if larger) gives.
SET_TOLERANCE = 2.0
#: Pixels whose albedo basis is under this share of the surface's median are left out (grazing,
#: shadowed: their albedo estimate is noise).
MIN_LIT = 0.2
#: A pixel off the colour set by more than this many σ (its projected residual) is an outlier
#: (an edge, a speck) and left out of the second pass.
OUTLIER_SIGMAS = 5.0
#: Fewest pixels for an estimate.
MIN_PIXELS = 50
#: Most passes of colour set then lobe (a start far off leaves its colour in the first set).
PASSES = 5
#: Scan step in log2 of the shape parameter.
SCAN_STEP = 0.5
#: Most pixels the scan evaluates (it finds where to start; the search and refinement use every pixel).
SCAN_PIXELS = 2000


@dataclass
class ColourLobe:
    """One textured surface's lobe from colour (see the module docstring).

    ``ks`` grey; ``theta`` the model's shape parameter ``shape`` (natural units); ``sigma_ks`` and
    ``sigma_theta`` their one-sigma (natural units); ``dims`` 1 (line) or 2 (plane): the texture's
    colour set; ``pixels`` used, ``rejected`` left out as outliers; ``misfit`` per degree of
    freedom over the reference noise (1 when the set and the lobe explain the pixels to the noise).
    """

    surface: int
    shape: str
    ks: float
    theta: float
    sigma_ks: float
    sigma_theta: float
    dims: int
    pixels: int
    rejected: int
    misfit: float

    def resolved(self) -> bool:
        """Both known to half their value (θ in log2: a factor 1.41)."""
        return bool(self.ks > 0 and self.sigma_ks <= 0.5 * self.ks
                    and self.sigma_theta <= 0.5 * np.log(2.0) * self.theta)

    def to_json(self) -> dict:
        return {"ks": round(self.ks, 6), "sigma_ks": _finite(self.sigma_ks), self.shape: round(self.theta, 6),
                f"sigma_{self.shape}": _finite(self.sigma_theta), "colour_set": ("line", "plane")[self.dims - 1],
                "pixels": self.pixels, "rejected": self.rejected, "misfit": round(self.misfit, 3)}


def _finite(v: float):
    return round(float(v), 6) if np.isfinite(v) else None


def lobed_textured(materials, textured, held=None):
    """``(s, model, shape, given)`` for each textured surface whose model has ks and one shape
    parameter, neither of them given by the user (``held[s]``: the names held)."""
    for s in np.flatnonzero(np.asarray(textured, dtype=bool)):
        model = get_model(materials[s].brdf)
        if "ks" not in model.linear or model.n_nonlinear != 1:
            continue
        shape = model.nonlinear[0]
        given = set() if held is None else set(held[s])
        if not {"ks", shape} & given:
            yield int(s), model, shape, given


def _direct_pixels(trees, s: int, textured, mask) -> tuple[np.ndarray, np.ndarray]:
    """Nodes of surface ``s`` seen directly whose pixel has no other textured node, and their pixels."""
    tex = np.asarray(textured, dtype=bool)[trees.surface]
    npix = trees.width * trees.height
    n_tex = np.bincount(trees.pixel[tex], minlength=npix)
    nodes = np.flatnonzero((np.asarray(trees.surface) == s) & (np.asarray(trees.level) == 1))
    px = trees.pixel[nodes]
    ok = (n_tex[px] == 1) & (True if mask is None else np.asarray(mask, dtype=bool).reshape(-1)[px])
    return nodes[ok], px[ok]


class _Pixels:
    """The model's parts at one surface's directly seen pixels, for any θ of that surface."""

    def __init__(self, trees, materials, intensities, image, s, nodes, px, j, reflects: bool):
        self.j = j  # the lobe's linear slot
        npix = trees.width * trees.height

        def per_pixel(light, sel=slice(None)):
            return np.stack([np.bincount(trees.pixel[sel], weights=light[sel, c], minlength=npix) for c in range(3)], axis=1)[px]

        basis = linear_basis(trees, materials, intensities)
        light = node_radiance(trees, materials, intensities, basis=basis)
        # The surface's own reflection (what it mirrors, per unit r): a nuisance solved with the
        # lobe, since a misfitted r lands on the same pixels (tile_mirror: r 0.02 for 0 moved ks
        # 0.15 -> 0.10). Nodes whose path starts with a reflection at s.
        first = np.array([len(p) > 0 and p[0][0] == s and not p[0][1] for p in trees.paths], dtype=bool)[trees.path]
        self.h = None
        rest = np.ones(len(light), dtype=bool)
        rest[nodes] = False
        if reflects and first.any():
            mats = list(materials)
            mats[s] = dataclasses.replace(mats[s], params=dict(mats[s].params) | {"r": np.ones(3)})
            self.h = per_pixel(node_radiance(trees, mats, intensities, basis=basis), first)
            rest &= ~first
        self.pp = path_products(trees, materials)[nodes]
        # What the rest of the model puts in these pixels (other surfaces, the lamps).
        self.r = np.asarray(image, dtype=np.float64).reshape(-1, 3)[px] - per_pixel(light, rest)
        self.e = self.pp * basis[nodes, :, 0]
        # The model evaluated on these nodes alone (as rendering.linear_basis does on all of them):
        # the scan asks for dozens of θ, and the whole trees' basis is 20 MB at 640x480.
        self.model = get_model(materials[s].brdf)
        self.geometry = model_geometry(self.model, node_geometry(trees, nodes))  # its θ-independent terms once
        self.intensities = np.asarray(intensities, dtype=np.float64).reshape(trees.n_lights, 3)

    def lobe(self, theta: float, rows=None) -> np.ndarray:
        """(m, 3) the lobe's image per unit ks at shape ``theta`` (at ``rows`` of them: a
        :meth:`geometry_at` tuple)."""
        rows, geometry = (slice(None), self.geometry) if rows is None else rows
        return self.pp[rows] * basis_on(self.model, [theta], geometry, self.intensities)[:, :, self.j]

    def geometry_at(self, keep: np.ndarray) -> tuple:
        """(rows, their node geometry) of the pixels ``keep`` (bool (m,)), for :meth:`lobe`."""
        terms, weight = self.geometry
        k = weight.shape[1]
        at = (np.flatnonzero(keep)[:, None] * k + np.arange(k)).ravel()
        return keep, (tuple(t[at] for t in terms), weight[keep])


def _colour_set(albedo: np.ndarray, dims: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean (3,) and the ``dims`` principal directions (3, dims) of albedo samples (m, 3)."""
    mu = albedo.mean(axis=0)
    _, V = np.linalg.eigh(np.cov((albedo - mu).T))
    return mu, V[:, ::-1][:, :dims]


class _Objective:
    """The profiled objective of one colour set: per pixel ``w`` out, (μ, ks) solved, θ given."""

    def __init__(self, px: _Pixels, D: np.ndarray, scale: np.ndarray, keep: np.ndarray):
        self.px, self.keep, self.rows = px, keep, px.geometry_at(keep)
        self._args, self._coarse = (D, scale), None
        self.sw = 1.0 / scale  # whitening per band
        M = (px.e[keep] * self.sw)[:, :, None] * D[None]  # (m, 3, k): each pixel's albedo directions
        self.Q = np.linalg.qr(M)[0]
        self.cols = [self.P(px.e[keep] * self.sw * np.eye(3)[c]) for c in range(3)]  # μ per band
        if px.h is not None:  # and the surface's own r per band
            self.cols += [self.P(px.h[keep] * self.sw * np.eye(3)[c]) for c in range(3)]
        # Degrees of freedom: each pixel's bands off the set, less the nuisances and ks.
        self.dof = max(int(keep.sum()) * (3 - D.shape[1]) - len(self.cols) - 1, 1)
        # The nuisance columns do not depend on θ: an orthonormal basis of their span (SVD, rank
        # deficiency dropped) is formed once, and each θ needs only its lobe's column projected
        # off it. Stable where the normal equations are not (the columns are near collinear).
        self.y = self.P(px.r[keep] * self.sw).ravel()
        U, S, Vt = np.linalg.svd(np.stack([c.ravel() for c in self.cols], axis=1), full_matrices=False)
        rank = S > S[0] * 1e-10 if S.size and S[0] > 0 else np.zeros(S.shape, dtype=bool)
        self.U, self.pinv = U[:, rank], Vt[rank].T / S[rank]  # columns' pseudo-inverse = pinv @ U.T
        self.y_off = self.y - self.U @ (self.U.T @ self.y)

    def coarse(self) -> "_Objective":
        """The objective on at most :data:`SCAN_PIXELS` of its pixels (evenly taken): the scan
        only finds where to start the full objective's search."""
        idx = np.flatnonzero(self.keep)
        if len(idx) <= SCAN_PIXELS:
            return self
        if self._coarse is None:
            sub = np.zeros_like(self.keep)
            sub[idx[:: -(-len(idx) // SCAN_PIXELS)]] = True
            self._coarse = _Objective(self.px, *self._args, sub)
        return self._coarse

    def P(self, v: np.ndarray) -> np.ndarray:
        """Project (m, 3) whitened vectors off each pixel's albedo directions."""
        return v - np.einsum("mik,mk->mi", self.Q, np.einsum("mik,mi->mk", self.Q, v))

    def solve(self, theta: float):
        """(objective, nuisances (μ, r), ks, residual (m, 3), lobe column (m, 3)) at ``theta``; ks
        within its plausible range."""
        g = self.P(self.px.lobe(theta, self.rows) * self.sw).ravel()
        g_off = g - self.U @ (self.U.T @ g)
        gg = float(g_off @ g_off)
        # No lobe: ks at its bound 0; one beyond the plausible range (ranges.py) at that bound:
        # where the lobe's column lies almost in the set (a white highlight on inks whose plane
        # holds white) least squares would take any ks, 4.6e9 on the demo's box.
        ks = min(max(float(g_off @ self.y_off) / gg, 0.0), ks_upper(self.px.model, theta)) if gg > 0 else 0.0
        f = self.y_off - ks * g_off
        nuisances = self.pinv @ (self.U.T @ (self.y - ks * g))
        return float(f @ f), nuisances, ks, f.reshape(-1, 3), g.reshape(-1, 3)


def _estimate(obj: _Objective, lo: float, hi: float, near: float | None = None) -> tuple[float, float]:
    """(θ, objective) minimising the profiled objective: a scan in log2 θ (only within one step
    of ``near``, the last pass's θ, when given) on :meth:`_Objective.coarse`, the full objective
    walked down the grid from its minimum, then Brent between that point's neighbours."""
    grid = np.arange(np.log2(lo), np.log2(hi) + 1e-9, SCAN_STEP)
    if near is not None:
        grid = np.clip(np.log2(near) + SCAN_STEP * np.arange(-2, 3), np.log2(lo), np.log2(hi))
    coarse = obj.coarse()
    # The subsample's minimum can sit a step or two off the full objective's (the lobe's
    # information is in the few highlight pixels): walk down the full objective from it.
    i, at = _walk(obj, grid, int(np.argmin([coarse.solve(2.0**u)[0] for u in grid])))
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    if b - a <= 0:
        return 2.0 ** grid[i], at
    best = minimize_scalar(lambda u: obj.solve(2.0**u)[0], bounds=(a, b), method="bounded", options={"xatol": 1e-3})
    return (2.0 ** float(best.x), float(best.fun)) if best.fun <= at else (2.0 ** grid[i], at)


def _walk(obj: _Objective, grid: np.ndarray, i: int) -> tuple[int, float]:
    """(index, objective) of the full objective's local minimum on the log2 ``grid``, walked
    down from index ``i``."""
    full = {}
    while True:
        for j in (i - 1, i, i + 1):
            if 0 <= j < len(grid) and j not in full:
                full[j] = obj.solve(2.0 ** grid[j])[0]
        j = min((j for j in (i - 1, i, i + 1) if j in full), key=full.get)
        if j == i:
            return i, full[i]
        i = j


def _sigmas(obj: _Objective, theta: float, rows: np.ndarray, width: int, height: int,
            blocks=None) -> tuple[float, float, float, float]:
    """(ks, σ ks, σ θ, misfit per dof) at the estimate: Gauss–Newton in (μ, r, ks, log2 θ), robust."""
    val, _, ks, f, g = obj.solve(theta)
    h = 0.01
    g_up, g_dn = obj.solve(theta * 2**h)[4], obj.solve(theta * 2**-h)[4]
    dg = (g_up - g_dn) / (2 * h)  # d lobe / d log2 θ, projected
    J = np.stack([c.reshape(-1, 3) for c in obj.cols] + [g, ks * dg], axis=2)  # (m, 3, n)
    n = J.shape[2]
    misfit = val / max(obj.dof - 1, 1)  # θ fitted as well
    Jf = J.reshape(-1, n)
    H = Jf.T @ Jf / max(misfit, 1.0)  # whitened; the misfit, if above the noise, scales the model's σ
    per_pixel = np.einsum("mij,mi->jm", J, f) / max(misfit, 1.0)
    tile, n_tiles = tile_index(rows, width, height)
    scores = np.zeros((n, n_tiles))
    np.add.at(scores.T, tile, per_pixel.T)
    sd = robust_sd(H, scores, rows, width, height, blocks)
    return ks, float(sd[-2]), float(sd[-1] * theta * np.log(2.0)), float(misfit)


def colour_lobes(trees, materials, intensities, image, textured, noise, *, mask=None, held=None,
                 rms=None) -> dict:
    """Each textured surface's grey lobe where its texture's colours identify it.

    Parameters
    ----------
    trees : reflab.inverse.forward.trees.Trees
    materials : list of Material
        The fitted materials (the rest of the model is subtracted at these values).
    intensities : (K, 3) array_like
    image : (H, W, 3) array_like
    textured : (S,) bool
    noise : (3,) array_like
        The photograph's noise σ per band (the fit's estimate).
    mask : (H*W,) bool, optional
        Pixels that may be used (the fit's).
    held : list of set of str, optional
        Names the user gave: a surface whose ks or shape they gave is left alone.
    rms : (3,) array_like, optional
        The fit's residual RMS per band: the colour set is judged against the larger of it and the
        noise (a noise-free photograph still differs from the model by its rendering).

    Returns
    -------
    dict
        Surface index → :class:`ColourLobe`, for every textured Phong or Ward surface with a
        colour set and at least :data:`MIN_PIXELS` pixels (resolved or not: see
        :meth:`ColourLobe.resolved`).
    """
    from reflab.reconstruction.scene import SCALAR_RANGE

    image = np.asarray(image, dtype=np.float64)
    peak = max(float(image.max()), 1e-300)
    scale = np.maximum(np.asarray(noise, dtype=np.float64), NOISE_FLOOR * peak)
    # What the set is judged against: the noise, or the fit's residual where the model differs
    # from the photograph by more (a noise-free photograph still differs by its rendering).
    ref = 1.0 if rms is None else max(1.0, float(np.mean((np.asarray(rms, dtype=np.float64) / scale) ** 2)))
    out = {}
    for s, model, shape, given in lobed_textured(materials, textured, held):
        nodes, px = _direct_pixels(trees, s, textured, mask)
        if len(nodes) < MIN_PIXELS:
            continue
        parts = _Pixels(trees, materials, intensities, image, s, nodes, px, model.linear.index("ks"), "r" not in given)
        lit = np.all(parts.e > MIN_LIT * np.median(parts.e, axis=0), axis=1)
        if lit.sum() < MIN_PIXELS:
            continue
        lo, hi = FIT_RANGE.get(shape, SCALAR_RANGE.get(shape))
        lo, hi = max(lo, 1e-3), (min(hi, 2.0**12) if shape == "ns" else hi)
        start = (float(np.mean(materials[s]["ks"])), float(materials[s][shape]))
        # A line when it explains the pixels to the noise, or to the fit's residual and about as well
        # as a plane; else a plane when it does; else the texture has more colours than that. The
        # fit's residual alone let a three-ink box through as a line (zoo seed 6, noise-free: misfit
        # 3.5e4 against a residual of 2.2e4; ks 5.47 ± 0.13 for 5.12; the plane: 5.1163 ± 0.0003).
        obj, theta, keep, misfit = _fit_set(parts, lit, 1, *start, scale, lo, hi)
        if misfit > SET_TOLERANCE:
            plane = _fit_set(parts, lit, 2, *start, scale, lo, hi)
            if misfit > SET_TOLERANCE * max(plane[3], 1.0) or misfit > SET_TOLERANCE * ref:
                obj, theta, keep, misfit = plane
        if misfit > SET_TOLERANCE * ref:
            continue
        ks, sk, st, misfit = _sigmas(obj, theta, px[keep], trees.width, trees.height,
                                     trees.stats.get("block_row0") if isinstance(trees.stats, dict) else None)
        out[int(s)] = ColourLobe(int(s), shape, ks, theta, sk, st, obj.Q.shape[2], int(keep.sum()),
                                 int(lit.sum() - keep.sum()), misfit)
    return out


def _fit_set(parts: _Pixels, lit, dims: int, ks: float, theta: float, scale, lo: float, hi: float):
    """(objective, θ, pixels kept, misfit per dof) of one colour-set size: the set from the
    albedo under the current lobe, then the lobe, then again (outliers out) until θ settles."""
    keep = lit.copy()
    for it in range(PASSES):
        before = theta
        lobe = ks * parts.lobe(theta)
        albedo = (parts.r - lobe) / np.maximum(parts.e, 1e-300)
        # The set from the half of the pixels the current lobe touches least: a lobe guessed wrong
        # leaves its colour in the albedo, and a plane fitted through it would hold the lobe.
        share = lobe.sum(axis=1) / np.maximum(np.abs(parts.r).sum(axis=1), 1e-300)
        quiet = keep & (share <= np.median(share[keep]))
        _, D = _colour_set(albedo[quiet], dims)
        obj = _Objective(parts, D, scale, keep)
        theta, _ = _estimate(obj, lo, hi, near=theta if it > 1 else None)  # after two global scans
        val, _, ks, f, _ = obj.solve(theta)
        off = np.sum(f * f, axis=1) / max(val / obj.dof, 1.0)
        outlier = np.zeros_like(keep)
        outlier[np.flatnonzero(keep)] = off > OUTLIER_SIGMAS**2 * (3 - dims)
        keep = keep & ~outlier
        if it and abs(np.log2(theta / before)) < 1e-3:
            break
    obj = _Objective(parts, D, scale, keep)
    return obj, theta, keep, obj.solve(theta)[0] / obj.dof
