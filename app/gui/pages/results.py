"""The results page: the model against the photograph, a novel view under dimmed lamps, and the
model exported for outside tools (``reflab export``'s stage function, on a worker thread)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import (QComboBox, QFileDialog, QFormLayout, QGridLayout, QGroupBox, QHBoxLayout, QLineEdit,
                               QPushButton, QSlider, QVBoxLayout, QWidget)

from reflab.app.gui.pages.page import StepPage, fmt, read_image, refill, table
from reflab.app.gui.widgets import ImageView, text_label
from reflab.core.workspace import Workspace


PARAM_HEADERS = ["surface", "parameter", "value ± σ", "determined by"]


def parameter_rows(fit: dict) -> list:
    """fit.json's surfaces as rows: surface, parameter, value ± σ per band (or "undetermined"),
    and the photographs holding ≥ 10 % of its information (several photographs)."""
    rows = []
    for s in fit.get("surfaces", []) if isinstance(fit, dict) else []:
        mat, sig = s.get("material") or {}, s.get("sigma") or {}
        und, by = set(s.get("undetermined") or []), s.get("determined_by") or {}
        for key, value in mat.items():
            if key in ("brdf", "ior") or value is None:
                continue
            from reflab.app.report.sections.fit import value_text

            shown = value_text(mat.get("brdf", ""), key, mat, sig.get(key),
                               [u for u in und if u == key or u.startswith(key + "[")])
            if "undetermined" in shown:  # its plausible range, as the report shows it, never a σ wider than it
                text = f"{shown}; {'held' if sig.get(key) is None else 'fitted'} at {fmt(value)}"
            else:
                sd = sig.get(key)
                text = f"{fmt(value)} ± {fmt(sd, 2)}" if sd is not None else f"{fmt(value)} (given)"
            who = sorted({p for k, v in by.items() if k == key or k.startswith(key + "[") for p in v})
            rows.append([s.get("name"), key, text, ", ".join(who) or ("input" if key not in und and sig.get(key) else "")])
    return rows


class ResultsPage(StepPage):
    preview_stretch = 0
    run_text = "Re-render and report"
    #: A novel view ended: (ok, its description or the failure's message).
    novel_rendered = Signal(bool, str)
    #: An export ended: (ok, what it wrote or the failure's message).
    exported = Signal(bool, str)

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
        pw = QWidget()
        self.params_layout = QVBoxLayout(pw)
        self.params_table = table("results_parameters", PARAM_HEADERS, [])
        self.params_layout.addWidget(self.params_table)
        self.tab(pw, "Parameters")
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
        self.tab(self._build_export(), "Export")

    def _build_export(self) -> QWidget:
        """``reflab export`` from the window: a format, a folder (asked for), Export, a status line."""
        from reflab.core.options import describe
        from reflab.inverse.export.stage import FORMATS, ExportOptions

        ex = QWidget()
        form = QFormLayout(ex)
        self.export_format = QComboBox()
        self.export_format.setObjectName("export_format")
        self.export_format.addItems(FORMATS)
        self.export_format.setToolTip(describe(ExportOptions, "format"))
        self.export_format.currentTextChanged.connect(self._default_export_folder)
        form.addRow("format", self.export_format)
        folder = QHBoxLayout()
        self.export_output = QLineEdit()
        self.export_output.setObjectName("export_output")
        self.export_output.setToolTip(describe(ExportOptions, "output"))
        folder.addWidget(self.export_output, 1)
        choose = QPushButton("Choose…")
        choose.setObjectName("export_choose")
        choose.clicked.connect(self.choose_export_folder)
        folder.addWidget(choose)
        form.addRow("folder", folder)
        self.export_button = QPushButton("Export")
        self.export_button.setObjectName("export_run")
        self.export_button.clicked.connect(self.run_export)
        form.addRow(self.export_button)
        self.export_info = text_label("Mitsuba 3 scene, glTF 2.0 binary (.glb) or PLY meshes with their textures: the "
                                      "same files as reflab export (docs/export.md).", "export_status")
        form.addRow(self.export_info)
        self._default_export_folder()
        return ex

    def _default_export_folder(self, _=None) -> None:
        self.export_output.setText(str(self.ws.export(self.export_format.currentText())))

    def choose_export_folder(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Export into folder", self.export_output.text())
        if folder:
            self.export_output.setText(folder)

    def run_export(self) -> None:
        from reflab.inverse.export.stage import ExportOptions, export

        fmt_name, out = self.export_format.currentText(), self.export_output.text().strip()
        options = ExportOptions(self.window.workspace, format=fmt_name, output=Path(out) if out else None)
        self.export_button.setEnabled(False)
        self.export_info.setText(f"running: exporting {fmt_name}…")
        self.window.background(lambda task: export(options, task), self._export_done, "export")

    def _export_done(self, ok: bool, result) -> None:
        self.export_button.setEnabled(True)
        if not ok:
            self.export_info.setText(f"failed: {result}")
            self.exported.emit(False, str(result))
            return
        n = len(result.written)
        text = f"done: wrote {result.path} ({len(result.notes)} surfaces, {n} file{'' if n == 1 else 's'})"
        if result.warnings:
            text += "; " + "; ".join(result.warnings)
        self.export_info.setText(text)
        self.exported.emit(True, text)

    def refresh(self):
        self._refresh_parameters()
        ws = self.ws
        if not ws.render().exists() or not ws.input_image.exists():
            self.summary.setText(self.nothing_yet("re-render"))
            return
        photo, model = read_image(ws.input_image), read_image(ws.render())
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

    def _refresh_parameters(self):
        """Each fitted parameter: value ± σ (or undetermined) and the photographs that determined it."""
        from reflab.core.workspace import WorkspaceError, read_json

        try:
            fit = read_json(self.ws.fit) if self.ws.fit.exists() else {}
        except WorkspaceError:
            fit = {}
        rows = parameter_rows(fit)
        refill(self.params_table, rows, {(i, 2) for i, r in enumerate(rows) if r[2].startswith("undetermined")})

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

    from reflab.calibration.rotations import axis_rotation

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

    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights
    from reflab.inverse.stages import render_workspace

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
    guess = float(np.mean(info["undetermined_pixels"]))
    if guess:  # docs/fit.md, "Renders that say where they guess"
        text += f"; {100 * guess:.0f}% of the pixels rest on values the photograph did not determine (a guess)"
    return image, text
