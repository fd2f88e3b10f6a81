"""Physically plausible range of every fitted parameter (docs/fit.md, "Plausible ranges").

Units are the project's: a white Lambertian surface has ``kd = 1`` (the 1/π lives in the lamp
intensities), so a surface's directional albedo at normal incidence, relative to white, is

    a = kd + ks · L(θ)

with ``L`` the specular lobe's own albedo per unit ``ks``. A surface reflects no more light than
it receives, so each term alone is at most 1:

- ``kd`` in [0, 1] (with a known absolute texture, kd is a gain on it: at most 1 over its peak);
- Phong ``ks`` in [0, 1 / L(ns)], ``L(ns) = 2 ∫₀^{π/2} cos^ns(θ/2) cos θ sin θ dθ`` (the lobe of
  ``(n·h)^ns`` about the mirror direction at normal incidence, closed form below): 1.2 at
  ns = 2, 4.5 at ns = 30, 37 at ns = 300 — a sharper lobe concentrates the same energy;
- Ward ``ks`` (its ρ_s, already normalised) in [0, 1];
- ``r``, ``t`` in [0, 1] (attenuations of ideal reflection and transmission);
- θ in scene.json's ranges (:data:`reflab.reconstruction.scene.SCALAR_RANGE`): Ward α in [1e-4, 1],
  Oren–Nayar σ in [0, π/2]; ns in [2, 2^20] (:data:`FIT_RANGE`; scene.json accepts 1e-3, but a
  lobe broader than ns = 2 is as broad as diffuse light and only trades with kd).

F-TBO keeps every value inside these ranges (its inner bounded least squares takes the θ-
dependent upper bound of ks); :func:`clip` projects the result of a method that does not
(NF-TBO's unbounded reparametrisation); :func:`at_bound` names values sitting on a bound;
:func:`plausible` moves an undetermined value off a bound to the field's plausible value;
:func:`render_value` is the value a view is rendered with when the data leave an r or t loose;
:func:`shape_prior` and :func:`lobe_evidence` are the prior over a lobe the data leave open and
what the data say of it (:func:`reflab.inverse.fit.determined.plausible_lobes` weighs them).
"""
from __future__ import annotations

import numpy as np

from reflab.reconstruction.scene import INITIAL, SCALAR_RANGE

#: Upper bound of kd, Ward ks, r and t.
UNIT = 1.0
#: The fit's narrower ranges than scene.json's: a Phong lobe broader than ns = 2 is as broad as
#: diffuse light and trades with kd (a fitted ns there is held as undetermined).
FIT_RANGE = {"ns": (2.0, 2.0**20)}
#: Relative distance to a bound under which a value counts as on it.
ON_BOUND = 1e-6


def phong_lobe_albedo(ns) -> np.ndarray:
    """``L(ns)``: albedo at normal incidence of ``(n·h)^ns`` per unit ks (closed form).

    With ``c = cos(θ/2)``: ``L = 8 [2 c^(ns+4)/(ns+4) − c^(ns+2)/(ns+2)]`` from ``c = 1/√2`` to 1.
    """
    ns = np.asarray(ns, dtype=np.float64)
    lo = np.sqrt(0.5)

    def prim(c):
        return 2.0 * c ** (ns + 4.0) / (ns + 4.0) - c ** (ns + 2.0) / (ns + 2.0)

    return 8.0 * (prim(1.0) - prim(lo))


def ks_upper(model, shape: float) -> float:
    """Upper bound of ``model``'s ks at its shape parameter ``shape``: a Phong lobe's albedo at
    most 1 (``1 / L(ns)``), else :data:`UNIT`."""
    return 1.0 / float(phong_lobe_albedo(shape)) if model.name == "phong" else UNIT


def linear_upper(fac, theta) -> np.ndarray:
    """(X,) upper bound of each flat linear parameter at nonlinear parameters ``theta``."""
    lay = fac.layout
    out = np.full(lay.n_x, UNIT)
    gain = _kd_gain_limit(fac)
    for k, (s, name) in enumerate(lay.x_names):
        model = fac.models[s]
        if name == "kd":
            out[k] = gain[s]
        if name == "ks" and model.name == "phong":
            out[k] = ks_upper(model, theta[lay.theta_offset[s] + list(model.nonlinear).index("ns")])
    return out


def _kd_gain_limit(fac) -> np.ndarray:
    """(S,) upper bound of each surface's kd: 1; with a known absolute texture (``fac.albedo`` at
    most 1, kd a gain on it) 1 over its largest value. A relative texture (the texture rounds:
    kd the surface's mean albedo) keeps 1: its largest value comes from a noisy recovery."""
    out = np.ones(len(fac.models))
    if getattr(fac, "albedo", None) is None:
        return out
    if not hasattr(fac, "_kd_gain_limit"):
        surf = np.asarray(fac.trees.surface)[fac.node]
        peak = np.zeros(len(fac.models))
        np.maximum.at(peak, surf, fac.albedo.max(axis=1))
        fac._kd_gain_limit = np.maximum(1.0, np.where(peak > 0, 1.0 / np.maximum(peak, 1e-300), 1.0))
    return fac._kd_gain_limit


def theta_bounds(fac) -> tuple[np.ndarray, np.ndarray]:
    """(Q,), (Q,) lower and upper bounds of the nonlinear parameters (natural units) in the fit."""
    names = [name for _, name in fac.layout.theta_names]
    rng = {**SCALAR_RANGE, **FIT_RANGE}
    lo = np.array([rng[n][0] for n in names], dtype=np.float64).reshape(-1)
    hi = np.array([rng[n][1] for n in names], dtype=np.float64).reshape(-1)
    return lo, hi


def clip(fac, p) -> bool:
    """Project ``p`` (:class:`reflab.inverse.fit.rounds.Params`) onto the ranges in place; True if it moved."""
    lo, hi = theta_bounds(fac)
    theta = np.clip(np.where(np.isnan(p.theta), lo, p.theta), lo, hi)  # NaN: to the lower bound
    x = np.clip(np.nan_to_num(p.x, nan=0.0), 0.0, linear_upper(fac, theta)[:, None])
    s = np.clip(np.nan_to_num(p.s, nan=0.0), 0.0, UNIT)
    moved = bool(np.any(theta != p.theta) or np.any(x != p.x) or np.any(s != p.s))  # NaN != NaN: moved
    p.theta[:], p.x[:], p.s[:] = theta, x, s
    return moved


def _side(value, lo, hi):
    tol = ON_BOUND * max(hi - lo, 1.0) if np.isfinite(hi) else ON_BOUND
    if value >= hi - tol:
        return "upper"
    if value <= lo + tol:
        return "lower"
    return None


def at_bound(fac, p, free) -> list:
    """Per surface, ``{name: side}`` of the fitted values on a bound (``"ks[0]": "upper"``).

    Only fitted values count (held ones are the user's or the start's). ``r = 0``, ``t = 0`` or
    ``ks = 0`` at the lower bound are listed too: they are real answers, but the σ of a value on
    a bound is one-sided.
    """
    lay = fac.layout
    ub = linear_upper(fac, p.theta)
    lo_t, hi_t = theta_bounds(fac)
    out = [dict() for _ in fac.models]

    def band(name, c):
        return f"{name}[{c}]"

    for k, (s, name) in enumerate(lay.x_names):
        for c in range(p.x.shape[1]):
            if free.x[k, c] and (side := _side(p.x[k, c], 0.0, ub[k])):
                out[s][band(name, c)] = side
    for f in range(lay.n_factors):
        s, name = f // 2, ("r", "t")[f % 2]
        for c in range(p.s.shape[1]):
            if free.s[f, c] and (side := _side(p.s[f, c], 0.0, UNIT)):
                out[s][band(name, c)] = side
    for q, (s, name) in enumerate(lay.theta_names):
        if free.theta[q]:
            # Shininess and roughness in log2 (as the fit searches them); Oren-Nayar's σ, whose
            # range starts at 0, linearly.
            side = (_side(np.log2(max(p.theta[q], 1e-300)), np.log2(lo_t[q]), np.log2(hi_t[q])) if name in ("ns", "alpha")
                    else _side(p.theta[q], lo_t[q], hi_t[q]))
            if side:
                out[s][name] = side
    return out


def plausible(fac, p, loose) -> list:
    """Move every undetermined lobe value that sits on a bound to the plausible one, in place.

    A lobe the photograph leaves open (``loose``: fitted, but its σ spans its scale) may end on
    either bound of its range: ks = 0, or ks at 1 / L(ns), a lobe reflecting all the light, which
    a novel view renders as a highlight brighter than anything in the scene. Any value within
    its σ explains the photograph as well; the one reported and rendered is the prior's centre
    over the field's materials, :data:`reflab.reconstruction.scene.INITIAL` (the start of every
    fit): a shininess or roughness on a bound takes its initial value, and a ks with a band on a
    bound takes the initial ks in every loose band (a grey lobe), kept under the θ's bound. σ is
    not touched: the value stays reported undetermined.

    Returns
    -------
    list
        ``(surface, name)`` of the values moved ("ks[0]" for a band).
    """
    lay, moved = fac.layout, []
    lo, hi = theta_bounds(fac)
    for q, (s, name) in enumerate(lay.theta_names):
        if loose.theta[q] and name in INITIAL:
            log = name in ("ns", "alpha")
            v, a, b = ((np.log2(max(p.theta[q], 1e-300)), np.log2(lo[q]), np.log2(hi[q])) if log
                       else (p.theta[q], lo[q], hi[q]))
            if _side(v, a, b):
                p.theta[q] = float(np.clip(INITIAL[name], lo[q], hi[q]))
                moved.append((s, name))
    ub = linear_upper(fac, p.theta)
    for k, (s, name) in enumerate(lay.x_names):
        if name == "kd" or not loose.x[k].any():
            continue
        if any(loose.x[k, c] and _side(p.x[k, c], 0.0, ub[k]) for c in range(p.x.shape[1])):
            p.x[k, loose.x[k]] = min(INITIAL.get(name, INITIAL["ks"]), ub[k])
            moved += [(s, f"{name}[{c}]") for c in np.flatnonzero(loose.x[k])]
        p.x[k] = np.minimum(p.x[k], ub[k])  # a moved θ may lower the bound of a determined band
    return moved


def plausible_range(brdf: str, name: str, material: dict | None = None) -> tuple[float, float] | None:
    """The plausible range (lo, hi) of fit.json's parameter ``name`` of a ``brdf`` surface, None when
    it has none (``ior``); ``material`` (fit.json's material) gives Phong ks its ns-dependent bound.

    The same ranges the fit keeps its values in (module docstring), for the report and the GUI to
    show an undetermined value as its range rather than as a σ wider than it.
    """
    if name in ("kd", "r", "t"):
        return 0.0, UNIT
    if name == "ks":
        ns = (material or {}).get("ns")
        if brdf == "phong" and isinstance(ns, (int, float)) and np.isfinite(ns) and ns > 0:
            return 0.0, 1.0 / float(phong_lobe_albedo(max(float(ns), FIT_RANGE["ns"][0])))
        return 0.0, UNIT
    rng = {**SCALAR_RANGE, **FIT_RANGE}
    return tuple(float(v) for v in rng[name]) if name in rng else None


#: Prior probability that a surface has no ideal reflection (or transmission) at all, r = 0 (t = 0):
#: most materials have none, and a fit cannot tell a faint one from none within its σ. The rest
#: of the prior is spread over the fitted value's plausible range.
ABSENT = 0.5
#: Fitted values with a σ under this are rendered as fitted (the normal density underflows anyway).
MIN_SIGMA = 1e-12


def render_value(value, sigma, lo: float = 0.0, hi: float = UNIT, absent: float = ABSENT) -> np.ndarray:
    """The value a fitted r or t is rendered with: its posterior mean when a prior gives "absent"
    (the range's lower bound, 0) the probability ``absent`` and the rest of the range the rest.

    With the fit's estimate ``value ± sigma`` (Gaussian likelihood), the posterior probability of
    absence is ``P0 = a·N(lo; v, σ) / (a·N(lo; v, σ) + (1 − a)·(Φ((hi − v)/σ) − Φ((lo − v)/σ))/(hi − lo))``
    and the posterior mean is ``(1 − P0)·v`` (``v`` standing for the present case): a value many σ
    above 0 is unchanged (P0 ≈ 0), one within a σ or two of 0 shrinks toward it — the shiny box's
    r[0] 0.035 ± 0.024 (true 0) renders at 0.005 instead of mirroring the ground into a relit
    view. fit.json keeps the fitted value and its σ; a value without a finite σ is returned as is.

    Parameters
    ----------
    value, sigma : array_like
        Fitted values and their σ (same shape; NaN or inf σ: undetermined, left alone).
    lo, hi : float
        The plausible range (:func:`plausible_range`).
    absent : float
        Prior probability of ``lo`` (:data:`ABSENT`).

    Returns
    -------
    ndarray
        Values in [lo, value], float64.
    """
    from scipy.special import ndtr

    v = np.asarray(value, dtype=np.float64)
    s = np.asarray(sigma, dtype=np.float64)
    ok = np.isfinite(s) & (s > MIN_SIGMA) & np.isfinite(v)
    s_ok = np.where(ok, s, 1.0)
    z = (v - lo) / s_ok
    spike = absent * np.exp(-0.5 * z * z) / (np.sqrt(2.0 * np.pi) * s_ok)
    slab = (1.0 - absent) * (ndtr((hi - v) / s_ok) - ndtr((lo - v) / s_ok)) / (hi - lo)
    p0 = np.divide(spike, spike + slab, out=np.zeros_like(v), where=(spike + slab) > 0)
    return np.where(ok, lo + (1.0 - p0) * (v - lo), v)


#: The prior over an undetermined lobe's shape, the field's materials (docs/fit.md, "Undetermined
#: means plausible"): log2 of Phong ns or Ward α normal about :data:`INITIAL`'s (ns 2^6.5 ≈ 90,
#: α 0.2) with this spread in log2 units — glossy paints and plastics ns 5–300, metals and glazes
#: sharper; Ward α 0.05–0.5.
SHAPE_PRIOR_SD = {"ns": 2.0, "alpha": 1.0}
#: The shapes an undetermined lobe is weighed at (besides its fitted one and the prior's centre):
#: ns every two octaves from 2 to 2^13 (a lobe sharper than that is a mirror's point), α every
#: octave from 1/64 to 1.
SHAPE_GRID = {"ns": 2.0 ** np.arange(1.0, 14.0, 2.0), "alpha": 2.0 ** np.arange(-6.0, 0.5, 1.0)}
#: The prior over a lobe's albedo ``a = ks·L`` (:func:`lobe_albedo`): none (a = 0) with probability
#: :data:`ABSENT`, else uniform on [0, LOBE_ALBEDO] — the lobes of the field's materials reflect
#: 2–35 % of the light (docs/simulated-lab.md's zoo draws them so); a lobe reflecting half the light
#: is a polished metal's.
LOBE_ALBEDO = 0.5


def lobe_albedo(model, shape: float) -> float:
    """The albedo at normal incidence of ``model``'s lobe per unit ks at its shape: ``L(ns)`` for
    Phong, 1 for Ward (its ρ_s is normalised already)."""
    return float(phong_lobe_albedo(shape)) if model.name == "phong" else 1.0


def shape_prior(name: str, value) -> np.ndarray:
    """Log prior density (up to a constant) of a lobe's shape ``value`` (ns or α) per log2 unit."""
    z = (np.log2(np.maximum(np.asarray(value, dtype=np.float64), 1e-300)) - np.log2(INITIAL[name])) / SHAPE_PRIOR_SD[name]
    return -0.5 * z * z


def lobe_evidence(a_hat, sigma, top: float = LOBE_ALBEDO, absent: float = ABSENT) -> tuple[float, np.ndarray]:
    """What a lobe's conditional fit at one shape says under the prior over its albedo.

    With the per-band albedo ``a_hat ± sigma`` the data give at that shape (Gaussian likelihood,
    ``sigma`` inf where no pixel shows the lobe) and the prior of :data:`LOBE_ALBEDO`: none with
    probability ``absent`` (in every band at once), else uniform on [0, top] per band,

    - the log of the likelihood integrated over that prior, relative to the likelihood at
      ``a_hat``: log(absent·Π exp(−z₀²/2) + (1 − absent)·Π σ√(2π)/top·(Φ((top − â)/σ) − Φ(−â/σ))),
      z₀ = â/σ. 0 where no pixel shows the lobe (every albedo explains the data); about log(absent)
      where the data bound the albedo near 0 (only "none" explains them);
    - the posterior mean albedo per band: (1 − P0)·the mean of N(â, σ) truncated to [0, top], P0
      the posterior probability of none. A lobe many σ above 0 keeps â, one the data bound near 0
      renders within a σ of it, one no pixel shows the prior's mean, (1 − absent)·top/2.

    Returns
    -------
    log_evidence : float
    mean : (bands,) ndarray
        Posterior mean albedo, float64, in [0, top].
    """
    from scipy.special import erf

    a = np.maximum(np.asarray(a_hat, dtype=np.float64), 0.0)  # above top: the prior's edge is near it
    s = np.asarray(sigma, dtype=np.float64)
    seen = np.isfinite(s) & (s > MIN_SIGMA)
    s_ok = np.where(seen, s, 1.0)
    alpha, beta = -a / s_ok, (top - a) / s_ok
    # Φ(β) − Φ(α) and φ(α) − φ(β) without cancellation when σ dwarfs the range (a lobe barely seen).
    mass = 0.5 * (erf(beta / np.sqrt(2.0)) + erf(-alpha / np.sqrt(2.0)))
    dphi = (np.expm1(-0.5 * alpha * alpha) - np.expm1(-0.5 * beta * beta)) / np.sqrt(2.0 * np.pi)
    # Per band, log of the slab's integral and of the spike's (0 where unseen: the prior's whole mass).
    log_slab = np.where(seen, np.log(s_ok * np.sqrt(2.0 * np.pi) / top) + np.log(np.maximum(mass, 1e-300)), 0.0)
    log_spike = np.where(seen, -0.5 * alpha * alpha, 0.0)
    lo_, ls_ = np.log(absent) + log_spike.sum(), np.log1p(-absent) + log_slab.sum()
    top_log = max(lo_, ls_)
    evidence = top_log + np.log(np.exp(lo_ - top_log) + np.exp(ls_ - top_log))
    p0 = float(np.exp(lo_ - evidence))
    mean_slab = np.where(mass > 0, a + s_ok * dphi / np.maximum(mass, 1e-300), a)
    mean_slab = np.where(seen, np.clip(mean_slab, 0.0, top), 0.5 * top)
    return float(evidence), (1.0 - p0) * mean_slab
