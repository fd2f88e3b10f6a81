"""The sweep page: the turntable sweep's options and the corner marks of mirrors and glass."""
from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtWidgets import (QCheckBox, QComboBox, QFormLayout, QHBoxLayout, QLabel, QListWidget, QListWidgetItem,
                               QVBoxLayout, QWidget)

from reflab.app.gui import stages
from reflab.app.gui.pages.page import StepPage, from_table, mark_editor, read_image, spin
from reflab.app.gui.widgets import text_label
from reflab.hardware.capture import CaptureOptions


CORNERS = [(x, y, z) for z in (1, -1) for y in (-1, 1) for x in (-1, 1)]


def corner_name(corner) -> str:
    """A corner label in the box's own axes (marks.json) in words: x left/right, y front/back, z bottom/top."""
    x, y, z = (int(v) for v in corner)
    return f"{'left' if x < 0 else 'right'} {'front' if y < 0 else 'back'} {'bottom' if z < 0 else 'top'}"


class SweepPage(StepPage):
    preview_stretch = 1
    run_text = "Capture the sweep"

    def build(self):
        self.add_option("count", "Shots over 360°", from_table(CaptureOptions, "count", 1, 720))
        self.add_option("recapture", "", QCheckBox("capture again"))
        editor = QWidget()
        el = QHBoxLayout(editor)
        left = QVBoxLayout()
        left.addWidget(QLabel("Surface to mark:"))
        self.surface = QComboBox()
        self.surface.setObjectName("corner_surface")
        self.surface.setEditable(True)
        self.surface.addItems(["mirror", "sheet"])
        self.surface.currentTextChanged.connect(lambda _: self._load_surface())
        left.addWidget(self.surface)
        form = QFormLayout()
        self.kind = QComboBox()
        self.kind.addItems(["mirror (opaque, reflects)", "transparent (glass, plastic)", "matte", "glossy"])
        self.kind.setObjectName("corner_kind")
        self.ior = spin(1.5, 1.0, 3.0, 0.01, 3)
        self.ior.setObjectName("corner_ior")
        self.textured = QCheckBox("textured")
        self.textured.setObjectName("corner_textured")
        self.thickness = spin(0.0, 0.0, 1.0, 0.001, 4, " m")
        self.thickness.setObjectName("corner_thickness")
        self.thickness.setToolTip("known thickness (box's own y edge) when only the front face is marked; 0 = unknown")
        form.addRow("what it is", self.kind)
        form.addRow("index (transparent)", self.ior)
        form.addRow("", self.textured)
        form.addRow("thickness", self.thickness)
        left.addLayout(form)
        left.addWidget(QLabel("Corner (as the box stands in shot 0):"))
        self.corner = QComboBox()
        self.corner.setObjectName("corner_label")
        self.corner.addItems([corner_name(c) for c in CORNERS])
        self.corner.currentIndexChanged.connect(lambda _: self._show_marks())
        left.addWidget(self.corner)
        left.addWidget(QLabel("Shot:"))
        self.shots = QListWidget()
        self.shots.setObjectName("sweep_shots")
        self.shots.currentRowChanged.connect(lambda _: self._show_shot())
        left.addWidget(self.shots, 1)
        left.addWidget(text_label("Click the chosen corner on two or more shots."))
        self.view = mark_editor(self, left, el, "Save corners", "save_corner_marks", "sweep_view",
                                "sweep shots appear here after Run")
        self.tab(editor, "Mark mirror and glass corners")
        self.surfaces: dict = {}

    def refresh(self):
        self.surfaces = {s["name"]: s for s in stages.read_marks_file(self.window.workspace).get("surfaces", [])
                         if "corners" in s}
        for name in self.surfaces:
            if self.surface.findText(name) < 0:
                self.surface.addItem(name)
        row = self.shots.currentRow()
        self.shots.clear()
        for rec in stages.manifest_status(self.window.workspace, "sweep").get("shots", []):
            item = QListWidgetItem(f"{rec['file']}  {rec['angle']:.1f}°")
            item.setData(Qt.ItemDataRole.UserRole, f"captures/turntable/{rec['file']}")
            self.shots.addItem(item)
        if self.shots.count():
            self.shots.setCurrentRow(min(max(row, 0), self.shots.count() - 1))
        self._load_surface()

    def _spec(self) -> dict:
        name = self.surface.currentText().strip() or "surface"
        return self.surfaces.setdefault(name, {"name": name, "shape": "box", "brdf": "phong", "ior": None,
                                               "textured": False, "size": [None, None, None], "corners": []})

    def _load_surface(self):
        spec = self.surfaces.get(self.surface.currentText().strip())
        if spec:
            self.kind.setCurrentIndex(1 if spec.get("ior") else 2 if spec.get("matte") or spec.get("brdf") == "lambert"
                                      else 0 if spec.get("mirror", not spec.get("textured")) else 3)
            self.ior.setValue(spec.get("ior") or 1.5)
            self.textured.setChecked(bool(spec.get("textured")))
            self.thickness.setValue((spec.get("size") or [None, None, None])[1] or 0.0)
        self._show_marks()

    def _corner(self) -> list:
        return list(CORNERS[self.corner.currentIndex()])

    def _image(self):
        item = self.shots.currentItem()
        return item.data(Qt.ItemDataRole.UserRole) if item else None

    def _show_shot(self):
        image = self._image()
        if image and (self.window.workspace / image).exists():
            self.view.set_image(read_image(self.window.workspace / image))
        self._show_marks()

    def _show_marks(self):
        self.view.clear_marks()
        image = self._image()
        spec = self.surfaces.get(self.surface.currentText().strip())
        if not spec or image is None:
            return
        for c in spec["corners"]:
            if image in c["marks"]:
                here = list(c["corner"]) == self._corner()
                self.view.set_mark(tuple(c["corner"]), *c["marks"][image], colour="#ffcc00" if here else "#00e0ff",
                                   label=corner_name(c["corner"]))

    def _set(self, key, u, v):
        image = self._image()
        if image is None:
            return
        spec, corner = self._spec(), list(key)
        entry = next((c for c in spec["corners"] if list(c["corner"]) == corner), None)
        if entry is None:
            entry = {"corner": corner, "marks": {}}
            spec["corners"].append(entry)
        entry["marks"][image] = [float(u), float(v)]
        self._show_marks()

    def _clicked(self, u, v):
        self._set(tuple(self._corner()), u, v)

    def save_marks(self):
        spec = self._spec()
        kind = self.kind.currentIndex()  # mirror, transparent, matte, glossy
        for key in ("mirror", "matte", "untextured"):
            spec.pop(key, None)
        spec["ior"] = float(self.ior.value()) if kind == 1 else None
        spec["brdf"] = "lambert" if kind == 2 else "phong"
        spec["textured"] = bool(self.textured.isChecked()) and kind in (2, 3)
        spec["size"] = [None, float(self.thickness.value()) or None, None]
        # what the user knows, in marks.json's plain words (reconstruction/marks.py), beside brdf/textured
        if kind == 0:
            spec["mirror"] = True
        elif kind == 2:
            spec["matte"] = True
        if not spec["textured"] and kind != 0 and spec["ior"] is None:
            spec["untextured"] = True
        usable = [s for s in self.surfaces.values() if any(len(c["marks"]) >= 2 for c in s["corners"])]
        for s in usable:
            s["corners"] = [c for c in s["corners"] if len(c["marks"]) >= 2]
        others = [s for s in stages.read_marks_file(self.window.workspace).get("surfaces", []) if "corners" not in s]
        stages.update_marks_file(self.window.workspace, surfaces=usable + others)
        self.window.log(f"saved corners of {len(usable)} surface(s) to {self.ws.marks}"
                        + ("" if usable else " (a corner needs marks on two or more shots)"))
