"""The page every step's page builds on (:class:`StepPage`: what to do at the rig, a live camera view,
the step's options, Run, its status and its result, read from the workspace's files, so a reopened
workspace shows its earlier results too) and the helpers pages share.
"""
from __future__ import annotations

import numpy as np
from PySide6.QtCore import Qt
from PySide6.QtGui import QColor, QFont
from PySide6.QtWidgets import (QCheckBox, QComboBox, QDoubleSpinBox, QFormLayout, QGroupBox, QHBoxLayout, QHeaderView,
                               QLabel, QLineEdit, QPushButton, QSpinBox, QSplitter, QTableWidget, QTableWidgetItem, QTabWidget,
                               QVBoxLayout, QWidget)

from reflab.app.gui import stages
from reflab.app.gui.sketch import SKETCHED, RigSketch
from reflab.app.gui.widgets import ImageView, text_label
from reflab.core.workspace import Workspace


def table(name: str, headers: list[str], rows: list[list], bad: set | None = None) -> QTableWidget:
    """A read-only table named ``name``; the cells ``bad`` ((row, column) pairs) in red."""
    widget = QTableWidget(len(rows), len(headers))
    widget.setObjectName(name)
    widget.setHorizontalHeaderLabels(headers)
    widget.verticalHeader().setVisible(False)
    widget.setEditTriggers(QTableWidget.EditTrigger.NoEditTriggers)
    refill(widget, rows, bad)
    widget.horizontalHeader().setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
    widget.horizontalHeader().setStretchLastSection(True)
    return widget


def refill(widget: QTableWidget, rows: list[list], bad: set | None = None) -> None:
    """Replace the rows of a :func:`table` (the cells ``bad`` in red)."""
    widget.setRowCount(len(rows))
    for i, row in enumerate(rows):
        for j, value in enumerate(row):
            item = QTableWidgetItem(str(value))
            if bad and (i, j) in bad:
                item.setForeground(QColor("#c00000"))
            widget.setItem(i, j, item)


def fmt(value, digits: int = 3) -> str:
    """A value for a table cell: floats (also in lists) to ``digits`` significant digits."""
    if isinstance(value, (list, tuple, np.ndarray)):
        return "[" + ", ".join(fmt(v, digits) for v in value) + "]"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def read_image(path):
    """:func:`reflab.core.images.read_image`, imported when a page first shows an image."""
    from reflab.core import images

    return images.read_image(path)


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
        head.addWidget(text_label(self.instructions(), f"instructions_{step.name}"))
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
        if self.preview_stretch:  # a capture page's live view keeps its share whatever the result tabs ask for
            box.setMinimumWidth(320)
            split.setSizes([1000 * self.preview_stretch, 1000 * (3 - self.preview_stretch if self.preview_stretch < 3 else 1)])
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

    @staticmethod
    def clear(layout) -> None:
        """Remove and delete every widget of ``layout`` (a result tab about to be filled anew)."""
        while layout.count():
            layout.takeAt(0).widget().deleteLater()

    def instructions(self) -> str:
        """The step's instructions, naming this page's button (“Capture and calibrate”, not “Run”)."""
        return self.step.instructions.replace("Run ", f"“{self.run_text}” ")

    def nothing_yet(self, what: str) -> str:
        """The result tab's text before the step has run: what is missing and which button makes it
        (while the step runs, that it is being made)."""
        if getattr(self.window, "running", None) == self.step.name:
            return f"No {what} yet: <b>{self.run_text}</b> is running…"
        return f"No {what} yet: press <b>{self.run_text}</b> above."

    def add_option(self, key: str, label: str, widget, tip: str = "") -> QWidget:
        if isinstance(widget, tuple):  # from_table's (widget, tip)
            widget, tip = widget[0], tip or widget[1]
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


#: Units as a field's suffix.
_SUFFIX = {"deg": " °"}


def from_table(cls, name: str, lo: float | None = None, hi: float | None = None, step: float = 1.0,
               decimals: int = 0):
    """(widget, tip) for option ``name`` of the stage's options table ``cls`` (reflab.core.options): its
    default (or typical value) as the starting value, its unit as the suffix, its help as the tip.
    A spin box when ``lo`` and ``hi`` are given (an empty default reads 0), else a line edit."""
    from reflab.core.options import describe, info, show

    i = info(cls, name)
    value = i["default"] if i["default"] is not None else i["typical"]
    tip = describe(cls, name)
    if lo is None:
        return QLineEdit("" if value is None else show(value)), tip
    unit = i["unit"] and _SUFFIX.get(i["unit"], f" {i['unit']}")
    return spin(value if value is not None else 0, lo, hi, step, decimals, unit or ""), tip


def mark_editor(page, left: QVBoxLayout, outer: QHBoxLayout, save_text: str, save_name: str, view_name: str,
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


def draw_segments(img: np.ndarray, a: np.ndarray, b: np.ndarray, colour) -> None:
    """Draw the segments a[i]-b[i] (pixel coordinates; sampled points, vectorised) onto an 8-bit image."""
    t = np.linspace(0.0, 1.0, 64)[:, None, None]
    p = np.rint(a[None] + t * (b - a)[None]).reshape(-1, 2).astype(int)
    h, w = img.shape[:2]
    ok = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
    img[p[ok, 1], p[ok, 0]] = colour
