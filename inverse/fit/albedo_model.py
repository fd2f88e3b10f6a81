"""Which albedo model a surface declared textured gets: one colour, a few inks, or a free texture (issue 35).

A surface marked ``textured`` in scene.json gets a free albedo per texel in the texture rounds
(:mod:`reflab.inverse.fit.texture_aware`), which absorbs any light seen only on its pixels: its
own lobe and reflection are then reported undetermined, even when its photograph shows one
colour (or a few inks) under a white highlight and the colours would determine them. Here the
photograph decides. After the homogeneous fit, on every pixel where the diffuse light of one
directly seen textured surface carries almost all the predicted light (the pixels the texture
rounds recover texture from), the albedo that pixel implies is

    a = kd + (image − model) / E,    its noise σ / E,

``E`` the light per unit albedo there (path product × the diffuse basis) and ``σ`` the
photograph's noise per band: the smallest of the fit's image-wide estimate (fit.json's
``noise``), the one measured on those very pixels from the second differences of their albedos
(:func:`_local_noise`) and the same measured on the fit's residual inside untextured surfaces.
Texture inflates each, each elsewhere: the image-wide one counts a fine texture anywhere in view
as noise (twice the true σ on two_textured at 80×60, which called its two-ink box uniform), the
local one the surface's own fine print (shiny_box at 80×60: 1.9×). Models of those albedos are
compared by the Bayesian information criterion, ``χ² + k ln n`` (``n`` the pixel values, ``k``
the free parameters):

- **uniform**: one colour (3 parameters);
- **texture**: a free colour per block of ``b × b`` pixels (3 per block), for each block size of
  :data:`SCALES` (a texel of the rounds is :data:`~reflab.inverse.fit.texture_aware.TEXEL_SCALE`
  = 2 pixel footprints across; coarser blocks see smooth textures whose contrast per texel is
  under the noise); the best of them;
- **palette**: 2 … 4 inks, a Gaussian mixture with a mix of two inks allowed per pixel at its
  price (:mod:`reflab.inverse.fit.palette`), chosen only when its inks hold: misfit at the
  noise, white residuals, sharp edges.

The start's lobe is the one the free texture left: where it took the highlight (ks 0), a
one-colour surface's albedos carry that highlight and look textured. A surface called texture is
therefore judged again under the lobe and reflection one colour gives it (:func:`uniform_lobes`),
and is uniform if it is so there; its refit starts from that lobe.

A surface whose uniform model has the lower BIC is fitted as homogeneous (its kd a free
parameter, its lobe and reflection fitted with the rest, every σ from every pixel); a palette
likewise, its kd a gain on its inks (:func:`select`); the user's flag still rules the texture
stage. Nothing here is tuned but the palette's share of mixed edge pixels
(:data:`~reflab.inverse.fit.palette.SHARP`): a texture whose contrast stays within the noise over every block
size is called uniform, and the misfit it leaves counts in the robust σ
(:mod:`reflab.inverse.fit.uncertainty`) like any other. Pixels on a surface's outline are left
out: an edge pixel's mix of two surfaces is no albedo.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from reflab.inverse.fit.palette import best_mixture, sharp, white

#: Block sizes (pixels across) of the free-texture alternatives.
SCALES = (2, 4, 8)
#: Second differences needed to measure the noise on a surface's pixels (fewer: nothing judged).
MIN_DOF = 30
#: A pixel counts when directly seen textured diffuse light carries at least this share of its
#: predicted light in every band (the texture rounds' :data:`~reflab.inverse.fit.texture_aware.MIN_SHARE`).
MIN_SHARE = 0.9
#: Palette passes: the inks estimated under the current lobe, then the fit on them.
PASSES = 2
#: Whether a surface may be fitted as a palette of inks. Off by default: on the zoo at 640x480
#: (seed 4) a three-ink print with soft edges passed every test as four inks, and its lobe came
#: out confidently wrong (ks 4.18 ± 0.014 for 4.05, ns 85.2 ± 0.7 for 89.4; docs/fit.md).
PALETTES = False


@dataclass
class AlbedoEvidence:
    """What the photograph says of one textured surface's albedo (:func:`albedo_evidence`)."""

    #: ``"uniform"`` or ``"texture"``.
    model: str
    #: Pixels that informed it (seen directly, diffuse-lit, inside the outline).
    pixels: int
    #: χ² of the one-colour model over those pixels and the three bands.
    chi2_uniform: float
    #: χ² of the best free-texture model, its block size (pixels) and its number of blocks.
    chi2_texture: float
    block: int
    blocks: int
    #: BIC(uniform) − BIC(texture): negative selects uniform.
    delta_bic: float
    #: The one colour (weighted mean albedo per band).
    colour: list
    #: The noise σ per band used: the smaller of the fit's and the one measured here (:func:`_local_noise`).
    noise: list
    #: The best palette of 2 … :data:`~reflab.inverse.fit.palette.MAX_INKS` inks
    #: (:func:`reflab.inverse.fit.palette.best_mixture`), None when too few pixels.
    palette: object = None
    #: BIC(palette) − the lower of BIC(uniform) and BIC(texture): negative selects palette.
    delta_bic_palette: float = float("nan")
    #: The surface's lobe the albedos were judged under: ``"fitted"`` (the homogeneous fit's, with
    #: the declared flags) or ``"one colour"`` (its own lobe and reflection fitted to the pixels as
    #: one colour, :func:`uniform_lobes`).
    lobe: str = "fitted"

    def to_json(self) -> dict:
        out = {"model": self.model, "pixels": self.pixels, "chi2_uniform": round(self.chi2_uniform, 3),
               "chi2_texture": round(self.chi2_texture, 3), "block_px": self.block, "blocks": self.blocks,
               "delta_bic": round(self.delta_bic, 3), "colour": [round(float(v), 6) for v in self.colour],
               "noise": [float(v) for v in self.noise], "lobe": self.lobe}
        if self.palette is not None:
            m = self.palette
            out.update({"chi2_palette": round(float(m.cost), 3), "delta_bic_palette": round(self.delta_bic_palette, 3),
                        "inks": [[round(float(v), 6) for v in ink] for ink in m.inks],
                        "inks_sigma": [[float(f"{v:.4g}") for v in s] for s in m.sigma],
                        "ink_pixels": [int(v) for v in m.pixels], "mixed_pixels": int(np.sum(m.labels < 0)),
                        "ink_misfit": round(float(m.misfit), 4)})
        return out


def _pixel_albedo(trees, materials, intensities, image, textured, mask, min_share, relative=None, other=False):
    """Per pixel of a textured surface seen directly inside its outline: its index, its surface,
    the albedo it implies, that albedo's weight E², whether diffuse light carries ``min_share`` of
    it (``clean``: judged), and the noise σ per band measured on untextured surfaces' residual
    (None: too few pixels). ``relative`` (N, 3): a palette's albedo per node over its surface's kd
    (NaN: 1). ``other``: also the light the model adds to the pixel's diffuse term, per unit albedo
    (its highlight, reflections), whose height the start's fit may have wrong."""
    from reflab.inverse.forward.rendering import accumulate, linear_basis, node_radiance, path_products

    npix = trees.width * trees.height
    img = np.asarray(image, dtype=np.float64).reshape(npix, 3)
    basis = linear_basis(trees, materials, intensities)
    kd_nodes = None
    if relative is not None:
        kd_nodes = np.stack([np.broadcast_to(m["kd"], (3,)) for m in materials]).astype(np.float64)[trees.surface]
        kd_nodes = kd_nodes * np.where(np.isfinite(relative), relative, 1.0)
    model = accumulate(trees, node_radiance(trees, materials, intensities, kd_nodes=kd_nodes, basis=basis))
    model = model.reshape(npix, 3)
    coef = path_products(trees, materials) * basis[:, :, 0]  # light per unit albedo (kd in slot 0)
    level1 = np.asarray(trees.level) == 1
    first = np.full(npix, -1, dtype=np.int64)  # the surface each pixel sees directly
    first[trees.pixel[level1]] = trees.surface[level1]
    many = np.bincount(trees.pixel[level1], minlength=npix) != 1
    first[many] = -1
    on = level1 & np.asarray(textured, dtype=bool)[trees.surface]
    E = np.zeros((npix, 3))
    np.add.at(E, trees.pixel[on], coef[on])
    kd = np.stack([np.broadcast_to(m["kd"], (3,)) for m in materials]).astype(np.float64)
    surf = np.where(first >= 0, first, 0)
    kd_pixel = kd[surf]
    if kd_nodes is not None:  # a palette pixel's own ink
        kd_pixel = kd_pixel.copy()
        kd_pixel[trees.pixel[level1 & ~many[trees.pixel]]] = kd_nodes[level1 & ~many[trees.pixel]]
    diffuse = E * kd_pixel
    ok = (first >= 0) & np.asarray(textured, dtype=bool)[surf] & np.all(E > 0, axis=1)
    clean = np.all(diffuse >= min_share * np.maximum(model, 1e-300), axis=1)
    if mask is not None:
        ok &= np.asarray(mask, dtype=bool).reshape(npix)
    # Inside the outline: the four neighbours see the same surface directly.
    grid = first.reshape(trees.height, trees.width)
    inner = np.zeros_like(grid, dtype=bool)
    inner[1:-1, 1:-1] = ((grid[1:-1, 1:-1] == grid[:-2, 1:-1]) & (grid[1:-1, 1:-1] == grid[2:, 1:-1])
                         & (grid[1:-1, 1:-1] == grid[1:-1, :-2]) & (grid[1:-1, 1:-1] == grid[1:-1, 2:]))
    ok &= inner.reshape(npix)
    px = np.flatnonzero(ok)
    albedo = kd_pixel[px] + (img[px] - model[px]) / E[px]
    # The noise where the model needs no albedo: inside untextured surfaces seen directly.
    plain = inner.reshape(npix) & (first >= 0) & ~np.asarray(textured, dtype=bool)[surf]
    if mask is not None:
        plain &= np.asarray(mask, dtype=bool).reshape(npix)
    q = np.flatnonzero(plain)
    sigma = _local_noise(q, img[q] - model[q], np.ones((len(q), 3)), trees.width, trees.height)
    if not other:
        return px, first[px], albedo, E[px] ** 2, clean[px], sigma
    return px, first[px], albedo, E[px] ** 2, clean[px], sigma, (model[px] - diffuse[px]) / E[px]


def _rss(a, w, groups) -> np.ndarray:
    """(3,) weighted squared residual per band of a free colour per group (weighted means)."""
    _, g = np.unique(groups, return_inverse=True)
    out = np.empty(3)
    for c in range(3):
        sw = np.bincount(g, weights=w[:, c])
        mean = np.bincount(g, weights=w[:, c] * a[:, c]) / np.maximum(sw, 1e-300)
        out[c] = np.sum(w[:, c] * (a[:, c] - mean[g]) ** 2)
    return out


def _local_noise(px, a, e, width, height) -> np.ndarray | None:
    """(3,) the pixel noise σ per band from the second differences of the albedos ``a`` along
    rows and columns (pixels ``px``, light per unit albedo ``e``): ``a(x−1) − 2a(x) + a(x+1)``
    scaled by ``e`` has variance 6σ² and no trace of a texture's gradients; the median absolute
    value (× 1.4826) is blind to the few that straddle an ink's edge. None with fewer than
    :data:`MIN_DOF` differences."""
    grid = np.full((width * height, 3), np.nan)
    grid[px] = a
    x = px % width
    diffs = []
    for step, inside in ((1, (x > 0) & (x < width - 1)), (width, (px >= width) & (px < width * (height - 1)))):
        p = px[inside]
        d = (grid[p - step] - 2 * grid[p] + grid[p + step]) * e[inside]
        diffs.append(d[np.all(np.isfinite(d), axis=1)])
    d = np.concatenate(diffs)
    if len(d) < MIN_DOF:
        return None
    return 1.4826 * np.median(np.abs(d), axis=0) / np.sqrt(6.0)


def albedo_evidence(trees, materials, intensities, image, textured, noise=None, *, mask=None,
                    min_share: float = MIN_SHARE, palettes: bool | None = None) -> dict:
    """Per textured surface seen directly: uniform, palette or texture, by BIC (see the module docstring).

    Parameters
    ----------
    trees : reflab.inverse.forward.trees.Trees
    materials : list of Material
        The homogeneous fit's (its ``kd`` is each surface's mean albedo).
    intensities : (K, 3) array_like
    image : (H, W, 3) array_like
    textured : (S,) bool array_like
        The surfaces declared textured.
    noise : (3,) array_like, optional
        The fit's image-wide noise σ per band (``stats["noise"]``): the noise used is the smaller
        of it and the one measured on the surface (:func:`_local_noise`), both of which a texture
        can only inflate.
    mask : (H*W,) bool, optional
        Pixels the fit may use.
    min_share : float
        A pixel counts when directly seen textured diffuse light carries at least this share of
        its predicted light in every band.
    palettes : bool, optional
        Also weigh a palette of a few inks (:mod:`reflab.inverse.fit.palette`); default
        :data:`PALETTES`.

    Returns
    -------
    dict
        Surface index → :class:`AlbedoEvidence`, for each textured surface with a usable pixel.
    """
    px, surf, albedo, e2, clean, plain = _pixel_albedo(trees, materials, intensities, image, textured, mask, min_share)
    px, surf, albedo, e2 = px[clean], surf[clean], albedo[clean], e2[clean]
    x, y = px % trees.width, px // trees.width
    out = {}
    for s in np.unique(surf):
        sel = surf == s
        a, w = albedo[sel], e2[sel]  # w: a pixel value's error over its albedo's, squared
        n = a.size  # pixel values: three per pixel
        colour = [float(v) for v in (w * a).sum(axis=0) / np.maximum(w.sum(axis=0), 1e-300)]
        rss = {b: _rss(a, w, (y[sel] // b) * (trees.width // b + 1) + x[sel] // b) for b in SCALES}
        blocks = {b: len(np.unique((y[sel] // b) * (trees.width // b + 1) + x[sel] // b)) for b in SCALES}
        uniform = _rss(a, w, np.zeros(len(a), dtype=np.int64))
        sigma = _local_noise(px[sel], a, np.sqrt(w), trees.width, trees.height)
        if sigma is None:  # too few pixels to measure the noise: the user's flag stands
            out[int(s)] = AlbedoEvidence("texture", int(sel.sum()), float("nan"), float("nan"), 0, 0, float("nan"),
                                         colour, [float("nan")] * 3)
            continue
        if noise is not None:
            sigma = np.fmin(sigma, np.asarray(noise, dtype=np.float64).reshape(3))
        if plain is not None:
            sigma = np.fmin(sigma, plain)
        var = np.maximum(sigma ** 2, 1e-300)
        chi2_u = float(np.sum(uniform / var))
        bic = {b: float(np.sum(rss[b] / var)) + 3 * blocks[b] * np.log(n) for b in SCALES if blocks[b] > 1}
        b = min(bic, key=bic.get)
        bic_u = chi2_u + 3 * np.log(n)
        delta = bic_u - bic[b]
        inks = best_mixture(a, w / var, n) if (PALETTES if palettes is None else palettes) else None
        delta_p = inks.bic(n) - min(bic_u, bic[b]) if inks is not None else float("nan")
        held_ = (inks is not None and inks.at_noise() and white(px[sel], a, w / var, inks, trees.width, trees.height)
                 and sharp(px[sel], a, w / var, inks, trees.width, trees.height))
        model = "palette" if delta_p < 0 and held_ else "uniform" if delta < 0 else "texture"
        out[int(s)] = AlbedoEvidence(model, int(sel.sum()), chi2_u, float(np.sum(rss[b] / var)), b, blocks[b],
                                     float(delta), colour, [float(v) for v in np.sqrt(var)], inks, float(delta_p))
    return out


def uniform_lobes(trees, materials, intensities, image, textured, noise, *, mask=None, held=None) -> dict:
    """Each declared textured surface's grey lobe and own reflection fitted to its pixels with its
    albedo one colour: what the uniform model's lobe would be.

    The homogeneous fit with a surface declared textured lets its free texture take its highlight
    (its ks then 0, or the prior's guess): judged under that lobe, a one-colour surface's albedos
    carry the highlight it missed and look textured (zoo seed 5's one-ink box, noise-free: χ² of
    one colour 5e7 per value, 3.0 under its true lobe). This is the dichromatic objective of
    :mod:`reflab.inverse.fit.dichromatic` with a colour set of one point: per shape θ the colour,
    the own r and ks solved linearly, θ by a scan in log2 then Brent.

    Parameters
    ----------
    trees, materials, intensities, image, textured, mask
        As :func:`albedo_evidence` takes them.
    noise : (3,) array_like
        The photograph's noise σ per band (whitens the bands).
    held : list of set of str, optional
        Names the user gave: a surface whose ks or shape they gave is left out; one whose r they
        gave keeps it.

    Returns
    -------
    dict
        Surface index → its Material with ``kd``, ``ks``, the shape and (unless given) ``r`` so
        fitted, for each textured Phong or Ward surface with enough directly seen lit pixels.
    """
    from reflab.inverse.fit.dichromatic import MIN_LIT, MIN_PIXELS, _estimate, _Objective, _Pixels, lobed_textured
    from reflab.inverse.fit.problem import NOISE_FLOOR
    from reflab.inverse.fit.ranges import FIT_RANGE
    from reflab.reconstruction.scene import SCALAR_RANGE

    image = np.asarray(image, dtype=np.float64)
    scale = np.maximum(np.asarray(noise, dtype=np.float64).reshape(3), NOISE_FLOOR * max(float(image.max()), 1e-300))
    # Every pixel that sees one surface directly, also where it mirrors a textured one (the
    # colour lobes leave those out): the evidence judges them, and their reflection is this r's
    # (zoo seed 5's box mirrors its textured ground at r 0.05, on its dim faces 40 % of the light).
    level1 = np.asarray(trees.level) == 1
    single = np.bincount(trees.pixel[level1], minlength=trees.width * trees.height) == 1
    if mask is not None:
        single &= np.asarray(mask, dtype=bool).reshape(-1)
    out = {}
    for s, model, shape, given in lobed_textured(materials, textured, held):
        nodes = np.flatnonzero(level1 & (np.asarray(trees.surface) == s))
        nodes = nodes[single[trees.pixel[nodes]]]
        px = trees.pixel[nodes]
        if len(nodes) < MIN_PIXELS:
            continue
        parts = _Pixels(trees, materials, intensities, image, s, nodes, px, model.linear.index("ks"), "r" not in given)
        seen = np.all(parts.e > 0, axis=1)
        lit = seen & np.all(parts.e > MIN_LIT * np.median(parts.e, axis=0), axis=1)
        if lit.sum() < MIN_PIXELS:
            continue
        lo, hi = FIT_RANGE.get(shape, SCALAR_RANGE.get(shape))
        lo, hi = max(lo, 1e-3), (min(hi, 2.0**12) if shape == "ns" else hi)
        # The lobe from the lit pixels, as the colour lobes take it; then the colour and r at that
        # lobe from the dim ones too, which show the reflection best: fitted with the lobe there,
        # the reflected texture (at its mean in the model) moved it (seed 5's box: ks 0.39 for 0.98).
        obj = _Objective(parts, np.zeros((3, 0)), scale, lit)
        theta, _ = _estimate(obj, lo, hi)
        ks = obj.solve(theta)[2]
        obj = _Objective(parts, np.zeros((3, 0)), scale, seen)
        g = obj.P(parts.lobe(theta, obj.rows) * obj.sw).ravel()
        nuisances = obj.pinv @ (obj.U.T @ (obj.y - ks * g))
        params = dict(materials[s].params)
        params["kd"] = np.clip(nuisances[:3], 0.0, 1.0)
        params["ks"] = np.full(np.shape(params["ks"]), ks) if np.ndim(params["ks"]) else float(ks)
        params[shape] = float(theta)
        if parts.h is not None and "r" in params:
            params["r"] = np.clip(nuisances[3:6], 0.0, 1.0)
        out[int(s)] = dataclasses.replace(materials[s], params=params)
    return out


def _off_bounds(materials, initial, bounds) -> list:
    """``materials`` with each value listed in ``bounds`` (per surface ``{"ks[0]": "lower"}``,
    :func:`reflab.inverse.fit.ranges.at_bound`) set back to its value in ``initial``."""
    out = list(materials)
    for i, found in enumerate(bounds or []):
        params = dict(out[i].params)
        for label in found:
            name, _, band = label.partition("[")
            if name not in params or name not in initial[i].params:
                continue
            start = np.broadcast_to(np.asarray(initial[i][name], dtype=np.float64), np.shape(params[name]))
            if band:
                value = np.array(params[name], dtype=np.float64)
                value[int(band.rstrip("]"))] = start[int(band.rstrip("]"))]
                params[name] = value
            else:
                params[name] = start.copy() if np.ndim(start) else float(start)
        out[i] = dataclasses.replace(out[i], params=params)
    return out


def _palette(trees, materials, intensities, image, declared, inks: dict, noise: dict, mask, min_share,
             previous=None):
    """The palette surfaces' inks estimated again and every node labelled (:mod:`reflab.inverse.fit.palette`).

    ``inks``: surface → :class:`~reflab.inverse.fit.palette.Mixture` (the starting inks);
    ``noise``: surface → σ per band; ``previous``: the palette the ``materials`` were fitted
    with, whose judged pixels (lit diffusely under the start's model) judge the inks again.
    Returns the :class:`~reflab.inverse.fit.palette.Palette` and the new inks.
    """
    from reflab.inverse.fit.palette import Palette, boundary, chi2_along, mix_chi2, mixture, mixture_costs, node_weights

    npix = trees.width * trees.height
    relative = None if previous is None else previous.relative
    px, surf, albedo, e2, clean, _, other = _pixel_albedo(trees, materials, intensities, image, declared, mask,
                                                          min_share, relative, other=True)
    judged_all = np.zeros(npix, dtype=bool)
    out = np.full((len(trees.pixel), 3), np.nan)
    node_weights_ = {}
    leave = np.zeros(npix, dtype=bool)
    found, whites = {}, {}
    for s, m in inks.items():
        sel = surf == s
        a, q, judged = albedo[sel], e2[sel] / np.maximum(np.asarray(noise[s]) ** 2, 1e-300), clean[sel]
        if previous is not None:  # judged where the start's model lit them diffusely (the evidence's pixels)
            judged = previous.judged[px[sel]]
        penalty = np.log(max(3 * int(judged.sum()), 2))
        m = mixture(a[judged], q[judged], m.count, penalty, inks=m.inks) or m
        cost, resp = mixture_costs(a, q, m.inks, m.weights)
        share = np.eye(m.count)[np.argmax(resp, axis=1)]
        # Under a highlight (or a reflection) the implied albedo is off along the light the model
        # adds there, by as much as its height is wrong: the ink is the one nearest along that
        # line. Where no ink is nearer than the rest by the penalty (inks alike), the pixel's
        # albedo is their mean under its posterior.
        lit = ~judged
        along = chi2_along(a[lit], q[lit], m.inks, other[sel][lit])
        post = np.log(np.maximum(m.weights, 1e-300))[None, :] - 0.5 * along
        post = np.exp(post - post.max(axis=1, keepdims=True))
        post /= post.sum(axis=1, keepdims=True)
        best = np.sort(along, axis=1)
        sure = np.ones(len(a), dtype=bool)
        sure[lit] = best[:, 1] - best[:, 0] >= penalty
        share[lit] = np.where(sure[lit][:, None], np.eye(m.count)[np.argmax(post, axis=1)], post)
        labels = np.where(sure, np.argmax(share, axis=1), -1)
        # A diffuse-lit pixel that a mix of two inks explains better is an ink's edge; under a
        # highlight the lobe (the start's fitted against one colour) is not trusted to tell: there
        # a surely labelled pixel is left out where a surely labelled neighbour's label differs.
        mixed = cost > mix_chi2(a, q, m.inks) + penalty
        off = np.where(judged, mixed, sure & boundary(px[sel], labels, trees.width, trees.height))
        if previous is not None:
            # Under the fitted lobe every kept pixel's albedo is its ink's: the inks from all of them.
            m = dataclasses.replace(m, inks=m.inks.copy())
            for k in range(m.count):
                on_k = ~off & sure & (labels == k)
                if on_k.any():
                    m.inks[k] = (q[on_k] * a[on_k]).sum(axis=0) / np.maximum(q[on_k].sum(axis=0), 1e-300)
        judged_all[px[sel][judged]] = True
        leave[px[sel][off]] = True
        node, more = node_weights(trees, s, px[sel][~off], share[~off], sure[~off], leave)
        leave |= more
        whites[s] = (white(px[sel][judged], a[judged], q[judged], m, trees.width, trees.height)
                     and sharp(px[sel][judged], a[judged], q[judged], m, trees.width, trees.height))
        kd_ref = (m.pixels @ m.inks) / max(int(m.pixels.sum()), 1)
        on = np.flatnonzero(np.asarray(trees.surface) == s)
        node[leave[trees.pixel[on]]] = 0.0
        out[on] = np.where(node.sum(axis=1, keepdims=True) > 0, (node @ m.inks) / np.maximum(kd_ref, 1e-6), 1.0)
        node_weights_[s] = (node, on)
        found[s] = m
    return Palette(out, leave, {s: (m.inks, (m.pixels @ m.inks) / max(int(m.pixels.sum()), 1), m.sigma, m.pixels)
                                for s, m in found.items()}, whites, judged_all, node_weights_), found


def _with_kd(materials, palette) -> list:
    """``materials`` with each palette surface's kd at its inks' mean (the palette's reference)."""
    out = list(materials)
    for s, (_, kd_ref, _, _) in palette.inks.items():
        out[s] = dataclasses.replace(out[s], params=dict(out[s].params) | {"kd": np.asarray(kd_ref, dtype=np.float64)})
    return out


def _continued(start, again):
    """``again`` (a refit) with ``start``'s trace, time and counts before its own and its outliers beside them."""
    rejected = start.stats.get("rejected", {"count": 0, "pixels": []})
    more = again.stats.get("rejected", {"count": 0, "pixels": []})
    pixels = list(rejected["pixels"]) + list(more["pixels"])
    stats = {**again.stats, "rejected": {**rejected, **more, "count": len(pixels), "pixels": pixels}}
    if "complete" in again.stats:
        def complete(done=again.stats["complete"]):
            full = done()
            return dataclasses.replace(full, stats={**full.stats, "rejected": stats["rejected"]})
        stats["complete"] = complete
    return dataclasses.replace(again, stats=stats, trace=start.trace + [[start.time_s + t, r] for t, r in again.trace],
                               time_s=start.time_s + again.time_s, evaluations=start.evaluations + again.evaluations,
                               iterations=start.iterations + again.iterations)


def _refit(trees, scene, models, intensities, image, start, found, models_of, *, mask, method, maxiter, max_seconds,
           task, held, min_share, starts=None):
    """:func:`select`'s refit with each surface's albedo model ``models_of`` (surface → model):
    (scene, fit, palette or None); None when none is uniform or a palette; the list of palette
    surfaces whose inks, estimated again after the first fit, are no longer at the noise (or lost
    an ink): the caller gives them their texture and tries again. ``starts``: surface → the
    Material its uniform model starts from (:func:`uniform_lobes`), where the evidence was judged
    under it."""
    from reflab.inverse.forward.factorization import Factorization
    from reflab.inverse.fit.rounds import fit
    from reflab.reconstruction.scene import Scene

    declared = np.array([s.textured for s in scene], dtype=bool)
    plain = [s for s, m in models_of.items() if m in ("uniform", "palette")]
    if not plain:
        return None
    inks = {s: e.palette for s, e in found.items() if models_of[s] == "palette"}
    noise = {s: np.asarray(e.noise, dtype=np.float64) for s, e in found.items()}
    textured = declared.copy()
    textured[plain] = False
    scene = Scene([dataclasses.replace(s, textured=bool(t)) for s, t in zip(scene, textured)], scene.root)
    last = not np.isin(trees.surface, np.flatnonzero(textured)).any()
    # From the start's values, without the global scan (the flags change which pixels judge
    # what, not the objective: its shininesses are in their basins), but those it fitted onto a
    # bound from the scene's starting values, where a fit from scratch would hold them if the
    # refit finds them unresolved.
    materials = _off_bounds(start.materials, [s.material for s in scene], start.stats.get("at_bound"))
    # A surface judged under its one-colour lobe starts there: the start's lobe was the texture's.
    materials = [(starts or {}).get(i, m) if models_of.get(i) == "uniform" else m for i, m in enumerate(materials)]
    if inks:
        # The start fitted a palette surface's own r and t against one colour, so they carry its
        # inks' variation (texture_aware.without_own_paths): the palette's fit starts them at 0.
        given = held or [set() for _ in materials]
        materials = [dataclasses.replace(m, params=dict(m.params) | {n: np.zeros(3) for n in ("r", "t")
                                                                       if n in m.params and n not in given[i]})
                     if i in inks else m for i, m in enumerate(materials)]
    palette, again, passes = None, start, PASSES if inks else 1
    for k in range(passes):
        final = k == passes - 1
        if inks:  # the inks under the current lobe, each pixel's label, then the fit on them
            palette, inks = _palette(trees, materials, intensities, image, declared, inks, noise, mask, min_share,
                                     palette)
            failed = [s for s, m in inks.items() if not (m.at_noise() and np.all(m.pixels > 0) and palette.white[s])]
            if failed:
                return failed
            materials = _with_kd(materials, palette)
        fac = Factorization(trees, models, intensities, mask=mask if palette is None else mask & ~palette.leave_out,
                            albedo=None if palette is None else palette.relative)
        kw = dict(textured=list(textured), names=scene.names, scan=False, maxiter=maxiter, task=task, held=held,
                  reject=False, uncertainty=False, nuisance=None if palette is None else palette.nuisance)
        left = None if max_seconds is None else max(max_seconds - (again.time_s - start.time_s), 1e-3)
        # What the start found without signal or held stays so on the surfaces whose light the
        # changed flags do not touch (their holding rounds would find it again); the changed ones,
        # and those seen in the same pixels (a mirror showing one), start anew.
        touched = _sharing(trees, plain)
        structure, still = _anew(fac, start.structure, touched), _anew(fac, start.free, touched)
        if k:
            structure, still = again.structure, again.free
        again = _continued(again, fit(fac, image, materials, method, max_seconds=left, structure=structure,
                                      still_held=still, **kw))
        if final and not again.message.startswith("stopped"):
            # The start's outliers are out already; those the refit's flags no longer excuse (a
            # surface's diffuse light is no longer free texture) go in one pass, and the refit
            # from there keeps what it held (its holding rounds would find it again).
            bad = _outliers(fac, image, again, textured)
            if len(bad):
                left = None if max_seconds is None else max(max_seconds - (again.time_s - start.time_s), 1e-3)
                more = fit(fac.without(bad), image, again.materials, method, max_seconds=left,
                           **kw | dict(structure=again.structure, still_held=again.free))
                again = _continued(_rejected(again, bad, trees.width), more)
        if final and last:  # no texture round follows: the σ now
            done = again.stats["complete"]()
            again = dataclasses.replace(done, trace=again.trace, time_s=again.time_s, evaluations=again.evaluations,
                                        iterations=again.iterations)
        materials = again.materials
    return scene, again, palette


def _sharing(trees, surfaces) -> list:
    """``surfaces`` and every surface with a node in a pixel where one of them has one."""
    on = np.isin(trees.surface, surfaces)
    hit = np.zeros(trees.width * trees.height, dtype=bool)
    hit[trees.pixel[on]] = True
    return sorted(set(int(v) for v in np.unique(trees.surface[hit[trees.pixel]])) | set(int(v) for v in surfaces))


def _anew(fac, free, surfaces):
    """``free`` (a :class:`~reflab.inverse.fit.problem.Free`) with every parameter of ``surfaces``
    free where the system has a column for it (their r and t where some path meets them)."""
    out = free.copy()
    lay = fac.layout
    for s in surfaces:
        out.x[lay.x_offset[s]:lay.x_offset[s + 1]] = True
        out.theta[lay.theta_offset[s]:lay.theta_offset[s + 1]] = True
        for f in (2 * s, 2 * s + 1):
            out.s[f] = bool(fac.exponents[:, f].any())
    return out


def _outliers(fac, image, result, textured) -> np.ndarray:
    """Flat pixel indices the refit ``result`` calls outliers (:func:`reflab.inverse.fit.diagnosis.outliers`),
    none when more than :data:`~reflab.inverse.fit.diagnosis.REJECT_SHARE` of the pixels (a misfit, not outliers)."""
    from reflab.inverse.fit.diagnosis import REJECT_SHARE, outliers
    from reflab.inverse.fit.problem import Problem

    pb = Problem(fac, image, [m.transparent for m in result.materials])
    A = fac.matrices(result.params.theta)
    bad = outliers(pb, result.params, A, pb.residual(A, fac.y(result.params.x, result.params.s)), textured)
    return bad if len(bad) <= REJECT_SHARE * fac.n_rows else np.zeros(0, dtype=np.int64)


def _rejected(result, bad, width: int):
    """``result`` with the flat pixels ``bad`` listed among its rejected outliers (as [x, y])."""
    from reflab.inverse.fit.diagnosis import REJECT_SIGMAS

    rejected = result.stats.get("rejected", {"count": 0, "pixels": []})
    pixels = list(rejected["pixels"]) + [[int(i % width), int(i // width)] for i in bad]
    return dataclasses.replace(result, stats={**result.stats, "rejected": {**rejected, "count": len(pixels),
                                                                           "pixels": pixels,
                                                                           "threshold_sigmas": REJECT_SIGMAS}})


def select(trees, scene, models, intensities, image, start, *, mask, method, maxiter=None, max_seconds=None,
           task=None, held=None, min_share: float = MIN_SHARE):
    """The texture rounds' start with the surfaces the photograph shows uniform or in a few inks
    fitted as such.

    Parameters
    ----------
    trees, scene, models, intensities, image
        As :func:`reflab.inverse.fit.texture_aware.fit_with_texture` takes them; each surface's
        ``material`` holds the fit's starting values.
    start : FitSolution
        The homogeneous fit with the declared ``textured`` flags.
    mask : (H*W,) bool
        Pixels the rounds may use (the start's outliers left out).
    min_share : float
        As :func:`albedo_evidence` takes it (the rounds' own).
    method, maxiter, max_seconds, task, held
        For the refit; its σ is computed at once when no textured surface is left in view (no
        texture round follows), else later (``stats["complete"]``).

    Returns
    -------
    scene : Scene
        ``scene`` with those surfaces' ``textured`` False (itself when none).
    start : FitSolution
        The homogeneous fit again with those flags (a palette surface's kd a gain on its inks),
        from ``start``'s values (those on a bound of their range from the scene's starting values);
        ``start`` when none. Its trace, time and counts continue ``start``'s.
    evidence : dict
        Surface name → :meth:`AlbedoEvidence.to_json`, per textured surface judged; a palette's
        ``inks`` and ``inks_sigma`` those of the refit.
    palette : reflab.inverse.fit.palette.Palette or None
        The palette surfaces' albedo per node and the pixels they leave out, which the texture
        rounds keep (None: no palette).
    """
    declared = np.array([s.textured for s in scene], dtype=bool)
    if not declared.any():
        return scene, start, {}, None
    noise = start.stats.get("noise")
    found = albedo_evidence(trees, start.materials, intensities, image, declared, noise, mask=mask,
                            min_share=min_share)
    starts = {}
    if noise is not None and any(e.model == "texture" for e in found.values()):
        # Judged under the lobe the free texture left (it took the highlight), a one-colour surface
        # looks textured: judged again under the lobe one colour gives it, uniform if it then is so.
        lobes = uniform_lobes(trees, start.materials, intensities, image, declared, noise, mask=mask, held=held)
        lobes = {s: m for s, m in lobes.items() if s in found and found[s].model == "texture"}
        if lobes:
            materials = [lobes.get(i, m) for i, m in enumerate(start.materials)]
            again = albedo_evidence(trees, materials, intensities, image, declared, noise, mask=mask,
                                    min_share=min_share, palettes=False)
            for s in lobes:
                if s in again and again[s].model == "uniform":
                    found[s] = dataclasses.replace(again[s], lobe="one colour")
                    starts[s] = lobes[s]
    evidence = {scene.names[s]: e.to_json() for s, e in found.items()}
    models_of = {s: e.model for s, e in found.items()}
    while True:
        done = _refit(trees, scene, models, intensities, image, start, found, models_of, mask=mask, method=method,
                      maxiter=maxiter, max_seconds=max_seconds, task=task, held=held, min_share=min_share,
                      starts=starts)
        if not isinstance(done, list):
            break
        for s in done:  # inks that do not hold under the fitted lobe: a free texture after all
            models_of[s] = "texture"
            evidence[scene.names[s]].update(model="texture", palette_held=False)
    if done is None:
        return scene, start, evidence, None
    scene, again, palette = done
    if palette is not None:
        for s, (ink, kd_ref, sig, _) in palette.inks.items():
            kd = np.asarray(again.materials[s]["kd"], dtype=np.float64)
            gain = kd / np.maximum(kd_ref, 1e-12)
            # Each ink's σ: its estimate's, and the gain's (kd's σ) where the refit has it already.
            j = sum(len(m.linear) for m in models[:s]) + models[s].linear.index("kd")
            rel = np.asarray(again.sigma.x[j], dtype=np.float64) / np.maximum(kd, 1e-12)
            rel = np.where(np.isfinite(rel), rel, 0.0)
            inks_sig = np.sqrt((sig * gain) ** 2 + (ink * gain * rel) ** 2)
            nodes = palette.weights[s][1]
            evidence[scene.names[s]].update({"inks": [[round(float(v), 6) for v in c * gain] for c in ink],
                                             "inks_sigma": [[float(f"{v:.4g}") for v in c] for c in inks_sig],
                                             "ink_pixels": [int(v) for v in palette.inks[s][3]],
                                             "left_out": int(len(np.unique(trees.pixel[nodes][palette.leave_out[
                                                 trees.pixel[nodes]]])))})
    return scene, again, evidence, palette


def annotate(report: dict) -> dict:
    """fit.json's ``albedo_models`` (surface name → evidence) moved to each surface's
    ``albedo_model`` (the model) and ``albedo_evidence`` (the statistic); ``report`` itself."""
    for item in report.get("surfaces", []):
        found = (report.get("albedo_models") or {}).get(item["name"])
        if found:
            item["albedo_model"] = found["model"]
            item["albedo_evidence"] = {k: v for k, v in found.items() if k != "model"}
    report.pop("albedo_models", None)
    return report
