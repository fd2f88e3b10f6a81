"""The camera calibration page: the target's options, and each view's reprojection with its residuals."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PySide6.QtWidgets import QCheckBox, QHBoxLayout, QTableWidget, QVBoxLayout, QWidget

from reflab.app.gui.pages.page import StepPage, draw_segments, from_table, read_image, table
from reflab.app.gui.widgets import ImageView, text_label
from reflab.calibration.stages import CameraOptions
from reflab.core.workspace import read_json
from reflab.hardware.capture import CaptureOptions


class CameraPage(StepPage):
    preview_stretch = 1
    run_text = "Capture and calibrate"

    def build(self):
        self.add_option("grid", "Target circles (COLSxROWS)", from_table(CameraOptions, "grid"))
        self.add_option("spacing", "Circle spacing", from_table(CameraOptions, "spacing", 0.001, 1.0, 0.001, 4))
        self.add_option("angles", "Turntable angles (°)", from_table(CaptureOptions, "angles"))
        self.add_option("recapture", "", QCheckBox("capture again"))
        self.summary = text_label("", "camera_summary")
        self.views = QWidget()
        row = QHBoxLayout(self.views)
        lay = QVBoxLayout()
        lay.addWidget(self.summary)
        self.table_holder = QVBoxLayout()
        lay.addLayout(self.table_holder, 1)
        row.addLayout(lay, 2)
        right = QVBoxLayout()
        self.residual_caption = text_label("", "camera_residual_caption")
        right.addWidget(self.residual_caption)
        self.residual_view = ImageView(placeholder="pick a view in the table")
        self.residual_view.setObjectName("camera_residuals")
        right.addWidget(self.residual_view, 1)
        row.addLayout(right, 3)
        self.tab(self.views, "Reprojection per view")
        self.calibration: dict = {}

    def refresh(self):
        self.clear(self.table_holder)
        if not self.ws.camera.exists():
            self.summary.setText(self.nothing_yet("camera.json"))
            return
        cam = read_json(self.ws.camera)
        cal = self.calibration = cam.get("calibration", {})
        K, s = cam["K"], cal.get("sigma", {})
        pm = lambda key, v: f"{v:.2f} ± {s[key]:.2f}" if key in s else f"{v:.2f}"  # noqa: E731
        self.summary.setText(
            f"fx {pm('fx', K[0][0])} &nbsp; fy {pm('fy', K[1][1])}<br>cx {pm('cx', K[0][2])} &nbsp; cy {pm('cy', K[1][2])}"
            f" &nbsp; k1 {cam['dist'][0]:.4f}<br>reprojection RMS <b>{cal.get('rms_px', float('nan')):.3f} px</b> over "
            f"{len(cal.get('views', []))} views"
            + (f"; skipped {', '.join(Path(str(v)).name for v in cal['skipped'])} (no grid found; the log "
               "says why)" if cal.get("skipped") else "")
            + "".join(f"<br>⚠ {text}" for text in cal.get("warnings", [])))
        rows = [[Path(v["image"]).name, f"{v['rms_px']:.3f}", f"{v['worst_px']:.3f}"] for v in cal.get("views", [])]
        bad = {(i, 1) for i, v in enumerate(cal.get("views", [])) if v["rms_px"] > 0.5}
        view_table = table("camera_views", ["view", "RMS (px)", "worst (px)"], rows, bad)
        view_table.setSelectionBehavior(QTableWidget.SelectionBehavior.SelectRows)
        view_table.currentCellChanged.connect(lambda r, *_: self.show_residuals(r))
        self.table_holder.addWidget(view_table)
        if rows:
            view_table.selectRow(int(np.argmax([v["rms_px"] for v in cal["views"]])))  # the worst view first

    def show_residuals(self, row: int) -> None:
        """View ``row``'s image with each circle's residual (model minus measured centre) drawn magnified."""
        views, residuals = self.calibration.get("views", []), self.calibration.get("residuals_px") or []
        if not 0 <= row < len(views) or len(residuals) != len(views) or not Path(views[row]["image"]).exists():
            return
        from reflab.core.images import to_display

        img = to_display(read_image(views[row]["image"])).copy()
        a = np.asarray(residuals[row], float).reshape(-1, 4)
        typical = float(np.percentile(np.hypot(a[:, 2], a[:, 3]), 95)) or 1.0
        gain = max(1.0, round(0.04 * img.shape[1] / typical))  # the 95th percentile drawn 4 % of the width long
        draw_segments(img, a[:, :2], a[:, :2] + gain * a[:, 2:], (255, 40, 40))
        draw_segments(img, a[:, :2] - 1, a[:, :2] + 1, (40, 255, 40))  # the measured centre
        self.residual_view.set_image(img)
        self.residual_caption.setText(f"{Path(views[row]['image']).name}: residuals × {gain:g} (red) from each "
                                      "measured centre (green). Random directions: noise; a swirl or a radial trend: "
                                      "a model error.")
