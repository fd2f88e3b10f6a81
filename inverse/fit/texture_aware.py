"""Fit the non-Lambertian parameters of a textured scene against its recovered texture.

F-TBO on a textured photograph holds each surface's albedo constant, as the dissertation does
(docs/method.md §3), so texture passes for specular light, reflections and transmission; the
texture stage then absorbs those errors (docs/texture.md). Alternating the two plainly does not
undo it: a texture recovered with wrong parameters explains the image with them. Here the
texture is recovered only from the pixels that directly seen texture lights almost alone, so
that it cannot absorb a wrong highlight, reflection or transmission, and the fit then judges
those against it. Each round:

1. the share of every pixel's predicted light that comes from the diffuse term of textured
   surfaces seen directly (the first node of its tree), with the current parameters and texture
   (:func:`direct_share`);
2. the texture from the pixels where that share is at least ``min_share`` in every band, or
   a surface's best half where that would keep fewer (:func:`feeds_texture`;
   :func:`reflab.inverse.texture.solve.recover_texture` with ``exclude``);
3. F-TBO from the current parameters (no global scan) with every textured node's diffuse term
   scaled by its albedo relative to its surface's mean (:func:`relative_albedo`,
   ``Factorization(albedo=...)``): ``kd`` stays the surface's mean albedo, and texels no kept
   pixel sees count as the mean. Where the texture is read from a sample of several photographs,
   pixels whose light rests on such texels, or on texels read from fewer than
   :data:`MIN_SUPPORT` pixels, by more than :data:`SUPPORT_SIGMAS` noise σ are left out of the
   round (:func:`loosely_textured`): their residual is the sample's ignorance of the texture,
   which the fit would otherwise turn into r, t or a lobe.

The last round holds textured lobes grey (:func:`grey_lobes`), and a lobe the texture's colours
determine at that estimate (:func:`colour_held`, :mod:`reflab.inverse.fit.dichromatic`).

Measured on the demo (docs/fit.md): the mirror's r, the sheet's t and the tile's ks and r come
to within 0.03 of the truth; the box's shininess, whose stripes cross its highlight, does not.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from reflab.inverse.forward.factorization import Factorization
from reflab.inverse.fit.albedo_model import select
from reflab.inverse.fit.rounds import FitSolution, fit
from reflab.inverse.forward.rendering import linear_basis, node_radiance, path_products
from reflab.inverse.forward.trees import seen_first
from reflab.inverse.texture.solve import SolverOptions, build_maps, recover_texture, sample_texture

#: A round whose fit leaves an RMS residual more than RISE times the best so far is not kept. Each
#: round's residual is against its own texture, so the rounds share no objective: a lower RMS does
#: not mean better parameters (measured on the textured lab: round 2 right with a higher RMS than
#: round 1), but a several-fold rise means the round's texture went wrong.
RISE = 2.0
#: A pixel feeds the texture when directly seen texture's diffuse term carries at least this share
#: of its light.
MIN_SHARE = 0.9
#: Of the pixels a textured surface is first seen in, at least this share feeds its texture
#: (:func:`feeds_texture`), down to pixels whose share is :data:`SHARE_FLOOR`.
KEEP = 0.5
SHARE_FLOOR = 0.5
#: The rounds' texels are this many pixel footprints across: a reflection is regressed on texels
#: recovered from noisy pixels (errors in variables), which pulls its r toward 0 by the texels'
#: noise over their contrast; four pixels per texel quarter that noise. Floor in a mirror, 1 %
#: noise, 80x60: mirror r[2] 3.0σ low on average at 1 footprint, within 1σ at 2 (docs/fit.md).
TEXEL_SCALE = 2.0
#: A round's texel is known from at least this many pixels' weight (the texture stage asks 0.1): a
#: coarse texel half over an occlusion edge (the ground behind the demo's sheet) would otherwise
#: extrapolate the visible side's albedo into what the sheet transmits (sheet t 0.11 off).
MIN_COVERAGE = 1.0
#: A texel read from less than this many pixels' weight is too loosely known to judge a lobe,
#: reflection or transmission against: its noise is that of a pixel or more. Not critical: the
#: lab at 160x120, seven photographs read through a quarter of the sample budget, recovers 25, 24,
#: 23 of 37 parameters at 1, 2, 4 (26 at SUPPORT_SIGMAS 1 or 3), none beyond 1.7σ; 15 without.
MIN_SUPPORT = 2.0
#: A round's fit leaves out a pixel whose light from such texels (or texels not known at all,
#: taken at the mean) exceeds this many image-noise σ in some band: its residual would be the
#: texture's error, not the parameters'.
SUPPORT_SIGMAS = 2.0
#: Rounds go on past ``rounds`` (to at most :data:`MAX_ROUNDS` in all) while a textured surface's lobe
#: still moves by more than this share between rounds (:func:`lobe_moved`). Texture and lobe
#: alternate as a linearly converging pair: each round takes back part of the highlight the last
#: texture kept. The lab's textured box, seven photographs at 160x120: ks 0.148, 0.219, 0.249,
#: 0.244 (true 0.25) over rounds 1–4, ns 17.6 → 29.9 (30); two rounds reported 0.149 / 20.5.
SETTLE = 0.05
#: At most this many texture rounds, however far a lobe still moves: a lobe the last round takes
#: from the texture's colours may wander before it (the lab's tile at 640x480), and the lab's seven
#: photographs gave the same values within 10 % at 4 as at 6 (160, 320 and 640 wide; 640: 19 s
#: against 23 s).
MAX_ROUNDS = 4
#: A lobe height below this counts its change against it, and its shape's change not at all (a
#: surface without a lobe has no shininess to settle).
LOBE_FLOOR = 0.05
#: A lobe from the texture's colours whose height is known to this share is held over several
#: photographs as it is; a looser one is weighed against the rounds' own estimate, which costs the
#: last round twice (the zoo's seeds 0-9 and 20-31 at 320x240 and 0-9 at 640x480, six or seven
#: photographs: 14 of its 15 lobes from the colours with their height within 5 %, none of the 15
#: known better to the rounds; comparing two whose shape was looser than 5 % cost seeds 4 and 7 at
#: 640x480 a last round of 5-7 s more, for the same values).
KNOWN = 0.05
#: Lobe heights a textured surface's last round holds at their mean over the bands (see
#: :func:`grey_lobes`).
GREY = ("ks",)


def grey_lobes(materials, textured, held=None) -> tuple[list, list]:
    """Textured surfaces' lobe heights (:data:`GREY`) set to their mean over the bands.

    A textured surface is a dielectric (print, paper, laminate, glaze): its highlight is reflected
    at the surface, before the light reaches the pigment, so it has the lamp's colour (the
    neutral-interface assumption of the dichromatic reflection model; the lamp's colour is in the
    intensities, so its ks is the same in every band). Fitted per band, a lobe the photograph does
    not determine takes up the texture's colour instead (shiny box, 160x120, 1 % noise: ks [0.33,
    0.29, 0.26] for 0.3; held at their mean and the shininess refitted: 0.296, ns 41.3 for 40, the
    relit view 6 dB closer to the true materials'). Values the user gave (``held``) are left alone.

    Returns
    -------
    materials : list of Material
        ``materials`` with those lobes grey.
    guessed : list of set of str
        Per surface, the names made grey: the round that uses them holds them, its σ counting
        them free (:func:`reflab.inverse.fit.rounds.fit`'s ``guessed``).
    """
    out, guessed = list(materials), [set() for _ in materials]
    for i, (m, tex) in enumerate(zip(materials, textured)):
        given = set() if held is None else held[i]
        guessed[i] = {n for n in GREY if tex and n in m.params and n not in given}
        if guessed[i]:
            out[i] = dataclasses.replace(m, params=dict(m.params) | {n: np.full(3, float(np.mean(m[n]))) for n in guessed[i]})
    return out, guessed


def colour_held(trees, materials, guessed, intensities, image, textured, noise, mask, held, rms):
    """``materials`` and ``guessed`` with each textured lobe the texture's colours resolve
    (:func:`reflab.inverse.fit.dichromatic.colour_lobes`) set to that estimate and held as a guess, and those
    lobes (surface index → ColourLobe; None if none). Without a noise estimate, nothing."""
    from reflab.inverse.fit.dichromatic import colour_lobes

    if noise is None:
        return materials, guessed, None
    lobes = {s: lobe for s, lobe in colour_lobes(trees, materials, intensities, image, textured, noise, mask=mask,
                                                   held=held, rms=rms).items() if lobe.resolved()}
    if not lobes:
        return materials, guessed, None
    return (*hold_colour(materials, guessed, lobes), lobes)


def hold_colour(materials, guessed, lobes) -> tuple[list, list]:
    """``materials`` and ``guessed`` with each of ``lobes`` (surface index → ColourLobe) set to its
    estimate and held as a guess."""
    materials, guessed = list(materials), [set(g) for g in guessed]
    for s, lobe in lobes.items():
        materials[s] = dataclasses.replace(materials[s], params=dict(materials[s].params)
                                           | {"ks": np.full(3, lobe.ks), lobe.shape: float(lobe.theta)})
        guessed[s] |= {"ks", lobe.shape}
    return materials, guessed


def lobe_known(lobe) -> bool:
    """A lobe from the texture's colours whose height is known to :data:`KNOWN` of it: held over
    several photographs without fitting the rounds' own to compare (a last round more)."""
    return bool(lobe.sigma_ks <= KNOWN * lobe.ks)


def rounds_lobe_sigma(fac, result: FitSolution, s: int, shape: str) -> tuple[float, float]:
    """The σ of surface ``s``'s lobe height (its largest over the bands) and of its ``shape`` as a
    round fitted them, inf where the round leaves them undetermined: what a lobe from the
    texture's colours is weighed against over several photographs (:func:`fit_with_texture`)."""
    model = fac.models[s]
    names = result.undetermined[s] if s < len(result.undetermined) else ()
    if "ks" not in model.linear or shape not in model.nonlinear \
            or any(str(n).split("[")[0] in ("ks", shape) for n in names):
        return float("inf"), float("inf")
    sd = np.asarray(result.sigma.x[fac.layout.x_offset[s] + model.linear.index("ks")], dtype=np.float64)
    st = float(result.sigma.theta[fac.layout.theta_offset[s] + model.nonlinear.index(shape)])
    return (float(np.max(sd)) if np.all(np.isfinite(sd)) else float("inf")), (st if np.isfinite(st) else float("inf"))


def without_own_paths(materials, textured) -> list:
    """``materials`` with every textured surface's ``r`` and ``t`` at 0 (the others unchanged)."""
    return [dataclasses.replace(m, params=dict(m.params) | {n: np.zeros(3) for n in ("r", "t") if n in m.params})
            if tex else m for m, tex in zip(materials, textured)]


def direct_share(trees, materials, intensities, textured, relative=None) -> np.ndarray:
    """(H*W, 3) share of each pixel's predicted light that the diffuse term of directly seen
    textured surfaces carries.

    Parameters
    ----------
    trees : reflab.inverse.forward.trees.Trees
    materials : list of Material
    intensities : (K, 3) array_like
    textured : (S,) bool array_like
        Which surfaces are textured.
    relative : (N, 3) ndarray, optional
        Per-node albedo relative to the surface's ``kd`` (:func:`relative_albedo`); None: 1.

    Returns
    -------
    (H*W, 3) ndarray
        In [0, 1]; 0 where the model predicts no light.
    """
    npix = trees.width * trees.height
    kd = np.stack([np.broadcast_to(m["kd"], (3,)) for m in materials]).astype(np.float64)[trees.surface]
    on = np.asarray(textured, dtype=bool)[trees.surface]
    if relative is not None:
        kd = np.where(on[:, None], kd * relative, kd)
    basis = linear_basis(trees, materials, intensities)  # (N, 3, L), kd in slot 0
    light = node_radiance(trees, materials, intensities, kd_nodes=kd, basis=basis)
    # Only the diffuse term of a directly seen textured node counts (path product · kd's basis · kd,
    # as reflab.inverse.texture.solve.build_system weighs a texel): its highlight the texture must not absorb.
    diffuse = path_products(trees, materials) * basis[:, :, 0] * kd
    first = (np.asarray(trees.level) == 1) & on  # the primary hit: seen directly

    def per_pixel(values, sel):
        return np.stack([np.bincount(trees.pixel[sel], weights=values[sel, c], minlength=npix) for c in range(3)], axis=1)

    total = per_pixel(light, np.ones(len(trees.pixel), dtype=bool))
    return np.divide(per_pixel(diffuse, first), total, out=np.zeros((npix, 3)), where=total > 0)


def feeds_texture(trees, textured, share, min_share: float = MIN_SHARE, keep: float = KEEP,
                  floor: float = SHARE_FLOOR) -> np.ndarray:
    """(H*W,) bool: the pixels a round's texture is recovered from.

    Those whose directly seen texture carries at least ``min_share`` of their light in every band
    (``share``, :func:`direct_share`). Where that leaves a textured surface under ``keep`` of the
    pixels it is first seen in, a broad lobe lights it everywhere, and the surface's threshold
    falls to the share of its best ``keep`` of them, not below ``floor``: a texture starved
    of pixels leaves the round to fit the surface as one colour, which sets its lobe apart from
    the round before, and the rounds swing (zoo seed 49, 320x240, seven photographs: a ground
    lobe of ns 5, albedo 0.09 beside a green kd of 0.28; every other round read 1 500 of 20 000
    texels, its green kd 0.43 made a sphere mirroring the ground report r[1] 0.030 ± 0.0035
    for 0.046).
    """
    npix = trees.width * trees.height
    least = np.asarray(share, dtype=np.float64).reshape(npix, -1).min(axis=1)
    feeds = least >= min_share
    seen_on = seen_first(trees, npix)
    for s in np.flatnonzero(np.asarray(textured, dtype=bool)):
        on = (seen_on == s) & (least > 0)
        if on.any() and feeds[on].mean() < keep:
            threshold = max(float(np.quantile(least[on], 1.0 - keep)), floor)
            feeds |= on & (least >= threshold)
    return feeds


def seen_elsewhere(trees, textured) -> np.ndarray:
    """(N,) bool: nodes of textured surfaces seen in a mirror or through glass (not directly)."""
    return np.asarray(textured, dtype=bool)[trees.surface] & (np.asarray(trees.level) > 1)


def noise_like(image, trees, textured, sigma=None) -> np.ndarray | None:
    """Gaussian noise of the photograph's own σ per band (``sigma``, the fit's estimate; default
    :func:`reflab.inverse.fit.photograph.image_noise`), seeded, for :func:`deattenuated`; None where nothing
    textured is seen in a mirror or through glass, or the photograph is noise-free (σ under 1e-4
    of its peak)."""
    from reflab.inverse.fit.photograph import image_noise

    image = np.asarray(image, dtype=np.float64)
    if not seen_elsewhere(trees, textured).any():
        return None
    sigma = image_noise(image) if sigma is None else np.asarray(sigma, dtype=np.float64)
    if not np.any(sigma > 1e-4 * max(float(image.max()), 1e-300)):
        return None
    return np.random.default_rng(0).normal(0.0, 1.0, image.shape) * sigma


def deattenuated(relative, trees, textured, tex, only=None) -> np.ndarray:
    """``relative`` where a textured surface is seen in a mirror or through glass, shrunk toward
    its mean by the texels' reliability: regression calibration for errors in variables.

    A reflection or transmission is regressed on texels recovered from noisy pixels; their noise
    pulls its r or t toward 0 by the noise's share of the texels' variance (and the reflecting
    surface's own kd up): floor in a mirror, 160x120, 1 % noise: mirror r[2] 0.83 for 0.85 in every
    realisation, 3–4σ off; with the true texture 0.85. The texels' expected value given their
    noisy estimate, ``μ + (1 − λ)(a − μ)`` with λ = noise variance / total variance per band over
    those nodes, removes that bias. The noise variance is measured, not modelled: ``tex`` was also
    solved from the photograph plus noise of its own σ (:func:`noise_like`,
    ``TextureSolution.perturbed``), and the change at the nodes is that noise's image. Without it
    (a noise-free photograph) ``relative`` is returned as it is. Directly seen nodes are not
    touched: they were made from the very pixels they explain. ``only`` (N,) bool, optional: the
    nodes of the pixels the fit reads (:func:`loosely_textured` leaves out those on the noisiest
    texels), λ measured over them alone: over all, it over-corrects theirs (the lab at 160x120,
    seven photographs read through a quarter of the sample budget: worst 3.2σ, 1.5σ over them).
    """
    if not tex.perturbed:
        return relative
    seen = seen_elsewhere(trees, textured) & np.all(np.isfinite(relative), axis=1)
    if only is not None:
        seen &= np.asarray(only, dtype=bool)
    nodes = np.flatnonzero(seen)
    if len(nodes) < 2:
        return relative
    moved = relative_albedo(trees, textured, dataclasses.replace(tex, kd=tex.perturbed), only=seen)[nodes]
    a = relative[nodes]
    spread = a.var(axis=0)
    lam = np.clip(np.divide(np.nanvar(moved - a, axis=0), spread, out=np.zeros(3), where=spread > 0), 0.0, 0.5)
    out = relative.copy()
    out[nodes] = a.mean(axis=0) + (1.0 - lam) * (a - a.mean(axis=0))
    return out


def relative_albedo(trees, textured, result, only=None) -> np.ndarray:
    """(N, 3) each textured node's recovered albedo over its surface's mean; NaN elsewhere.

    Nodes whose texels are unknown get 1 (the mean); so do bands whose mean is 0. ``only`` (N,)
    bool, optional: those nodes alone (the rest NaN).
    """
    out = np.full((len(trees.pixel), 3), np.nan)
    for s in np.flatnonzero(np.asarray(textured, dtype=bool)):
        sel = np.nonzero((trees.surface == s) & (True if only is None else np.asarray(only, dtype=bool)))[0]
        if len(sel) == 0:
            continue
        out[sel] = 1.0
        if s not in result.kd or not result.mask[s].any():
            continue
        mean = result.kd[s][result.mask[s]].mean(axis=0)
        a = sample_texture(result.maps[s], result.kd[s], result.mask[s], trees.triangle[sel], trees.barycentric[sel])
        rel = np.divide(a, mean, out=np.ones_like(a), where=mean > 1e-6)
        out[sel] = np.where(np.isfinite(rel), rel, 1.0)
    return out


def texel_support(trees, textured, tex) -> np.ndarray:
    """(N, 3) pixels' weight that recovered the texels under each textured node (bilinear over
    its four texels; 0 where they are unknown); inf on surfaces that are not textured."""
    out = np.full((len(trees.pixel), 3), np.inf)
    for s in np.flatnonzero(np.asarray(textured, dtype=bool)):
        sel = np.flatnonzero(trees.surface == s)
        if not len(sel):
            continue
        out[sel] = 0.0
        if s not in tex.kd or not tex.mask[s].any():
            continue
        idx, w = tex.maps[s].bilinear(trees.triangle[sel], trees.barycentric[sel])
        weight = np.where(tex.mask[s][..., None], tex.weight[s], 0.0).reshape(-1, 3)
        out[sel] = np.einsum("nj,njc->nc", w, weight[idx])
    return out


def loosely_textured(trees, materials, intensities, textured, tex, noise,
                     min_support: float = MIN_SUPPORT, sigmas: float = SUPPORT_SIGMAS) -> np.ndarray:
    """(H*W,) bool: pixels whose predicted light rests on texels the round's texture barely knows.

    A node on a texel read from fewer than ``min_support`` pixels (or from none: the surface's
    mean stands in) carries that texel's error into its pixel at full strength; where that
    diffuse light exceeds ``sigmas`` × the image noise, the pixel's residual is the texture's,
    and the fit would turn it into a wrong r, t or lobe (the lab's mirror and sheet at 320x240,
    seven photographs: texels seen only in the further photographs' sample).

    That holds for a directly seen node whose own pixel fed the texture too: a texel read from a
    pixel or two fits them only where they agree, and where the photographs disagree on it
    (detail finer than the texels, seen from seven places) its value runs wild. Such nodes, 9 %
    of the directly seen ground's weight in the lab's seven noise-free 320x240 photographs, came
    out 2-8 % too bright and set the ground's kd 0.2-0.4 % low, which the mirror's r and the
    sheet's t took up (0.8516 / 0.8527 / 0.8531 for 0.85, 3σ); left out, 0.8498.
    """
    npix = trees.width * trees.height
    if noise is None or tex is None:
        return np.zeros(npix, dtype=bool)
    support = texel_support(trees, textured, tex).min(axis=1)
    poor = support < min_support
    if not poor.any():
        return np.zeros(npix, dtype=bool)
    # At the surface's mean albedo, not the texels' own estimate: a choice made on the noisy
    # estimate would keep the texels that came out dark and bias what they are regressed on.
    kd = np.stack([np.broadcast_to(m["kd"], (3,)) for m in materials]).astype(np.float64)[trees.surface]
    diffuse = path_products(trees, materials) * linear_basis(trees, materials, intensities)[:, :, 0] * kd
    pixel = trees.pixel[poor]
    light = np.stack([np.bincount(pixel, weights=diffuse[poor, c], minlength=npix) for c in range(3)], axis=1)
    return np.any(light > sigmas * np.asarray(noise, dtype=np.float64), axis=1)


def lobe_moved(before, after, models, textured, held=None) -> float:
    """The largest change of a textured surface's lobe between two rounds' materials: its ``ks``
    per band relative to the larger of its value and :data:`LOBE_FLOOR`, its shape parameters in
    log (where the lobe is there). Values the user gave (``held``) do not move. 0 without a lobe."""
    out = 0.0
    for s in np.flatnonzero(np.asarray(textured, dtype=bool)):
        model, given = models[s], set() if held is None else held[s]
        if "ks" not in model.linear or "ks" in given:
            continue
        a, b = (np.asarray(m["ks"], dtype=np.float64) for m in (before[s], after[s]))
        out = max(out, float(np.max(np.abs(b - a) / np.maximum(np.abs(a), LOBE_FLOOR))))
        if max(float(np.max(a)), float(np.max(b))) < LOBE_FLOOR:
            continue
        for name in model.nonlinear:
            if name not in given:
                u, v = (max(float(np.mean(m[name])), 1e-300) for m in (before[s], after[s]))
                out = max(out, abs(float(np.log(v / u))))
    return out


def _leave_out(mask, result, width) -> None:
    """Clear ``mask`` (H*W,) at ``result``'s rejected outlier pixels."""
    rejected = result.stats.get("rejected", {"count": 0, "pixels": []})
    if rejected["count"]:
        xy = np.asarray(rejected["pixels"], dtype=np.int64).reshape(-1, 2)
        mask[xy[:, 1] * width + xy[:, 0]] = False


def fit_with_texture(trees, scene, models, intensities, image, start: FitSolution, *, mask=None, rounds: int = 2,
                     max_rounds: int | None = None,
                     min_share: float = MIN_SHARE, method: str = "ftbo", options: SolverOptions | None = None,
                     maxiter: int | None = None, max_seconds: float | None = None,
                     progress=None, task=None, held=None, select_models: bool = True,
                     view=None, colour_mask=None) -> tuple[FitSolution, list]:
    """Refit the parameters of a textured scene in rounds against its recovered texture.

    Parameters
    ----------
    trees : reflab.inverse.forward.trees.Trees
    scene : reflab.reconstruction.scene.Scene
        ``textured`` flags and names.
    models : list
        One model per surface (as for :class:`Factorization`).
    intensities : (K, 3) array_like
    image : (H, W, 3) ndarray
    start : FitSolution
        The homogeneous fit (:func:`reflab.inverse.fit.rounds.fit`).
    mask : (H*W,) bool, optional
        Pixels the fit may use (saturated ones left out).
    rounds : int
        Texture-then-fit rounds, at least; with two or more, rounds are added before the last
        while a textured lobe still moves by more than :data:`SETTLE` (:func:`lobe_moved`).
    max_rounds : int, optional
        At most this many rounds in all, never fewer than ``rounds``. Default: :data:`MAX_ROUNDS`
        over several photographs, whose texels seen twice tell lobe from texture as the rounds
        settle; ``rounds`` over one (its rounds settle nothing a texel seen once could tell: the
        zoo at 640x480, 1 % noise, took 1.5x the time for 3 fewer values within 10 %).
    min_share : float
        A pixel feeds the texture when directly seen texture carries at least this share of its
        predicted light in every band.
    method : {"ftbo", "nftbo"}
    options : SolverOptions, optional
        The rounds' texture settings; default: texels :data:`TEXEL_SCALE` footprints across.
    maxiter : int, optional
        Outer iteration cap of each round's fit.
    max_seconds : float, optional
        Wall-clock budget of all rounds together: no round starts once it is spent, and each
        round's fit gets what is left.
    progress : callable, optional
        Called with each round's record.
    task : reflab.core.task.Task, optional
        Handed to each round's fit; no round starts once it is out of time.
    held : list of set of str, optional
        Per surface, the names given in scene.json (held; :func:`reflab.inverse.fit.rounds.fit`).
    select_models : bool
        First ask the photograph whether each textured surface's albedo is one colour or a few
        inks (:mod:`reflab.inverse.fit.albedo_model`); those that are are refitted as homogeneous
        (a palette's kd scaled per node by its ink) and get no texture here
        (``stats["albedo_models"]`` says what each got). When none is left textured in view, the
        refit is the result and no round runs.

    view : (Trees, image, noise), optional
        Where the rounds recover their texture, when not from ``trees`` and ``image`` themselves:
        a large photograph's binned view (:mod:`reflab.inverse.fit.large`) and its noise σ per
        band, whose texture the fit's rows, ``trees``' nodes, then look up; or, over several
        sampled photographs, the reference and the sample without the colour lobes' pixels
        (:func:`reflab.inverse.fit.workspace_fit.fit_scene`).
    colour_mask : (H*W,) bool, optional
        The pixels the lobes from the texture's colours (:func:`colour_held`) read, when not
        ``mask``: a uniform sample (:func:`reflab.inverse.fit.sampling.even`) where the fit reads
        a weighted one drawn by evidence (``mask``). That estimate weighs its pixels alike, so on
        the evidence's sample it leans toward the favoured pixels (zoo seed 7 at 640x480: a
        printed cylinder's ns 9.4 ± 0.8 for 12.2; 12.0 ± 0.9 from every pixel).

    Returns
    -------
    FitSolution
        The last round kept: a round is dropped when its RMS residual (against its own texture)
        is more than :data:`RISE` times the best so far, and the next round starts from the
        best; ``stats["best_round"]`` says which was kept (0 = the start); ``trace`` continues the start's, ``time_s``, ``evaluations`` and
        ``iterations`` add up, ``stats["best_round"]`` says which (0 = the start).
    list of dict
        Per round: ``round``, ``pixels_left_out`` (from the texture), ``loosely_textured`` (of
        the fit's pixels, left out of the round: :func:`loosely_textured`), ``rms`` per band,
        ``texture_s``, ``fit_s``.
    """
    if not 0.0 < min_share <= 1.0:
        raise ValueError(f"min_share must be in (0, 1], got {min_share!r}")
    given = None if mask is None else np.asarray(mask, dtype=bool).reshape(-1).copy()
    options = options or SolverOptions(texel_scale=TEXEL_SCALE, min_coverage=MIN_COVERAGE)
    # The start's outliers stay out; the rounds reject no more (the texture's own misfit would pass
    # for outliers where the homogeneous fit excused it as albedo variation).
    n_pix = trees.width * trees.height
    mask = np.ones(n_pix, dtype=bool) if mask is None else np.asarray(mask, dtype=bool).reshape(n_pix).copy()
    _leave_out(mask, start, trees.width)
    albedo_models, palette = {}, None
    if select_models:
        # Surfaces whose photograph shows one colour or a few inks are fitted as such (albedo_model).
        scene, start, albedo_models, palette = select(trees, scene, models, intensities, image, start, mask=mask,
                                                      method=method, maxiter=maxiter, max_seconds=max_seconds,
                                                      task=task, held=held, min_share=min_share)
        _leave_out(mask, start, trees.width)  # the refit's outliers too
        if palette is not None:  # a palette's ink edges stay out, its inks scale its kd (albedo_model)
            mask &= ~palette.leave_out
    rejected = start.stats.get("rejected", {"count": 0, "pixels": []})
    textured = np.array([s.textured for s in scene], dtype=bool)
    if not np.isin(trees.surface, np.flatnonzero(textured)).any():  # every one uniform: no round
        if "complete" in start.stats:
            start = dataclasses.replace(start.stats["complete"](), trace=start.trace, time_s=start.time_s,
                                        evaluations=start.evaluations, iterations=start.iterations)
        return dataclasses.replace(start, stats={**start.stats, "best_round": 0, "albedo_models": albedo_models}), []
    result, records, relative, tex = start, [], None, None
    best, best_err, best_round = start, float(np.sum(np.asarray(start.rms) ** 2)), 0
    best_relative = None
    view_trees, view_image, view_noise = (trees, image, start.stats.get("noise")) if view is None else view
    relative_view, best_relative_view = None, None
    trace, elapsed = [list(p) for p in start.trace], start.time_s
    evaluations, iterations = start.evaluations, start.iterations
    if colour_mask is not None:  # what left the fit's pixels (outliers: the start's list holds the refit's too) stays out
        colour_mask = np.asarray(colour_mask, dtype=bool).reshape(n_pix).copy()
        _leave_out(colour_mask, start, trees.width)
        if given is not None:
            colour_mask &= ~(given & ~mask)
    t_start = time.perf_counter()
    from reflab.inverse.forward.photographs import photograph_count

    several = photograph_count(trees) > 1
    if max_rounds is None:  # one photograph: a texel seen once settles nothing (zoo at 640x480: 1.5x the time, no gain)
        max_rounds = MAX_ROUNDS if several else int(rounds)

    def one_round(k, last, materials, guessed, colour, tex, relative_view, previous, left, t0):
        """One round: the texture under ``materials``, then the fit against it (module docstring)."""
        # The first round's pixels are chosen with each textured surface's own r and t at 0: the
        # homogeneous start fitted them against one kd, so they carry the texture's variation (shiny
        # box with a lamp alone: r [0, 0.07, 0.18] for 0), and chosen with them no pixel of the
        # surface is left to recover the texture that would show them wrong.
        share = direct_share(view_trees, without_own_paths(materials, textured) if k == 0 else materials,
                             intensities, textured, relative_view)
        left_out = ~feeds_texture(view_trees, textured, share, min_share)
        # The round whose values are reported (an earlier one only seeds it) also sees what the
        # photograph's noise makes of the texels (deattenuated).
        tex = recover_texture(scene, view_trees, materials, intensities, view_image, options, exclude=left_out,
                              maps=build_maps(scene, view_trees, options, crop=True) if tex is None else tex.maps,
                              perturb=noise_like(view_image, view_trees, textured, view_noise)
                              if last else None)
        round_mask, only = mask, None
        if view is not None and (view_trees.width, view_trees.height) == (trees.width, trees.height):
            # Read through a sample of the same pixels (several photographs): a texel seen only where the
            # sample is sparse is known from a pixel or two, or not at all. The pixels whose light
            # rests on such texels are left out of this round's fit, and the texels' noise is
            # measured over the nodes of the pixels it reads. (Every pixel read, the rounds fit a
            # left-out highlight against the mean of its texels by design: its lobe's evidence.)
            round_mask = mask & ~loosely_textured(trees, materials, intensities, textured, tex,
                                                  start.stats.get("noise"))
            only = round_mask[np.asarray(trees.pixel, dtype=np.int64)]
        relative = deattenuated(relative_albedo(trees, textured, tex), trees, textured, tex, only=only)
        relative_view = relative if view is None else deattenuated(relative_albedo(view_trees, textured, tex),
                                                                   view_trees, textured, tex)
        t1 = time.perf_counter()
        fac = Factorization(trees, models, intensities, mask=round_mask,
                            albedo=relative if palette is None else palette.merged(relative))
        # σ only for the last round (the one kept, unless its texture went wrong: see below). After
        # a kept round, what it held stays held: its holding rounds would find it again (same
        # fit.json on the 640×480 benchmark scenes, 0.2 s less a round), and the σ still counts it
        # free (passed as the structure, it did not: a mirror kd[1] held at 0.001 for 0.02 left
        # r[1] 0.8825 ± 0.0007 for 0.85, 47σ); after the homogeneous start, whose holds the
        # texture may undo, they start anew.
        out = fit(fac, image, materials, method, textured=list(textured), names=scene.names, scan=False,
                  maxiter=maxiter, max_seconds=None if left is None else max(left - (t1 - t0), 1e-3), task=task,
                  held=held, guessed=guessed, reject=False, structure=start.structure,
                  still_held=None if best_round == 0 else previous.free,
                  uncertainty=last, colour=colour, nuisance=None if palette is None else palette.nuisance)
        return out, fac, tex, relative, relative_view, left_out, round_mask, t1

    planned, cap = int(rounds), max(int(rounds), int(max_rounds))
    k = -1
    while k + 1 < planned:
        k += 1
        t0 = time.perf_counter()
        left = None if max_seconds is None else max_seconds - (t0 - t_start)
        if (left is not None and left <= 0) or (task is not None and task.out_of_time):
            break
        if task is not None:
            task.step(k, planned, "texture round")
        # The last round holds textured surfaces' lobes grey (grey_lobes), its texture recovered
        # under them: earlier rounds fit them per band, which sets the grey value; the last refits
        # their shininess under it (can of texture_seed 4: relit −9.1 → −6.5 dB against the true
        # materials when the texture, too, was made with the grey lobe).
        last = k == planned - 1
        before = result.materials
        materials, guessed = grey_lobes(result.materials, textured, held) if last else (result.materials, None)
        colour, colour_s = None, None
        if last:
            # A lobe the texture's colours determine is held at that estimate (reflab.inverse.fit.dichromatic).
            colour = colour_held(trees, materials, guessed, intensities, image, textured, start.stats.get("noise"),
                                 mask if colour_mask is None else colour_mask, held, result.rms)[2]
            colour_s = time.perf_counter() - t0
        dropped = {}
        if colour and several and any(not lobe_known(lobe) for lobe in colour.values()):
            # Over several photographs the rounds fit a textured lobe from its texels seen twice: a
            # lobe from the texture's colours is not held where the rounds, fitting it free, know
            # both its height and its shape better (floor_mirror's floor, seven 320x240
            # photographs: from colour ks 0.0446 +- 0.0062, ns 13.1 +- 1.4; the rounds 0.0392 +-
            # 0.0006, 10.7 +- 0.6; for 0.04, 12). Where each knows one better it is held (the same
            # at 160x120: 0.0396 +- 0.0023, 11.8 +- 0.7 against 0.0404 +- 0.0009, 14.2 +- 1.0).
            free_round = one_round(k, last, materials, guessed, None, tex, relative_view, result, left, t0)
            precise = {}
            for s_, lobe in colour.items():
                if lobe_known(lobe):
                    precise[s_] = lobe
                    continue
                sk, st = rounds_lobe_sigma(free_round[1], free_round[0], s_, lobe.shape)
                fitted = free_round[0].materials[s_]
                info = {"colour": [lobe.ks, lobe.sigma_ks, lobe.theta, lobe.sigma_theta],
                        "rounds": [float(np.mean(fitted["ks"])), sk, float(fitted[lobe.shape]), st]}
                if sk <= lobe.sigma_ks and st <= lobe.sigma_theta:
                    dropped[scene.names[s_]] = info
                else:
                    precise[s_] = lobe
            colour = precise or None
            if colour:
                materials, guessed = hold_colour(materials, guessed, colour)
                now = time.perf_counter()
                out = one_round(k, last, materials, guessed, colour, free_round[2], relative_view, result,
                                None if max_seconds is None else max_seconds - (now - t_start), now)
            else:
                out = free_round
        else:
            if colour:
                materials, guessed = hold_colour(materials, guessed, colour)
            out = one_round(k, last, materials, guessed, colour, tex, relative_view, result, left, t0)
        result, fac, tex, relative, relative_view, left_out, round_mask, t1 = out
        t2 = time.perf_counter()
        trace += [[elapsed + (t1 - t0) + t, rms] for t, rms in result.trace]
        elapsed += t2 - t0
        evaluations += result.evaluations
        iterations += result.iterations
        record = {"round": k + 1, "pixels_left_out": int(left_out.sum()),
                  "loosely_textured": int((mask & ~round_mask).sum()), "rms": [float(v) for v in result.rms],
                  "texture_s": round(t1 - t0, 3), "fit_s": round(t2 - t1, 3)}
        if colour_s is not None:  # of texture_s: the lobes from the texture's colours
            record["colour_s"] = round(colour_s, 3)
        if dropped:  # lobes from the colours the rounds fitted more precisely (not held)
            record["colour_lobes_not_held"] = dropped
        if not last:
            record["lobe_moved"] = round(lobe_moved(before, result.materials, models, textured, held), 4)
        err = float(np.sum(np.asarray(result.rms) ** 2))
        record["kept"] = bool(err < RISE**2 * best_err)
        if record["kept"]:
            best, best_err, best_round = result, min(err, best_err), k + 1
        else:  # a round whose texture made the image worse: its successor starts from the best
            result, relative, relative_view = best, best_relative, best_relative_view
        if best_round == k + 1:
            best_relative, best_relative_view = relative, relative_view
        if not last and record["kept"] and k == planned - 2 and planned < cap and record["lobe_moved"] > SETTLE:
            planned += 1  # a lobe still settling: one more round before the last (SETTLE)
        records.append(record)
        if progress is not None:
            progress(record)
    if "complete" in best.stats:  # an earlier round (or the start) kept, or time ran out: its σ now
        best = best.stats["complete"]()
    warnings = [w for w in start.stats.get("warnings", []) if "outlier" in w] + best.stats.get("warnings", [])
    result = dataclasses.replace(best, stats={**best.stats, "best_round": best_round, "rejected": rejected,
                                              "warnings": warnings, "albedo_models": albedo_models}, trace=trace, time_s=elapsed, evaluations=evaluations, iterations=iterations)
    return result, records
