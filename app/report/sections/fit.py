"""The fit section: fit.json's materials with σ against the truth, where its time went, and the
re-rendered model against the photograph."""
from __future__ import annotations

import math

import numpy as np

from reflab.app.report import figures as F
from reflab.app.report.data import Sources, as_dict, as_list
from reflab.app.report.sections.section import Section, floats, num, pm, pm_range


#: fit.json's method, as the docs name it.
METHOD_NAMES = {"ftbo": "F-TBO", "nftbo": "NF-TBO"}
#: The photometric parameters shown per surface, in this order.
MATERIAL_KEYS = ("kd", "ks", "ns", "alpha", "sigma", "r", "t", "ior")


def fit_section(src: Sources, model: dict | None) -> Section | None:
    fit = src.fit
    if fit is None:
        return None
    sec = Section("fit", "Fit", "fit.json: the non-Lambertian parameters fitted to the input photograph, their "
                                "uncertainties, and how well the model explains the image.")
    status = fit.get("status")
    if status:
        sec.note(status_text(fit, src.textures is not None),
                 "good" if status == "ok" else "bad" if status == "poor fit" else
                 "info" if status == "texture pending" and src.textures is not None else "warn")
    for w in as_list(fit.get("warnings")):
        sec.note(f"at fit time: {w}", "warn")
    image = as_dict(fit.get("image"))
    sec.kv([("method", method_name(fit)), ("depth", fit.get("depth")),
            ("image", f"{image.get('file')} {image.get('width')} × {image.get('height')}, {image.get('saturated_pixels')} saturated pixels masked"
             if image else None),
            ("RMS residual per band (linear radiance)", num(fit.get("rms"))),
            ("image noise σ per band (linear radiance)", num(fit.get("noise"))),
            ("outlier pixels left out of the fit", _rejected_text(fit.get("rejected"))),
            ("iterations / evaluations", f"{fit.get('iterations')} / {fit.get('evaluations')}" if "iterations" in fit else None),
            ("fit time", f"{num(fit.get('time_s'), 3)} s" if fit.get("time_s") is not None else None),
            ("set-up", ", ".join(f"{k} {num(v, 3)} s" for k, v in fit["setup_s"].items()) if isinstance(fit.get("setup_s"), dict) else None)])
    phases = {k: v for k, v in (fit.get("phases_s") or {}).items() if isinstance(v, (int, float)) and v > 0} \
        if isinstance(fit.get("phases_s"), dict) else {}
    if phases:
        sec.figure(_phases_figure(phases), "Where the fit's time went (fit.json phases_s), in the order they run; "
                   "the error-vs-time plot below shows the error over the same seconds.")
    truth, truth_file = src.truth_materials()
    items = [s for s in as_list(fit.get("surfaces")) if isinstance(s, dict)]
    keys = [k for k in MATERIAL_KEYS if any(isinstance(s.get("material"), dict) and s["material"].get(k) is not None
                                             for s in items)]
    rows = []
    for s in items:
        name, mat = str(s.get("name")), as_dict(s.get("material"))
        sig = as_dict(s.get("sigma"))
        und = [str(u) for u in as_list(s.get("undetermined"))]
        bounds = as_dict(s.get("at_bound"))  # {"ks[0]": "upper"}
        true = truth.get(name, {})
        row = [name, mat.get("brdf", "–")]
        for key in keys:
            if mat.get(key) is None:
                row.append("")
                continue
            held = [u for u in und if u == key or u.startswith(key + "[")]
            lines = [value_text(mat.get("brdf", ""), key, mat, sig.get(key), held)]
            if held or "undetermined" in lines[0]:
                lines.append(("held at " if sig.get(key) is None else "fitted at ") + num(mat[key], 4)
                             + ("" if held == [key] else " (undetermined: " + ", ".join(held) + ")"))
            on = [f"{k} {side}" for k, side in bounds.items() if k == key or str(k).startswith(key + "[")]
            if on:
                lines.append("at its bound: " + ", ".join(on))
            if true.get(key) is not None and key != "ior":
                a, b = floats(mat[key]), floats(true[key])
                err = (a - b).tolist() if a is not None and b is not None and a.shape == b.shape else None
                lines.append(f"truth {num(true[key])}, error {num(err, 3)}")
            who = _determined_by(s, key)
            if who:
                lines.append("determined by " + who)
            row.append("\n".join(lines))
        rows.append(row)
    sec.table(["surface", "BRDF"] + list(keys), rows,
              "value ± σ (one standard deviation, per band R, G, B where there are three; kd, ks, r, t relative to "
              "white, ns and α dimensionless, Oren–Nayar σ in radians); undetermined: the image does not fix it, shown "
              "as its plausible range (docs/fit.md, \"Plausible ranges\"), never with a σ wider than that range: either "
              "held at its initial or user-given value, or fitted with a σ that spans the range (the value used below)" + (f"; truth: {truth_file}." if truth else "."))
    _colour_lobes(sec, fit)
    _albedo_models(sec, items)
    _photographs(sec, fit)
    if model and model.get("image") is not None:
        _model_images(sec, src, fit, model)
    elif model and model.get("error"):
        sec.note(f"re-render of the model failed: {model['error']}", "bad")
    return sec


def value_text(brdf: str, key: str, material: dict, sigma, held: list) -> str:
    """One fitted value as the report and its summary show it: 'value ± σ', or 'undetermined
    (plausible range lo–hi)' where fit.json calls it undetermined (``held``: its names, ``key`` or
    ``key[band]``) or its σ is wider than its plausible range (:func:`reflab.inverse.fit.ranges.plausible_range`)."""
    from reflab.inverse.fit.ranges import plausible_range

    value = material.get(key)
    rng = plausible_range(str(brdf), key, material)
    flags = key in held
    if isinstance(value, list):
        flags = [key in held or f"{key}[{c}]" in held for c in range(len(value))]
    return pm_range(value, sigma, rng, flags, 4, log=key in ("ns", "alpha"))


def status_text(fit: dict, textured: bool) -> str:
    """fit.json's status in words; "texture pending" once textures/ exists says that the texture ran."""
    status = fit.get("status")
    text = f"status: {status}" + (f" — {fit['message']}" if fit.get("message") else "")
    if status == "texture pending" and textured:
        text = ("status at fit time: texture pending; the texture stage has run since (textures/index.json): "
                "the re-render below includes the recovered texture and shows what it explains")
    return text


def _determined_by(surface: dict, key: str) -> str:
    """Which photographs determined parameter ``key`` (fit.json ``determined_by``, several photographs)."""
    shares = as_dict(surface.get("determined_by"))
    names = sorted({str(p) for k, v in shares.items() if k == key or str(k).startswith(key + "[") for p in as_list(v)})
    return ", ".join(names)


def _photographs(sec: Section, fit: dict) -> None:
    """The photographs fitted together (fit.json ``photographs``), when there are several."""
    photos = [p for p in as_list(fit.get("photographs")) if isinstance(p, dict)]
    if len(photos) < 2:
        return
    def unexplained(p):
        v = p.get("unexplained")
        return f"{100 * v:.1f} %" if isinstance(v, (int, float)) else "–"

    sec.table(["photograph", "file", "size", "lamps lit", "pixels used", "RMS per band", "unexplained"],
              [[p.get("name"), p.get("file"), f"{p.get('width')} × {p.get('height')}", num(p.get("lamps")),
                num(p.get("pixels_used")), num(p.get("rms"), 3), unexplained(p)] for p in photos],
              "The photographs fitted together (the reference input and inputs/, docs/fit.md \"Several photographs "
              "and the plan\"): one set of parameters for all; \"determined by\" in the table above names the "
              "photographs holding at least 10 % of a parameter's information. RMS: the fitted model with "
              "homogeneous albedo, linear radiance. Unexplained: the share of its pixels read that the model, "
              "with its texture, leaves above six times the noise; a photograph far above the others is "
              "named in the warnings (its lamps or camera may not be those its sidecar gives).")


def _colour_lobes(sec: Section, fit: dict) -> None:
    """Which textured lobes the texture's colours determined (fit.json ``colour_lobes``)."""
    lobes = {str(k): v for k, v in as_dict(fit.get("colour_lobes")).items() if isinstance(v, dict)}
    if not lobes:
        return
    rows = []
    for name, lobe in lobes.items():
        shape = "alpha" if "alpha" in lobe else "ns"
        brdf = "ward" if shape == "alpha" else "phong"
        rows.append([name, value_text(brdf, "ks", lobe, lobe.get("sigma_ks"), []),
                     f"{shape} {value_text(brdf, shape, lobe, lobe.get('sigma_' + shape), [])}",
                     lobe.get("colour_set", "–"), f"{num(lobe.get('pixels'))} ({num(lobe.get('rejected'))} outliers)",
                     num(lobe.get("misfit"), 3)])
    sec.table(["surface", "ks", "shape", "texture's colours", "pixels", "misfit"], rows,
              "Textured surfaces seen once whose lobe the texture's colours determined (docs/fit.md, \"A textured lobe "
              "from its colours\"): the texture's albedo lies on a line or plane in RGB, the highlight has the lamps' "
              "colour, so the light off that set is the lobe's. The materials table above holds these values; misfit is per "
              "degree of freedom over the image noise (about 1 when the set and the lobe explain the pixels).")


def _albedo_models(sec: Section, items: list) -> None:
    """What the photograph said of each textured surface's albedo (fit.json ``albedo_model``)."""
    rows = []
    for s in items:
        model, ev = s.get("albedo_model"), as_dict(s.get("albedo_evidence"))
        if model is None:
            continue
        inks, sig = ev.get("inks"), ev.get("inks_sigma")
        palette = "–"
        if isinstance(inks, list) and inks:
            palette = f"{len(inks)}: " + "; ".join(
                num(c, 3) + (f" ± {num(e, 2)}" if isinstance(sig, list) and i < len(sig) else "")
                for i, (c, e) in enumerate(zip(inks, sig if isinstance(sig, list) else [None] * len(inks))))
            d = ev.get("delta_bic_palette")
            palette += f" (ΔBIC {num(int(round(d)) if isinstance(d, (int, float)) and math.isfinite(d) else d)})"
        rows.append([str(s.get("name")), str(model), num(ev.get("pixels")), num(ev.get("delta_bic"), 4),
                     f"{num(ev.get('block_px'))} px ({num(ev.get('blocks'))} blocks)", num(ev.get("noise"), 3),
                     palette])
    if rows:
        sec.table(["surface", "albedo fitted as", "pixels", "ΔBIC", "best texture model", "noise σ per band",
                   "best palette: inks ± σ"], rows,
                  "Surfaces declared textured, as their photograph shows them (docs/fit.md, \"Model selection\"): "
                  "\"uniform\" when one colour explains their diffuse-lit pixels better than a free colour per block "
                  "(BIC(uniform) − BIC(texture) = ΔBIC < 0): fitted as homogeneous, their lobe and reflection "
                  "judged like an untextured surface's; \"palette\" when two to four inks with sharp edges do "
                  "better than both (the palette's ΔBIC < 0, its residuals at the noise): each pixel's albedo one "
                  "of them, the lobe and reflection judged from every pixel; \"texture\": a free texture, as "
                  "declared. The texture stage textures all three.")


def method_name(fit: dict):
    """fit.json's method as the docs name it (F-TBO, NF-TBO); another value as written."""
    m = fit.get("method")
    return METHOD_NAMES.get(m, m) if isinstance(m, str) else m


def _phases_figure(phases: dict) -> str:
    fig, (ax,) = F.new_figure(6.0, 0.5 + 0.16 * len(phases))
    left = 0.0
    for i, (name, secs) in enumerate(phases.items()):
        ax.barh(0, secs, left=left, color=F.COLOURS[i % len(F.COLOURS)], label=f"{name} {secs:.2g} s")
        left += secs
    ax.set_yticks([])
    ax.set_xlabel("seconds", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    return F.figure_uri(fig)


def _rejected_text(rejected) -> str | None:
    if not isinstance(rejected, dict) or not rejected.get("count"):
        return None
    return (f"{rejected['count']} (residual above {num(rejected.get('threshold_sigmas'))} σ; cyan in the map below)"
            if rejected.get("threshold_sigmas") is not None else str(rejected["count"]))


def rerender_misfit(fit: dict, model: dict | None) -> dict | None:
    """How well the re-rendered model explains the input photograph: the one computation the fit
    section's maps and the summary both show. None without a re-render of the photograph's size.

    Returns ``bad`` (H, W) unexplained pixels (residual above DIAG_SIGMAS σ + DIAG_FLOOR × peak in
    some band, σ fit.json's image noise), ``count``, ``total`` (all image pixels), ``share`` of the
    squared residual they hold, ``rms`` per band and ``relative_pct`` (RMS over the photograph's RMS).
    """
    if not model or model.get("image") is None or model.get("photo") is None or model["photo"].shape != model["image"].shape:
        return None
    from reflab.inverse.fit.rounds import DIAG_FLOOR, DIAG_SIGMAS

    img, photo = model["image"], model["photo"]
    res = img - photo
    noise = floats(fit.get("noise"))
    noise = noise if noise is not None and noise.shape == (3,) else None
    tol = DIAG_SIGMAS * (noise if noise is not None else np.zeros(3)) + DIAG_FLOOR * float(photo.max())
    bad = np.any(np.abs(res) > tol, axis=2)
    return {"bad": bad, "count": int(bad.sum()), "total": int(bad.size), "noise": noise,
            "share": float(np.sum(res[bad] ** 2) / max(np.sum(res ** 2), 1e-300)),
            "rms": np.sqrt(np.mean(res ** 2, axis=(0, 1))).tolist(),
            "relative_pct": 100 * float(np.sqrt(np.mean(res ** 2)) / max(np.sqrt(np.mean(photo ** 2)), 1e-300)),
            "textured": bool(model.get("textured"))}


def _model_images(sec: Section, src: Sources, fit: dict, model: dict) -> None:
    photo, img = model["photo"], model["image"]
    if photo is None or photo.shape != img.shape:
        sec.images([(F.thumb(F.display(img), 480, 360), "re-rendered model")])
        return
    from reflab.inverse.fit.rounds import DIAG_FLOOR, DIAG_SIGMAS

    exposure = 1.0 / max(float(np.percentile(photo, 99.5)), 1e-12)
    diff = np.abs(img - photo).max(axis=2)
    m = rerender_misfit(fit, model)
    noise, bad, share = m["noise"], m["bad"], m["share"]
    overlay = F.display(photo, exposure).copy()
    overlay[bad] = [255, 0, 255]
    rejected = floats(as_dict(fit.get("rejected")).get("pixels"))
    if rejected is not None and rejected.ndim == 2 and rejected.shape[1] == 2:
        x, y = rejected[:, 0].astype(int), rejected[:, 1].astype(int)
        inside = (x >= 0) & (x < overlay.shape[1]) & (y >= 0) & (y < overlay.shape[0])
        overlay[y[inside], x[inside]] = [0, 255, 255]
    what = "fitted materials with the recovered texture" if model.get("textured") else "fitted materials, homogeneous kd"
    sec.images([(F.thumb(F.display(photo, exposure), 480, 360), "input photograph"),
                (F.thumb(F.display(img, exposure), 480, 360), f"re-rendered model ({what}), same exposure")])
    sec.images([(F.heat_with_bar(diff, "|model − input|, largest band", "linear radiance"), "difference", True),
                (F.thumb(overlay, 480, 360), f"unexplained pixels of this re-render (magenta): {int(bad.sum())} of all {bad.size} image pixels, residual "
                                             f"above {DIAG_SIGMAS:g} σ + {DIAG_FLOOR:g} × peak in some band"
                                             + ("; outliers the fit left out in cyan" if rejected is not None else ""))])
    sec.note(f"Unexplained pixels of this re-render: {int(bad.sum())} of all {bad.size} image pixels, holding "
             f"{100 * share:.0f}% of its squared residual (the fit's test, docs/fit.md, with σ = fit.json's image noise "
             f"{num(noise.tolist() if noise is not None else None, 3)}, no allowance for texture: the re-render "
             + ("includes the recovered texture" if model.get("textured") else "uses homogeneous albedo, so texture shows")
             + "). The warning \"at fit time\" above counts another thing: the pixels the fit used (saturated and "
             "outlier pixels left out), the model with homogeneous albedo, with an allowance on textured surfaces.")
    sec.kv([("model vs input RMS per band (linear radiance)", num(m["rms"])),
            ("relative RMS", f"{num(m['relative_pct'], 3)} %"),
            ("render time", f"trees {num(model.get('trees_s'), 2)} s, render {num(model.get('render_s'), 2)} s")])
