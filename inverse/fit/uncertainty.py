"""One-sigma uncertainties of the fitted parameters that hold when the model is imperfect.

The textbook covariance ``σ² (JᵀJ)⁻¹`` assumes independent Gaussian pixel noise around a
correct model. A textured photograph breaks that: where the fit holds an albedo constant (or the
recovered texture is imperfect), the residual is spatially correlated over whole texture
features, edges misalign over runs of pixels, and ``σ² (JᵀJ)⁻¹`` then reports errors 100 times
too small (docs/fit.md). So the covariance is the larger, per parameter, of

- the **model-based** one, ``H⁻¹`` with ``H = JᵀWJ``, ``W = 1/σ_c²`` per band (σ_c from the
  residual, never below :data:`reflab.inverse.fit.problem.NOISE_FLOOR` of the peak); and
- the **cluster-robust sandwich** over image tiles, ``H⁻¹ M H⁻¹`` with ``M = T/(T−1) Σ_t g_t g_tᵀ``
  and ``g_t = Σ_{i ∈ tile t} J_iᵀ W r_i`` (the gradient of the objective contributed by tile t):
  the spread of the parameters that the residual's actual structure implies, correlations within
  a tile included (Liang–Zeger; White's heteroscedastic sandwich for one-pixel tiles).

When the model is right both agree (the sandwich is the noisier estimate); when it is not, the
sandwich grows with the misfit that correlates with each parameter's image, which is what moves
that parameter. A linear parameter's σ is never NaN: directions the data do not constrain get
``inf`` (and are judged undetermined by the caller).
"""
from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix, diags

from reflab.inverse.forward.factorization import BANDS, gram
from reflab.inverse.forward.photographs import photograph_of
from reflab.inverse.fit.problem import NOISE_FLOOR, Free, Params, Problem

#: Target number of tiles across the image's shorter side (tile size = shorter side / this, ≥ 4 px).
TILES_ACROSS = 12
#: The sandwich is also taken over tiles this many times larger (about 4 across the short side),
#: the larger σ kept: misfit coherent over a whole surface (reconstructed geometry, a texture
#: regressed on noisy texels) is one cluster at the fine scale and shows only at the coarse one.
COARSE_FACTOR = 3
#: Smallest tile side in pixels.
MIN_TILE = 4


def tile_size(width: int, height: int) -> int:
    """Side in pixels of the square tiles of the sandwich (about :data:`TILES_ACROSS` on the short side)."""
    return max(MIN_TILE, int(min(width, height)) // TILES_ACROSS)


def tile_index(rows: np.ndarray, width: int, height: int) -> tuple[np.ndarray, int]:
    """Tile of each used pixel (flat index ``rows``), renumbered 0..T−1 over the tiles in use."""
    side = tile_size(width, height)
    nx = -(-width // side)
    rows = np.asarray(rows)
    tile = (rows // width // side) * nx + (rows % width) // side
    used, inv = np.unique(tile, return_inverse=True)
    return inv.reshape(-1), len(used)


def coarser(rows: np.ndarray, width: int, height: int, factor: int) -> tuple[np.ndarray, int]:
    """(T,) the tile of ``factor`` x ``factor`` fine tiles (:func:`tile_index`) holding each fine tile, and their count."""
    side = tile_size(width, height)
    rows = np.asarray(rows)
    fine, n_fine = tile_index(rows, width, height)
    big = side * factor
    coarse = (rows // width // big) * (-(-width // big)) + (rows % width) // big
    used, inv = np.unique(coarse, return_inverse=True)
    out = np.zeros(n_fine, dtype=np.int64)
    out[fine] = inv.reshape(-1)
    return out, len(used)


def covariance(H: np.ndarray, scores: np.ndarray | None = None, middle: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Standard deviations from the normal matrix ``H`` (n, n) and tile scores (n, T).

    ``middle`` (n, n): for rows weighed by a sample's 1/p (Horvitz–Thompson), ``Σ w² JᵀWJ``, the
    noise's variance of the weighted score; the model-based covariance is then ``H⁻¹ middle H⁻¹``
    (``H⁻¹`` when every weight is 1).

    Returns
    -------
    model : (n,) ndarray
        ``sqrt(diag(H⁻¹))`` (``sqrt(diag(H⁻¹ middle H⁻¹))``); ``inf`` where ``H`` is singular along the parameter.
    robust : (n,) ndarray
        ``sqrt(diag(H⁻¹ M H⁻¹))`` (``model`` where no scores are given); ``inf`` likewise.
    """
    n = H.shape[0]
    model = np.full(n, np.inf)
    robust = np.full(n, np.inf)
    if n == 0:
        return model, robust
    dg = np.sqrt(np.maximum(np.diag(H), 0.0))
    ok = dg > 0
    if not ok.any():
        return model, robust
    Hs = H[np.ix_(ok, ok)] / np.outer(dg[ok], dg[ok])
    w, V = np.linalg.eigh(Hs)
    floor = 1e-14 * max(w.max(), 1e-300)
    w = np.maximum(w, floor)
    inv = (V / w) @ V.T  # scaled (H⁻¹ up to the diagonal scaling)
    if middle is None:
        model[ok] = np.sqrt(np.maximum(np.diag(inv), 0.0)) / dg[ok]
    else:
        mid = middle[np.ix_(ok, ok)] / np.outer(dg[ok], dg[ok])
        model[ok] = np.sqrt(np.maximum(np.einsum("ij,jk,ki->i", inv, mid, inv), 0.0)) / dg[ok]
    if scores is None or scores.shape[1] < 2:
        robust[:] = model
        return model, robust
    T = scores.shape[1]
    G = scores[ok] / dg[ok, None]
    B = inv @ G  # (n_ok, T)
    var = np.einsum("it,it->i", B, B) * T / (T - 1.0)
    robust[ok] = np.sqrt(np.maximum(var, 0.0)) / dg[ok]
    return model, robust


def robust_sd(H: np.ndarray, scores: np.ndarray | None, rows, width: int, height: int, blocks=None,
              middle: np.ndarray | None = None) -> np.ndarray:
    """(n,) the larger, per parameter, of the model-based σ and the sandwich over the fine tiles
    (``scores`` (n, T) summed per :func:`tile_index` of the used pixels ``rows``; None: the model's
    alone) and over tiles :data:`COARSE_FACTOR` times larger; inf where unconstrained, never NaN.

    ``blocks``: the first pixel row of each photograph of a stacked image (several photographs,
    :mod:`reflab.inverse.forward.photographs`): the sandwich is also taken over whole photographs.
    A misfit that one photograph's pixels share (a highlight a slightly wrong geometry shows in
    the wrong place, in the only photograph that shows it) is one cluster there, and the tiles'
    sandwich, where it spans one or two tiles, would not see it. ``middle``: as :func:`covariance`
    takes it (weighted rows)."""
    model, sandwich = covariance(H, scores, middle)
    if scores is not None:
        group, n_big = coarser(rows, width, height, COARSE_FACTOR)
        big = np.zeros((scores.shape[0], n_big))
        np.add.at(big.T, group, scores.T)
        sandwich = np.fmax(sandwich, covariance(H, big)[1])
        if blocks is not None and len(blocks) > 1:
            fine, n_fine = tile_index(rows, width, height)
            photo_of_tile = np.zeros(n_fine, dtype=np.int64)
            photo_of_tile[fine] = photograph_of(rows, blocks, width)
            per_photo = np.zeros((scores.shape[0], len(blocks)))
            np.add.at(per_photo.T, photo_of_tile, scores.T)
            sandwich = np.fmax(sandwich, covariance(H, per_photo)[1])
    sd = np.fmax(model, sandwich)
    return np.where(np.isnan(sd), np.inf, sd)


def normal_matrix(pb: Problem, p: Params, free: Free, weights, A=None, grad=None, res=None, tiles=None, keep=None):
    """JᵀWJ of the free parameters (natural units) with band weights; and the label of each row.

    ``A``, ``grad`` from ``fac.matrices_and_grad(p.theta)`` when the caller has them. With the
    residual ``res`` (3, R) and ``tiles`` = (tile of each used pixel, T), also the per-tile
    gradients ``g_t = Σ_{i∈t} J_iᵀ W r_i`` (n, T) of :func:`reflab.inverse.fit.uncertainty.covariance`.
    ``keep`` (R,) bool: only these pixels inform (the others' rows count as zero); a float
    array scales each row by it (its square in ``H``).
    """
    fac = pb.fac
    if A is None:
        A, grad = fac.matrices_and_grad(p.theta)
    y = fac.y(p.x, p.s)
    q = np.flatnonzero(free.theta)
    # The θ's image derivatives only on the rows where they act (``used``): zero elsewhere.
    img, used = grad.images(y, q, compact=True) if len(q) else (np.zeros((0, BANDS, 0)), np.zeros(0, np.int64))
    if keep is not None:
        img = img * keep[used]
        res = None if res is None else res * keep
    blocks, labels = [], []
    for c in range(BANDS):
        D, lab = pb.dy(p, c, free)
        blocks.append(D)
        labels += [(kind, i, c) for kind, i in lab]
    n_lin = sum(b.shape[1] for b in blocks)
    n = n_lin + len(q)
    H = np.zeros((n, n))
    scores = None
    if res is not None:
        tile, n_tiles = tiles
        P = csr_matrix((np.ones(len(tile)), (np.arange(len(tile)), tile)), shape=(len(tile), n_tiles))
        wr = weights[:, None] * res  # (3, R)
        scores = np.zeros((n, n_tiles))
        if len(q):
            scores[n_lin:] = np.asarray((P[used].T @ (img * wr[:, used]).sum(axis=1).T).T)
    # In monomial space: (A D)ᵀ(A D) = Dᵀ(AᵀA)D, (A D)ᵀ img = Dᵀ(Aᵀ img) and the tiles' sums
    # Pᵀ diag(w r) A D = (Aᵀ diag(w r) P)ᵀ D, so no (pixels × parameters) product is formed
    # (640×480 textured fit: 0.95 → 0.3 s in all; F-TBO's θ curvature is these blocks too).
    rows = None if keep is None else diags(np.asarray(keep, dtype=np.float64))
    off = 0
    for c in range(BANDS):
        D = blocks[c]
        k = D.shape[1]
        if k == 0:
            continue
        Ac = A[c] if rows is None else (rows @ A[c]).tocsr()
        At = Ac.T
        H[off:off + k, off:off + k] = weights[c] * (D.T @ (gram(A, c) if rows is None else (At @ Ac).toarray()) @ D)
        if scores is not None:
            Pw = csr_matrix((wr[c], (np.arange(len(tile)), tile)), shape=P.shape)
            scores[off:off + k] = D.T @ (At @ Pw).toarray()
        if len(q):
            cross = weights[c] * (D.T @ np.asarray(Ac[used].T @ img[:, c, :].T))
            H[off:off + k, n_lin:] = cross
            H[n_lin:, off:off + k] = cross.T
        off += k
    if len(q):
        H[n_lin:, n_lin:] = sum(weights[c] * (img[:, c, :] @ img[:, c, :].T) for c in range(BANDS))
    labels += [("theta", i, -1) for i in q]
    if res is not None:
        return H, labels, scores
    return H, labels


def row_jacobian(pb: Problem, p: Params, free: Free, rows) -> np.ndarray:
    """(3, len(rows), n): each band's image derivative on the used pixels ``rows`` (indices into
    ``fac.rows``) by the free parameters, in :func:`normal_matrix`'s order (each band's linear
    parameters, then θ). For the few pixels :func:`profiled` needs, not the whole image."""
    fac = pb.fac
    rows = np.asarray(rows, dtype=np.int64)
    A, grad = fac.matrices_and_grad(p.theta)
    q = np.flatnonzero(free.theta)
    blocks = [pb.dy(p, c, free)[0] for c in range(BANDS)]
    n_lin = sum(b.shape[1] for b in blocks)
    J = np.zeros((BANDS, len(rows), n_lin + len(q)))
    off = 0
    for c, D in enumerate(blocks):
        if D.shape[1]:
            J[c, :, off:off + D.shape[1]] = A[c][rows] @ D
        off += D.shape[1]
    if len(q):
        img, used = grad.images(fac.y(p.x, p.s), q, compact=True)  # (q, 3, used)
        at = np.full(fac.n_rows, -1)
        at[used] = np.arange(len(used))
        hit = at[rows] >= 0
        J[:, hit, n_lin:] = np.transpose(img[:, :, at[rows[hit]]], (1, 2, 0))
    return J


def profiled(J, e, group, weights, res, tile, n_tiles) -> tuple[np.ndarray, np.ndarray]:
    """Normal-matrix and tile-score terms of pixels whose albedo is a free nuisance per texel.

    Parameters
    ----------
    J : (3, m, n) ndarray
        The pixels' image derivatives (:func:`row_jacobian`).
    e : (3, m) ndarray
        Each pixel's derivative by its texel's albedo (the diffuse term it carries).
    group : (m,) int ndarray
        Each pixel's texel, 0..G−1.
    weights : (3,) ndarray
    res : (3, m) ndarray
        The pixels' residuals.
    tile : (m,) int ndarray
        Each pixel's tile (:func:`tile_index`), of ``n_tiles``.

    Each texel's albedo, free per band, is profiled out: the pixels' derivatives are projected
    off its direction e (the Schur complement of the texel's own block), so a texel seen once says
    nothing, and one seen twice (directly and in a mirror) only through how the two pixels
    differ. Returns ``(H, scores)`` to add to :func:`normal_matrix`'s.
    """
    n = J.shape[2]
    n_groups = int(group.max()) + 1 if len(group) else 0
    H, scores = np.zeros((n, n)), np.zeros((n, n_tiles))
    for c in range(BANDS):
        num = np.zeros((n_groups, n))
        np.add.at(num, group, e[c][:, None] * J[c])
        den = np.bincount(group, weights=e[c] * e[c], minlength=n_groups)
        Jt = J[c] - e[c][:, None] * (num / np.maximum(den, 1e-300)[:, None])[group]
        H += weights[c] * (Jt.T @ Jt)
        np.add.at(scores.T, tile, Jt * (weights[c] * res[c])[:, None])
    return H, scores


def sigmas(pb: Problem, p: Params, free: Free, res, robust: bool = True, keep=None, extra=None) -> Params:
    """One-sigma uncertainties (natural units) of the free parameters; inf where unconstrained.

    The noise of band c is estimated from its residual, but never below :data:`NOISE_FLOOR` of
    the image peak; the model-based covariance is ``(JᵀWJ)⁻¹`` with ``W = 1/σ_c²``. With
    ``robust`` each σ is the larger of that and the cluster-robust sandwich over image tiles
    (:mod:`reflab.inverse.fit.uncertainty`), which holds when the model is imperfect. ``keep`` (R,) bool:
    only these pixels inform (:func:`reflab.inverse.fit.determined.texture_absorbed` leaves out what a free texture explains).
    ``extra``: ``extra(free, weights, tiles) -> (H, scores)`` or None, terms of further pixels
    added to the normal matrix and the tile scores (:func:`profiled`). Never NaN.

    Rows weighed by a sample's 1/p (``pb.scale``, :mod:`reflab.inverse.fit.sampling`): ``H`` and
    the tile scores are the weighted ones (Horvitz–Thompson estimates of every pixel's), and the
    model-based covariance is ``H⁻¹ (Σ w² JᵀWJ) H⁻¹``, the spread the noise of the pixels read
    gives the weighted estimate; the sandwich over tiles, from the weighted scores, holds the
    sampling's share of a misfit too.
    """
    n_free = free.count()
    dof = max(BANDS * pb.fac.n_rows - n_free, 1)
    var = np.sum(res * res, axis=1) / max(dof / BANDS, 1.0)
    if getattr(pb, "scale", None) is not None:  # weighted residuals: per unit of weight
        var = var * pb.fac.n_rows / max(float(np.sum(pb.scale ** 2)), 1e-300)
    var = np.maximum(var, (NOISE_FLOOR * pb.peak) ** 2)
    sig = Params(np.full_like(p.x, np.inf), np.full_like(p.s, np.inf), np.full_like(p.theta, np.inf))
    # The tiles only where they serve: the holding rounds' many model-based calls need none.
    tiles = tile_index(pb.fac.rows, pb.fac.width, pb.fac.height) if robust or extra is not None else None
    if robust:
        H, labels, scores = normal_matrix(pb, p, free, 1.0 / var, res=res, tiles=tiles, keep=keep)
    else:
        (H, labels), scores = normal_matrix(pb, p, free, 1.0 / var, keep=keep), None
    if not labels:
        return sig
    middle = None
    if getattr(pb, "scale", None) is not None:
        # Σ w² JᵀWJ: the rows (already scaled by sqrt(w)) scaled by sqrt(w) once more.
        middle = normal_matrix(pb, p, free, 1.0 / var, keep=pb.scale * (1.0 if keep is None else keep))[0]
    more = extra(free, 1.0 / var, tiles) if extra is not None else None
    if more is not None:
        H = H + more[0]
        middle = None if middle is None else middle + more[0]  # (their w² term: the sandwich holds it)
        scores = None if scores is None else scores + more[1]
    stats = getattr(pb.fac.trees, "stats", None)
    blocks = stats.get("block_row0") if isinstance(stats, dict) else None
    sd = robust_sd(H, scores, pb.fac.rows, pb.fac.width, pb.fac.height, blocks, middle)
    return scatter(labels, sd, sig)


def scatter(labels, values, into):
    """``into`` (Params) with each of ``values`` written where its label (kind, surface, band) says."""
    for (kind, i, c), v in zip(labels, values):
        if kind == "x":
            into.x[i, c] = v
        elif kind == "s":
            into.s[i, c] = v
        else:
            into.theta[i] = v
    return into
