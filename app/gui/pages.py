"""One page per step: what to do at the rig, a live camera view, the step's options, Run, its status
and its result with the quality figure, read from the workspace's files (so a reopened workspace
shows its earlier results too)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QColor, QFont
from PySide6.QtWidgets import (QCheckBox, QComboBox, QDoubleSpinBox, QFormLayout, QGridLayout, QGroupBox, QHBoxLayout,
                               QHeaderView, QLabel, QLineEdit, QListWidget, QListWidgetItem, QPushButton, QRadioButton,
                               QSlider, QSpinBox, QSplitter, QTableWidget, QTableWidgetItem, QTabWidget, QVBoxLayout,
                               QWidget)

from app.gui import stages
from app.gui.sketch import SKETCHED, RigSketch
from app.gui.widgets import Curve, ImageView, text_label
from hardware.workspace import Workspace, read_json

LAMP_COLOURS = ["#ff5050", "#50a0ff", "#50d050", "#ffb000"]


def _table(name: str, headers: list[str], rows: list[list], bad: set | None = None) -> QTableWidget:
    table = QTableWidget(len(rows), len(headers))
    table.setObjectName(name)
    table.setHorizontalHeaderLabels(headers)
    table.verticalHeader().setVisible(False)
    table.setEditTriggers(QTableWidget.EditTrigger.NoEditTriggers)
    for i, row in enumerate(rows):
        for j, value in enumerate(row):
            item = QTableWidgetItem(str(value))
            if bad and (i, j) in bad:
                item.setForeground(QColor("#c00000"))
            table.setItem(i, j, item)
    table.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
    table.horizontalHeader().setStretchLastSection(True)
    return table


def _fmt(value, digits: int = 3) -> str:
    if isinstance(value, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_fmt(v, digits) for v in value) + "]"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def _read_image(path):
    from hardware.images import read_image

    return read_image(path)


class StepPage(QWidget):
    """The common page: title, instructions, options, Run + status, live camera view, result tabs."""

    #: Relative width of the live camera view against the result (capture pages show it large).
    preview_stretch = 1
    run_text = "Run"

    def __init__(self, step: stages.GuiStep, window):
        super().__init__()
        self.step, self.window = step, window
        self.setObjectName(f"page_{step.name}")
        self._options: dict = {}
        outer = QVBoxLayout(self)
        header = QHBoxLayout()
        head = QVBoxLayout()
        header.addLayout(head, 1)
        if step.name in SKETCHED:  # what to set up at the rig, drawn
            header.addWidget(RigSketch(step.name), 0, Qt.AlignmentFlag.AlignTop)
        outer.addLayout(header)
        title = QLabel(step.title)
        f = QFont(title.font())
        f.setPointSize(f.pointSize() + 5)
        f.setBold(True)
        title.setFont(f)
        head.addWidget(title)
        head.addWidget(text_label(step.instructions, f"instructions_{step.name}"))
        row = QHBoxLayout()
        self.form = QFormLayout()
        row.addLayout(self.form)
        row.addStretch(1)
        buttons = QVBoxLayout()
        self.run_button = QPushButton(self.run_text)
        self.run_button.setObjectName(f"run_{step.name}")
        self.run_button.setMinimumWidth(140)
        self.run_button.clicked.connect(lambda: window.run_step(step.name))
        buttons.addWidget(self.run_button)
        following = stages.NAMES.index(step.name) + 1
        self.next_button = None
        if following < len(stages.STEPS):  # the way on, bold once this step is done
            after = stages.STEPS[following]
            self.next_button = QPushButton(f"Next: {after.title} ›")
            self.next_button.setObjectName(f"next_{step.name}")
            self.next_button.clicked.connect(lambda: window.go_to(after.name))
            buttons.addWidget(self.next_button)
        buttons.addStretch(1)
        row.addLayout(buttons)
        head.addLayout(row)
        head.addStretch(1)
        self.status = text_label("", f"status_{step.name}")
        outer.addWidget(self.status)
        split = QSplitter(Qt.Orientation.Horizontal)
        box = QGroupBox("Camera (live)")
        bl = QVBoxLayout(box)
        self.preview = ImageView(placeholder="live view" if self.preview_stretch == 0 else
                                 "the camera shows here\nonce the rig is connected\n(Devices)")
        self.preview.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.preview.setVerticalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.preview.setObjectName(f"preview_{step.name}")
        bl.addWidget(self.preview)
        split.addWidget(box)
        if self.preview_stretch == 0:  # nothing to do at the rig: a glance at the camera is enough
            box.setMaximumWidth(220)
            self.preview.setMaximumHeight(170)
            bl.addStretch(1)
        self.tabs = QTabWidget()
        self.tabs.setObjectName(f"results_{step.name}")
        split.addWidget(self.tabs)
        split.setStretchFactor(0, self.preview_stretch)
        split.setStretchFactor(1, 3 - self.preview_stretch if self.preview_stretch < 3 else 1)
        outer.addWidget(split, 1)
        self.build()
        self.set_status("done (earlier run)" if step.done(window.workspace) else "not run yet")

    # -- to override ------------------------------------------------------------------
    def build(self) -> None:
        """Add options and result tabs."""

    def refresh(self) -> None:
        """Show the step's result from the workspace's files."""

    def before_run(self) -> None:
        """Called just before the step starts."""

    # -- helpers ----------------------------------------------------------------------
    @property
    def ws(self) -> Workspace:
        return Workspace(self.window.workspace)

    def set_status(self, text: str) -> None:
        self.status.setText(text)
        state = text.split(':')[0].split(' ')[0]
        colour = {"done": "#207020", "failed": "#c00000", "cancelled": "#a06000", "running": "#2050a0"}
        self.status.setStyleSheet(f"color: {colour.get(state, '#444')}; font-weight: bold")
        if self.next_button is not None:
            self.next_button.setStyleSheet("font-weight: bold" if state == "done" else "")

    def nothing_yet(self, what: str) -> str:
        """The result tab's text before the step has run: what is missing and which button makes it."""
        return f"No {what} yet: press <b>{self.run_text}</b> above."

    def add_option(self, key: str, label: str, widget: QWidget, tip: str = "") -> QWidget:
        widget.setObjectName(f"option_{self.step.name}_{key}")
        if tip:
            widget.setToolTip(tip)
        self._options[key] = widget
        self.form.addRow(label, widget)
        return widget

    def options(self) -> dict:
        out = {}
        for key, w in self._options.items():
            if isinstance(w, QCheckBox):
                out[key] = w.isChecked()
            elif isinstance(w, (QSpinBox, QDoubleSpinBox)):
                out[key] = w.value()
            elif isinstance(w, QComboBox):
                out[key] = w.currentText()
            else:
                out[key] = w.text()
        return out

    def tab(self, widget: QWidget, title: str) -> QWidget:
        self.tabs.addTab(widget, title)
        return widget


def spin(value: float, lo: float, hi: float, step: float = 1.0, decimals: int = 0, suffix: str = ""):
    w = QSpinBox() if decimals == 0 else QDoubleSpinBox()
    if decimals:
        w.setDecimals(decimals)
    w.setRange(lo, hi)
    w.setSingleStep(step)
    w.setValue(value)
    if suffix:
        w.setSuffix(suffix)
    return w


# ====================================================================== devices
class DevicesPage(StepPage):
    preview_stretch = 2
    run_text = "Connect"

    def build(self):
        box = QWidget()
        lay = QVBoxLayout(box)
        self.hw_status = text_label("not connected", "hw_status")
        lay.addWidget(QLabel(f"Board: <b>{self.window.port}</b> &nbsp; Camera: <b>{self.window.camera}</b>"))
        lay.addWidget(self.hw_status)
        self.disconnect_button = QPushButton("Disconnect")
        self.disconnect_button.setObjectName("hw_disconnect")
        self.disconnect_button.clicked.connect(self.window.disconnect_rig)
        lay.addWidget(self.disconnect_button)
        jog = QGroupBox("Turntable")
        jl = QGridLayout(jog)
        for i, deg in enumerate((-90, -10, -1, 1, 10, 90)):
            b = QPushButton(f"{deg:+d}°")
            b.setObjectName(f"jog_{'m' if deg < 0 else 'p'}{abs(deg)}")
            b.clicked.connect(lambda _=False, d=deg: self.window.hardware_action("rotate", d, True))
            jl.addWidget(b, 0, i)
        self.goto = spin(0.0, -3600, 3600, 5.0, 2, " °")
        self.goto.setObjectName("jog_angle")
        go = QPushButton("Go to")
        go.setObjectName("jog_go")
        go.clicked.connect(lambda: self.window.hardware_action("rotate", self.goto.value(), False))
        jl.addWidget(self.goto, 1, 0, 1, 3)
        jl.addWidget(go, 1, 3, 1, 3)
        lay.addWidget(jog)
        lamps = QGroupBox("Lamps")
        ll = QHBoxLayout(lamps)
        self.lamp_boxes = []
        for k in range(len(self.window.rig.config.lamps)):  # one switch per configured lamp
            c = QCheckBox(f"lamp {k}")
            c.setObjectName(f"lamp_{k}")
            c.clicked.connect(lambda on, k=k: self.window.hardware_action("lamp", k, on))
            ll.addWidget(c)
            self.lamp_boxes.append(c)
        lay.addWidget(lamps)
        lay.addStretch(1)
        self.hw_widgets = [self.disconnect_button, jog, lamps]
        self.tab(box, "Board and lamps")
        self.show_connection(None)

    def show_connection(self, status: str | None) -> None:
        rig = self.window.rig
        self.hw_status.setText(status or ("connected" if rig.connected else "not connected"))
        for w in self.hw_widgets:
            w.setEnabled(rig.connected)
        if rig.connected:
            for box, on in zip(self.lamp_boxes, rig.controller.lamps):
                box.setChecked(on)

    def refresh(self):
        self.show_connection(self.window.rig.status() if self.window.rig.connected else None)


# ====================================================================== camera calibration
class CameraPage(StepPage):
    preview_stretch = 1
    run_text = "Capture and calibrate"

    def build(self):
        self.add_option("grid", "Target circles (COLSxROWS)", QLineEdit("11x8"))
        self.add_option("spacing", "Circle spacing", spin(0.015, 0.001, 1.0, 0.001, 4, " m"))
        self.add_option("angles", "Turntable angles (°)", QLineEdit(""),
                        "target on its wedge at each angle (empty: 0, 45, 90, 135, 225, 270, 315)")
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
        while self.table_holder.count():
            self.table_holder.takeAt(0).widget().deleteLater()
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
        table = _table("camera_views", ["view", "RMS (px)", "worst (px)"], rows, bad)
        table.setSelectionBehavior(QTableWidget.SelectionBehavior.SelectRows)
        table.currentCellChanged.connect(lambda r, *_: self.show_residuals(r))
        self.table_holder.addWidget(table)
        if rows:
            table.selectRow(int(np.argmax([v["rms_px"] for v in cal["views"]])))  # the worst view first

    def show_residuals(self, row: int) -> None:
        """View ``row``'s image with each circle's residual (model minus measured centre) drawn magnified."""
        views, residuals = self.calibration.get("views", []), self.calibration.get("residuals_px") or []
        if not 0 <= row < len(views) or len(residuals) != len(views) or not Path(views[row]["image"]).exists():
            return
        from hardware.images import to_display

        img = to_display(_read_image(views[row]["image"])).copy()
        a = np.asarray(residuals[row], float).reshape(-1, 4)
        typical = float(np.percentile(np.hypot(a[:, 2], a[:, 3]), 95)) or 1.0
        gain = max(1.0, round(0.04 * img.shape[1] / typical))  # the 95th percentile drawn 4 % of the width long
        _draw_segments(img, a[:, :2], a[:, :2] + gain * a[:, 2:], (255, 40, 40))
        _draw_segments(img, a[:, :2] - 1, a[:, :2] + 1, (40, 255, 40))  # the measured centre
        self.residual_view.set_image(img)
        self.residual_caption.setText(f"{Path(views[row]['image']).name}: residuals × {gain:g} (red) from each "
                                      "measured centre (green). Random directions: noise; a swirl or a radial trend: "
                                      "a model error.")


def _mark_editor(page, left: QVBoxLayout, outer: QHBoxLayout, save_text: str, save_name: str, view_name: str,
                 placeholder: str) -> ImageView:
    """The common end of a click-to-mark editor: a save button and a hint under the controls
    (``left``), and the zoomable image, wired to the page's ``_clicked``, ``_set`` and ``save_marks``."""
    save = QPushButton(save_text)
    save.setObjectName(save_name)
    save.clicked.connect(page.save_marks)
    left.addWidget(save)
    left.addWidget(text_label("Wheel zooms, shift-drag pans, double-click fits. Drag a mark to move it."))
    outer.addLayout(left, 1)
    view = ImageView(placeholder=placeholder)
    view.setObjectName(view_name)
    view.clicked.connect(page._clicked)
    view.mark_moved.connect(lambda key, u, v: page._set(key, u, v))
    outer.addWidget(view, 3)
    return view


# ====================================================================== lamp calibration (rod marks)
class LightsPage(StepPage):
    preview_stretch = 1
    run_text = "Capture and locate lamps"

    def build(self):
        self.add_option("rod_height", "Rod height", spin(0.10, 0.005, 2.0, 0.005, 3, " m"))
        self.add_option("angles", "Turntable angles (°)", QLineEdit(""), "empty: 0, 90, 180, 270")
        self.add_option("card_reflectance", "Grey card reflectance", spin(0.0, 0.0, 1.0, 0.01, 3),
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
        self.view = _mark_editor(self, left, el, "Save marks", "save_rod_marks", "rod_view",
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
        self.view.set_image(_read_image(self.window.workspace / image))
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
        while self.lamps_layout.count():
            self.lamps_layout.takeAt(0).widget().deleteLater()
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
                         worst, _fmt(light.get("intensity"))])
        self.lamps_layout.addWidget(_table("lamp_table", ["lamp", "position (m)", "σ x, y, z (mm)", "worst mark (px)",
                                                          "intensity"], rows))


# ====================================================================== sweep (corner marks)
CORNERS = [(x, y, z) for z in (1, -1) for y in (-1, 1) for x in (-1, 1)]


def corner_name(corner) -> str:
    """A corner label in the box's own axes (marks.json) in words: x left/right, y front/back, z bottom/top."""
    x, y, z = (int(v) for v in corner)
    return f"{'left' if x < 0 else 'right'} {'front' if y < 0 else 'back'} {'bottom' if z < 0 else 'top'}"


class SweepPage(StepPage):
    preview_stretch = 1
    run_text = "Capture the sweep"

    def build(self):
        self.add_option("count", "Shots over 360°", spin(36, 1, 720))
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
        self.view = _mark_editor(self, left, el, "Save corners", "save_corner_marks", "sweep_view",
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
            self.view.set_image(_read_image(self.window.workspace / image))
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


# ====================================================================== reconstruction
class ReconstructPage(StepPage):
    preview_stretch = 0
    run_text = "Reconstruct"

    def build(self):
        self.add_option("turntable_centre", "Turntable axis x,y (m)", QLineEdit("0,0" if self.window.port == "sim" else ""),
                        "where the turntable axis meets the ground, to fix the scale (empty: use a target)")
        self.add_option("force", "", QCheckBox("redo from scratch"))
        w = QWidget()
        lay = QHBoxLayout(w)
        left = QVBoxLayout()
        self.summary = text_label("", "reconstruct_summary")
        left.addWidget(self.summary)
        self.view = ImageView(placeholder="sparse points and surfaces appear here")
        self.view.setObjectName("reconstruct_view")
        self.view.clicked.connect(self._point)
        left.addWidget(self.view, 1)
        lay.addLayout(left, 3)
        name = QGroupBox("Name a fitted surface")
        nl = QFormLayout(name)
        nl.addRow(text_label("Click the surface on the image, name it and say what it is; Run again applies it "
                             "(marks.json).", wrap=True))
        self.point_name = QLineEdit()
        self.point_name.setObjectName("point_name")
        self.point_name.setPlaceholderText("e.g. tile")
        self.point_kind = QComboBox()
        self.point_kind.setObjectName("point_kind")
        self.point_kind.addItems(POINT_KINDS)
        self.point_ior = spin(1.5, 1.0, 3.0, 0.01, 3)
        self.point_ior.setObjectName("point_ior")
        add = QPushButton("Add")
        add.setObjectName("point_add")
        add.clicked.connect(self.add_point)
        self.points = QListWidget()
        self.points.setObjectName("point_list")
        nl.addRow("name", self.point_name)
        nl.addRow("it is", self.point_kind)
        nl.addRow("index", self.point_ior)
        nl.addRow(add)
        nl.addRow(self.points)
        lay.addWidget(name, 1)
        self.tab(w, "Shots, sparse points and surfaces")
        self.point = None

    def _point(self, u, v):
        self.point = (float(u), float(v))
        self.view.set_mark("point", u, v, colour="#ff40ff", label=self.point_name.text() or "?")

    def add_point(self):
        """Append {name, at, what the user knows} to marks.json's surfaces (reconstruction/marks.py)."""
        name = self.point_name.text().strip()
        if self.point is None or not name:
            self.window.log("name a surface: click it on the image and type its name first")
            return
        entry = {"name": name, "at": list(self.point)}
        entry.update(POINT_WORDS[self.point_kind.currentIndex()])
        if "ior" in entry:
            entry["ior"] = float(self.point_ior.value())
        items = [s for s in stages.read_marks_file(self.window.workspace).get("surfaces", []) if s.get("name") != name]
        stages.update_marks_file(self.window.workspace, surfaces=items + [entry])
        self.window.log(f"marks.json: the surface at ({self.point[0]:.0f}, {self.point[1]:.0f}) is {name!r}, "
                        f"{POINT_KINDS[self.point_kind.currentIndex()]}; Run applies it")
        self.point = None
        self.refresh()

    def refresh(self):
        ws = self.ws
        self.points.clear()
        self.view.clear_marks()
        for item in stages.read_marks_file(ws.root).get("surfaces", []):
            if "at" in item:
                self.view.set_mark(("at", item["name"]), *item["at"], colour="#ff40ff", label=item["name"])
                words = ", ".join(k if v is True else f"{k} {v}" for k, v in item.items() if k not in ("name", "at"))
                self.points.addItem(f"{item['name']} at ({item['at'][0]:.0f}, {item['at'][1]:.0f}): {words or 'glossy'}")
        lines = []
        sfm = read_json(ws.sfm) if ws.sfm.exists() else None
        if sfm:
            s = sfm.get("sfm", {})
            lines.append(f"<b>{s.get('registered')}/{s.get('images')}</b> shots registered, "
                         f"<b>{s.get('points')}</b> sparse points, reprojection {s.get('reprojection_px', float('nan')):.3f} px")
            tt = sfm.get("turntable")
            if tt:
                lines.append(f"turntable axis tilt {tt.get('axis_tilt_deg', 0):.3f}°, angle error max "
                             f"{tt.get('max_angle_error_deg', 0):.3f}°")
        if ws.scene.exists():
            surf = read_json(ws.scene).get("surfaces", [])
            lines.append("surfaces: " + ", ".join(f"{s['name']} ({s.get('source', 'given')})" for s in surf))
        self.summary.setText("<br>".join(lines) or self.nothing_yet("scene.json"))
        self._overlay(sfm)

    def _overlay(self, sfm):
        """The input view (or the first shot) with the sparse points and the surfaces' edges drawn over it."""
        from calibration.camera import Camera
        from reconstruction.scene import Scene

        ws = self.ws
        if not ws.camera.exists():
            return
        base = ws.input_image if ws.input_image.exists() else None
        shots = stages.manifest_status(ws.root, "sweep").get("shots", [])
        if base is None and shots:
            base = ws.captures / "turntable" / shots[0]["file"]
        if base is None or not Path(base).exists():
            return
        cam = Camera.load(ws.camera)
        from hardware.images import to_display

        img = to_display(_read_image(base)).copy()
        h, w = img.shape[:2]
        if ws.sparse.exists():
            pts = _read_ply_points(ws.sparse)
            if len(pts):
                uv = np.rint(cam.project(pts)).astype(int)
                ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
                img[uv[ok, 1], uv[ok, 0]] = (0, 255, 0)
        if ws.scene.exists():
            scene = Scene.load(ws.scene)
            for k, s in enumerate(scene):
                colour = QColor(LAMP_COLOURS[k % len(LAMP_COLOURS)])
                uv = cam.project(s.mesh.vertices)
                _draw_edges(img, uv, s.mesh.triangles, (colour.red(), colour.green(), colour.blue()))
        self.view.set_image(img)


#: What a user can say about a surface (reconstruction/marks.py's plain words).
POINT_KINDS = ["matte (paper, wood)", "glossy, textured", "glossy, one colour", "mirror", "transparent"]
POINT_WORDS = [{"matte": True}, {}, {"untextured": True}, {"mirror": True}, {"ior": 1.5}]


def _read_ply_points(path) -> np.ndarray:
    import open3d as o3d

    return np.asarray(o3d.io.read_point_cloud(str(path)).points)


def _draw_edges(img: np.ndarray, uv: np.ndarray, triangles: np.ndarray, colour) -> None:
    """Draw every triangle edge onto an 8-bit image."""
    tri = np.asarray(triangles)
    _draw_segments(img, uv[np.concatenate([tri[:, 0], tri[:, 1], tri[:, 2]])],
                   uv[np.concatenate([tri[:, 1], tri[:, 2], tri[:, 0]])], colour)


def _draw_segments(img: np.ndarray, a: np.ndarray, b: np.ndarray, colour) -> None:
    """Draw the segments a[i]-b[i] (pixel coordinates; sampled points, vectorised) onto an 8-bit image."""
    t = np.linspace(0.0, 1.0, 64)[:, None, None]
    p = np.rint(a[None] + t * (b - a)[None]).reshape(-1, 2).astype(int)
    h, w = img.shape[:2]
    ok = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
    img[p[ok, 1], p[ok, 0]] = colour


# ====================================================================== input photograph
class InputPage(StepPage):
    preview_stretch = 2
    run_text = "Take the photograph"

    def build(self):
        self.add_option("angle", "Turntable angle", spin(0.0, -360, 360, 1.0, 2, " °"))
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
        from hardware.images import clip_level

        path = self.ws.input_image
        if not path.exists():
            self.summary.setText(self.nothing_yet("input photograph"))
            return
        img = _read_image(path)
        clip = clip_level(img)
        sat = int(np.count_nonzero(np.any(img >= clip, axis=2))) if clip is not None else 0
        self.summary.setText(f"{path.name}: {img.shape[1]}×{img.shape[0]}, peak {img.max():.3f}, "
                             f"{sat} saturated pixels" + (" (left out of the fit)" if sat else ""))
        self.view.set_image(img)


# ====================================================================== fit
class FitPage(StepPage):
    preview_stretch = 0
    run_text = "Fit"

    def build(self):
        self.add_option("texture_rounds", "Texture rounds", spin(2, 0, 10))
        self.add_option("max_seconds", "Time budget (s, 0 = none)", spin(0.0, 0.0, 36000, 10, 1))
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
        while self.materials_layout.count():
            self.materials_layout.takeAt(0).widget().deleteLater()
        if not self.ws.fit.exists():
            self.materials_layout.addWidget(QLabel(self.nothing_yet("fit.json")))
            return
        fit = read_json(self.ws.fit)
        rows, bad = [], set()
        for item in fit.get("surfaces", []):
            sigma, und = item.get("sigma", {}), set(item.get("undetermined", []))
            for key, value in item.get("material", {}).items():
                if key in ("brdf", "ior") or value is None:
                    continue
                if key in und:
                    bad.add((len(rows), 3))
                rows.append([item["name"], key, _fmt(value), "undetermined" if key in und else _fmt(sigma.get(key, "–"), 2)])
        head = text_label(f"status <b>{fit.get('status', 'ok')}</b>, RMS per band {_fmt(fit.get('rms'))}, "
                          f"{fit.get('method')} in {fit.get('time_s', 0):.1f} s")
        self.materials_layout.addWidget(head)
        for text in fit.get("warnings", []):
            self.materials_layout.addWidget(text_label(f"⚠ {text}"))
        self.materials_layout.addWidget(_table("fit_table", ["surface", "parameter", "value", "σ"], rows, bad))
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


# ====================================================================== texture
class TexturePage(StepPage):
    preview_stretch = 0
    run_text = "Recover textures"

    def build(self):
        self.grid_widget = QWidget()
        self.grid = QGridLayout(self.grid_widget)
        self.tab(self.grid_widget, "Textures")

    def refresh(self):
        while self.grid.count():
            self.grid.takeAt(0).widget().deleteLater()
        folder = self.ws.textures
        files = sorted(p for p in folder.glob("*.exr") if not p.stem.endswith("_diag")) if folder.is_dir() else []
        if not files:
            self.grid.addWidget(QLabel(self.nothing_yet("textures")), 0, 0)
            return
        for i, path in enumerate(files):
            tex = np.nan_to_num(_read_image(path))
            view = ImageView()
            view.setObjectName(f"texture_{path.stem}")
            view.set_image(tex, exposure=1.0)  # kd itself, sRGB-encoded
            mask = folder / f"{path.stem}_mask.png"
            known = ""
            if mask.exists():
                m = _read_image(mask)
                known = f", {100 * float(np.mean(m > 0)):.0f}% determined by the image"
            box = QGroupBox(path.stem)
            bl = QVBoxLayout(box)
            bl.addWidget(text_label(f"{tex.shape[1]}×{tex.shape[0]} texels{known}"))
            bl.addWidget(view, 1)
            self.grid.addWidget(box, i // 3, i % 3)


# ====================================================================== results
class ResultsPage(StepPage):
    preview_stretch = 0
    run_text = "Re-render and report"
    #: A novel view ended: (ok, its description or the failure's message).
    novel_rendered = Signal(bool, str)

    def build(self):
        w = QWidget()
        lay = QGridLayout(w)
        self.views = {}
        for (key, title), (r, c) in zip((("input", "photograph"), ("render", "model re-rendered"),
                                         ("difference", "|model − photograph| × 4")), ((0, 0), (0, 1), (1, 0))):
            view = ImageView()
            view.setObjectName(f"results_{key}")
            box = QGroupBox(title)
            QVBoxLayout(box).addWidget(view)
            lay.addWidget(box, r, c)
            self.views[key] = view
        self.summary = text_label("", "results_summary")
        self.summary.setAlignment(Qt.AlignmentFlag.AlignTop | Qt.AlignmentFlag.AlignLeft)
        lay.addWidget(self.summary, 1, 1)
        self.tab(w, "Model against photograph")
        nv = QWidget()
        nl = QHBoxLayout(nv)
        controls = QFormLayout()
        self.azimuth = QSlider(Qt.Orientation.Horizontal)
        self.azimuth.setObjectName("novel_azimuth")
        self.azimuth.setRange(-60, 60)
        self.elevation = QSlider(Qt.Orientation.Horizontal)
        self.elevation.setObjectName("novel_elevation")
        self.elevation.setRange(-20, 20)
        controls.addRow("orbit (°)", self.azimuth)
        controls.addRow("raise (°)", self.elevation)
        self.dimmers = []
        for k in range(len(self.window.rig.config.lamps)):  # a dimmer per lamp of the rig
            s = QSlider(Qt.Orientation.Horizontal)
            s.setObjectName(f"dim_lamp_{k}")
            s.setRange(0, 200)
            s.setValue(100)
            controls.addRow(f"lamp {k} (%)", s)
            self.dimmers.append(s)
        for slider in [self.azimuth, self.elevation] + self.dimmers:
            slider.valueChanged.connect(self._describe_novel)
        self.novel_button = QPushButton("Render this view")
        self.novel_button.setObjectName("render_novel")
        self.novel_button.clicked.connect(self.render_novel)
        controls.addRow(self.novel_button)
        self.novel_info = text_label("Move the sliders, then render.", "novel_info")
        controls.addRow(self.novel_info)
        nl.addLayout(controls, 1)
        self.novel = ImageView(placeholder="the model from the chosen view and lamps")
        self.novel.setObjectName("novel_view")
        nl.addWidget(self.novel, 3)
        self.tab(nv, "Novel view and relighting")

    def refresh(self):
        ws = self.ws
        if not ws.render().exists() or not ws.input_image.exists():
            self.summary.setText(self.nothing_yet("re-render"))
            return
        photo, model = _read_image(ws.input_image), _read_image(ws.render())
        exposure = 1.0 / max(float(np.percentile(photo, 99.5)), 1e-12)
        self.views["input"].set_image(photo, exposure)
        self.views["render"].set_image(model, exposure)
        if photo.shape == model.shape:
            diff = np.abs(model - photo)
            self.views["difference"].set_image(diff, 4 * exposure)
            rel = float(np.sqrt(np.mean((model - photo) ** 2)) / max(np.sqrt(np.mean(photo ** 2)), 1e-300))
            html = ws.report
            report = (f"<br><br>The whole account (calibration, geometry, materials with σ, textures): <b>{html}</b>, "
                      "to open in a browser." if html.exists() else "")
            self.summary.setText(f"RMS difference <b>{100 * rel:.2f}%</b> of the photograph's RMS.{report}<br><br>"
                                 "The next tab shows the model from another view and under dimmed or brightened lamps.")

    def _describe_novel(self, _=None):
        dims = ", ".join(f"{s.value()}%" for s in self.dimmers)
        self.novel_info.setText(f"orbit {self.azimuth.value():+d}°, raise {self.elevation.value():+d}°, lamps {dims}: "
                                "press Render this view")

    def render_novel(self):
        az, el = float(self.azimuth.value()), float(self.elevation.value())
        dims = [s.value() / 100.0 for s in self.dimmers]
        self.novel_button.setEnabled(False)
        self.novel_info.setText("rendering…")
        self.window.background(lambda task: novel_view(self.window.workspace, az, el, dims), self._novel_done, "novel")

    def _novel_done(self, ok: bool, result):
        self.novel_button.setEnabled(True)
        if not ok:
            self.novel_info.setText(f"failed: {result}")
            self.novel_rendered.emit(False, str(result))
            return
        image, text = result
        self.novel.set_image(image)
        self.novel_info.setText(text)
        self.novel_rendered.emit(True, text)


def orbit(camera, azimuth: float, elevation: float):
    """The camera moved on a sphere about where its optical axis meets the ground: turned ``azimuth``
    degrees about the vertical, then raised ``elevation`` degrees; same intrinsics, no roll added."""
    from dataclasses import replace

    from calibration.rotations import axis_rotation

    eye, axis = camera.center, camera.R[2]
    target = eye + axis * (eye[2] / max(-axis[2], 1e-6))  # the optical axis meets z = 0
    side = np.cross(axis, [0.0, 0.0, 1.0])  # the camera's horizontal axis: raising turns about it
    side = side if np.linalg.norm(side) > 1e-9 else camera.R[0]  # looking straight down: its x axis
    Q = axis_rotation([0.0, 0.0, 1.0], azimuth) @ axis_rotation(side, -elevation)
    R = camera.R @ Q.T
    return replace(camera, R=R, t=-R @ (Q @ (eye - target) + target), extra={})


def novel_view(workspace, azimuth: float, elevation: float, dims) -> tuple:
    """Render the recovered model from the input camera orbited (:func:`orbit`), each lamp's
    intensity scaled by ``dims``."""
    import tempfile

    from calibration.camera import Camera
    from calibration.lights import Lights
    from inverse.stages import render_workspace

    ws = Workspace(workspace)
    cam = orbit(Camera.load(ws.require(ws.camera, "the Calibrate the camera step")), azimuth, elevation)
    lights = Lights.load(ws.require(ws.lights, "the Calibrate the lamps step"))
    dims = list(dims) + [1.0] * (len(lights) - len(dims))
    scaled = Lights([type(l)(l.position, np.asarray(l.intensity) * d) for l, d in zip(lights, dims)])
    with tempfile.TemporaryDirectory() as tmp:
        moved, dimmed = Path(tmp) / "orbit_camera.json", Path(tmp) / "dimmed_lights.json"
        cam.save(moved)
        scaled.save(dimmed)
        image, info = render_workspace(workspace, moved, dimmed)
    text = (f"orbit {azimuth:+.0f}°, raise {elevation:+.0f}°, lamps "
            + ", ".join(f"{100 * d:.0f}%" for d in dims) + f" — trees {info['trees_s']:.1f} s, render {info['render_s']:.1f} s")
    return image, text


PAGES = {"devices": DevicesPage, "calibrate_camera": CameraPage, "calibrate_lights": LightsPage, "sweep": SweepPage,
         "reconstruct": ReconstructPage, "input": InputPage, "fit": FitPage, "texture": TexturePage,
         "results": ResultsPage}
