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

A lobe the fit left open has no one value to predict at: the photographs may show a broad lobe
at one albedo as well as they show no sharp one at any. Its prediction is made under each shape
the fit weighed it at (fit.json's ``lobe_shapes``, :func:`reflab.inverse.fit.determined.plausible_lobes`:
ns 8 to 2048, each at the albedo the photographs give it there, or a faint one where they do not
bind it) besides the fitted values, and a shot is scored by its gain under each, weighed by the
prior over shapes: a shot that lands a sharp highlight on the surface (the mirror direction of a
lamp off the surface into the camera after the turn) gains under the sharp shapes, which a broad
lobe's prediction never sees.

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
#: Shapes of an open lobe whose prior (:func:`reflab.inverse.fit.ranges.shape_prior`) is below this
#: fraction of the largest are no hypothesis (ns 2 and 8192: 0.02 and 0.005).
MIN_PRIOR = 0.05
#: The albedo of a hypothesis where the photographs do not bind the lobe at its shape (fit.json's
#: basis "prior"): the faintest of the field's lobes (2 % of the light, ranges.LOBE_ALBEDO's
#: comment), not the prior's mean 0.125 — a shot planned to show a faint highlight shows a bright one.
FAINT_ALBEDO = 0.02


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


@dataclass
class Hypothesis:
    """Materials a shot's information is predicted at: the fitted ones, or with each open lobe at
    one shape (``lobes``: surface name -> its shape, ks and albedo) and its prior ``weight``."""

    label: str
    weight: float
    materials: list
    lobes: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"label": self.label, "weight": round(float(self.weight), 4),
                "lobes": {k: {n: float(v) for n, v in lobe.items()} for k, lobe in self.lobes.items()}}


def hypotheses(scene, materials, models, lobe_shapes=None) -> list:
    """The fitted materials, then one :class:`Hypothesis` per shape an open lobe was weighed at.

    ``lobe_shapes``: fit.json's (surface name -> records in increasing shape,
    :func:`reflab.inverse.fit.determined.plausible_lobes`). Shape ``v`` sets every open lobe weighed
    at ``v`` to it, at the albedo the photographs gave it there (:data:`FAINT_ALBEDO` at most where
    they do not bind it) and its ks so; shapes whose prior is under :data:`MIN_PRIOR` of the
    largest are left out. Weights: the prior over shapes, the fitted materials one share like a
    shape of the prior's largest (it is the fit's posterior mode); they sum to 1.
    """
    from reflab.inverse.fit.ranges import lobe_albedo, shape_prior

    index = {s.name: i for i, s in enumerate(scene)}
    grid = {}  # shape -> {surface index: record}
    for name, records in (lobe_shapes or {}).items():
        i = index.get(name)
        if i is None or not models[i].nonlinear or "ks" not in models[i].linear:
            continue
        shape_name = models[i].nonlinear[0]
        for rec in records:
            if isinstance(rec.get(shape_name), (int, float)) and np.isfinite(rec[shape_name]) and rec[shape_name] > 0:
                grid.setdefault((shape_name, float(rec[shape_name])), {})[i] = rec
    out = [Hypothesis("fitted", 1.0, materials)]
    if not grid:
        return out
    prior = {key: float(np.exp(shape_prior(*key))) for key in grid}
    top = {n: max(v for (m, _), v in prior.items() if m == n) for n, _ in grid}
    for (shape_name, v), recs in sorted(grid.items()):
        if prior[(shape_name, v)] < MIN_PRIOR * top[shape_name]:
            continue
        mats, lobes = [m.copy() for m in materials], {}
        for i, rec in recs.items():
            albedo = float(rec.get("albedo", 0.0))
            if rec.get("basis") == "prior":
                albedo = min(albedo, FAINT_ALBEDO)
            ks = albedo / max(lobe_albedo(models[i], v), 1e-300)
            mats[i].params[shape_name] = np.asarray(v, dtype=np.float64)
            mats[i].params["ks"] = np.full(BANDS, ks)
            lobes[scene[i].name] = {shape_name: v, "ks": ks, "albedo": albedo}
        label = ", ".join(f"{k}.{shape_name} {v:.3g}" for k in lobes)
        out.append(Hypothesis(label, prior[(shape_name, v)] / top[shape_name], mats, lobes))
    total = sum(h.weight for h in out)
    for h in out:
        h.weight /= total
    return out


def _labels_index(labels) -> dict:
    return {lab: i for i, lab in enumerate(labels)}


def information(trees, models, materials, intensities, noise, free, scale: float = 1.0):
    """``JᵀWJ`` of one view (its trees) at ``materials`` for the ``free`` parameters, times ``scale``.

    Returns (H, labels) as :func:`reflab.inverse.fit.uncertainty.normal_matrix`.
    """
    Hs, labels = views_information(trees, models, [materials], intensities, noise, free, scale)
    return (None, None) if Hs is None else (Hs[0], labels[0])


def relative_sigma(H, labels, p, theta_log) -> dict:
    """Label -> σ relative to the parameter's scale (x: its value, at least 0.1; r, t: 1;
    θ: σ of log2 θ for log-searched names, else absolute); inf where H is singular along it."""
    return relative_sigmas(np.asarray(H)[None], labels, [p], theta_log)[0]


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
               reported=None, lobe_shapes=None, task=None, log=None) -> PlanResult:
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
    lobe_shapes : dict, optional
        fit.json's ``lobe_shapes``: the shapes each open lobe was weighed at (:func:`hypotheses`).
        Under a hypothesis, the lobe's own ks and shape are predicted as they are (not scaled by
        the fit's reported σ, which is the fitted values').
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
    hyps = hypotheses(scene, mats, models, lobe_shapes)
    fac = Factorization(stack.trees, models, stack.intensities)
    ps = [params_of(fac, h.materials) for h in hyps]
    p = ps[0]
    free = Free(np.ones_like(p.x, dtype=bool), np.ones_like(p.s, dtype=bool), np.ones_like(p.theta, dtype=bool))
    free.s[1::2] = np.array([m.transparent for m in mats])[:, None]
    hold(fac, free, held if held is not None else [set() for _ in scene])
    theta_log = Search(fac).log
    H_now, lab_now = views_information(stack.trees, models, [h.materials for h in hyps], stack.intensities, noise,
                                       free)
    labels = lab_now[0]
    index = _labels_index(labels)
    H_now = np.stack([_aligned(H, lab, index, len(labels)) for H, lab in zip(H_now, lab_now)])
    # Relative σ = σ / scale × the fit's inflation, per hypothesis (rows) and label (columns).
    scales = np.stack([_scales(labels, q, theta_log) for q in ps])
    raw_now = _batched_sd(H_now) / scales
    names = parameter_names(fac, scene)
    inflate = np.ones(len(labels))
    for j, lab in enumerate(labels):  # the fit's reported σ over this model-based one (>= 1)
        rep, mine = (reported or {}).get(names[lab]), raw_now[0, j]
        if rep is not None and np.isfinite(mine) and mine > 0:
            inflate[j] = max(1.0, rep / mine) if np.isfinite(rep) else max(1.0, 1.01 * LOOSE / mine)
    lay = fac.layout
    # Under a shape hypothesis, the open lobe's ks and shape are its own: not the fitted values' σ.
    own = np.zeros((len(hyps), len(labels)), dtype=bool)
    for j, h in enumerate(hyps):
        for i, s in enumerate(scene):
            if s.name in h.lobes:
                k = lay.x_offset[i] + models[i].linear.index("ks")
                own[j] |= [lab[:2] == ("x", k) or (lab[0] == "theta" and lay.theta_names[lab[1]][0] == i)
                           for lab in labels]
    factor = np.where(own, 1.0, inflate) / scales  # (hypotheses, labels)
    nows = raw_now * np.where(own, 1.0, inflate)
    now = dict(zip(labels, nows[0]))
    # Targets: parameters of surfaces the photographs show, loose or undetermined now.
    seen = np.zeros(len(scene), dtype=bool)
    seen[np.unique(stack.trees.surface)] = True
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
    H_shot = []  # per candidate: (hypotheses, n, n) or None
    for i, shot in enumerate(cands):  # one small ray cast per candidate view, its information under each hypothesis
        task.step(i, len(cands), f"plan: view {i + 1} of {len(cands)} (turntable {shot.angle:g}°, lamps {shot.lamps})")
        cam, li = turned_view(small, lights, shot.angle, centre, direction=direction, lit=shot.lamps)
        trees = build_trees(scene, cam, li, depth=depth)
        Hs, labs = views_information(trees, models, [h.materials for h in hyps], li.intensities, noise, free, scale)
        H_shot.append(None if Hs is None else np.stack([_aligned(H, lab, index, len(labels)) for H, lab in zip(Hs, labs)]))
    task.check()
    weights = np.array([h.weight for h in hyps])
    T = np.array([index[t] for t in targets], dtype=np.int64)

    def log_sigma(rel):  # (..., targets) clipped log relative σ: no credit below GOOD_ENOUGH, inf as 1e6
        r = rel[..., T]
        return np.where(np.isfinite(r), np.log(np.maximum(r, GOOD_ENOUGH)), np.log(1e6))

    chosen, H_acc, rel_acc = [], H_now, nows
    base = log_sigma(nows)  # (hypotheses, targets)
    for _ in range(max_shots):
        live = [i for i, H in enumerate(H_shot) if H is not None and all(c["index"] != i for c in chosen)]
        if not live:
            break
        # Every candidate under every hypothesis in one batched inverse.
        rels = (_batched_sd(np.concatenate([H_acc + H_shot[i] for i in live])).reshape(len(live), len(hyps), -1)
                * factor)
        gains = (base - log_sigma(rels)).sum(axis=2) @ weights  # (candidates,)
        c = int(np.argmax(gains))
        if gains[c] < MIN_GAIN:
            break
        i = live[c]
        H_acc = H_acc + H_shot[i]
        chosen.append({"index": i, "shot": cands[i], "gain": float(gains[c]), "relative_sigma": rels[c],
                       "before": rel_acc})
        base, rel_acc = log_sigma(rels[c]), rels[c]
        log(f"plan: {cands[i].name} (turntable {cands[i].angle:g}°, lamps {list(cands[i].lamps)}): gain {gains[c]:.2f}")

    def determined(rel):  # per target, the share of the hypotheses' weight under which it is determined
        return weights @ (rel[:, T] <= LOOSE)

    lobed = [t for t in targets if any(scene[surf_of[t[:2]]].name in h.lobes for h in hyps)]
    shots = []
    for c in chosen:
        rel, before = c["relative_sigma"], c["before"]
        after_w, before_w = determined(rel), determined(before)
        under = {names[t]: [_label(h, scene[surf_of[t[:2]]].name) for j, h in enumerate(hyps)
                            if rel[j, index[t]] <= LOOSE < before[j, index[t]]] for t in lobed}
        shots.append({"name": c["shot"].name, "angle_deg": c["shot"].angle, "lamps": list(c["shot"].lamps),
                      "gain": round(c["gain"], 4),
                      "predicted_relative_sigma": {names[t]: _num(rel[0, index[t]]) for t in targets},
                      "determines": sorted(names[t] for t, a, b in zip(targets, after_w, before_w) if a >= 0.5 > b),
                      "determines_under": {k: v for k, v in sorted(under.items()) if v},
                      "predicted_relative_sigma_by_hypothesis": {
                          h.label: {names[t]: _num(rel[j, index[t]]) for t in targets if own[j, index[t]]}
                          for j, h in enumerate(hyps) if j}})
    final = determined(rel_acc)
    sd_after = _batched_sd(H_acc)
    report = {"targets": [names[t] for t in targets],
              "relative_sigma_now": {names[t]: _num(now[t]) for t in targets},
              "hypotheses": [h.to_json() for h in hyps],
              "shots": shots,
              "predicted_sigma_now": _sigmas(H_now[0], labels, p, names),
              "predicted_sigma_after": _sigmas(H_acc[0], labels, p, names),
              "predicted_sigma_after_by_hypothesis": {
                  h.label: {names[t]: _num(sd_after[j, k]) for k, t in enumerate(labels) if own[j, k]}
                  for j, h in enumerate(hyps) if j},
              "left_open": sorted(names[t] for t, w in zip(targets, final) if w < 0.5),
              "candidates": len(cands), "reduce": int(reduce), "time_s": round(time.perf_counter() - t0, 3)}
    return PlanResult([c["shot"] for c in chosen], [names[t] for t in targets], report)


def views_information(trees, models, materials_list, intensities, noise, free, scale: float = 1.0):
    """:func:`information` of one view under several materials (one Factorization, one render).

    Returns (list of H, list of labels), or (None, None) where the view shows nothing.
    """
    from reflab.inverse.fit.problem import Problem, params_of
    from reflab.inverse.fit.uncertainty import normal_matrix
    from reflab.inverse.forward.factorization import Factorization
    from reflab.inverse.forward.rendering import render

    fac = Factorization(trees, models, intensities)
    if fac.n_columns == 0:
        return None, None
    image = render(trees, materials_list[0], intensities)  # J does not depend on it; the problem's scale does
    pb = Problem(fac, image, [m.transparent for m in materials_list[0]])
    weights = 1.0 / np.maximum(np.asarray(noise, dtype=np.float64), 1e-300) ** 2
    Hs, labels = [], []
    for mats in materials_list:
        H, lab = normal_matrix(pb, params_of(fac, mats), free, weights)
        Hs.append(scale * H)
        labels.append(lab)
    return Hs, labels


def relative_sigmas(Hs, labels, ps, theta_log) -> list:
    """:func:`relative_sigma` (a dict per matrix) of a batch of normal matrices ``Hs`` (B, n, n) at
    parameters ``ps`` (B of them), in one batched inverse (:func:`_batched_sd`)."""
    rel = _batched_sd(np.asarray(Hs, dtype=np.float64)) / np.stack([_scales(labels, p, theta_log) for p in ps])
    return [{lab: float(v) for lab, v in zip(labels, row)} for row in rel]


def _scales(labels, p, theta_log) -> np.ndarray:
    """(n,) what each label's σ is relative to (:func:`relative_sigma`)."""
    out = np.ones(len(labels))
    for j, (kind, i, c) in enumerate(labels):
        if kind == "x":
            out[j] = max(abs(float(p.x[i, c])), PLAUSIBLE)
        elif kind == "theta" and theta_log[i]:
            out[j] = max(float(p.theta[i]), 1e-300) * np.log(2.0)
    return out


def _batched_sd(Hs):
    """(B, n) ``sqrt(diag(H⁻¹))`` of each (n, n) ``H`` as :func:`reflab.inverse.fit.uncertainty.covariance`
    (diagonal scaling, the spectrum held 1e-14 of its top above 0); inf where the diagonal is 0.

    A Cholesky factor per matrix with that floor added (40× faster than the eigen-decomposition
    on the plan's 500 matrices of 46 parameters); the eigen-decomposition where one is not positive."""
    B, n = Hs.shape[0], Hs.shape[1]
    if n == 0:
        return np.zeros((B, 0))
    dg = np.sqrt(np.maximum(np.einsum("bii->bi", Hs), 0.0))
    ok = dg > 0
    d = np.where(ok, dg, 1.0)
    Hs = Hs / (d[:, :, None] * d[:, None, :])
    Hs = np.where(ok[:, :, None] & ok[:, None, :], Hs, 0.0) + np.where(ok, 0.0, 1.0)[:, :, None] * np.eye(n)
    try:  # unit diagonal: the top eigenvalue is between 1 and n
        L = np.linalg.cholesky(Hs + (1e-14 * n) * np.eye(n))
        Li = np.linalg.inv(L)
        diag = np.einsum("bki,bki->bi", Li, Li)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(Hs)
        w = np.maximum(w, 1e-14 * np.maximum(w.max(axis=1, keepdims=True), 1e-300))
        diag = np.einsum("bij,bj->bi", V * V, 1.0 / w)
    return np.where(ok, np.sqrt(np.maximum(diag, 0.0)) / d, np.inf)


def _label(h: Hypothesis, surface: str) -> str:
    """A hypothesis named by what it says of ``surface``'s lobe ("ns 128"), else by its label
    ("fitted": the fit's values)."""
    lobe = h.lobes.get(surface)
    if lobe is None:
        return h.label
    name = next(k for k in lobe if k not in ("ks", "albedo"))
    return f"{name} {lobe[name]:.3g}"


def why(shot: dict) -> str:
    """plan.json's shot in words: what it determines, and an open lobe's shape under which shapes of it."""
    out = ", ".join(shot.get("determines") or []) or "nothing new (narrows)"
    shapes = {k: [x for x in v if x != "fitted"] for k, v in (shot.get("determines_under") or {}).items()
              if k.endswith((".ns", ".alpha"))}
    shapes = {k: v for k, v in shapes.items() if v}
    if shapes:
        out += " (" + "; ".join(f"{k} if the lobe is {' or '.join(v)}" for k, v in shapes.items()) + ")"
    return out


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
