"""The result of a fit and the fit.json object of docs/formats.md."""
from __future__ import annotations

import dataclasses

from dataclasses import dataclass, field

import numpy as np

from reflab.inverse.forward.factorization import Factorization
from reflab.inverse.fit.problem import Free, Params


@dataclass
class FitSolution:
    """Everything ``fit.json`` reports (docs/formats.md) plus diagnostics."""

    method: str
    params: Params
    free: Free
    materials: list
    sigma: Params
    rms: np.ndarray
    time_s: float
    trace: list
    undetermined: list
    rounds: int
    evaluations: int
    iterations: int
    message: str
    stats: dict = field(default_factory=dict)
    #: Which parameters have signal in the image (before any was held): a refit of the same scene
    #: reuses it (:func:`reflab.inverse.fit.rounds.fit`'s ``structure``).
    structure: Free | None = None


def fit_json(result: FitSolution, fac: Factorization, scene, depth: int, extra: dict | None = None) -> dict:
    """The fit.json object of docs/formats.md (plus diagnostics)."""
    lay, surfaces = fac.layout, []
    bounds = result.stats.get("at_bound")
    for i, (surf, model, mat) in enumerate(zip(scene.surfaces, fac.models, result.materials)):
        sigma = {}
        for j, name in enumerate(model.linear):
            k = lay.x_offset[i] + j
            sigma[name] = _sigma_list(result.sigma.x[k], result.free.x[k])
        for j, name in enumerate(model.nonlinear):
            q = lay.theta_offset[i] + j
            sigma[name] = float(result.sigma.theta[q]) if result.free.theta[q] and np.isfinite(result.sigma.theta[q]) else None
        sigma["r"] = _sigma_list(result.sigma.s[2 * i], result.free.s[2 * i])
        sigma["t"] = _sigma_list(result.sigma.s[2 * i + 1], result.free.s[2 * i + 1])
        surfaces.append({"name": surf.name, "material": mat.to_json(), "sigma": sigma,
                         "undetermined": result.undetermined[i], "at_bound": bounds[i] if bounds else {}})
    out = {
        "method": result.method, "depth": int(depth), "time_s": round(result.time_s, 6),
        "rms": [float(v) for v in result.rms], "trace": result.trace, "surfaces": surfaces,
        "columns": {"used": int(fac.n_columns), "monomials": len(fac.monomials),
                    "dense_dissertation": fac.dense_columns, "names": fac.column_names()},
        "iterations": result.iterations, "evaluations": result.evaluations, "rounds": result.rounds,
        "message": result.message,
    }
    out.update({k: v for k, v in result.stats.items() if k != "at_bound"})
    out.update(extra or {})
    return _finite(out)


def parameter_names(fac: Factorization, scene) -> dict:
    """(kind, index, band) label of :func:`reflab.inverse.fit.uncertainty.normal_matrix` -> readable
    name ``surface.param[band]`` (``surface.param`` for a nonlinear parameter)."""
    lay, out = fac.layout, {}
    for i, (s, name) in enumerate(lay.x_names):
        for c in range(3):
            out[("x", i, c)] = f"{scene[s].name}.{name}[{c}]"
    for f in range(lay.n_factors):
        for c in range(3):
            out[("s", f, c)] = f"{scene[f // 2].name}.{'rt'[f % 2]}[{c}]"
    for q, (s, name) in enumerate(lay.theta_names):
        out[("theta", q, -1)] = f"{scene[s].name}.{name}"
    return out


def _finite(obj):
    """``obj`` (JSON-like) with every NaN or infinite float replaced by None."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _sigma_list(sig, free) -> list:
    """Per-band sigma, None where the band is undetermined (JSON null, never NaN/inf)."""
    return [float(v) if f and np.isfinite(v) else None for v, f in zip(sig, free)]


@dataclasses.dataclass
class SceneFit:
    """What :func:`reflab.inverse.fit.workspace_fit.fit_scene` found: the fit, the system it was judged on (``fac``: its rows are
    the pixels read), the texture rounds' records, the sampling's counts, seconds per phase."""

    result: "FitSolution"
    fac: object  # reflab.inverse.forward.factorization.Factorization
    rounds: dict | None
    sampling: dict | None
    phases: dict
    scan_evaluations: int
