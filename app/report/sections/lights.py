"""The lights section: lights.json's lamps with σ against the truth, and the rod marks."""
from __future__ import annotations

import numpy as np

from reflab.app.report import figures as F
from reflab.app.report.data import Sources, as_dict, as_list
from reflab.app.report.sections.section import Section, floats, mm, num


def lights_section(src: Sources) -> Section | None:
    lights = src.lights
    if lights is None:
        return None
    items = [l for l in as_list(lights.get("lights")) if isinstance(l, dict)]
    sec = Section("lights", "Lights", "lights.json: point lamps located from rod shadows (marks.json), with "
                                      "one-sigma uncertainties.")
    truth = src.truth("lights")
    true_items = [l for l in as_list((truth or {}).get("lights")) if isinstance(l, dict)]
    rows = []
    for k, l in enumerate(items):
        pos = floats(l.get("position"))
        cov = floats(l.get("sigma_position"))
        sd = np.sqrt(np.clip(np.diag(cov), 0, None)) * 1e3 if cov is not None and cov.shape == (3, 3) else None
        cal = as_dict(l.get("calibration"))
        row = [k, num(pos.tolist() if pos is not None else None, 5), num(sd.tolist(), 2) if sd is not None else "–",
               num(l.get("intensity"), 4), num(cal.get("mark_sigma_px"), 3), num(cal.get("outliers") or "none")]
        if true_items:
            tp = floats(true_items[k].get("position")) if k < len(true_items) else None
            err = float(np.linalg.norm(pos - tp)) * 1e3 if pos is not None and tp is not None else None
            ti = floats(true_items[k].get("intensity")) if k < len(true_items) else None
            li = floats(l.get("intensity"))
            ierr = (100 * float(np.max(np.abs(li / ti - 1))) if li is not None and ti is not None and li.shape == ti.shape
                    and np.all(ti > 0) else None)
            row += [num(tp.tolist() if tp is not None else None, 5), mm(err),
                    num(err / float(np.linalg.norm(sd)), 2) if err is not None and sd is not None and np.linalg.norm(sd) > 0 else "–",
                    f"{ierr:.1f}" if ierr is not None else "–"]
        rows.append(row)
    head = ["lamp", "position (m)", "σ x, y, z (mm)", "intensity (R, G, B; radiance × m²)", "mark σ (px)", "outlier marks"]
    sec.table(head + (["truth (m)", "error (mm)", "error / |σ|", "intensity error (%, worst band)"] if true_items else []), rows)
    if not any(isinstance(l.get("calibration"), dict) for l in items):
        sec.note("lights.json has no calibration blocks (written by hand or by another tool): no mark residuals.")
    marks = src.marks
    if marks and isinstance(marks.get("marks"), list):
        fig = _marks_figure(src, marks, items)
        sec.figure(fig, "Rod marks: the rod's foot (dot) and its shadow's tip (cross) in the camera image (behind: the "
                        "first marked image), one colour per lamp (left); each mark's reprojection error after the lamp "
                        "fit (right).")
        sec.kv([("rod height", f"{num(marks.get('rod_height'))} m"), ("marks", len(marks["marks"]))])
    return sec


def _marks_figure(src: Sources, marks: dict, items: list) -> str | None:
    cam = src.camera or {}
    fig, (ax, bx) = F.new_figure(10.0, 3.8, ncols=2)
    ms = [m for m in marks["marks"] if isinstance(m, dict)]
    backdrop = next((img for img in (src.image(m["image"]) for m in ms[:1] if isinstance(m.get("image"), str))
                     if img is not None), None)
    if backdrop is not None:
        h, w = backdrop.shape[:2]
        ax.imshow(F.display(backdrop), extent=(-0.5, w - 0.5, h - 0.5, -0.5), alpha=0.6)
    for m in ms:
        b, t = floats(m.get("base")), floats(m.get("tip"))
        if b is None or t is None:
            continue
        c = F.COLOURS[int(m.get("light", 0)) % len(F.COLOURS)]
        ax.plot([b[0], t[0]], [b[1], t[1]], "-", color=c, lw=1)
        ax.plot(b[0], b[1], "o", color=c, ms=3)
        ax.plot(t[0], t[1], "x", color=c, ms=4)
    if cam.get("width") and cam.get("height"):
        ax.set_xlim(0, cam["width"])
        ax.set_ylim(cam["height"], 0)
    else:
        ax.invert_yaxis()
    ax.set_aspect("equal")
    ax.set_title("marks in the image (px)", fontsize=9)
    ax.tick_params(labelsize=7)
    x0, ticks, names = 0, [], []
    for k, l in enumerate(items):
        errs = floats((l.get("calibration") or {}).get("mark_errors_px"))
        if errs is None:
            continue
        errs = errs.reshape(len(errs), -1)  # one row per mark of this lamp: foot, tip
        x = np.arange(len(errs)) + x0
        for j, name in enumerate(["foot", "tip"][: errs.shape[1]]):
            bx.bar(x + (j - 0.5) * 0.4, errs[:, j], 0.4, color=F.COLOURS[k % len(F.COLOURS)],
                   alpha=1.0 if j else 0.5, label=f"lamp {k} {name}")
        # Each mark named by its image (marks.json lists a lamp's marks in the order of its errors).
        images = [str(m.get("image", "")).rsplit("/", 1)[-1].rsplit(".", 1)[0] for m in ms if m.get("light") == k]
        ticks += x.tolist()
        names += images if len(images) == len(errs) else [str(i) for i in range(len(errs))]
        x0 += len(errs) + 1
    if x0:
        bx.set_xticks(ticks, names, rotation=90 if len(ticks) > 12 else 0, fontsize=7)
        bx.set_ylabel("reprojection error (px)", fontsize=8)
        bx.set_xlabel("mark (its image)", fontsize=8)
        bx.legend(fontsize=7)
        bx.tick_params(labelsize=7)
        bx.grid(axis="y", alpha=0.3)
    else:
        bx.set_visible(False)
    return F.figure_uri(fig)
