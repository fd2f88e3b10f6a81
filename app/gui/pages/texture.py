"""The texture page: each recovered albedo map and the share of it the image determines."""
from __future__ import annotations

import numpy as np
from PySide6.QtWidgets import QGridLayout, QGroupBox, QLabel, QVBoxLayout, QWidget

from reflab.app.gui.pages.page import StepPage, from_table, read_image
from reflab.app.gui.widgets import ImageView, text_label


class TexturePage(StepPage):
    preview_stretch = 0
    run_text = "Recover textures"

    def build(self):
        from reflab.inverse.stages import TextureOptions

        self.add_option("texel_scale", "Texel scale", from_table(TextureOptions, "texel_scale", 0.1, 4.0, 0.25, 2))
        self.add_option("smoothness", "Smoothness", from_table(TextureOptions, "smoothness", 0.0, 10.0, 0.01, 3))
        self.grid_widget = QWidget()
        self.grid = QGridLayout(self.grid_widget)
        self.tab(self.grid_widget, "Textures")

    def refresh(self):
        self.clear(self.grid)
        folder = self.ws.textures
        files = sorted(p for p in folder.glob("*.exr") if not p.stem.endswith("_diag")) if folder.is_dir() else []
        if not files:
            self.grid.addWidget(QLabel(self.nothing_yet("textures")), 0, 0)
            return
        for i, path in enumerate(files):
            tex = np.nan_to_num(read_image(path))
            view = ImageView()
            view.setObjectName(f"texture_{path.stem}")
            view.set_image(tex, exposure=1.0)  # kd itself, sRGB-encoded
            mask = folder / f"{path.stem}_mask.png"
            known = ""
            if mask.exists():
                m = read_image(mask)
                known = f", {100 * float(np.mean(m > 0)):.0f}% determined by the image"
            box = QGroupBox(path.stem)
            bl = QVBoxLayout(box)
            bl.addWidget(text_label(f"{tex.shape[1]}×{tex.shape[0]} texels{known}"))
            bl.addWidget(view, 1)
            self.grid.addWidget(box, i // 3, i % 3)
