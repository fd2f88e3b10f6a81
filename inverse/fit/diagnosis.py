"""Does the fitted model explain the image: the diagnosis in words and the outlier pixels."""
from __future__ import annotations

import numpy as np

from reflab.inverse.forward.factorization import BANDS
from reflab.inverse.forward.trees import seen_first
from reflab.inverse.fit.problem import Params, Problem


#: The diagnosis flags a pixel whose residual exceeds this many image-noise σ plus DIAG_FLOOR of the peak.
DIAG_SIGMAS = 6.0
DIAG_FLOOR = 1e-4
#: Unexplained pixels that hold less than SCATTERED_SHARE of the squared residual and are fewer
#: than SCATTERED_PIXELS of those read are scattered pixels, said in a warning: the status stays "ok".
SCATTERED_SHARE = 0.01
SCATTERED_PIXELS = 1e-3
#: A pixel is an outlier, left out and the fit repeated, when its residual exceeds this many image-noise σ
#: (plus DIAG_FLOOR of the peak); only when such pixels are at most REJECT_SHARE of those used (more
#: is a misfit for the diagnosis, not outliers).
REJECT_SIGMAS = 6.0
REJECT_SHARE = 0.01
#: Passes of rejection and refit at most.
REJECT_PASSES = 4


def diagnose(pb: Problem, p: Params, A, res, textured=None, names=None, per_photograph: list | None = None
             ) -> tuple[str, list]:
    """Does the fitted model explain the image? A safety net for a wrong basin or a bad scene.

    A pixel is *unexplained* when its residual in some band exceeds :data:`DIAG_SIGMAS` times the
    noise σ estimated from the image itself (:func:`reflab.inverse.fit.photograph.image_noise`) plus :data:`DIAG_FLOOR` of the
    peak, plus — on textured surfaces — the diffuse radiance that their homogeneous ``kd`` predicts
    there (albedo variation is the texture stage's job, not a misfit). With Gaussian noise no pixel
    gets there; a highlight left in the wrong place, a missing reflection or wrong geometry does.

    Parameters
    ----------
    pb : Problem
    p : Params
        The fitted parameters.
    A : list of CSR
        ``fac.matrices(p.theta)``.
    res : (3, R) ndarray
        Model minus image.
    textured : list of bool, optional
        Per surface (default: none).
    names : list of str, optional
        Surface names for the messages.
    per_photograph : list, optional
        Filled, over stacked photographs (``trees.stats["block_row0"]``), with each photograph's
        share of unexplained pixels among those read (a sample's rows weighed by their 1/p):
        what :func:`mismatched_photographs` reads.

    Returns
    -------
    status : {"ok", "poor fit", "texture pending"}
        "texture pending" instead of "poor fit" when some surface is textured: its albedo may vary
        by more than the allowance, so only ``reflab texture`` can tell. :func:`reflab.inverse.fit.rounds.fit` turns "ok"
        into "not converged" when a method stopped at its cap.
    warnings : list of str
        Plain-language diagnosis: empty when ``status == "ok"``, but for a few scattered pixels
        over the line that hold almost none of the misfit (:data:`SCATTERED_SHARE`,
        :data:`SCATTERED_PIXELS`), which one warning names.
    """
    fac = pb.fac
    n_surf = len(fac.models)
    textured = [False] * n_surf if textured is None else [bool(t) for t in textured]
    names = [f"surface {i}" for i in range(n_surf)] if names is None else list(names)
    # What a residual may reach besides the noise: a floor, and on textured surfaces their albedo's variation.
    allowance = np.full(res.shape, DIAG_FLOOR * pb.peak)
    diffuse = np.array([textured[s] and fac.layout.x_names[i][1] == "kd"
                        for s, i in zip(fac.col_surface, fac.col_x)], dtype=bool)
    if diffuse.any():
        y = fac.y(p.x, p.s)
        allowance += np.stack([A[c] @ np.where(diffuse, y[c], 0.0) for c in range(BANDS)])
    bad = np.any(np.abs(res) > allowance + DIAG_SIGMAS * pb.noise[:, None], axis=0)
    if per_photograph is not None:
        per_photograph[:] = _shares(fac, res, allowance, pb.noise, getattr(pb, "scale", None))
    if not bad.any():
        return "ok", []
    # Which surface each unexplained pixel sees first (its primary hit).
    first = seen_first(fac.trees, fac.width * fac.height)
    where = first[fac.rows[bad]]
    counts = np.bincount(where[where >= 0], minlength=n_surf)
    share = float(np.sum(res[:, bad] ** 2) / max(np.sum(res**2), 1e-300))
    parts = ", ".join(f"{names[i]} {int(counts[i])}" for i in np.argsort(-counts) if counts[i])
    rms = ", ".join(f"{v:.3g}" for v in pb.rms(res))
    noise = ", ".join(f"{v:.3g}" for v in pb.noise)
    pending = any(textured)
    if not pending and share < SCATTERED_SHARE and bad.mean() < SCATTERED_PIXELS:
        # A few pixels over the line that carry almost none of the misfit: an edge the meshes
        # place a fraction of a pixel off, a hot pixel; not a poor fit (the zoo's seed 31, seven
        # 320x240 photographs: 4 of 267 427 pixels, 0.0 % of the squared residual, had made it one).
        return "ok", [f"{int(bad.sum())} of {fac.n_rows} pixels have a residual above {DIAG_SIGMAS:g} times the "
                      f"image noise [{noise}] but hold {100 * share:.1f}% of the squared residual (scattered "
                      f"pixels, not a misfit); first seen surface: {parts or 'none'}"]
    return ("texture pending" if pending else "poor fit"), [
        f"the fitted {'homogeneous ' if pending and fac.albedo is None else ''}model"
        f"{' (with the recovered texture)' if fac.albedo is not None else ''} does not explain {int(bad.sum())} of {fac.n_rows} pixels (residual above "
        f"{DIAG_SIGMAS:g} times the image noise [{noise}]{' plus textured albedo' if diffuse.any() else ''}); "
        f"they hold {100 * share:.0f}% of the squared residual; first seen surface: {parts or 'none'}",
        f"RMS residual per band [{rms}]: "
        + ("texture (run reflab texture and compare its re-render), or " if pending else "")
        + "a wrong basin (try another starting shininess in scene.json), a wrong BRTDF model, "
        "or geometry, lights or camera that do not match the image"]


def _shares(fac, res, allowance, noise, scale) -> list:
    """Per stacked photograph, the share of its read rows whose residual ``res`` (3, R) exceeds
    :data:`DIAG_SIGMAS` times that photograph's own noise (``trees.stats["block_noise"]``, else
    the fit's ``noise``) plus ``allowance`` (3, R) ([] for one photograph)."""
    stats = getattr(fac.trees, "stats", None)
    row0 = stats.get("block_row0") if isinstance(stats, dict) else None
    if row0 is None or len(row0) < 2:
        return []
    from reflab.inverse.forward.photographs import photograph_of

    photo = photograph_of(fac.rows, row0, fac.width)
    own = stats.get("block_noise")
    own = np.asarray(own if own is not None and len(own) == len(row0) else [noise] * len(row0), dtype=np.float64)
    allowance = allowance + DIAG_SIGMAS * own[photo].T
    bad = np.any(np.abs(res) > allowance, axis=0)
    w = np.ones(len(bad)) if scale is None else np.asarray(scale, dtype=np.float64) ** 2
    read = np.bincount(photo, weights=w, minlength=len(row0))
    flagged = np.bincount(photo, weights=w * bad, minlength=len(row0))
    return [float(f / r) if r > 0 else 0.0 for f, r in zip(flagged, read)]


#: A photograph of several is called mismatched when its share of unexplained pixels (against its
#: own noise) is at least MISMATCH_SHARE and MISMATCH_RATIO times the median of the others' (a
#: photograph whose lamps or camera are not those its sidecar gives: the lab's two lamp-alone shots
#: swapped, 160x120, left 24 % of their pixels unexplained, the others 0.3 % in the median).
MISMATCH_SHARE = 0.05
MISMATCH_RATIO = 5.0


def mismatched_photographs(shares) -> list:
    """``(index, the others' median share)`` of each photograph whose unexplained share
    (:func:`diagnose`'s ``per_photograph``) stands out from the others' (:data:`MISMATCH_SHARE`,
    :data:`MISMATCH_RATIO`)."""
    shares = np.asarray(shares, dtype=np.float64)
    out = []
    for i, v in enumerate(shares):
        others = np.delete(shares, i)
        median = float(np.median(others)) if len(others) else 0.0
        if len(others) and v >= MISMATCH_SHARE and v >= MISMATCH_RATIO * median:
            out.append((i, median))
    return out


def outlier_tolerance(pb: Problem, p: Params, A, res, textured=None) -> np.ndarray:
    """(3, R) the residual beyond which :func:`outliers` calls a pixel an outlier."""
    fac = pb.fac
    textured = [False] * len(fac.models) if textured is None else [bool(t) for t in textured]
    # The scale: the image noise, or the residual's own robust spread when larger (an outlier that
    # pulled the fit leaves every pixel a little off, far below its own residual).
    spread = 1.4826 * np.median(np.abs(res), axis=1) if res.size else np.zeros(BANDS)
    tol = np.broadcast_to((REJECT_SIGMAS * np.maximum(pb.noise, spread) + DIAG_FLOOR * pb.peak)[:, None], res.shape).copy()
    diffuse = np.array([textured[s] and fac.layout.x_names[i][1] == "kd" for s, i in zip(fac.col_surface, fac.col_x)], dtype=bool)
    if diffuse.any() and fac.albedo is None:
        y = fac.y(p.x, p.s)
        tol += np.stack([A[c] @ np.where(diffuse, y[c], 0.0) for c in range(BANDS)])
    return tol


def outliers(pb: Problem, p: Params, A, res, textured=None) -> np.ndarray:
    """Flat pixel indices whose residual exceeds :data:`REJECT_SIGMAS` σ in some band (σ the image
    noise or 1.4826 × the median absolute residual, the larger).

    The same test as :func:`diagnose`'s (plus :data:`DIAG_FLOOR` of the peak, plus on textured
    surfaces the diffuse radiance their homogeneous kd predicts), at a lower threshold.
    """
    fac = pb.fac
    excess = np.max(np.abs(res) / outlier_tolerance(pb, p, A, res, textured), axis=0)
    over = excess > 1.0
    if over.sum() > REJECT_SHARE * fac.n_rows:
        # Too many to be outliers — unless a few strong ones pulled the fit so that the rest
        # misfit a little: take the worst (over half the largest excess) first, refit, repeat.
        over &= excess > 0.5 * excess.max()
    return fac.rows[over]
