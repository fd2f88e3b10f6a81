"""The error-against-run-time section: every fit and solve's error against the seconds it ran."""
from __future__ import annotations

import math

import numpy as np

from reflab.app.report import figures as F
from reflab.app.report.data import Sources, as_dict, as_list
from reflab.app.report.sections.fit import method_name
from reflab.app.report.sections.section import Section, floats


def error_section(src: Sources) -> Section | None:
    fit, idx, cam, sfm = src.fit, src.textures, src.camera, src.sfm
    photometric, convergence, geometric = [], [], []

    def band_mean(v):
        a = floats(v)
        return None if a is None else float(np.mean(a))

    if fit and isinstance(fit.get("trace"), list):
        # [seconds, rms per band] or [seconds, rms, phase name]: one series per phase where named.
        raw = [(p[0], band_mean(p[1]), p[2] if len(p) > 2 and isinstance(p[2], str) else None)
               for p in fit["trace"] if isinstance(p, (list, tuple)) and len(p) >= 2]
        raw = [r for r in raw if isinstance(r[0], (int, float)) and r[1] is not None]
        pts = [(t, e) for t, e, _ in raw]
        method = method_name(fit)
        for phase in dict.fromkeys(ph for _, _, ph in raw):
            sel = [(t, e) for t, e, ph in raw if ph == phase]
            what = ", ".join(str(w) for w in (method, phase) if w)
            photometric.append({"label": f"fit ({what})" if what else "fit", "points": sel})
        rounds = as_dict(fit.get("texture_rounds")).get("rounds")
        if isinstance(rounds, list) and rounds and pts:
            t_end = pts[-1][0]
            t = t_end - sum((r.get("texture_s") or 0) + (r.get("fit_s") or 0) for r in rounds if isinstance(r, dict))
            marks = []
            for r in rounds:
                if isinstance(r, dict):
                    t += (r.get("texture_s") or 0) + (r.get("fit_s") or 0)
                    if band_mean(r.get("rms")) is not None:
                        marks.append((t, band_mean(r.get("rms"))))
            if marks:
                photometric.append({"label": "fit, end of each texture round", "points": marks, "style": "s",
                                    "phase": (t_end - sum((r.get("texture_s") or 0) + (r.get("fit_s") or 0)
                                                          for r in rounds if isinstance(r, dict)), "texture rounds start")})
    if idx and isinstance(idx.get("stats"), dict):
        st = idx["stats"]
        trace = st.get("trace")
        if isinstance(trace, list) and trace:
            pts = [(p[0], band_mean(p[1])) for p in trace if isinstance(p, (list, tuple)) and len(p) >= 2]
            convergence.append({"label": f"texture CG ({st.get('trace_quantity', 'residual')}, "
                                         f"{st.get('active_set_rounds', '?')} active-set rounds)",
                                "points": [(t, e) for t, e in pts if isinstance(t, (int, float)) and e is not None]})
        if st.get("total_s") is not None and band_mean(st.get("residual_rms")) is not None:
            photometric.append({"label": f"texture solve, end ({st.get('iterations', '?')} CG iterations)",
                                "points": [(st["total_s"], band_mean(st["residual_rms"]))], "style": "D"})
    cal = as_dict(as_dict(cam).get("calibration"))
    if cal.get("time_s") is not None and cal.get("rms_px") is not None:
        geometric.append({"label": "camera calibration", "points": [(cal["time_s"], cal["rms_px"])], "style": "o"})
    for k, l in enumerate(as_list((src.lights or {}).get("lights"))):
        c = (l or {}).get("calibration") if isinstance(l, dict) else None
        if isinstance(c, dict) and c.get("time_s") is not None and floats(c.get("mark_errors_px")) is not None:
            e = floats(c["mark_errors_px"])
            geometric.append({"label": f"lamp {k}", "points": [(c["time_s"], float(np.sqrt(np.mean(e ** 2))))], "style": "v"})
    if sfm:
        s = as_dict(sfm.get("sfm"))
        ts = as_dict(s.get("time_s"))
        if ts.get("total_s") is not None and s.get("reprojection_px") is not None:
            geometric.append({"label": "structure from motion", "points": [(ts["total_s"], s["reprojection_px"])], "style": "^"})
        rt = as_dict(sfm.get("rigid_turntable"))
        if rt.get("time_s") is not None and rt.get("rms_px") is not None:
            geometric.append({"label": "one turntable axis", "points": [(rt["time_s"], rt["rms_px"])], "style": "s"})
    if not photometric and not convergence and not geometric:
        return None
    sec = Section("error", "Error against run time", "Every fit and solve: its error against the seconds it ran "
                                                      "(each from its own start).")
    homogeneous = ("; until the texture rounds start the fit's model has homogeneous albedo, so texture counts as "
                   "its error there" if any(s.get("phase") for s in photometric) else "")
    panels = [(series, ylabel, what) for series, ylabel, what in (
        (photometric, "RMS residual (linear radiance)", "photometric fits: RMS residual in linear radiance (mean of "
                                                        "the bands; fit: over pixels, texture: over its equations"
                                                        + homogeneous + ")"),
        (convergence, "relative residual", "the texture solver's conjugate gradient: its normal-equation residual "
                                           "relative to that of the homogeneous kd (the stopping test's scale); each "
                                           "jump starts an active-set round (texels outside [0, 1] fixed at the bound, "
                                           "the rest solved again)"),
        (geometric, "RMS reprojection (px)", "geometric solves: RMS reprojection error in pixels")) if series]
    where = ["Left", "middle", "right"] if len(panels) == 3 else ["Left", "right"] if len(panels) == 2 else [""]
    caption = "; ".join(f"{w}: {what}" if w else what for w, (_, _, what) in zip(where, panels))
    sec.figure(_error_plot([(series, ylabel) for series, ylabel, _ in panels]), caption[0].upper() + caption[1:] + ".",
               id="error-vs-time")
    return sec


def _error_plot(panels) -> str:
    """One figure, one log-log panel per (series, y label): error against seconds."""
    fig, axes = F.new_figure(4.6 * len(panels), 3.6, ncols=len(panels))
    for ax, (series, ylabel) in zip(axes, panels):
        for i, s in enumerate(series):
            t = np.maximum([p[0] for p in s["points"]], 1e-3)
            e = [p[1] for p in s["points"]]
            style = s.get("style")
            ax.plot(t, e, (style or ".") + ("" if style else "-"), color=F.COLOURS[i % len(F.COLOURS)],
                    ms=6 if style else 3, lw=1, label=s["label"])
            if s.get("phase"):
                ax.axvline(max(s["phase"][0], 1e-3), color="0.4", ls=":", lw=1)
                ax.annotate(s["phase"][1], (max(s["phase"][0], 1e-3), 0.5), xycoords=("data", "axes fraction"),
                            rotation=90, fontsize=7, color="0.3", ha="right", va="center")
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):
            _plain_log_labels(axis)
        ax.set_xlabel("run time (s)", fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.tick_params(which="both", labelsize=7)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    return F.figure_uri(fig)


def _plain_log_labels(axis) -> None:
    """Label a log axis (already holding its data) in plain numbers at 1, 2, 5 × 10^k, and at 3 × 10^k
    too where it spans less than a decade. Matplotlib's default labels every minor tick as
    'a × 10^b' on an axis spanning under two decades, where they overlap."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    lo, hi = sorted(axis.get_view_interval())
    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    threes = FuncFormatter(lambda v, _: f"{v:g}" if v > 0 and round(v / 10 ** math.floor(math.log10(v)), 6) == 3 else "")
    axis.set_minor_formatter(threes if lo > 0 and hi / lo < 10 else NullFormatter())
