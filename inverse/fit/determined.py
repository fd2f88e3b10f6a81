"""Which parameters the image determines.

Parameters with no signal in their columns (a surface never seen, no reflection or transmission
through a surface) are out of the fit from the start (:func:`structural_free`); those whose
one-sigma exceeds :data:`RESOLVE` of their scale (a hidden highlight, ks ≈ 0 leaving ns free) are
held at their initial value round by round (:func:`unresolved`), and so are values the user gave
(:func:`hold`); all are named in fit.json's ``undetermined`` (:func:`undetermined_names`). On
textured scenes only the pixels that a free texture cannot explain inform the other parameters
(:func:`texture_absorbed`). A lobe the image leaves open is reported at the value the data and a
prior over the field's lobes agree on (:func:`plausible_lobes`).
"""
from __future__ import annotations

import numpy as np

from reflab.inverse.forward.factorization import BANDS, Factorization
from reflab.inverse.fit.problem import SCAN_POINTS, Free, Params, Problem, materials_of
from reflab.inverse.forward.trees import derived
from reflab.reconstruction.scene import INITIAL
from reflab.inverse.fit.uncertainty import profiled, row_jacobian


#: A parameter whose one-sigma exceeds this fraction of its scale (its value or initial value for
#: x, the range [0, 1] for r and t, a factor 2 for a log2 parameter) is undetermined.
RESOLVE = 1.0
#: A fitted shininess is reported undetermined when its final (robust) one-sigma exceeds this many
#: log2 units (a factor √2): the linearised σ of a log-scale parameter understates its long tail.
RESOLVE_THETA = 0.5
#: A lobe's height (ks) beside a free shape is judged as its shape is, in log2 units: one-sigma
#: past RESOLVE_THETA log2 units of its value (a factor √2, σ over 0.35 of ks) is undetermined.
#: Along the ridge of a barely seen lobe its height's σ shrinks with its estimate: zoo seed 28 at
#: 160x120, seven photographs, gave a wall's ks 0.35 ± 0.15 for 1.09 (5σ), where four other noise
#: realisations gave 0.64-1.21 ± 0.42-0.62 and the noise-free photographs leave it undetermined.
RESOLVE_LOBE = RESOLVE_THETA * np.log(2.0)
#: Within this (relative) distance of a bound a parameter counts as pinned there.
BOUND_TOL = 1e-3
#: Column signal below this fraction of the image peak counts as none.
SIGNAL_FLOOR = 1e-9
#: A pixel where directly seen texture carries at least this share of the light says nothing about
#: the other parameters once the texture is free (:func:`texture_absorbed`).
ABSORB_SHARE = 0.02


def structural_free(pb: Problem, p: Params) -> Free:
    """Parameters with signal in their columns (exact zeros left out).

    Signal counts at the initial θ or anywhere on the global scan's grid (:mod:`reflab.inverse.fit.ftbo`): a start
    at ns = 2^14 hides every highlight that a broader lobe would show.
    """
    fac, lay, srch = pb.fac, pb.fac.layout, pb.search
    floor = SIGNAL_FLOOR * max(pb.peak, 1e-300)
    live = np.zeros((fac.n_columns, BANDS), dtype=bool)
    th_free = np.zeros(lay.n_theta, dtype=bool)
    u0 = srch.to_u(p.theta)
    for k in range(SCAN_POINTS + 1 if lay.n_theta else 1):  # the initial θ, then the scan grid
        u = u0 if k == 0 else pb.scan_lo + (pb.scan_hi - pb.scan_lo) * (k - 1) / (SCAN_POINTS - 1)
        A, grad = fac.matrices_and_grad(srch.to_theta(u))
        now = np.stack([abs(A[c]).max(axis=0).toarray().ravel() for c in range(BANDS)], axis=1) > floor  # (C, 3)
        live |= now
        if lay.n_theta:
            # θ acts through the columns of its surface's x: only those with signal count.
            img, _ = grad.images(now.T.astype(np.float64), compact=True)  # only the rows θ reach
            th_free |= np.abs(img).max(axis=(1, 2), initial=0.0) > floor
            if th_free.all() and k > 0:
                break
    x_free = np.zeros((lay.n_x, BANDS), dtype=bool)
    np.logical_or.at(x_free, fac.col_x, live)
    s_free = np.zeros((lay.n_factors, BANDS), dtype=bool)
    for f in np.flatnonzero(fac.exponents.any(axis=0)):
        s_free[f] = live[fac.exponents[:, f] > 0].any(axis=0)
    for i, transparent in enumerate(pb.transparent):
        if not transparent:
            s_free[2 * i + 1] = False
    return Free(x_free, s_free, th_free)


def unresolved(pb: Problem, p: Params, init: Params, free: Free, sig: Params, A, theta_resolve=RESOLVE,
                bounds_hold: bool = True, lobe_resolve: float = RESOLVE) -> Free:
    """Free parameters whose one-sigma exceeds :data:`RESOLVE` of their scale (a lobe's height
    beside a free shape: ``lobe_resolve``; the report passes :data:`RESOLVE_LOBE`, the fit's
    holding rounds keep :data:`RESOLVE`, holding at its start a height they could still fit).

    ``A`` = ``fac.matrices(p.theta)``, the system at the fitted θ. With ``bounds_hold`` a value
    pinned at a bound counts as determined whatever its σ (the fit's rounds); without, it is
    judged by its σ like any other (the final report: ks = 0 ± 3000 is undetermined).
    """
    fac = pb.fac
    # Scale of x: its value, but at most 1 (albedo units) — a ks of 1e9 under a faint lobe tail
    # must not count as resolved relative to itself — and at least its initial value.
    xs = np.maximum(np.maximum(np.minimum(np.abs(p.x), 1.0), np.abs(init.x)), 1e-3)
    # A parameter pinned at a bound is held there by the data (moving inside would show), even
    # where the linearisation is blind to it (t² has zero slope at t = 0) — but only if its
    # columns show at the fitted θ (ks = 0 under a held ns = 2^14 is seen by no pixel).
    live = np.stack([abs(A[c]).max(axis=0).toarray().ravel() for c in range(BANDS)], axis=1) > SIGNAL_FLOOR * max(pb.peak, 1e-300)
    seen = np.zeros_like(free.x)
    np.logical_or.at(seen, fac.col_x, live)
    lay = fac.layout
    shaped = np.zeros_like(free.x)
    for k, (s, name) in enumerate(lay.x_names):
        if name == "ks" and np.any(free.theta[lay.theta_offset[s]:lay.theta_offset[s + 1]]):
            shaped[k] = True
    limit = np.where(shaped, lobe_resolve, RESOLVE) * xs
    bad_x = free.x & ~(sig.x <= limit) & ((p.x > BOUND_TOL * xs) | ~seen | (not bounds_hold))
    bad_s = free.s & ~(sig.s <= RESOLVE) & (((p.s > BOUND_TOL) & (p.s < 1.0 - BOUND_TOL)) | (not bounds_hold))
    # A shininess pinned at its lower bound is a lobe as broad as diffuse light: it trades with kd
    # and fits misfit, not a highlight (docs/fit.md). So is a Ward α at its upper bound; at its
    # lower one, a spike as sharp as the range allows, it is a limit, not an estimate.
    u = pb.search.to_u(p.theta)
    pinned = pb.search.log & ((u <= pb.search.lo + 1e-6) | (pb.search.wider_up & (u >= pb.search.hi - 1e-6)))
    bad_t = free.theta & (~(theta_resolution(pb, p, sig) <= theta_resolve) | pinned)
    return Free(bad_x, bad_s, bad_t)


def theta_resolution(pb: Problem, p: Params, sig: Params) -> np.ndarray:
    """σ of each θ relative to its scale: in log2 units for :data:`LOG2` names, else of the range."""
    srch = pb.search
    return np.where(srch.log, sig.theta / np.maximum(p.theta * np.log(2.0), 1e-300),
                    sig.theta / np.maximum(srch.hi - srch.lo, 1e-300))


def hold(fac: Factorization, free: Free, held) -> None:
    """Take the user-given parameters (per surface, a set of names) out of ``free`` in place."""
    lay = fac.layout
    for k, (s, name) in enumerate(lay.x_names):
        if name in held[s]:
            free.x[k] = False
    for q, (s, name) in enumerate(lay.theta_names):
        if name in held[s]:
            free.theta[q] = False
    for i in range(len(fac.models)):
        if "r" in held[i]:
            free.s[2 * i] = False
        if "t" in held[i]:
            free.s[2 * i + 1] = False


def undetermined_names(fac: Factorization, free: Free, materials, loose: Free | None = None) -> list:
    """Per surface, the names of the parameters held at their initial value ("ks[2]" for one band),
    and of those fitted whose (robust) σ exceeds their scale (``loose``)."""
    lay, out = fac.layout, []
    if loose is None:
        loose = Free(np.zeros_like(free.x), np.zeros_like(free.s), np.zeros_like(free.theta))
    for i, (model, mat) in enumerate(zip(fac.models, materials)):
        names = []
        for j, name in enumerate(model.linear):
            k = lay.x_offset[i] + j
            names += _band_names(name, ~free.x[k] | loose.x[k])
        names += _band_names("r", ~free.s[2 * i] | loose.s[2 * i])
        names += _band_names("t", ~free.s[2 * i + 1] | loose.s[2 * i + 1])
        names += [name for j, name in enumerate(model.nonlinear)
                  if not free.theta[lay.theta_offset[i] + j] or loose.theta[lay.theta_offset[i] + j]]
        out.append(names)
    return out


def _band_names(name, held) -> list:
    if held.all():
        return [name]
    return [f"{name}[{c}]" for c in np.flatnonzero(held)]


def texture_confounded(pb: Problem, p: Params, materials, textured) -> tuple[np.ndarray, np.ndarray]:
    """(n_factors, 3) bool twice: the r and t of textured surfaces whose every pixel of signal is one
    where free texture shows (:func:`texture_absorbed`); and of those, the ones that pixels of
    texels seen twice show (:func:`twice_rows`).

    A textured surface's own faint reflection (or transmission) of a smooth surrounding is, pixel
    for pixel, light its free texture can take up; no pixel of a texel seen once tells the two
    apart. Fitted anyway against one kd (the homogeneous start), the coefficient takes up the
    texture's correlation with the reflected light instead (a box on a matte ground: r 0.1–0.2 per
    band for a true 0), and the texture rounds, which leave out the pixels it claims, lose the whole
    surface. Such a coefficient is held at 0 in that fit. Where texels seen twice (in two
    photographs, or directly and in a mirror) show it, their pixels share one albedo and the
    coefficient shows in how they differ: the fits against the recovered texture fit it (the
    second mask, :func:`reflab.inverse.fit.rounds.fit` keeps it in the structure) and its σ is
    judged like the surface's own lobe; otherwise it stays held and is reported undetermined
    (docs/fit.md).
    """
    fac = pb.fac
    out = np.zeros((fac.layout.n_factors, BANDS), dtype=bool)
    twice = out.copy()
    if textured is None or not any(textured):
        return out, twice
    factors = [f for i in np.flatnonzero(np.asarray(textured, dtype=bool)) for f in (2 * i, 2 * i + 1)
               if fac.exponents[:, f].any()]
    if not factors:
        return out, twice
    absorbed, _ = texture_absorbed(fac, p, materials, textured)
    A = fac.matrices(p.theta)
    floor = SIGNAL_FLOOR * max(pb.peak, 1e-300)

    def shown(rows):
        if not rows.any():
            return np.zeros((fac.n_columns, BANDS), dtype=bool)
        return np.stack([abs(A[c][rows]).max(axis=0).toarray().ravel() for c in range(BANDS)], axis=1) > floor

    clear = shown(~absorbed)
    for f in factors:
        out[f] = ~clear[(fac.exponents[:, f] > 0)].any(axis=0)
    held = np.zeros(len(textured), dtype=bool)
    held[[f // 2 for f in factors if out[f].any()]] = True
    if held.any():  # texels seen twice only for the surfaces whose r or t is held (a lambert ground's 300 000 nodes are not grouped)
        paired = shown(twice_rows(fac, held))
        for f in factors:
            twice[f] = out[f] & paired[(fac.exponents[:, f] > 0)].any(axis=0)
    return out, twice


def twice_rows(fac: Factorization, textured) -> np.ndarray:
    """(R,) bool: used pixels with a node of a texel of a textured surface that another used pixel
    sees too (:func:`texel_groups`: in another photograph, or in a mirror or through glass)."""
    tr = fac.trees
    group = texel_groups(tr, textured)
    row_of = np.full(fac.width * fac.height, -1, dtype=np.int64)
    row_of[fac.rows] = np.arange(fac.n_rows)
    row = row_of[np.asarray(tr.pixel, dtype=np.int64)]
    nodes = np.flatnonzero((group >= 0) & (row >= 0))
    out = np.zeros(fac.n_rows, dtype=bool)
    if len(nodes) == 0:
        return out
    # Distinct (texel, pixel) pairs: two nodes of one texel in one pixel are not two views.
    pairs = np.unique(np.stack([group[nodes], row[nodes]], axis=1), axis=0)
    ids, g, count = np.unique(pairs[:, 0], return_inverse=True, return_counts=True)
    out[pairs[count[g.reshape(-1)] >= 2, 1]] = True
    return out


def _free_texture_nodes(tr, textured) -> tuple[np.ndarray, np.ndarray]:
    """(N,) bool twice: nodes of textured surfaces; those whose texel no direct view pins (free).

    Geometry only: kept on the trees for the same ``textured`` flags (a fit asks twice).
    """
    flags = tuple(bool(t) for t in textured)

    def nodes():
        surf, level, pts = np.asarray(tr.surface), np.asarray(tr.level), np.asarray(tr.point, dtype=np.float64)
        tex = np.asarray(flags, dtype=bool)[surf]
        free_tex = tex & (level == 1)
        for s in np.flatnonzero(flags):
            direct, seen_else = (surf == s) & (level == 1), (surf == s) & (level > 1)
            if not seen_else.any():
                continue
            if not direct.any():
                free_tex |= seen_else
                continue
            ext = np.sort(np.ptp(pts[direct], axis=0))[::-1]
            cell = 2.0 * np.sqrt(max(ext[0] * ext[1], 1e-12) / direct.sum())
            key = np.floor(pts / cell).astype(np.int64)
            both = direct | seen_else
            lo = key[both].min(axis=0)
            span = key[both].max(axis=0) - lo + 1
            flat = np.ravel_multi_index(tuple((key - lo).clip(0).T), tuple(span), mode="clip")
            free_tex |= seen_else & ~np.isin(flat, flat[direct])
        return tex, free_tex

    return derived(tr, "free texture nodes", (flags, tr.point), nodes)


def texture_absorbed(fac: Factorization, p: Params, materials, textured) -> tuple[np.ndarray, np.ndarray]:
    """(R,) bool twice: used pixels where free texture carries at least :data:`ABSORB_SHARE` of the
    predicted light in some band; and the same counting every textured node as free.

    A texture free per texel (about one per pixel) can take up any residual where it shows — a
    highlight, a faint reflection — unless the same texel is pinned down elsewhere. Texture seen
    directly is free; texture seen only in a mirror or through glass (the demo box's back face) is
    free too; texture seen there AND directly (a floor in a mirror) is fixed by the direct view.
    So only pixels without free texture tell a specular term from albedo. Which points are seen
    directly: cells of twice the mean spacing of the surface's directly seen nodes. The second
    mask, with no texture pinned, is for a textured surface's own lobe, whose pinning view carries
    the same lobe (:func:`reflab.inverse.fit.rounds.fit`).
    """
    if textured is None or not any(textured):
        return np.zeros(fac.n_rows, dtype=bool), np.zeros(fac.n_rows, dtype=bool)
    from reflab.inverse.forward.rendering import linear_basis_and_grad, node_radiance

    tr = fac.trees
    tex, free_tex = _free_texture_nodes(tr, textured)  # geometry of every node: a view pins what it sees
    npix = fac.width * fac.height
    used = np.zeros(npix, dtype=bool)
    used[fac.rows] = True
    on = used[np.asarray(tr.pixel, dtype=np.int64)]
    mats = materials_of(fac, p, materials)
    if on.mean() < 0.5:
        # The light of the used pixels' nodes alone (a pilot reads 15 000 of 300 000 pixels; the
        # same numbers, node for node), its basis formed apart: linear_basis keeps the whole
        # trees' last one, from which the sample's choice updates only the surfaces whose θ moved.
        tr, tex, free_tex = tr.of_pixels(used), tex[on], free_tex[on]
        light = np.abs(node_radiance(tr, mats, fac._args[0],
                                     basis=linear_basis_and_grad(tr, mats, fac._args[0], grad=False)[0]))
    else:
        light = np.abs(node_radiance(tr, mats, fac._args[0]))
    out, anywhere = np.zeros(fac.n_rows, dtype=bool), np.zeros(fac.n_rows, dtype=bool)
    for c in range(BANDS):
        total = ABSORB_SHARE * np.maximum(np.bincount(tr.pixel, weights=light[:, c], minlength=npix)[fac.rows], 1e-300)
        out |= np.bincount(tr.pixel[free_tex], weights=light[free_tex, c], minlength=npix)[fac.rows] > total
        anywhere |= np.bincount(tr.pixel[tex], weights=light[tex, c], minlength=npix)[fac.rows] > total
    return out, anywhere


def _photograph_of(tr) -> np.ndarray:
    """(N,) the photograph of each node of stacked trees (``stats["block_row0"]``); 0 for one."""
    stats = getattr(tr, "stats", None)
    row0 = stats.get("block_row0") if isinstance(stats, dict) else None
    if row0 is None or len(row0) < 2:
        return np.zeros(len(tr.pixel), dtype=np.int64)
    from reflab.inverse.forward.photographs import photograph_of

    return photograph_of(tr.pixel, row0, tr.width)


def texel_groups(tr, textured) -> np.ndarray:
    """(N,) each textured node's texel, as the index of the directly seen node that starts it; −1
    elsewhere.

    A texel is one point of the surface, whatever photograph sees it. The first photograph's
    directly seen nodes each start one (one pixel's worth of albedo); a later photograph's direct
    node joins the nearest texel start within half the first photograph's median spacing of them
    (the same point), else starts a texel of its own. A node of the same surface seen in a mirror
    or through glass joins the nearest start within that distance, and stays out otherwise.
    Geometry only: kept on the trees for the same ``textured`` flags.
    """
    from scipy.spatial import cKDTree

    flags = tuple(bool(t) for t in textured)

    def groups():
        surf, level, pts = np.asarray(tr.surface), np.asarray(tr.level), np.asarray(tr.point, dtype=np.float64)
        photo = _photograph_of(tr)
        several = photo.max(initial=0) > 0
        out = np.full(len(surf), -1, dtype=np.int64)
        for s in np.flatnonzero(flags):
            direct = np.flatnonzero((surf == s) & (level == 1))
            other = np.flatnonzero((surf == s) & (level > 1))
            if len(direct) < 2 or (len(other) == 0 and not several):
                continue
            order = np.unique(photo[direct])
            starts = direct[photo[direct] == order[0]]
            first = starts if len(starts) >= 2 else direct
            sample = first[:: max(1, len(first) // 4096)]  # the median spacing, from a few thousand
            index = cKDTree(pts[first])
            spacing = float(np.median(index.query(pts[sample], k=2)[0][:, 1]))
            out[starts] = starts
            for k in order[1:]:  # a loop over photographs, not nodes
                mine = direct[photo[direct] == k]
                dist, near = cKDTree(pts[starts]).query(pts[mine])
                same = dist < 0.5 * spacing
                out[mine[same]] = starts[near[same]]
                out[mine[~same]] = mine[~same]
                starts = np.concatenate([starts, mine[~same]])
            if len(other):  # one photograph: its direct nodes are the starts, whose index is built
                dist, near = (index if len(order) == 1 else cKDTree(pts[starts])).query(pts[other])
                same = dist < 0.5 * spacing
                out[other[same]] = starts[near[same]]
        return out

    return derived(tr, "texel groups", (flags, tr.point), groups)


def seen_twice(pb: Problem, p: Params, materials, textured, anywhere, res, lobed=None):
    """``extra`` for :func:`reflab.inverse.fit.uncertainty.sigmas`: what pixels of textured surfaces seen
    twice (in two photographs, or directly and in a mirror or through glass) say with each
    texel's albedo free; None when no texel is seen twice. ``lobed`` (default ``textured``): the
    surfaces whose texels are grouped, those whose own lobe is judged (a lambert ground seen in a
    mirror has none: its 300 000 nodes at 640x480 are not grouped).

    A texel seen once is explained by its own albedo whatever the lobe; seen twice, at two angles,
    its two pixels must share one albedo, and the lobe's (or the reflection's) part shows in how
    they differ (:func:`reflab.inverse.fit.uncertainty.profiled`). Only pixels ``anywhere`` marks
    (the others already inform the σ fully) where the texel's node carries at least
    :data:`ABSORB_SHARE` of the pixel's light in some band and no other free or grouped textured
    node does (a texture a direct view pins, the ground the box reflects, is known there as in
    :func:`texture_absorbed`); a pixel that fails is left out, and its texel counts while two of
    its pixels remain (a lamp alone leaves half the lab's box dark in the pixels that see it).
    A weighed sample's rows (``pb.scale``) weigh the texel's direction alike.
    """
    if textured is None or not any(textured):
        return None
    from reflab.inverse.forward.rendering import linear_basis, node_radiance, path_products

    fac = pb.fac
    tr = fac.trees
    group = texel_groups(tr, textured if lobed is None else np.asarray(lobed, dtype=bool) & np.asarray(textured, dtype=bool))
    row_of = np.full(fac.width * fac.height, -1, dtype=np.int64)
    row_of[fac.rows] = np.arange(fac.n_rows)
    row = row_of[tr.pixel]
    nodes = np.flatnonzero((group >= 0) & (row >= 0))
    if len(nodes) == 0:
        return None
    mats = materials_of(fac, p, materials)
    used = row >= 0
    radiance = np.abs(node_radiance(tr, mats, fac._args[0]))  # (N, 3)
    total = np.stack([np.bincount(row[used], weights=radiance[used, c], minlength=fac.n_rows) for c in range(BANDS)], axis=1)
    tex = np.flatnonzero(np.asarray(textured, dtype=bool)[tr.surface] & used)
    light = radiance[tex]
    matters = np.zeros(len(tr.surface), dtype=bool)
    matters[tex] = (light >= ABSORB_SHARE * np.maximum(total[row[tex]], 1e-300)).any(axis=1)
    # Another surface's texture a direct view pins (the ground reflected in the box) is known
    # there, as texture_absorbed takes it: only free texture and the grouped texels count.
    counted = matters & (_free_texture_nodes(tr, textured)[1] | (group >= 0))
    n_textured = np.bincount(row[counted], minlength=fac.n_rows)
    ok = matters[nodes] & (n_textured[row[nodes]] == 1) & np.asarray(anywhere, dtype=bool)[row[nodes]]
    # A node that fails drops its pixel, not its texel: the others still share one albedo.
    nodes = nodes[ok]
    ids, g = np.unique(group[nodes], return_inverse=True)
    nodes = nodes[np.bincount(g, minlength=len(ids))[g] >= 2]
    if len(nodes) == 0:
        return None
    _, g = np.unique(group[nodes], return_inverse=True)
    rows = row[nodes]
    e = (linear_basis(tr, mats, fac._args[0])[nodes, :, 0] * path_products(tr, mats)[nodes]).T  # (3, m)
    if getattr(pb, "scale", None) is not None:
        e = e * pb.scale[rows]  # the rows of J are weighed by √w: the texel's direction too

    def extra(free, weights, tiles):
        tile, n_tiles = tiles
        return profiled(row_jacobian(pb, p, free, rows), e, g, weights, res[:, rows], tile[rows], n_tiles)

    return extra


def plausible_lobes(pb: Problem, p: Params, free: Free, loose: Free, sigma_free: Free, res, materials=None,
                    textured=None, fitted: Free | None = None, weighed: dict | None = None) -> tuple[Params, dict, Free]:
    """Every lobe the data leave open at the value they and the prior over the field's lobes agree on.

    A lobe is open when its ks is undetermined (``loose``, or held by the holding rounds: not in
    ``fitted``, default ``free``) and not the user's (``sigma_free``); ``free`` is what the fit
    fitted, refitted here. Its shape (ns, Ward α), when undetermined too, is weighed at the shapes
    of :data:`reflab.inverse.fit.ranges.SHAPE_GRID`, the prior's centre and its fitted one. At
    each, every free linear parameter (its ks included) is fitted again with the shape held (the
    profile: F-TBO's exact inner solve), and what the data say of the lobe's albedo there — one
    grey ``â ± σ``, the bands' conditional ks × ``L(shape)`` weighed by their model-based σ — is
    weighed with the prior over lobe albedos (:func:`reflab.inverse.fit.ranges.lobe_evidence`).
    The shape taken is the one of highest posterior, the prior's
    (:func:`reflab.inverse.fit.ranges.shape_prior`) × the profile likelihood ``exp(−χ²/2)`` (χ² in
    the residual's variance) × that evidence; its ks is the posterior mean albedo over
    ``L(shape)``, and the other linear parameters are fitted again with the lobe held there. So a
    lobe the photographs show no trace of at a shape is rendered there as the data bound it (a
    mirror's lobe held at ks 0.1, ns 3.4 added light to every view of floor_mirror, which the
    photographs bound near 0), a lobe they show where they show it, and one no pixel shows at the
    prior's mean, at a shape whose highlight falls where no photograph looked.

    Which pixels inform: another surface's lobe the pixels where no free texture shows
    (:func:`texture_absorbed`), as its σ. A textured surface's own lobe is weighed only while its
    shape is still the fit's start (no round shaped it), on every pixel with its texture as the
    fit holds it (its texture-free pixels may hold none of the lobe, and a lobe brighter than the
    surface would need a negative texture); one a round shaped from every pixel keeps that shape
    and height (weighed again against the texture made under it, its height ran to the range's
    top, and zoo seed 10's box moved from its fitted ns 5, true 6.2, to 8 at twice the albedo),
    and only :func:`reflab.inverse.fit.ranges.plausible` moves it, off a bound. Images of more
    than :data:`reflab.inverse.fit.ftbo.COARSE_MIN_ROWS` pixels are weighed on F-TBO's coarse
    subsample (:func:`reflab.inverse.fit.ftbo.coarse_problem`), its χ² and information scaled to
    the full image. σ is not touched: the values stay undetermined. They are values to report and
    render, not to start a fit from (a lobe bounded near 0 shows no shininess): a fit that seeds
    another runs without σ and never comes here.

    Returns
    -------
    p : Params
        A copy with the lobes moved (and the linear parameters refitted to them).
    moved : dict
        Surface index → what fit.json's ``plausible_lobes`` says of each lobe moved: its shape
        (``ns`` or ``alpha``), ``ks``, ``albedo`` and ``basis`` — ``"photographs"`` (they pin
        its albedo to a tenth of the prior's range), ``"none"`` (they pin it within a σ of 0),
        ``"prior"`` (they bound a lobe of that shape more loosely: the prior shapes the value).
    handled : Free
        The lobes weighed, ks and shape: :func:`reflab.inverse.fit.ranges.plausible` leaves them alone.

    ``weighed``, when given, receives per surface index every shape weighed, moved or not, in
    increasing shape: a list of ``moved``'s records with ``log_posterior`` (fit.json's
    ``lobe_shapes``), the hypotheses :mod:`reflab.inverse.plan` predicts a shot under.
    """
    fitted = free if fitted is None else fitted
    handled = Free(np.zeros_like(free.x), np.zeros_like(free.s), np.zeros_like(free.theta))
    lobes = _open_lobes(pb.fac, free, loose, sigma_free, fitted)
    if not lobes or pb.out_of_time():  # a spent budget: no more solves (ranges.plausible still moves bounds)
        return p.copy(), {}, handled
    from reflab.inverse.fit.ftbo import coarse_problem, ftbo

    fac = pb.fac
    small = coarse_problem(pb) or pb
    scale = pb.fac.n_rows / max(small.fac.n_rows, 1)  # the full image's χ² and information per the subsample's
    masks = (texture_absorbed(small.fac, p, materials, textured) if textured is not None and any(textured) else None)
    p, moved = p.copy(), {}
    for s, k, q, bands, open_shape in lobes:
        model, name = fac.models[s], fac.models[s].nonlinear[0]
        own = textured is not None and bool(textured[s])
        if own and not np.isclose(p.theta[q], INITIAL[name], rtol=1e-9, atol=0.0):
            continue  # a textured lobe an earlier round shaped from every pixel: no better estimate here
        keep = np.ones(small.fac.n_rows, dtype=bool) if masks is None or own else ~masks[0]
        lin = Free(free.x.copy(), free.s.copy(), np.zeros_like(free.theta))
        lin.x[k] |= bands
        shapes = [float(p.theta[q])]
        if open_shape:
            from reflab.inverse.fit.ranges import SHAPE_GRID

            lo, hi = (float(v[q]) for v in (small.search.to_theta(small.search.lo), small.search.to_theta(small.search.hi)))
            shapes += [float(v) for v in np.append(SHAPE_GRID[name], INITIAL[name]) if lo <= v <= hi]
        shapes = list(dict.fromkeys(shapes))  # the fitted shape may be the prior's centre: weighed once
        tried = [_weigh(small, p, lin, k, q, value, bands, keep, scale, model, name, res) for value in shapes]
        best = max(tried, key=lambda w: w[0])
        if weighed is not None:
            weighed[s] = [{**rec, "log_posterior": lp} for lp, _, _, rec in sorted(tried, key=lambda w: w[1])]
        _, value, ks, record = best
        cur = p.copy()
        cur.theta[q] = value
        # One grey lobe (the field's lobes are the lamp's colour): in every band, unless the data
        # determine some bands (those stay: a partly open lobe takes the value in its open bands).
        cur.x[k, bands if (sigma_free.x[k] & ~bands).any() else slice(None)] = ks
        held = Free(lin.x.copy(), lin.s, lin.theta)
        held.x[k] = False
        cur = ftbo(pb, cur, held, 0.0, [], scan=False)[0]  # the rest fitted again to the lobe
        if value != p.theta[q] or not np.allclose(cur.x[k], p.x[k]):
            moved[s] = record
        p = cur
        free = free.copy()
        free.x[k] = False  # the next lobe's solves keep this one where it is now
        handled.x[k] |= bands
        handled.theta[q] = open_shape
    return p, moved, handled


def _open_lobes(fac: Factorization, free: Free, loose: Free, sigma_free: Free, fitted: Free) -> list:
    """``(surface, ks index, shape index, open ks bands, shape open)`` of each lobe whose ks the data
    leave open (:func:`plausible_lobes`)."""
    lay, out = fac.layout, []
    for s, model in enumerate(fac.models):
        if "ks" not in model.linear or not model.nonlinear:
            continue
        k, q = lay.x_offset[s] + model.linear.index("ks"), lay.theta_offset[s]
        bands = sigma_free.x[k] & (loose.x[k] | ~fitted.x[k])
        if bands.any():
            out.append((s, k, q, bands, bool(sigma_free.theta[q] and (loose.theta[q] or not fitted.theta[q]))))
    return out


def _weigh(pb: Problem, p: Params, lin: Free, k: int, q: int, value: float, bands, keep, scale: float, model, name,
           res) -> tuple[float, float, float, dict]:
    """(log posterior, shape, posterior mean ks, fit.json's record) of a lobe held at shape ``value``
    (:func:`plausible_lobes`)."""
    from reflab.inverse.fit.ftbo import ftbo
    from reflab.inverse.fit.problem import NOISE_FLOOR
    from reflab.inverse.fit.ranges import LOBE_ALBEDO, lobe_albedo, lobe_evidence, shape_prior
    from reflab.inverse.fit.uncertainty import sigmas

    pb.task.check()  # a cancel between the solves (each a fraction of a second)
    cur = p.copy()
    cur.theta[q] = value
    cur = ftbo(pb, cur, lin, 0.0, [], scan=False)[0]  # the exact linear solve at this shape
    r = pb.residual(pb.fac.matrices(cur.theta), pb.fac.y(cur.x, cur.s))  # its matrices: cached by the solve
    # χ² in the fitted residual's variance per band (the same for every shape weighed).
    var = np.maximum(np.sum(res * res, axis=1) / max(res.shape[1] - 1, 1), (NOISE_FLOOR * max(pb.peak, 1e-300)) ** 2)
    chi2 = scale * float(np.sum(r[:, keep] ** 2 / var[:, None]))
    L = lobe_albedo(model, value)
    a = cur.x[k, bands] * L
    sd = sigmas(pb, cur, lin, r, robust=False, keep=keep).x[k, bands] * L / np.sqrt(scale)
    # One grey lobe: the bands' estimates combined by their information, their spread a misfit.
    # A band with σ beyond 1e150 says nothing (its square would overflow).
    w = np.where((sd > 0) & (sd < 1e150), 1.0 / np.clip(sd, 1e-150, 1e150) ** 2, 0.0)
    if w.sum() > 0:
        a_hat, s_hat = float(np.sum(w * a) / w.sum()), float(1.0 / np.sqrt(w.sum()))
        chi2 += float(np.sum(w * (a - a_hat) ** 2))
    else:
        a_hat, s_hat = 0.0, np.inf
    evidence, mean = lobe_evidence([a_hat], [s_hat])
    # What the value rests on: the prior where the data bound the albedo no better than a tenth of
    # its range, else the photographs — "none" where they put it within a σ of 0.
    basis = "prior" if not s_hat <= 0.1 * LOBE_ALBEDO else ("none" if mean[0] < s_hat else "photographs")
    return (float(shape_prior(name, value)) - 0.5 * chi2 + evidence, value, float(mean[0]) / L,
            {name: value, "ks": float(mean[0]) / L, "albedo": float(mean[0]), "basis": basis})
