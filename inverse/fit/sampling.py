"""Which pixels the fit reads: the evidence of every parameter, and a share of the rest (docs/fit.md "Sampling").

The fit has a few dozen unknowns and a photograph has hundreds of thousands of pixels, most of
them lit diffusely: each adds little to what the others already say of a surface's ``kd``, while
a highlight, a mirror's or a glass' pixels, the few that hold a lobe's or a reflection's
information, are rare. So the fit reads

1. a **pilot**: a uniform random sample of :data:`PILOT` of the budget, fitted as the homogeneous start;
2. then **the evidence and a share of the bulk**: under the pilot's parameters (undetermined
   lobes at their plausible value), each term that is not the diffuse light of a directly seen
   surface — a surface's lobe, a reflected or transmitted path, in any photograph — spreads its
   information over the pixels as its light squared; a pixel weighs its largest share of one
   term's, and pixels are drawn by that weight (:data:`EVIDENCE` of the budget, the strongest all
   kept), then a uniform random sample of the others (:data:`BULK` of it).

Each pixel read is weighed by 1 / its probability to be drawn (:func:`inclusion`, :func:`weights`;
Horvitz–Thompson): the fit's normal equations, sums over the pixels read, then estimate those over
every usable pixel without bias, whether or not the model is right. Unweighted, a draw that
favours the evidence pulls an imperfect model's estimate toward what the favoured pixels prefer,
and σ does not hold that pull (docs/fit.md, "Sampling"). Every σ is computed from the rows read
and their weights, so it is the honest σ of the estimate actually made. The sample is seeded (the
same photograph gives the same fit).
"""
from __future__ import annotations

import numpy as np

from reflab.inverse.forward.trees import seen_first

#: Pixels the fit reads at most, by default (``reflab fit --pixels``, :class:`reflab.inverse.stages.FitOptions`'
#: default is this number): above it, it samples.
PIXELS = 85_000
#: The fit reads every usable pixel up to this many (all photographs together; ``reflab fit
#: --sample-above``, in megapixels) and samples only above: about twice the budget, where reading
#: a sample starts to pay (a 640x480 photograph is sampled, a 320x240 one is read whole).
SAMPLE_ABOVE = 200_000
#: Of that budget: the pilot's share (uniform), the evidence's (drawn by information) and the
#: bulk's (uniform, beside the evidence).
PILOT, EVIDENCE, BULK = 15 / 85, 45 / 85, 25 / 85
#: Over several photographs, the budget (pilot, evidence and bulk) grows by this share of itself per
#: further photograph (:func:`budget`). A textured lobe shows in how a texel's pixels in
#: several photographs differ, and a texel counts once two of its pixels are read: a sample of
#: 85 000 of the lab's seven 320x240 photographs (16 %) left its box's highlight on texels read
#: once, the rounds' fit left those pixels out and the lobe stayed undetermined at ns 4 for 30;
#: 170 000 gave ks 0.249 ± 0.015, ns 30.4 ± 1.8 (0.25 / 30) in 10 s. A larger pilot mattered:
#: the evidence and bulk grown alone left the lobe at ns 2.8. Half rather than a sixth: where the
#: fit samples, its values are noise-limited by the sample (docs/fit.md, "Sampling").
PER_FURTHER = 1 / 2
#: The sampling's seed.
SEED = 0
#: Pixels per surface at most for an estimate that weighs its pixels alike (:func:`even`).
EVEN = 5_000
#: A further photograph of a sampled fit of several has its trees built only for about this share of
#: the budget ``pixels`` of its usable pixels (:func:`tiles`; 76 500 of the default budget: a
#: quarter of 640x480), the reference photograph for all: the sample reads 3–4 % of those.
FURTHER = 0.9
#: ... when that is at most this share of its pixels: above, the primary rays cast to draw the colour
#: lobes' sample and the evidence left out of the share cost more than the trees saved (the demo's
#: seven 480x360 photographs, a share of 0.45: 14.7 s of CPU against 14.2 s whole, the mirror's ks σ 1.3x).
MAX_SHARE = 1 / 3
#: ... in square tiles of this side (uniformly drawn): the image noise's 3×3 windows fit inside.
TILE = 4
#: Shapes at which a lobe the pilot left undetermined is looked for: where a broad, a glossy or a
#: sharp lobe would show (its shininess unknown, its highlight may be anywhere among them).
SHAPES = ({"ns": 8.0, "alpha": 0.3}, {"ns": 64.0, "alpha": 0.1}, {"ns": 512.0, "alpha": 0.02})
#: ... at this height where the pilot left it at 0 (the weights are shares of each lobe's own light).
OPEN_KS = 0.1


def uniform(mask, count: int, seed: int = SEED) -> np.ndarray:
    """``mask`` (bool) with at most ``count`` of its True pixels kept, chosen uniformly at random."""
    mask = np.asarray(mask, dtype=bool)
    idx = np.flatnonzero(mask)
    if len(idx) <= count:
        return mask.copy()
    keep = np.random.default_rng(seed).choice(idx, size=int(count), replace=False)
    out = np.zeros_like(mask)
    out[keep] = True
    return out


def tiles(usable, count: int, seed: int = SEED, tile: int = TILE) -> tuple[np.ndarray, float]:
    """A uniform share of a photograph's pixels, in ``tile`` × ``tile`` tiles, holding about ``count``
    of its ``usable`` (H, W) pixels: the pixels a further photograph's trees are built for.

    Every pixel is drawn with the same probability ``q`` (its tile's: tiles drawn uniformly
    without replacement), which a fit multiplies into each pixel's inclusion probability
    (Horvitz–Thompson, :func:`weights`): the sample drawn from these pixels then stands for the
    whole photograph. Tiles, not single pixels, so that the image noise's 3×3 windows
    (:func:`reflab.inverse.fit.photograph.image_noise`) still find whole windows.

    Returns
    -------
    pixels : (n,) int64
        Flat pixel indices (row-major), sorted; every pixel when ``usable`` holds at most ``count``.
    q : float
        Each pixel's probability to be drawn (1: every pixel).
    """
    usable = np.asarray(usable, dtype=bool)
    h, w = usable.shape
    n_usable = int(usable.sum())
    if n_usable <= int(count):
        return np.arange(h * w, dtype=np.int64), 1.0
    th, tw = -(-h // tile), -(-w // tile)
    n_tiles = th * tw
    chosen = int(min(n_tiles, max(1, np.ceil(n_tiles * count / n_usable))))
    pick = np.zeros(n_tiles, dtype=bool)
    pick[np.random.default_rng(seed + 5).choice(n_tiles, size=chosen, replace=False)] = True
    grid = np.repeat(np.repeat(pick.reshape(th, tw), tile, axis=0), tile, axis=1)[:h, :w]
    return np.flatnonzero(grid).astype(np.int64), chosen / n_tiles


def evidence_weight(trees, materials, intensities, surfaces=None) -> np.ndarray:
    """(H*W,) per pixel, the largest share it holds of any one term's information: per term (each
    surface's lobe, wherever it is seen; each reflected or transmitted path), the pixel's light of
    that term squared over the term's sum of squares. A term's few strong pixels (a sharp
    highlight) then weigh as much as another's many (a mirror's whole reflection). ``surfaces``:
    only those surfaces' lobes (the others' terms do not change with a lobe's shape)."""
    from scipy.sparse import coo_matrix, diags

    pixel, light, term, n_terms = _terms(trees, materials, intensities, surfaces)
    per = coo_matrix((light, (pixel, term)), shape=(trees.width * trees.height, n_terms)).tocsr()  # sums duplicates
    # Each term's light over its own peak before squaring: the shares do not depend on its scale,
    # and a faintly lit term (zoo seed 1 with seven photographs: a lobe the pilot left near 0,
    # whose squares summed to a subnormal and 1/total overflowed) keeps its shares.
    peak = np.asarray(abs(per).max(axis=0).todense()).ravel()
    per = per @ diags(np.divide(1.0, peak, out=np.zeros_like(peak), where=peak > 1e-300))
    per.data **= 2
    total = np.asarray(per.sum(axis=0)).ravel()
    per = per @ diags(np.divide(1.0, total, out=np.zeros_like(total), where=total > 0))
    return np.asarray(per.max(axis=1).todense()).ravel()


def _terms(trees, materials, intensities, surfaces=None):
    """Entries (pixel, light, term) and the count of terms: per node, its lobe's light (term: its
    surface) and, deeper than the first hit, its diffuse light carried by the path (term: the
    surface count + its path); the largest band of each, zero entries left out. ``surfaces``: the
    lobes of those surfaces' nodes alone."""
    from reflab.inverse.forward.models import get_model
    from reflab.inverse.forward.rendering import linear_basis, node_parameters, path_products

    basis = linear_basis(trees, materials, intensities)  # (N, 3, L), kd in slot 0
    pp = path_products(trees, materials)
    n_surf = len(materials)
    n_terms = n_surf + max(len(trees.paths), 1)
    if surfaces is not None:
        pixel, light, term = [], [], []
        surface = np.asarray(trees.surface)
        for s in surfaces:
            idx = np.flatnonzero(surface == int(s))
            x = np.zeros((3, basis.shape[2]))
            model = get_model(materials[s].brdf)
            x[:, :model.n_linear] = model.x_of(materials[s])
            pixel.append(np.asarray(trees.pixel, dtype=np.int64)[idx])
            light.append((pp[idx] * np.einsum("ncl,cl->nc", basis[idx, :, 1:], x[:, 1:])).max(axis=1))
            term.append(np.full(len(idx), int(s), dtype=np.int64))
        pixel, light, term = (np.concatenate(v) if v else np.zeros(0) for v in (pixel, light, term))
        keep = light > 0
        return pixel[keep].astype(np.int64), light[keep], term[keep].astype(np.int64), n_terms
    x, _ = node_parameters(trees, materials)
    lobe = (pp * np.einsum("ncl,ncl->nc", basis[:, :, 1:], x[:, :, 1:])).max(axis=1)
    deep = np.asarray(trees.level) > 1
    carried = np.where(deep, (pp * basis[:, :, 0] * x[:, :, 0]).max(axis=1), 0.0)
    light = np.concatenate([lobe, carried])
    term = np.concatenate([np.asarray(trees.surface, dtype=np.int64), n_surf + np.asarray(trees.path, dtype=np.int64)])
    pixel = np.concatenate([trees.pixel, trees.pixel]).astype(np.int64)
    keep = light > 0
    return pixel[keep], light[keep], term[keep], n_terms


def needed(mask, pixels: int = PIXELS, above: int = SAMPLE_ABOVE) -> bool:
    """Whether the fit samples: ``mask`` holds more than ``above`` pixels and more than the budget
    ``pixels`` (0: never)."""
    n = int(np.count_nonzero(mask))
    return 0 < int(pixels) < n and n > int(above)


def budget(pixels: int, photographs: int) -> int:
    """The sample's budget (pilot, evidence and bulk) over ``photographs`` photographs: ``pixels``
    for one, and :data:`PER_FURTHER` of it more per further photograph."""
    return int(round(int(pixels) * (1.0 + PER_FURTHER * max(int(photographs) - 1, 0))))


def pilot(mask, pixels: int = PIXELS, seed: int = SEED) -> np.ndarray:
    """The pilot's pixels: :data:`PILOT` of the budget ``pixels``, uniformly at random from ``mask``."""
    return uniform(mask, max(int(PILOT * pixels), 1), seed)


def open_lobes(result) -> list:
    """Surfaces whose lobe (any of ks, ns, alpha) a fit left undetermined."""
    return [s for s, names in enumerate(result.undetermined)
            if any(str(n).split("[")[0] in ("ks", "ns", "alpha") for n in names)]


def every_lobe(materials, held) -> list:
    """Surfaces with a lobe whose height the user did not give (``held``: per surface, the names
    given). Over several photographs each is looked for at every shape of :data:`SHAPES`, not only
    those the pilot left open: a pilot that reads a share of each further photograph can settle on
    a broad lobe where a further photograph holds a sharp highlight it never read (zoo seed 1,
    seven photographs at 320x240: a Ward box at alpha 0.76 ± 0.21, ks 0.055 ± 0.05 for 0.11 /
    0.27, the highlight's pixels never drawn)."""
    return [s for s, m in enumerate(materials) if "ks" in m.params and "ks" not in held[s]]


def shaped(materials, open_lobes, shape) -> list:
    """``materials`` with the lobes of the surfaces ``open_lobes`` at ``shape`` (:data:`SHAPES`)."""
    import dataclasses

    out = list(materials)
    for s in open_lobes:
        m = materials[s]
        params = dict(m.params)
        for name, value in shape.items():
            if name in params:
                params[name] = np.asarray(value, dtype=np.float64).reshape(np.shape(params[name]))
        if "ks" in params and not np.any(params["ks"] > 0):
            params["ks"] = np.full(np.shape(params["ks"]), OPEN_KS)
        out[s] = dataclasses.replace(m, params=params)
    return out


def fit_sample(trees, materials, intensities, mask, pixels: int = PIXELS, seed: int = SEED,
               open_lobes=()) -> tuple[np.ndarray, np.ndarray, dict]:
    """The pixels the fit reads after its pilot: ``mask``'s evidence and a uniform share of the rest.

    With ``evidence`` = :data:`EVIDENCE` · ``pixels``, each pixel is kept with probability
    ``min(1, c · w)``, ``w`` its largest share of one term's information (:func:`evidence_weight`)
    and ``c`` such that about ``evidence`` are drawn: every term (a lobe, a reflection, a
    transmission) keeps its strongest pixels, a sharp highlight all of them; then
    :data:`BULK` · ``pixels`` of the others, uniformly. The lobes of the surfaces ``open_lobes``
    (those the pilot left undetermined) are looked for at every shape of :data:`SHAPES` too: a
    pixel weighs the most it would hold under any of them.

    Returns
    -------
    keep : (H*W,) bool
    probability : (H*W,) float
        Each pixel's probability to be kept (:func:`inclusion`; 0 outside ``mask``): the fit
        weighs each kept pixel's row by its inverse (:func:`weights`, Horvitz–Thompson), so that
        its normal equations estimate those of every pixel of ``mask``.
    dict
        fit.json's ``sampling`` counts: ``evidence``, ``bulk``, ``of`` (the pixels ``mask`` held).
    """
    mask = np.asarray(mask, dtype=bool)
    evidence, bulk = int(EVIDENCE * pixels), int(BULK * pixels)
    w = evidence_weight(trees, materials, intensities)
    for shape in SHAPES if len(open_lobes) else ():
        # Only the open lobes' terms change with their shape: their shares alone (3x less work).
        w = np.maximum(w, evidence_weight(trees, shaped(materials, open_lobes, shape), intensities, open_lobes))
    w = np.where(mask, w, 0.0)
    total = float(w.sum())
    rng = np.random.default_rng(seed + 1)
    draw = rng.random(len(w))
    p_ev = np.zeros(len(w))
    if total > 0:
        # The scale c with Σ min(1, c·w) = evidence (bisection on the sorted weights).
        c = _scale(w[w > 0], float(evidence))
        p_ev = np.where(w > 0, np.minimum(1.0, c * w) if np.isfinite(c) else 1.0, 0.0)
    ev = draw < p_ev
    others = mask & ~ev
    rest = uniform(others, bulk, seed + 2)
    keep = ev | rest
    p_bulk = float(rest.sum()) / max(int(others.sum()), 1)
    return keep, np.where(mask, inclusion(p_ev, p_bulk), 0.0), {"pixels": int(pixels), "evidence": int(ev.sum()),
                                                                 "bulk": int(rest.sum()), "of": int(mask.sum())}


def even(trees, mask, surfaces, count: int = EVEN, seed: int = SEED) -> np.ndarray:
    """(H*W,) bool: for an estimate that weighs its pixels alike (the lobes from the texture's
    colours, :mod:`reflab.inverse.fit.dichromatic`), per photograph and per surface of ``surfaces``
    the pixels of ``mask`` that see it first, all of them up to ``count``, else ``count`` drawn
    uniformly. The evidence's draw would lean such an estimate toward the favoured pixels; reading
    every pixel of a large surface would make it slow (a zoo ground's 152 000 pixels at 640x480:
    13 s of 64 under cProfile). Per photograph (stacked trees' ``stats["block_row0"]``): each
    photograph of several is sampled as one alone would be, so a highlight that only a further
    photograph shows keeps its pixels (the demo's tile: its lobe undetermined from the reference's
    pixels alone, ks 0.35 ± 0.09, determined from every photograph's, ± 0.008)."""
    mask = np.asarray(mask, dtype=bool).reshape(-1)
    first = seen_first(trees, len(mask))
    stats = trees.stats if isinstance(getattr(trees, "stats", None), dict) else {}
    starts = np.asarray(stats.get("block_row0", [0]), dtype=np.int64) * int(trees.width)
    return even_of(first, mask, starts, surfaces, count, seed)


def even_of(first, mask, starts, surfaces, count: int = EVEN, seed: int = SEED) -> np.ndarray:
    """:func:`even` from each pixel's first seen surface ``first`` (H*W,) (−1: none) and the flat
    index where each photograph starts, ``starts``: the same draw without trees of every pixel."""
    mask = np.asarray(mask, dtype=bool).reshape(-1)
    first = np.asarray(first, dtype=np.int64).reshape(-1)
    starts = np.asarray(starts, dtype=np.int64)
    photo = np.searchsorted(starts, np.arange(len(mask)), side="right") - 1
    out = np.zeros_like(mask)
    for i in range(len(starts)):
        mine = mask & (photo == i)
        for k, s in enumerate(surfaces):
            # photograph 0 keeps the single photograph's seeds (the same draw as before)
            out |= uniform(mine & (first == int(s)), int(count), seed + 4 + k + 1009 * i)
    return out


def inclusion(*probabilities) -> np.ndarray:
    """A pixel's probability to be drawn by any of independent draws of the given probabilities
    (arrays or numbers): ``1 − Π (1 − p)``. Each draw's own: the evidence's ``min(1, c·w)``, a
    uniform draw's its count over the pixels it drew from (the bulk draws from those the
    evidence left, so independently of it given them)."""
    miss = 1.0
    for p in probabilities:
        miss = miss * (1.0 - np.clip(np.asarray(p, dtype=np.float64), 0.0, 1.0))
    return 1.0 - miss


def weights(keep, probability) -> np.ndarray:
    """(H*W,) 1 / ``probability`` on ``keep`` (0 elsewhere), scaled to average 1 over ``keep``:
    the fit's row weights (Horvitz–Thompson). The scale changes no estimate and no σ; at mean 1 a
    weighted residual's size stays a pixel's (the noise tests, the stopping rules)."""
    keep = np.asarray(keep, dtype=bool)
    p = np.broadcast_to(np.asarray(probability, dtype=np.float64), keep.shape)
    out = np.zeros(keep.shape)
    out[keep] = 1.0 / np.maximum(p[keep], 1e-12)
    mean = out[keep].mean() if keep.any() else 1.0
    return out / mean


def weighted(trees, weight):
    """``trees`` (a shallow copy) carrying the row weights ``weight`` (H*W,): every system built on
    them (:class:`reflab.inverse.forward.factorization.Factorization`: the fit, its outlier refits,
    the texture rounds, the albedo model's refit) weighs its rows alike."""
    import copy

    out = copy.copy(trees)
    out.weights = np.asarray(weight, dtype=np.float64)
    return out


def _scale(w, budget: float) -> float:
    """c such that Σ min(1, c·w) = budget (inf when every weight fits the budget)."""
    if budget >= len(w):
        return np.inf
    ws = np.sort(w)[::-1]
    # With the k largest capped at 1: k + c·Σ_{i≥k} w_i = budget, valid when c·w_k ≤ 1.
    k = np.arange(int(budget) + 1)
    tail = np.cumsum(ws[::-1])[::-1][k]
    c = np.divide(budget - k, tail, out=np.full(len(k), np.inf), where=tail > 0)
    ok = np.flatnonzero(c * ws[k] <= 1.0)
    return float(c[ok[0]]) if len(ok) else np.inf
