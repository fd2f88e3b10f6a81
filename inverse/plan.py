"""The further photographs that would fix what the fit left open (docs/method.md §6, docs/fit.md "Plan").

Photographs of one scene are independent measurements of the same parameters, so their Fisher
information adds: ``H = Σ_photo Jᵀ W J`` with ``W = 1/σ_c²`` the photograph's noise per band.
For each shot the rig can take (a subset of the lamps × a turntable angle) the trees of that
view are built at a reduced size (the information of a photograph grows with its pixel count:
a view at 1/s of the size carries about 1/s² of the full one's) and its ``JᵀWJ`` is evaluated at
the fitted parameters — with a lobe the photograph left undetermined at a plausible amplitude,
since a lobe of zero amplitude shows no shininess. The predicted σ of each parameter is
``sqrt(diag((H_now + H_shot)⁻¹))``; shots are chosen greedily by how much they shrink the
relative σ of the parameters that are undetermined or loose.

The prediction is the model-based σ: the fit's reported σ (the larger of it and the tile
sandwich) agrees with it when the model is right. A textured surface's free albedo per texel is
not profiled out here, so its lobe's predicted σ is a lower bound (docs/fit.md).
"""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import numpy as np

from reflab.inverse.forward.factorization import BANDS

#: A parameter is a target of the plan when its relative σ is above this (undetermined: inf).
LOOSE = 0.1
#: No credit for shrinking a relative σ below this.
GOOD_ENOUGH = 0.02
#: A shot must shrink the targets' summed log relative σ by at least this (natural log) to be planned.
MIN_GAIN = 0.2
#: Plausible amplitude of a lobe (ks) or an ideal reflection / transmission the fit left at ~0,
#: for predicting what a shot would show of it (docs/method.md §3's initial value).
PLAUSIBLE = 0.1
#: Candidate views are ray-cast at least this wide (or at the camera's width, if smaller).
MIN_WIDTH = 160
#: Turntable angles (degrees) tried by default.
ANGLES = tuple(range(-165, 181, 15))


@dataclass
class Shot:
    """A photograph the rig can take: turntable ``angle`` (degrees) and the lamps that are lit."""

    angle: float
    lamps: tuple

    @property
    def name(self) -> str:
        sign = "m" if self.angle < 0 else ""
        return f"a{sign}{abs(self.angle):g}_l{''.join(str(k) for k in self.lamps)}"


@dataclass
class PlanResult:
    """The planned shots in order, each with the σ predicted once it (and those before it) is taken."""

    shots: list
    targets: list  # (surface, parameter) names the plan aims at
    report: dict = field(default_factory=dict)
    path: object = None


def candidate_shots(n_lamps: int, angles=ANGLES, taken=()) -> list:
    """Every non-empty lamp subset at every angle, less the shots already ``taken`` (Shot list)."""
    subsets = [c for r in range(1, n_lamps + 1) for c in itertools.combinations(range(n_lamps), r)]
    have = {(round(float(s.angle), 6), tuple(s.lamps)) for s in taken}
    return [Shot(float(a), s) for a in angles for s in subsets if (round(float(a), 6), s) not in have]


def _labels_index(labels) -> dict:
    return {lab: i for i, lab in enumerate(labels)}


def information(trees, models, materials, intensities, noise, free, scale: float = 1.0):
    """``JᵀWJ`` of one view (its trees) at ``materials`` for the ``free`` parameters, times ``scale``.

    Returns (H, labels) as :func:`reflab.inverse.fit.uncertainty.normal_matrix`.
    """
    from reflab.inverse.fit.problem import Problem, params_of
    from reflab.inverse.fit.uncertainty import normal_matrix
    from reflab.inverse.forward.factorization import Factorization
    from reflab.inverse.forward.rendering import render

    fac = Factorization(trees, models, intensities)
    if fac.n_columns == 0:
        return None, None
    image = render(trees, materials, intensities)
    pb = Problem(fac, image, [m.transparent for m in materials])
    p = params_of(fac, materials)
    weights = 1.0 / np.maximum(np.asarray(noise, dtype=np.float64), 1e-300) ** 2
    H, labels = normal_matrix(pb, p, free, weights)
    return scale * H, labels


def relative_sigma(H, labels, p, theta_log) -> dict:
    """Label -> σ relative to the parameter's scale (x: its value, at least 0.1; r, t: 1;
    θ: σ of log2 θ for log-searched names, else absolute); inf where H is singular along it."""
    from reflab.inverse.fit.uncertainty import covariance

    sd, _ = covariance(H)
    out = {}
    for (kind, i, c), s in zip(labels, sd):
        if kind == "x":
            rel = s / max(abs(float(p.x[i, c])), PLAUSIBLE)
        elif kind == "s":
            rel = s
        else:
            rel = s / (max(float(p.theta[i]), 1e-300) * np.log(2.0)) if theta_log[i] else s
        out[(kind, i, c)] = float(rel) if np.isfinite(rel) else np.inf
    return out


def reported_relative_sigma(fit_report: dict) -> dict:
    """fit.json's relative σ per ``surface.param[band]`` (as :mod:`reflab.inverse.plan` names them):
    σ over max(|value|, PLAUSIBLE) for linear parameters (as :func:`relative_sigma`), σ for r and t,
    σ of log2 for ns and alpha;
    inf where fit.json calls it undetermined."""
    out = {}
    for s in fit_report.get("surfaces", []):
        mat, sig, und = s.get("material") or {}, s.get("sigma") or {}, set(s.get("undetermined") or [])
        for key, value in mat.items():
            if key in ("brdf", "ior") or value is None:
                continue
            values = value if isinstance(value, list) else [value]
            sigmas = sig.get(key) if isinstance(sig.get(key), list) else [sig.get(key)] * len(values)
            for c, (v, e) in enumerate(zip(values, sigmas)):
                name = f"{s.get('name')}.{key}" + (f"[{c}]" if isinstance(value, list) else "")
                if key in und or f"{key}[{c}]" in und or e is None:
                    out[name] = float("inf")
                elif key in ("ns", "alpha"):
                    out[name] = e / max(abs(v) * np.log(2.0), 1e-300)
                elif key in ("r", "t"):
                    out[name] = e
                else:
                    out[name] = e / max(abs(v), PLAUSIBLE)
    return out


def plan_shots(stack, scene, materials, noise, *, n_lamps: int, lights, camera, centre, direction: float = 1.0,
               angles=ANGLES, taken=(), max_shots: int = 3, reduce: int = 4, depth: int = 3, held=None,
               reported=None, task=None, log=None) -> PlanResult:
    """Choose up to ``max_shots`` further shots (see the module's description).

    Parameters
    ----------
    stack : reflab.inverse.forward.photographs.Stack
        The photographs already taken.
    scene : Scene
    materials : list of Material
        The fitted materials (fit.json).
    noise : (3,) array_like
        The photographs' noise σ per band (absolute radiance).
    n_lamps, lights, camera, centre, direction
        The rig: its lamps (the reference's lights.json), the reference camera, the turntable
        axis through ``centre`` (x, y) turning by ``direction`` (+1: counter-clockwise seen from +z).
    held : list of set of str, optional
        Per surface, names the user gave (not planned for).
    reduce : int
        Candidate views are ray-cast at 1/reduce of the camera's size.
    reported : dict, optional
        Name (``surface.param[band]``) -> the fit's reported relative σ (inf: reported undetermined).
        The fit reports the larger of the model-based σ and the tile sandwich: where it is larger
        than the model-based one here (misfit), every prediction for that parameter is scaled by
        the same factor, and a parameter the fit calls undetermined stays a target.
    """
    from reflab.core.task import ensure
    from reflab.inverse.fit.determined import hold
    from reflab.inverse.fit.problem import Free, Search, params_of
    from reflab.inverse.fit.result import parameter_names
    from reflab.inverse.forward.factorization import Factorization
    from reflab.inverse.forward.models import get_model
    from reflab.inverse.forward.photographs import turned_view
    from reflab.inverse.forward.trees import build_trees

    task = ensure(task)
    log = log or (lambda line: None)
    t0 = time.perf_counter()
    models = [get_model(s.material.brdf) for s in scene]
    mats = [m.copy() for m in materials]
    for m, model in zip(mats, models):  # a lobe or branch left at ~0 at a plausible amplitude
        for name in model.linear:
            if name != "kd" and np.max(m[name]) < PLAUSIBLE:
                m.params[name] = np.full(BANDS, PLAUSIBLE)
        if m.transparent and np.max(m["t"]) < PLAUSIBLE:
            m.params["t"] = np.full(BANDS, PLAUSIBLE)
    fac = Factorization(stack.trees, models, stack.intensities)
    p = params_of(fac, mats)
    free = Free(np.ones_like(p.x, dtype=bool), np.ones_like(p.s, dtype=bool), np.ones_like(p.theta, dtype=bool))
    free.s[1::2] = np.array([m.transparent for m in mats])[:, None]
    hold(fac, free, held if held is not None else [set() for _ in scene])
    theta_log = Search(fac).log
    H_now, labels = information(stack.trees, models, mats, stack.intensities, noise, free)
    index = _labels_index(labels)
    now = relative_sigma(H_now, labels, p, theta_log)
    names = parameter_names(fac, scene)
    inflate = {}
    for lab in labels:  # the fit's reported σ over this model-based one (>= 1)
        rep = (reported or {}).get(names[lab])
        if rep is not None and np.isfinite(now[lab]) and now[lab] > 0:
            inflate[lab] = max(1.0, rep / now[lab]) if np.isfinite(rep) else max(1.0, 1.01 * LOOSE / now[lab])
    _inflated = lambda rel: {k: v * inflate.get(k, 1.0) for k, v in rel.items()}  # noqa: E731
    now = _inflated(now)
    # Targets: parameters of surfaces the photographs show, loose or undetermined now.
    seen = np.zeros(len(scene), dtype=bool)
    seen[np.unique(stack.trees.surface)] = True
    lay = fac.layout
    surf_of = {("x", i): lay.x_names[i][0] for i in range(lay.n_x)}
    surf_of.update({("s", f): f // 2 for f in range(lay.n_factors)})
    surf_of.update({("theta", q): lay.theta_names[q][0] for q in range(lay.n_theta)})
    # A textured surface's kd is the texture stage's (its mean only scales the texels): no target.
    texture_kd = {("x", i) for i, (s, name) in enumerate(lay.x_names) if name == "kd" and scene[s].textured}
    targets = [lab for lab in labels if now[lab] > LOOSE and seen[surf_of[lab[:2]]] and lab[:2] not in texture_kd]

    w = min(camera.width, max(camera.width // reduce, MIN_WIDTH))
    small = camera.scaled(w, max(round(camera.height * w / camera.width), 1))
    scale = (camera.width * camera.height) / (small.width * small.height)
    cands = candidate_shots(n_lamps, angles, taken)
    H_shot = []
    for i, shot in enumerate(cands):  # one small ray cast per candidate view
        task.step(i, len(cands), f"plan: view {i + 1} of {len(cands)} (turntable {shot.angle:g}°, lamps {shot.lamps})")
        cam, li = turned_view(small, lights, shot.angle, centre, direction=direction, lit=shot.lamps)
        trees = build_trees(scene, cam, li, depth=depth)
        H, lab = information(trees, models, mats, li.intensities, noise, free, scale)
        H_shot.append(None if H is None else _aligned(H, lab, index, len(labels)))
    task.check()

    def score(rel):
        return sum(np.log(max(now[t], GOOD_ENOUGH) if np.isfinite(now[t]) else 1e6)
                   - np.log(max(rel[t], GOOD_ENOUGH) if np.isfinite(rel[t]) else 1e6) for t in targets)

    chosen, H_acc, best_rel = [], H_now.copy(), now
    base = score(now)
    for _ in range(max_shots):
        best = None
        for i, H in enumerate(H_shot):
            if H is None or any(c["index"] == i for c in chosen):
                continue
            rel = _inflated(relative_sigma(H_acc + H, labels, p, theta_log))
            gain = score(rel) - base
            if best is None or gain > best[0]:
                best = (gain, i, rel)
        if best is None or best[0] < MIN_GAIN:
            break
        gain, i, rel = best
        H_acc = H_acc + H_shot[i]
        chosen.append({"index": i, "shot": cands[i], "gain": float(gain), "relative_sigma": rel, "before": best_rel})
        base, best_rel = base + gain, rel
        log(f"plan: {cands[i].name} (turntable {cands[i].angle:g}°, lamps {list(cands[i].lamps)}): gain {gain:.2f}")

    sigma_now = _sigmas(H_now, labels, p, names)
    shots = []
    for c in chosen:
        shots.append({"name": c["shot"].name, "angle_deg": c["shot"].angle, "lamps": list(c["shot"].lamps),
                      "gain": round(c["gain"], 4),
                      "predicted_relative_sigma": {names[t]: _num(c["relative_sigma"][t]) for t in targets},
                      "determines": sorted(names[t] for t in targets
                                           if c["relative_sigma"][t] <= LOOSE < c["before"][t])})
    H_after = H_acc
    report = {"targets": [names[t] for t in targets],
              "relative_sigma_now": {names[t]: _num(now[t]) for t in targets},
              "shots": shots,
              "predicted_sigma_now": sigma_now,
              "predicted_sigma_after": _sigmas(H_after, labels, p, names),
              "left_open": sorted(names[t] for t in targets if best_rel[t] > LOOSE),
              "candidates": len(cands), "reduce": int(reduce), "time_s": round(time.perf_counter() - t0, 3)}
    return PlanResult([c["shot"] for c in chosen], [names[t] for t in targets], report)


def _aligned(H, lab, index, n):
    """``H`` (labels ``lab``) placed in a matrix of the reference labels' order."""
    out = np.zeros((n, n))
    where = np.array([index[label] for label in lab], dtype=np.int64)
    out[np.ix_(where, where)] = H
    return out


def _sigmas(H, labels, p, names) -> dict:
    from reflab.inverse.fit.uncertainty import covariance

    sd, _ = covariance(H)
    return {names[lab]: _num(v) for lab, v in zip(labels, sd)}


def _num(v):
    v = float(v)
    return v if np.isfinite(v) else None
