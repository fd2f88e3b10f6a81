"""The input photograph page: take it and see its size, peak and saturated pixels; after a fit,
plan and take the further photographs that fix what the fit left open (docs/fit.md, "Several
photographs and the plan"), shown in the plan's table."""
from __future__ import annotations

import numpy as np
from PySide6.QtWidgets import QCheckBox, QLineEdit, QVBoxLayout, QWidget

from reflab.app.gui.pages.page import StepPage, fmt, from_table, read_image, refill, spin, table
from reflab.app.gui.widgets import ImageView, text_label
from reflab.hardware.capture import CaptureOptions


class InputPage(StepPage):
    preview_stretch = 2
    run_text = "Take the photograph"

    def build(self):
        self.add_option("angle", "Turntable angle", from_table(CaptureOptions, "start", -360, 360, 1.0, 2))
        self.add_option("ambient", "", QCheckBox("ambient frame (lamps off) subtracted"))
        self.add_option("recapture", "", QCheckBox("capture again"))
        self.add_option("further", "", QCheckBox("then plan and take the further photographs (after a fit)"),
                        "With fit.json: plan the shots (lamps x turntable angle) that would determine what the fit "
                        "left open, take them into inputs/, then run Fit again.")
        self.add_option("detail", "", QCheckBox("then take photographs for the texture's detail"),
                        "Every lamp on, at the camera's full resolution (the size below times camera.json's), from "
                        "the input's view and the turntable turned by the angles below; then recover the textures "
                        "with texels of 1/size of the calibrated pixels' footprint (Textures page).")
        self.add_option("detail_scale", "Detail size (× calibrated)", spin(2, 1, 4, 1, 0, "×"),
                        "The detail photographs' size as a multiple of camera.json's (the same aspect ratio).")
        self.add_option("detail_angles", "Detail turntable angles", QLineEdit("0, 30, -30"),
                        "Degrees from the input's view, comma-separated; small turns keep the registration error "
                        "below the print's grain.")
        w = QWidget()
        lay = QVBoxLayout(w)
        self.summary = text_label("", "input_summary")
        lay.addWidget(self.summary)
        self.view = ImageView(placeholder="the input photograph appears here")
        self.view.setObjectName("input_view")
        lay.addWidget(self.view, 1)
        self.tab(w, "Input photograph")
        p = QWidget()
        self.plan_layout = QVBoxLayout(p)
        self.plan_summary = text_label("", "plan_summary")
        self.plan_layout.addWidget(self.plan_summary)
        self.plan_table = table("plan_table", ["shot", "turntable", "lamps", "determines"], [])
        self.plan_layout.addWidget(self.plan_table, 1)
        self.tab(p, "Further photographs")

    def refresh(self):
        self._refresh_plan()
        self._refresh_input()

    def _refresh_plan(self):
        from reflab.core.workspace import WorkspaceError, read_json
        from reflab.inverse.forward.photographs import input_names

        ws = self.ws
        try:
            plan = read_json(ws.plan) if ws.plan.exists() else {}
        except WorkspaceError:
            plan = {}
        taken = input_names(ws)
        rows = [[s.get("name"), f"{fmt(s.get('angle_deg'))}°", fmt(s.get("lamps")),
                 ", ".join(s.get("determines", [])) or "narrows"] for s in plan.get("shots", [])]
        refill(self.plan_table, rows)
        text = (f"{len(taken)} further photograph(s) in inputs/: {', '.join(taken)}." if taken
                else "No further photograph yet.")
        if plan:
            text += (f" The plan ({ws.plan.name}) aims at {len(plan.get('targets', []))} parameters the fit left "
                     f"undetermined or loose; still open after its shots: {', '.join(plan.get('left_open', [])) or 'none'}.")
        else:
            text += " After a fit, tick <b>then plan and take the further photographs</b> and press Run."
        self.plan_summary.setText(text)

    def _refresh_input(self):
        from reflab.core.images import clip_level

        path = self.ws.input_image
        if not path.exists():
            self.summary.setText(self.nothing_yet("input photograph"))
            return
        img = read_image(path)
        clip = clip_level(img)
        sat = int(np.count_nonzero(np.any(img >= clip, axis=2))) if clip is not None else 0
        self.summary.setText(f"{path.name}: {img.shape[1]}×{img.shape[0]}, peak {img.max():.3f}, "
                             f"{sat} saturated pixels" + (" (left out of the fit)" if sat else ""))
        self.view.set_image(img)
