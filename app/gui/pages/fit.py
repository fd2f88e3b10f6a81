"""The fit page: the materials with σ and the error against time, drawn live as the fit runs."""
from __future__ import annotations

import numpy as np
from PySide6.QtGui import QColor
from PySide6.QtWidgets import QLabel, QVBoxLayout, QWidget

from reflab.app.gui.pages.page import StepPage, fmt, from_table, table
from reflab.app.gui.widgets import Curve, text_label
from reflab.core.workspace import read_json
from reflab.inverse.stages import FitOptions


class FitPage(StepPage):
    preview_stretch = 0
    run_text = "Fit"

    def build(self):
        self.add_option("texture_rounds", "Texture rounds", from_table(FitOptions, "texture_rounds", 0, 10))
        self.add_option("max_seconds", "Time budget (0 = none)", from_table(FitOptions, "max_seconds", 0.0, 36000, 10, 1))
        self.materials = QWidget()
        self.materials_layout = QVBoxLayout(self.materials)
        self.tab(self.materials, "Materials (± σ)")
        self.curve = Curve("seconds", "RMS error")
        self.curve.setObjectName("fit_curve")
        self.tab(self.curve, "Error against time")
        self.previous: list = []
        self.live: list = []

    def before_run(self) -> None:
        """Keep the earlier fit's curve to draw beside the new one; start the live one."""
        self.previous = fit_trace(read_json(self.ws.fit)) if self.ws.fit.exists() else []
        self.live = []
        self.tabs.setCurrentWidget(self.curve)

    def live_point(self, seconds: float, rms: list) -> None:
        """One iteration's error, seconds since Run (trees included), drawn as it comes."""
        self.live.append((seconds, *rms[:3]))
        pts = np.asarray(self.live, float)
        colours = ("#d02020", "#20a020", "#2040d0")
        self.curve.set_series([(f"{band} band (running)", colour, pts[:, [0, 1 + b]])
                               for b, (band, colour) in enumerate(zip("RGB", colours)) if pts.shape[1] > 1 + b]
                              + [(f"{band}, earlier fit", QColor(colour).lighter(170), trace)
                                 for band, colour, trace in zip("RGB", colours, self.previous)])

    def refresh(self):
        self.clear(self.materials_layout)
        if not self.ws.fit.exists():
            self.materials_layout.addWidget(QLabel(self.nothing_yet("fit.json")))
            return
        from reflab.app.report.sections.fit import status_text, value_text

        fit = read_json(self.ws.fit)
        rows, bad = [], set()
        for item in fit.get("surfaces", []):
            mat, sigma, und = item.get("material", {}), item.get("sigma", {}), list(item.get("undetermined", []))
            for key, value in mat.items():
                if key in ("brdf", "ior") or value is None:
                    continue
                # As the report shows it: undetermined with its plausible range, never a σ wider than it.
                text = value_text(mat.get("brdf", ""), key, mat, sigma.get(key),
                                  [u for u in und if u == key or u.startswith(key + "[")])
                if "undetermined" in text:
                    bad.add((len(rows), 3))
                rows.append([item["name"], key, fmt(value), text if "undetermined" in text else fmt(sigma.get(key, "–"), 2)])
        status = fit.get("status", "ok")
        if status == "texture pending" and self.ws.texture_index.exists():
            status = status_text(fit, True).removeprefix("status at fit time: ")
        head = text_label(f"status <b>{status}</b>, RMS per band {fmt(fit.get('rms'))}, "
                          f"{fit.get('method')} in {fit.get('time_s', 0):.1f} s")
        self.materials_layout.addWidget(head)
        for text in fit.get("warnings", []):
            self.materials_layout.addWidget(text_label(f"⚠ at fit time: {text}"))
        self.materials_layout.addWidget(table("fit_table", ["surface", "parameter", "value", "σ"], rows, bad))
        colours = ("#d02020", "#20a020", "#2040d0")
        series = [(f"{band} band", colour, trace) for band, colour, trace in zip("RGB", colours, fit_trace(fit))]
        series += [(f"{band}, earlier fit", QColor(colour).lighter(170), trace)
                   for band, colour, trace in zip("RGB", colours, self.previous)]
        self.curve.set_series(series)


def fit_trace(fit: dict) -> list[np.ndarray]:
    """fit.json's ``trace`` ([seconds, rms or [r, g, b]] rows) as one (N, 2) array per band."""
    rows = [(float(t), np.broadcast_to(np.asarray(r, float), (3,))) for t, r in fit.get("trace", [])]
    if not rows:
        return []
    t = np.array([r[0] for r in rows])
    v = np.stack([r[1] for r in rows])
    return [np.column_stack([t, v[:, b]]) for b in range(3)]
