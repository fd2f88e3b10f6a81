"""The reconstruction page: shots registered, sparse points and surfaces drawn over the input view,
and naming a fitted surface (marks.json)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PySide6.QtGui import QColor
from PySide6.QtWidgets import (QCheckBox, QComboBox, QFormLayout, QGroupBox, QHBoxLayout, QLineEdit, QListWidget,
                               QPushButton, QVBoxLayout, QWidget)

from reflab.app.gui import stages
from reflab.app.gui.pages.page import StepPage, draw_segments, read_image, spin
from reflab.app.gui.widgets import ImageView, text_label
from reflab.core.options import describe
from reflab.core.workspace import read_json
from reflab.reconstruction.stages import ReconstructOptions

#: What a user can say about a surface (reconstruction/marks.py's plain words).
POINT_KINDS = ["matte (paper, wood)", "glossy, textured", "glossy, one colour", "mirror", "transparent"]
POINT_WORDS = [{"matte": True}, {}, {"untextured": True}, {"mirror": True}, {"ior": 1.5}]
#: One colour per surface in the overlay.
SURFACE_COLOURS = ["#ff5050", "#50a0ff", "#50d050", "#ffb000"]


class ReconstructPage(StepPage):
    preview_stretch = 0
    run_text = "Reconstruct"

    def build(self):
        from reflab.app.devices import SimOptions  # the simulated lab's axis, where the CLI's --camera sim puts it
        from reflab.core.options import default, show

        centre = show(default(SimOptions, "centre")) if self.window.port == "sim" else ""
        self.add_option("turntable_centre", "Turntable axis x,y (m)", QLineEdit(centre),
                        describe(ReconstructOptions, "turntable_centre") + " (empty: use a target)")
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
        from reflab.calibration.camera import Camera
        from reflab.reconstruction.scene import Scene

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
        from reflab.core.images import to_display

        img = to_display(read_image(base)).copy()
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
                colour = QColor(SURFACE_COLOURS[k % len(SURFACE_COLOURS)])
                uv = cam.project(s.mesh.vertices)
                _draw_edges(img, uv, s.mesh.triangles, (colour.red(), colour.green(), colour.blue()))
        self.view.set_image(img)


def _read_ply_points(path) -> np.ndarray:
    from reflab.core.open3d_env import open3d
    o3d = open3d()

    return np.asarray(o3d.io.read_point_cloud(str(path)).points)


def _draw_edges(img: np.ndarray, uv: np.ndarray, triangles: np.ndarray, colour) -> None:
    """Draw every triangle edge onto an 8-bit image."""
    tri = np.asarray(triangles)
    draw_segments(img, uv[np.concatenate([tri[:, 0], tri[:, 1], tri[:, 2]])],
                  uv[np.concatenate([tri[:, 1], tri[:, 2], tri[:, 0]])], colour)
