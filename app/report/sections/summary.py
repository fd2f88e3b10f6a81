"""The summary at the top of the report: what was recovered, how well the model explains the
photograph(s), what is undetermined and what would determine it, each stage's error against truth/.

Every number here is computed by the section that shows it in full (the fit section's
:func:`~reflab.app.report.sections.fit.rerender_misfit` and :func:`~reflab.app.report.sections.fit.value_text`,
the views section's :func:`~reflab.app.report.sections.views.scores`, the demo's camera and lamp
errors), so the summary and the sections agree.
"""
from __future__ import annotations

from reflab.app.report.data import Sources, as_dict, as_list
from reflab.app.report.sections.fit import method_name, rerender_misfit, status_text, value_text
from reflab.app.report.sections.section import Section, num
from reflab.app.report.sections.views import scores


def summary_section(src: Sources, model: dict | None, views: dict) -> Section | None:
    recovered = _recovered(src)
    if not recovered:
        return None
    sec = Section("summary", "Summary", "How good the model is, at a glance; the sections below hold the detail.")
    rows = [("recovered", "; ".join(recovered))]
    fit = src.fit or {}
    if fit.get("status"):
        rows.append(("fit status", status_text(fit, src.textures is not None).removeprefix("status: ")))
    m = rerender_misfit(fit, model) if fit else None
    if m:
        rows.append(("model vs input photograph",
                     f"RMS {m['relative_pct']:.3g} % of the photograph's (per band {num(m['rms'], 3)}, linear radiance); "
                     f"{m['count']} of {m['total']} pixels unexplained ({100 * m['count'] / max(m['total'], 1):.2g} %), "
                     f"holding {100 * m['share']:.0f} % of the squared residual; re-rendered "
                     + ("with the recovered texture" if m["textured"] else "with homogeneous albedo")))
    photos = [p for p in as_list(fit.get("photographs")) if isinstance(p, dict)]
    if len(photos) > 1:  # one photograph: fit.json's own RMS below says it
        rows.append((f"photographs fitted ({len(photos)})",
                     "; ".join(f"{p.get('name')}: RMS per band {num(p.get('rms'), 3)} (linear radiance, homogeneous "
                               f"albedo) over {num(p.get('pixels_used'))} pixels" for p in photos)))
    elif fit.get("rms") is not None:
        rows.append(("fit RMS per band", f"{num(fit.get('rms'), 3)} (linear radiance, homogeneous albedo; image noise "
                                         f"σ {num(fit.get('noise'), 3)})"))
    open_ = _undetermined(fit)
    rows.append(("undetermined", "; ".join(open_) if open_ else ("none: every fitted value has a σ inside its plausible range"
                                                              if fit else None)))
    if open_:
        rows.append(("what would determine it", _plan_text(src)))
    sec.kv(rows)
    truth = _truth_rows(src, views)
    if truth:
        sec.kv(truth, "Each stage's error against truth/ (the simulated lab's).")
    return sec


def _recovered(src: Sources) -> list[str]:
    out = []
    cam = src.camera
    if cam:
        rms = as_dict(cam.get("calibration")).get("rms_px")
        out.append("camera (camera.json" + (f", reprojection RMS {num(rms, 3)} px)" if rms is not None else ")"))
    lamps = as_list((src.lights or {}).get("lights"))
    if lamps:
        out.append(f"{len(lamps)} lamp{'s' * (len(lamps) != 1)} (lights.json)")
    surfaces = as_list((src.scene or {}).get("surfaces"))
    if surfaces:
        out.append(f"{len(surfaces)} surfaces (scene.json)")
    if src.fit:
        out.append(f"materials ({method_name(src.fit)}, fit.json)")
    if src.textures:
        tex = as_list(src.textures.get("surfaces"))
        out.append("texture" + (f" of {len(tex)} surfaces" if tex else "") + " (textures/)")
    return out


def _undetermined(fit: dict) -> list[str]:
    """'surface parameter: undetermined (plausible range lo–hi)' for every value the fit section shows so."""
    out = []
    for s in as_list(fit.get("surfaces")):
        if not isinstance(s, dict):
            continue
        mat, sig = as_dict(s.get("material")), as_dict(s.get("sigma"))
        held = [str(u) for u in as_list(s.get("undetermined"))]
        for key in ("kd", "ks", "ns", "alpha", "sigma", "r", "t"):
            if mat.get(key) is None:
                continue
            own = [u for u in held if u == key or u.startswith(key + "[")]
            text = value_text(mat.get("brdf", ""), key, mat, sig.get(key), own)
            if "undetermined" in text:
                out.append(f"{s.get('name')} {key}: {text}")
    return out


def _plan_text(src: Sources) -> str:
    plan = src.json(src.rel(src.ws.plan))
    if not plan:
        return f"run reflab plan {src.root} to find the further shots that would determine them"
    shots = [s for s in as_list(plan.get("shots")) if isinstance(s, dict)]
    parts = [f"{s.get('name')}: turntable {num(s.get('angle_deg'), 3)}°, lamps {num(s.get('lamps'))}"
             + (f", determines {', '.join(map(str, as_list(s.get('determines'))))}" if s.get("determines") else "")
             for s in shots]
    text = (f"plan.json's {len(shots)} further shot{'s' * (len(shots) != 1)} (reflab capture inputs --plan): "
            + "; ".join(parts)) if shots else "plan.json plans no further shot"
    left = [str(x) for x in as_list(plan.get("left_open"))]
    return text + (f"; left open even then: {', '.join(left)}" if left else "")


def _truth_rows(src: Sources, views: dict) -> list:
    if not src.truth_dir.is_dir():
        return []
    from reflab.app.demo_score import camera_error, lights_error
    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights
    from reflab.core.workspace import Workspace

    truth, rows = Workspace(src.truth_dir), []
    try:
        if src.camera and truth.camera.is_file():
            e = camera_error(Camera.load(src.ws.camera), Camera.load(truth.camera))
            rows.append(("camera", f"focal {e['focal_pct']:.3g} %, principal point {e['principal_px']:.3g} px, "
                                   f"centre {e['centre_mm']:.3g} mm, rotation {e['rotation_deg']:.3g}°"))
    except Exception as err:  # noqa: BLE001 - a summary row, not the report, fails
        rows.append(("camera", f"not compared ({type(err).__name__}: {err})"))
    try:
        if src.lights and truth.lights.is_file():
            errs = lights_error(Lights.load(src.ws.lights), Lights.load(truth.lights))
            rows.append(("lamps", "; ".join(f"lamp {e['lamp']} {e['position_mm']:.3g} mm, intensity {e['intensity_pct']:.3g} %"
                                           for e in errs)))
    except Exception as err:  # noqa: BLE001
        rows.append(("lamps", f"not compared ({type(err).__name__}: {err})"))
    for key, label in (("novel", "novel view"), ("relit", "relit view")):
        e = scores(views.get(key) or {})
        if e:
            rows.append((label, f"PSNR {num(e['psnr_db'], 4)} dB over the {e['known_pct']:.0f} % of pixels of known "
                                f"albedo, {num(e['psnr_all_db'], 4)} dB over all"))
    return rows
