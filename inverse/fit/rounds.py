"""Fit the non-Lambertian parameters from one image: F-TBO and NF-TBO (docs/method.md §3).

Both minimise the same objective (:mod:`reflab.inverse.fit.problem`) with bounds ``x ≥ 0`` and
``r, t ∈ [0, 1]``: **F-TBO** (:mod:`reflab.inverse.fit.ftbo`) optimises θ over the exact bounded linear
solution; **NF-TBO** (:mod:`reflab.inverse.fit.nftbo`) every parameter at once by conjugate gradient.
:func:`fit` runs either in rounds around them:

- parameters the image does not determine (:mod:`reflab.inverse.fit.determined`) — no signal in their
  columns, or a one-sigma uncertainty larger than their scale — are kept at their initial value,
  out of the fit, and named in ``undetermined``; so are values the user gave (``held``);
- the reported one-sigma uncertainties (:mod:`reflab.inverse.fit.uncertainty`) hold when the model is
  imperfect: the larger of ``σ² (JᵀJ)⁻¹`` and a cluster-robust sandwich over image tiles, and on
  textured scenes from the pixels a free texture cannot explain; a fitted value whose σ spans its
  scale is reported undetermined too;
- every value stays in its plausible range (:mod:`reflab.inverse.fit.ranges`); outlier pixels are left out
  and counted, and :func:`reflab.inverse.fit.diagnosis.diagnose` says in words whether the fitted model
  explains the image (``status``, ``warnings``).

The result and its fit.json are :mod:`reflab.inverse.fit.result`; the input photograph's checks and
noise :mod:`reflab.inverse.fit.photograph`. This module is the fit's front door: it also exports what its
callers use from those modules (``__all__``). The stage on a workspace is
:func:`reflab.inverse.fit.workspace_fit.fit_workspace`.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from reflab.core.task import Task, ensure
from reflab.inverse.fit.determined import (RESOLVE_LOBE, RESOLVE_THETA, hold, plausible_lobes, seen_twice, structural_free, texture_absorbed, texture_confounded,
                                theta_resolution, undetermined_names, unresolved)
from reflab.inverse.fit.diagnosis import DIAG_FLOOR, DIAG_SIGMAS, REJECT_PASSES, REJECT_SHARE, REJECT_SIGMAS, diagnose, outliers
from reflab.inverse.forward.factorization import Factorization, one_blas_thread
from reflab.inverse.fit.result import FitSolution, fit_json
from reflab.inverse.fit.ftbo import SEED_STOP_GAIN, STOP_GAIN, ftbo
from reflab.inverse.fit.nftbo import nftbo
from reflab.inverse.fit.photograph import check_image, saturated_pixels
from reflab.inverse.fit.problem import Free, Params, Problem, materials_of, params_of, trace_point
from reflab.inverse.fit.ranges import at_bound, clip, plausible
from reflab.inverse.fit.uncertainty import sigmas

__all__ = ["METHODS", "fit", "FitSolution", "fit_json", "check_image", "saturated_pixels", "Params", "Free", "Problem",
           "params_of", "materials_of", "DIAG_FLOOR", "DIAG_SIGMAS"]


METHODS = ("ftbo", "nftbo")


@one_blas_thread
def fit(fac: Factorization, image, materials, method: str = "ftbo", *, max_rounds: int | None = None,
        maxiter: int | None = None, max_seconds: float | None = None, textured=None,
        names=None, scan: bool = True, task: Task | None = None, held=None, reject: bool = True,
        structure: Free | None = None, uncertainty: bool = True, guessed=None, still_held: Free | None = None,
        colour=None, nuisance=None) -> FitSolution:
    """Fit every determinable photometric parameter from one image.

    Parameters
    ----------
    fac : Factorization
        The scene's factorized system (its ``rows`` are the pixels used, e.g. saturated ones left out).
    image : (H, W, 3) array_like
        Linear radiance (validated with :func:`check_image`).
    materials : list of Material
        Initial values, one per surface (scene.json's, else docs/method.md §3's). Their ``ior`` says
        which surfaces are transparent.
    method : {"ftbo", "nftbo"}
    max_rounds : int, optional
        Fit → find unresolved parameters → fix them → refit, at most this many times (default:
        3 + the number of nonlinear parameters, as θ are held one per round).
    maxiter : int, optional
        Outer iteration cap (Levenberg–Marquardt for F-TBO, CG for NF-TBO).
    max_seconds : float, optional
        Wall-clock budget of the fit: the methods stop at their next iteration once it is spent
        (``message`` = :data:`reflab.inverse.fit.problem.BUDGET_MESSAGE`), and the uncertainties are computed where they stopped.
    textured : list of bool, optional
        Per surface: its albedo varies (scene.json ``textured``), so the diagnosis
        (:func:`reflab.inverse.fit.diagnosis.diagnose`) excuses a residual up to its diffuse radiance. Default: none textured.
    names : list of str, optional
        Surface names for the diagnosis' warnings (default ``surface 0``, …).
    scan : bool
        F-TBO's coarse global scan of each θ before the local search (off when ``materials``
        already start near the answer, e.g. a refit).
    task : reflab.core.task.Task, optional
        Stepped once per outer iteration (raises ``Cancelled`` when cancelled); its deadline
        stops the methods like ``max_seconds``.
    held : list of set of str, optional
        Per surface, the parameter names the user gave (scene.json): held at their value, never
        fitted (default: none; :func:`reflab.inverse.fit.workspace_fit.fit_workspace` passes every name not ``defaulted``).
    guessed : list of set of str, optional
        Per surface, names held at a guessed value (a textured surface's grey lobe,
        :func:`reflab.inverse.fit.texture_aware.grey_lobes`): held and reported undetermined like ``held``, but
        every σ counts them as free, so that the others' σ keeps the guess's uncertainty.
    reject : bool or int
        Passes (True: :data:`reflab.inverse.fit.diagnosis.REJECT_PASSES`) in which outlier pixels
        (:func:`reflab.inverse.fit.diagnosis.outliers`: residual beyond ``REJECT_SIGMAS`` image-noise σ,
        at most ``REJECT_SHARE`` of the used pixels) are left out and the fit repeated from
        where it stopped; ``stats["rejected"]`` counts and lists them.
    structure : Free, optional
        Which parameters have signal, from an earlier fit of the same scene (``FitSolution.structure``;
        a refit without outliers or against a texture): skips the structure test, nine full
        evaluations of the system.
    still_held : Free, optional
        What an earlier fit of the same scene held for want of signal (its ``free``: False where
        held), held here from the start at the value ``materials`` gives; like the holding rounds'
        own, every σ counts them free.
    colour : dict, optional
        Surface index → :class:`reflab.inverse.fit.dichromatic.ColourLobe`: textured lobes estimated from the
        texture's colours, held (in ``guessed``) at that estimate; their ks and θ get its σ, and
        are reported determined when it resolves them. Listed in ``stats["colour_lobes"]``.
    nuisance : callable, optional
        ``nuisance(pb, p, materials, res)`` → an ``extra`` for :func:`reflab.inverse.fit.uncertainty.sigmas`
        or None: parameters held in the fit whose uncertainty every σ profiles out (a palette's
        inks, :meth:`reflab.inverse.fit.palette.Palette.nuisance`).
    uncertainty : bool
        False: return at once with σ = inf and what the holding rounds held as undetermined;
        ``stats["complete"]()`` then computes the robust σ, the undetermined values and the
        diagnosis (the result as ``uncertainty=True`` returns it). For a fit whose σ may never be
        reported: the homogeneous start and the early texture rounds of a textured scene.

    Returns
    -------
    FitSolution
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if len(materials) != len(fac.models):
        raise ValueError(f"{len(materials)} materials for {len(fac.models)} surfaces")
    t0 = time.perf_counter()
    pb = Problem(fac, image, [m.transparent for m in materials])
    pb.task = ensure(task)
    if max_seconds is not None:
        pb.deadline = t0 + float(max_seconds)
    init = params_of(fac, materials)
    srch = pb.search
    init.theta = srch.to_theta(srch.to_u(init.theta))
    p = init.copy()
    if structure is None:
        free = structural_free(pb, p)
        # A textured surface's r or t that only its own free texture's pixels show: held at 0 (a
        # refit given this structure starts from materials that hold it there already).
        unheld = free.copy()
        if held is not None:
            hold(fac, unheld, held)  # a value the user gave stays theirs
        confounded, twice = texture_confounded(pb, p, materials, textured)
        confounded &= unheld.s
        free.s &= ~confounded
        init.s[confounded], p.s[confounded] = 0.0, 0.0
        # One that texels seen twice show stays in the structure: held at 0 here (fitted against
        # one kd it takes up the texture), fitted by the fits against the recovered texture, which
        # take this structure, and judged like the surface's own lobe (_complete).
        twice &= confounded
    else:
        free, twice = structure.copy(), None
    found = free.copy()
    if twice is not None:
        found.s |= twice
    pb.phases["structure"] = time.perf_counter() - t0
    if held is not None:
        hold(fac, free, held)
    # What the σ counts free: all but what the user gave. A parameter held at a guess (below, or
    # by the holding rounds for want of signal) leaves the others' σ as wide as its uncertainty
    # makes them: holding it would tighten them around a value nobody knows.
    sigma_free = free.copy()
    if still_held is not None:
        if colour:  # a lobe the texture's colours now estimate is a fresh value, not the hold of an earlier round
            still_held = still_held.copy()
            for s, lobe in colour.items():
                still_held.x[fac.layout.x_offset[s] + fac.models[s].linear.index("ks")] = True
                still_held.theta[fac.layout.theta_offset[s] + fac.models[s].nonlinear.index(lobe.shape)] = True
        free = free & still_held
    grey = None
    if guessed is not None:
        fitted = free.copy()
        hold(fac, free, guessed)
        grey = fitted & ~free  # the guessed alone: a still_held value is a guess, never reported fitted
    trace, iterations, message = [], 0, ""
    rounds = 0
    kw = {} if maxiter is None else {"maxiter": maxiter}
    max_rounds = 3 + fac.layout.n_theta if max_rounds is None else max_rounds
    for rounds in range(1, max_rounds + 1):
        t_method = time.perf_counter()
        if method == "ftbo":
            # The global scan picks the basins once; later rounds only hold parameters.
            p, nit, message = ftbo(pb, p, free, t0, trace, scan=scan and rounds == 1,
                                   stop_gain=STOP_GAIN if uncertainty else SEED_STOP_GAIN, **kw)
        else:
            p, nit, message = nftbo(pb, p, free, t0, trace, **kw)
        pb.phases["refinement"] += time.perf_counter() - t_method
        clip(fac, p)  # NF-TBO's reparametrisation has no upper bounds (F-TBO stays inside)
        iterations += nit
        A = fac.matrices(p.theta)
        res = pb.residual(A, fac.y(p.x, p.s))
        # Which parameters to hold: the model-based σ (the data's own resolution); the robust σ
        # below also counts misfit, which holding a parameter at its start would not cure.
        sig = sigmas(pb, p, free, res, robust=False)
        bad = unresolved(pb, p, init, free, sig, A)
        if bad.count() == 0 or pb.out_of_time():
            break
        if bad.theta.any():
            # θ first: an unresolved shininess inflates its ks's σ; with θ held, ks is judged alone.
            # Only the worst θ per round: a misfit elsewhere (a hidden highlight still settling)
            # inflates every σ, and a two-pixel highlight resolves once the rest is refitted.
            worst = np.nanargmax(np.where(bad.theta, theta_resolution(pb, p, sig), -np.inf))
            bad.theta[:] = False
            bad.theta[worst] = True
            bad.x[:], bad.s[:] = False, False
        # Hold the unresolved ones at their initial value and refit the rest from there.
        for name in ("x", "s", "theta"):
            cur, b0, fr = getattr(p, name), getattr(init, name), getattr(bad, name)
            cur[fr] = b0[fr]
            getattr(free, name)[fr] = False
        if rounds == max_rounds:
            A = fac.matrices(p.theta)
            res = pb.residual(A, fac.y(p.x, p.s))
    rms = pb.rms(res)
    trace.append(trace_point(t0, rms))
    fitted = time.perf_counter() - t0
    pb.phases["refinement"] -= pb.phases["scan"]
    pb.phases["uncertainty"] = fitted - sum(pb.phases.values())  # the holding rounds
    inf = Params(np.full_like(p.x, np.inf), np.full_like(p.s, np.inf), np.full_like(p.theta, np.inf))
    if int(reject) > 0 and not message.startswith("stopped"):
        # Outliers first: a refit follows, and this pass's σ and diagnosis would be thrown away.
        bad = outliers(pb, p, *pb.unweighted(A, res), textured)  # each pixel against the noise
        if 0 < len(bad) <= REJECT_SHARE * fac.n_rows:
            first = FitSolution(method, p, free, materials_of(fac, p, materials), inf, rms, fitted, trace, [],
                              rounds, pb.evaluations, iterations, message,
                              {"phases_s": dict(pb.phases), "scan_evaluations": pb.scan_evaluations}, found)
            return _refit_without(first, fac, image, bad, method, maxiter=maxiter, textured=textured, names=names,
                                  task=task, held=held, guessed=guessed, passes=REJECT_PASSES if reject is True else int(reject),
                                  max_seconds=None if max_seconds is None else max_seconds - fitted,
                                  uncertainty=uncertainty, nuisance=nuisance, twice=twice)
    stats = {"used_pixels": int(fac.n_rows), "free_parameters": free.count(), "at_bound": at_bound(fac, p, free),
             "noise": [float(v) for v in pb.noise], "scan_evaluations": pb.scan_evaluations,
             "rejected": {"count": 0, "pixels": [], "threshold_sigmas": REJECT_SIGMAS}}
    if not uncertainty:
        def complete():
            # A seed stopped early (SEED_STOP_GAIN): converged as the reported fit is, then its σ.
            q, nit, msg, A_q, res_q, spent = p, iterations, message, A, res, 0.0
            if method == "ftbo" and not message.startswith("stopped"):
                t_polish = time.perf_counter()
                q, more, msg = ftbo(pb, p.copy(), free, t_polish - fitted, trace, scan=False)
                nit += more
                A_q = fac.matrices(q.theta)
                res_q = pb.residual(A_q, fac.y(q.x, q.s))
                spent = time.perf_counter() - t_polish
                pb.phases["refinement"] += spent
            return _complete(pb, q, init, free, found, res_q, A_q, materials, textured, names, method, trace, rounds,
                             nit, msg, fitted + spent, stats, sigma_free, grey, colour, nuisance)

        return FitSolution(method, p, free, materials_of(fac, p, materials), inf, rms, fitted, trace,
                         undetermined_names(fac, free, materials), rounds, pb.evaluations, iterations, message,
                         {**stats, "status": "ok", "warnings": [], "phases_s": {k: round(v, 6) for k, v in pb.phases.items()},
                          "complete": complete}, found)
    return _complete(pb, p, init, free, found, res, A, materials, textured, names, method, trace, rounds, iterations,
                     message, fitted, stats, sigma_free, grey, colour, nuisance)


def _complete(pb: Problem, p: Params, init: Params, free: Free, found: Free, res, A, materials, textured, names,
              method, trace, rounds, iterations, message, fitted, stats, sigma_free: Free | None = None,
              grey: Free | None = None, colour=None, nuisance=None) -> FitSolution:
    """The fit's robust σ, its undetermined values and its diagnosis, once its parameters are fitted.

    ``sigma_free``: what every σ counts free, ``free`` and the parameters held at a guess (by the
    holding rounds, or ``guessed``): holding those would tighten the σ of all that shares pixels
    with them around a value nobody knows. Default ``free``. ``grey``: those held at the mean of
    their bands' fitted values (``guessed``): reported determined when their σ resolves them, like
    a fitted value (a lobe one band-shared height, fitted the round before). ``colour``: lobes
    estimated from the texture's colours (:mod:`reflab.inverse.fit.dichromatic`), whose σ their ks and θ take.
    ``nuisance``: as :func:`fit` takes it, profiled out of the σ from every pixel.
    """
    t0 = time.perf_counter()
    fac = pb.fac
    sf = free if sigma_free is None else sigma_free
    sig = sigmas(pb, p, sf, res, extra=None if nuisance is None else nuisance(pb, p, materials, res))
    lay = fac.layout
    absorbed, anywhere = texture_absorbed(fac, p, materials, textured)
    if absorbed.any():
        # A free texture explains every pixel where it is seen directly: σ from the others only
        # (kd of a textured surface is its texture's mean: its σ stays the one from every pixel).
        tex_kd = np.array([bool(textured[s]) and name == "kd" for s, name in lay.x_names], dtype=bool)
        # The texture (its mean kd included) counts as known from the pixels that see it directly.
        sf_t = Free(sf.x & ~tex_kd[:, None], sf.s, sf.theta)  # a texture's mean kd keeps its every-pixel σ
        sig_t = sigmas(pb, p, sf_t, res, keep=~absorbed)
        every = sig.copy()  # every pixel's, for a lobe no texture-free pixel shows (below)
        sig = Params(np.where(tex_kd[:, None], sig.x, np.fmax(sig.x, sig_t.x)), np.fmax(sig.s, sig_t.s),
                     np.fmax(sig.theta, sig_t.theta))
        # A textured surface's own lobe (ks, θ): the view that pins its texture (the direct one)
        # carries the same lobe at another angle, so moving the lobe moves the pinned texture too,
        # which the σ above ignores. Such a lobe is judged only from pixels where no texture shows
        # (left free on the demo it fitted box ns 2.5 ± 0.7, true 30, from the box in the mirror).
        own = np.array([bool(textured[s]) and name != "kd" for s, name in lay.x_names], dtype=bool)
        own_theta = np.array([bool(textured[s]) for s, _ in lay.theta_names], dtype=bool)
        # Its own reflection and transmission likewise where no texture-free pixel shows them:
        # what the pixels of its pinned texture show of them, the texture moves with too
        # (floor_mirror's floor r, true 0, was held for want of a texture-free pixel although a
        # 0.01 move changes its photographs by χ² 102). Where one does, their σ is as before (the
        # lab's tile r read through a 320x240 sample: ± 0.01 so, ± 0.03 from the few texels read twice).
        own_s = np.array([bool(textured[f // 2]) for f in range(lay.n_factors)], dtype=bool)[:, None] \
            & sf.s & ~np.isfinite(sig_t.s)
        if (own[:, None] & sf.x).any() or (own_theta & sf.theta).any() or own_s.any():
            # ... and from texels seen twice (directly and in a mirror), each one's albedo free.
            lobed = np.zeros(len(textured), dtype=bool)  # textured surfaces with a lobe to judge
            lobed[[s for (s, _), o in zip(lay.x_names, own[:, None] & sf.x) if o.any()]] = True
            lobed[[s for (s, _), o in zip(lay.theta_names, own_theta & sf.theta) if o]] = True
            lobed[[f // 2 for f in np.flatnonzero(own_s.any(axis=1))]] = True
            sig_o = sigmas(pb, p, sf_t, res, keep=~anywhere,
                           extra=seen_twice(pb, p, materials, textured, anywhere, res, lobed))
            # A lobe seen only where its texture shows (sig_t inf: each photograph's view of a
            # texel free) is what its texels seen in several photographs say (issue #30).
            sig.x[own] = np.fmax(np.where(np.isfinite(sig_t.x[own]), sig.x[own], every.x[own]), sig_o.x[own])
            sig.theta[own_theta] = np.fmax(np.where(np.isfinite(sig_t.theta[own_theta]), sig.theta[own_theta],
                                                    every.theta[own_theta]), sig_o.theta[own_theta])
            # r and t that no texture-free pixel shows (held at 0 before: texture_confounded): what
            # the texels seen twice say, never below every pixel's σ.
            sig.s[own_s] = np.fmax(every.s[own_s], sig_o.s[own_s])
    for s, lobe in (colour or {}).items():
        # A lobe the texture's colours determine: every pixel of the surface informs it, with each
        # pixel's albedo free along the texture's colour set (its own σ, robust).
        sig.x[lay.x_offset[s] + fac.models[s].linear.index("ks")] = lobe.sigma_ks
        sig.theta[lay.theta_offset[s] + fac.models[s].nonlinear.index(lobe.shape)] = lobe.sigma_theta
    # Fitted, but the robust σ spans its scale (a value on a bound included): reported undetermined.
    fitted_free = free if grey is None else free | grey
    loose = unresolved(pb, p, init, fitted_free, sig, A, theta_resolve=RESOLVE_THETA, bounds_hold=False,
                       lobe_resolve=RESOLVE_LOBE)
    if textured is not None and any(textured):
        # A textured surface's θ is known from its texels seen twice at most, and its texels carry
        # its error into every other view: judged relative to its value, as a shininess is, even
        # where it is not a log parameter (Oren–Nayar box in a mirror: roughness 0.13 ± 0.22 for
        # 0.4 passed the range rule, and its novel view fell 2 dB over the pixels called determined).
        textured_theta = np.array([bool(textured[s]) for s, _ in lay.theta_names], dtype=bool)
        relative = sig.theta > RESOLVE_THETA * np.log(2.0) * np.abs(p.theta)
        loose.theta |= fitted_free.theta & textured_theta & relative
    # Nor its shininess without its height: a lobe whose ks is held or undetermined in every band
    # may not be there (a glass block's highlight out of view, only a faint tail seen: ns 106 ± 36
    # for a true 250 beside ks 0.013, true 0.15), so its θ is reported undetermined too.
    for s, model in enumerate(fac.models):
        shaped = [lay.x_offset[s] + j for j in model.shaped if not (textured is not None and textured[s] and model.linear[j] == "kd")]
        th = slice(lay.theta_offset[s], lay.theta_offset[s + 1])
        if shaped and all(np.all(~fitted_free.x[k] | loose.x[k]) for k in shaped):
            loose.theta[th] |= free.theta[th]
    # A lobe's ks means nothing without its shininess: held or undetermined θ makes its ks so too.
    for k, (s, name) in enumerate(lay.x_names):
        th = slice(lay.theta_offset[s], lay.theta_offset[s + 1])
        if name != "kd" and (np.any(~fitted_free.theta[th]) or np.any(loose.theta[th])):
            loose.x[k] |= fitted_free.x[k]
    shares = []  # per stacked photograph, its share of pixels the model does not explain
    status, warnings = diagnose(pb, p, *pb.unweighted(A, res), textured, names, per_photograph=shares)
    # An undetermined lobe is reported and rendered where the data and the prior over the field's
    # lobes agree (determined.plausible_lobes); any other undetermined value off a range bound.
    before = p
    shapes = {}
    p, lobes, handled = plausible_lobes(pb, p, free, loose, sf, res, materials, textured, fitted_free, shapes)
    if lobes:
        # The values fitted beside an open lobe depend on where it is held, which the data do not
        # say: what moving it moved them by joins their σ (zoo seed 7 at 640x480: a cylinder's kd
        # 0.627 ± 0.002 for a true 0.707 once its open lobe was held broad, ns 2).
        for name in ("x", "s"):
            sd, moved = getattr(sig, name), np.abs(getattr(p, name) - getattr(before, name))
            m = np.isfinite(sd) & ~getattr(handled, name)
            sd[m] = np.hypot(sd[m], moved[m])
    if plausible(fac, p, loose & ~handled) or lobes:
        stats = {**stats, "at_bound": at_bound(fac, p, free)}
    if lobes:  # fit.json says where each moved lobe's value comes from
        stats = {**stats, "plausible_lobes": {(names[s] if names else f"surface {s}"): r for s, r in lobes.items()}}
    if shapes:  # every shape an open lobe was weighed at: the plan's hypotheses (inverse/plan.py)
        stats = {**stats, "lobe_shapes": {(names[s] if names else f"surface {s}"): r for s, r in shapes.items()}}
    spent = time.perf_counter() - t0
    elapsed = fitted + spent
    phases = dict(pb.phases, uncertainty=pb.phases["uncertainty"] + spent)  # with the holding rounds and the diagnosis
    if message.startswith("stopped"):  # iteration cap or wall-clock budget
        warnings.insert(0, f"the fit did not converge ({message})")
        status = "not converged" if status == "ok" else status
    if shares:
        stats = {**stats, "unexplained_by_photograph": shares}
    if colour:
        stats = {**stats, "colour_lobes": {(names[s] if names else f"surface {s}"): lobe.to_json() for s, lobe in colour.items()}}
    return FitSolution(method, p, fitted_free, materials_of(fac, p, materials), sig, pb.rms(res), elapsed, trace,
                     undetermined_names(fac, fitted_free, materials, loose), rounds, pb.evaluations, iterations, message,
                     {**stats, "status": status, "warnings": warnings, "phases_s": {k: round(v, 6) for k, v in phases.items()}},
                     found)


def _refit_without(first: FitSolution, fac: Factorization, image, bad, method, *, passes, twice=None,
                   **kw) -> FitSolution:
    """Fit again from ``first`` with the pixels ``bad`` left out; traces, counts and time add up.

    ``twice``: a textured surface's r and t that ``first`` held at 0 but keeps in its structure
    (:func:`reflab.inverse.fit.determined.texture_confounded`): held in the refit too."""
    structure = first.structure if twice is None else Free(first.structure.x, first.structure.s & ~twice,
                                                            first.structure.theta)
    again = fit(fac.without(bad), image, first.materials, method, scan=False, reject=passes - 1,
                structure=structure, **kw)
    merged = _merged(first, again, fac.width, bad)
    if twice is not None:
        merged = dataclasses.replace(merged, structure=first.structure)
    if "complete" in again.stats:  # σ later: completing the refit completes the merge
        merged.stats["complete"] = lambda: dataclasses.replace(
            _merged(first, again.stats["complete"](), fac.width, bad), structure=merged.structure)
    return merged


def _merged(first: FitSolution, again: FitSolution, width: int, bad) -> FitSolution:
    """The refit ``again`` with ``first``'s trace, counts, time and phases added and its outliers listed."""
    pixels = [[int(i % width), int(i // width)] for i in bad] + again.stats["rejected"]["pixels"]
    rejected = {"count": len(pixels), "pixels": pixels, "threshold_sigmas": REJECT_SIGMAS}
    bad = pixels
    warnings = [f"{len(bad)} outlier pixel(s) left out of the fit (residual above {REJECT_SIGMAS:g} times the image noise or the residual's robust spread; "
                "fit.json 'rejected' lists them as [x, y])"] + [w for w in again.stats.get("warnings", []) if "outlier" not in w]
    offset = first.time_s
    return dataclasses.replace(
        again, trace=first.trace + [[offset + t, r] for t, r in again.trace], time_s=offset + again.time_s,
        evaluations=first.evaluations + again.evaluations, iterations=first.iterations + again.iterations,
        rounds=first.rounds + again.rounds, stats={**again.stats, "rejected": rejected, "warnings": warnings,
                                                   **_add_phases(first.stats, again.stats)})


def _add_phases(first: dict, again: dict) -> dict:
    """``phases_s`` and ``scan_evaluations`` of a fit and its refit, added up (each phase's total)."""
    return {"phases_s": {k: round(v + again["phases_s"].get(k, 0.0), 6) for k, v in first["phases_s"].items()},
            "scan_evaluations": first["scan_evaluations"] + again["scan_evaluations"]}
