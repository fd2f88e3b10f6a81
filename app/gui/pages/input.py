"""The input photograph page: take it and see its size, peak and saturated pixels."""
from __future__ import annotations

import numpy as np
from PySide6.QtWidgets import QCheckBox, QVBoxLayout, QWidget

from reflab.app.gui.pages.page import StepPage, from_table, read_image
from reflab.app.gui.widgets import ImageView, text_label
from reflab.hardware.capture import CaptureOptions


class InputPage(StepPage):
    preview_stretch = 2
    run_text = "Take the photograph"

    def build(self):
        self.add_option("angle", "Turntable angle", from_table(CaptureOptions, "start", -360, 360, 1.0, 2))
        self.add_option("ambient", "", QCheckBox("ambient frame (lamps off) subtracted"))
        self.add_option("recapture", "", QCheckBox("capture again"))
        w = QWidget()
        lay = QVBoxLayout(w)
        self.summary = text_label("", "input_summary")
        lay.addWidget(self.summary)
        self.view = ImageView(placeholder="the input photograph appears here")
        self.view.setObjectName("input_view")
        lay.addWidget(self.view, 1)
        self.tab(w, "Input photograph")

    def refresh(self):
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
