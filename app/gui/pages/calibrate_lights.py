"""The lamp calibration page: the rod's options, the rod marks editor and the lamps located."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PySide6.QtCore import Qt
from PySide6.QtWidgets import (QCheckBox, QHBoxLayout, QLabel, QLineEdit, QListWidget, QListWidgetItem, QRadioButton,
                               QVBoxLayout, QWidget)

from reflab.app.gui import stages
from reflab.app.gui.pages.page import StepPage, fmt, from_table, mark_editor, read_image, table
from reflab.calibration.stages import LightsOptions
from reflab.core.workspace import read_json
from reflab.hardware.capture import CaptureOptions


class LightsPage(StepPage):
    preview_stretch = 1
    run_text = "Capture and locate lamps"

    def build(self):
        self.add_option("rod_height", "Rod height", from_table(LightsOptions, "rod_height", 0.005, 2.0, 0.005, 3))
        self.add_option("angles", "Turntable angles (°)", from_table(CaptureOptions, "angles"))
        self.add_option("card_reflectance", "Grey card reflectance", from_table(LightsOptions, "sheet_reflectance",
                                                                                0.0, 1.0, 0.01, 3),
                        "the card's Lambertian reflectance, for each lamp's power (0: no card)")
        region = self.add_option("card_region", "Card on the table x0, x1, y0, y1 (m)", QLineEdit(""))
        region.setMinimumWidth(220)
        self.add_option("recapture", "", QCheckBox("capture again"))
        # marks editor
        editor = QWidget()
        el = QHBoxLayout(editor)
        left = QVBoxLayout()
        self.shots = QListWidget()
        self.shots.setObjectName("rod_shots")
        self.shots.currentRowChanged.connect(self._show_shot)
        left.addWidget(QLabel("Rod shots (lamp):"))
        left.addWidget(self.shots)
        self.mark_foot = QRadioButton("click sets the rod's foot")
        self.mark_tip = QRadioButton("click sets the shadow's tip")
        self.mark_foot.setChecked(True)
        left.addWidget(self.mark_foot)
        left.addWidget(self.mark_tip)
        self.view = mark_editor(self, left, el, "Save marks", "save_rod_marks", "rod_view",
                                "rod shots appear here after Run")
        self.tab(editor, "Rod marks")
        self.lamps = QWidget()
        self.lamps_layout = QVBoxLayout(self.lamps)
        self.tab(self.lamps, "Lamp positions")
        self.marks: dict = {}

    # marks: image -> {"image", "light", "base", "tip"}
    def refresh(self):
        self.marks = {m["image"]: m for m in stages.read_marks_file(self.window.workspace).get("marks", [])}
        current = self.shots.currentRow()
        self.shots.clear()
        for shot in stages.rod_shots(self.window.workspace):
            item = QListWidgetItem(f"{Path(shot.image).name} (lamp {shot.light})")
            item.setData(Qt.ItemDataRole.UserRole, (shot.image, shot.light))
            self.shots.addItem(item)
        if self.shots.count():
            self.shots.setCurrentRow(min(max(current, 0), self.shots.count() - 1))
        self._show_lamps()

    def _current(self):
        item = self.shots.currentItem()
        return item.data(Qt.ItemDataRole.UserRole) if item else (None, None)

    def _show_shot(self, row):
        image, lamp = self._current()
        self.view.clear_marks()
        if image is None or not (self.window.workspace / image).exists():
            return
        self.view.set_image(read_image(self.window.workspace / image))
        m = self.marks.get(image)
        if m:
            self.view.set_mark("base", *m["base"], colour="#00e0ff", label="foot")
            self.view.set_mark("tip", *m["tip"], colour="#ffcc00", label="tip")

    def _set(self, key, u, v):
        image, lamp = self._current()
        if image is None:
            return
        m = self.marks.setdefault(image, {"image": image, "light": lamp, "base": None, "tip": None})
        m[key] = [float(u), float(v)]
        self.view.set_mark(key, u, v, colour="#00e0ff" if key == "base" else "#ffcc00",
                           label="foot" if key == "base" else "tip")

    def _clicked(self, u, v):
        key = "base" if self.mark_foot.isChecked() else "tip"
        self._set(key, u, v)
        (self.mark_tip if key == "base" else self.mark_foot).setChecked(True)  # foot, then tip

    def save_marks(self):
        complete = [m for m in self.marks.values() if m.get("base") and m.get("tip")]
        stages.update_marks_file(self.window.workspace, rod_height=self._options["rod_height"].value(), marks=complete)
        self.window.log(f"saved {len(complete)} rod marks to {self.ws.marks}")

    def _show_lamps(self):
        self.clear(self.lamps_layout)
        if not self.ws.lights.exists():
            self.lamps_layout.addWidget(QLabel(self.nothing_yet("lights.json")))
            return
        rows = []
        for k, light in enumerate(read_json(self.ws.lights)["lights"]):
            p = light["position"]
            cov = light.get("sigma_position")
            sd = np.sqrt(np.diag(np.asarray(cov))) * 1000 if cov is not None else [float("nan")] * 3
            err = light.get("calibration", {}).get("mark_errors_px")
            worst = f"{np.max(err):.2f}" if err is not None and np.size(err) else "–"
            rows.append([f"lamp {k}", f"{p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}", f"{sd[0]:.1f}, {sd[1]:.1f}, {sd[2]:.1f}",
                         worst, fmt(light.get("intensity"))])
        self.lamps_layout.addWidget(table("lamp_table", ["lamp", "position (m)", "σ x, y, z (mm)", "worst mark (px)",
                                                         "intensity"], rows))
