"""The picture beside a capture page's instructions: the rig drawn as the step wants it set up.

A small oblique drawing (table, turntable, camera, lamps and the step's props: the circle target
flat and on its wedge, the rod and its shadow beside the grey card, the objects), painted with
QPainter so it needs no image files and stays sharp at any size. World units are decimetres,
x to the right, y away from the camera, z up.
"""
from __future__ import annotations

import numpy as np
from PySide6.QtCore import QPointF, QRectF, Qt
from PySide6.QtGui import QBrush, QColor, QFont, QPainter, QPen, QPolygonF
from PySide6.QtWidgets import QWidget

CAMERA = (-2.8, -2.4, 2.0)
LAMPS = [(2.4, 2.0, 2.3), (-2.8, 0.5, 2.2)]
TABLE = "#d9b98c"
TURNTABLE = "#9a9a9a"


class RigSketch(QWidget):
    """``RigSketch(step)``: the rig for step ``devices``, ``calibrate_camera``, ``calibrate_lights``,
    ``sweep`` or ``input`` (:data:`SKETCHED`)."""

    def __init__(self, step: str, parent=None):
        super().__init__(parent)
        self.step = step
        self.setObjectName(f"sketch_{step}")
        self.setFixedSize(270, 150)

    # -- projection ----------------------------------------------------------------------
    def at(self, x, y, z=0.0) -> QPointF:
        s = min(self.width() / 9.8, self.height() / 6.6)
        return QPointF(self.width() * 0.44 + s * (x + 0.45 * y), self.height() * 0.68 - s * (z + 0.5 * y))

    def poly(self, p: QPainter, pts, fill, outline="#555555") -> None:
        p.setPen(QPen(QColor(outline), 1))
        p.setBrush(QBrush(QColor(fill)))
        p.drawPolygon(QPolygonF([self.at(*q) for q in pts]))

    def disc(self, cx, cy, r, z=0.0, n=48):
        return [(cx + r * np.cos(a), cy + r * np.sin(a), z) for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]

    def box(self, p, centre, size, colour) -> None:
        (x, y, z), (w, d, h) = centre, size
        x0, x1, y0, y1, z1 = x - w / 2, x + w / 2, y - d / 2, y + d / 2, z + h
        c = QColor(colour)
        self.poly(p, [(x1, y0, z), (x1, y1, z), (x1, y1, z1), (x1, y0, z1)], c.darker(140))  # right side
        self.poly(p, [(x0, y0, z), (x1, y0, z), (x1, y0, z1), (x0, y0, z1)], c)  # front
        self.poly(p, [(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)], c.lighter(125))  # top

    def label(self, p, x, y, z, text, colour="#202020") -> None:
        p.setPen(QColor(colour))
        pt = self.at(x, y, z)
        p.drawText(QRectF(pt.x() - 60, pt.y() - 7, 120, 14), Qt.AlignmentFlag.AlignCenter, text)

    def turn_arrow(self, p, text) -> None:
        pts = [self.at(1.75 * np.cos(a), 1.75 * np.sin(a), 0.05) for a in np.linspace(-2.6, -0.5, 16)]
        p.setPen(QPen(QColor("#2050a0"), 2))
        for a, b in zip(pts, pts[1:]):
            p.drawLine(a, b)
        tip, before = pts[-1], pts[-3]
        d = tip - before
        d /= max(np.hypot(d.x(), d.y()), 1e-6)
        n = QPointF(-d.y(), d.x())
        p.setBrush(QColor("#2050a0"))
        p.drawPolygon(QPolygonF([tip + d * 6, tip + n * 4, tip - n * 4]))
        self.label(p, 2.2, -1.7, 0.0, text, "#2050a0")

    # -- painting ------------------------------------------------------------------------
    def paintEvent(self, event):
        p = QPainter(self)
        p.setRenderHint(QPainter.RenderHint.Antialiasing)
        dark = self.step == "input"
        p.fillRect(self.rect(), QColor("#3a3a48" if dark else "#f4f4f4"))
        p.setFont(QFont(p.font().family(), 7))
        self.poly(p, [(-3.5, -2.2, 0), (3.5, -2.2, 0), (3.5, 2.8, 0), (-3.5, 2.8, 0)], TABLE, "#a08060")
        self.poly(p, self.disc(0, 0, 1.5, -0.15), QColor(TURNTABLE).darker(130))
        self.poly(p, self.disc(0, 0, 1.5), TURNTABLE)
        lit = self.step in ("calibrate_lights", "input")
        getattr(self, f"_{self.step}")(p)
        for k, lamp in enumerate(LAMPS):
            self.lamp(p, lamp, k, lit)
        self.camera(p)
        if dark:
            self.label(p, 0.5, 2.8, 2.2, "room dark", "#e0e0e0")
        p.end()

    def lamp(self, p, pos, k, lit) -> None:
        c = self.at(*pos)
        if lit:
            p.setPen(QPen(QColor("#ffc000"), 1.5))
            for a in np.linspace(0, 2 * np.pi, 8, endpoint=False):
                p.drawLine(c + QPointF(9 * np.cos(a), 9 * np.sin(a)), c + QPointF(14 * np.cos(a), 14 * np.sin(a)))
        p.setPen(QPen(QColor("#404040"), 1))
        p.setBrush(QColor("#ffd84a" if lit else "#fff6cc"))
        p.drawEllipse(c, 7, 7)
        self.label(p, pos[0], pos[1], pos[2] + 0.9, f"lamp {k}", "#e0e0e0" if self.step == "input" else "#202020")

    def camera(self, p) -> None:
        c = self.at(*CAMERA)
        look = self.at(0, 0, 0.3) - c
        look /= max(np.hypot(look.x(), look.y()), 1e-6)
        p.setPen(QPen(QColor("#2050a0"), 1, Qt.PenStyle.DashLine))
        p.drawLine(c, self.at(0, 0, 0.3))
        p.setPen(QPen(QColor("#202020"), 1))
        p.setBrush(QColor("#303030"))
        p.drawRoundedRect(QRectF(c.x() - 13, c.y() - 9, 26, 18), 3, 3)
        p.setBrush(QColor("#7090c0"))
        p.drawEllipse(c + look * 11, 5, 5)
        self.label(p, CAMERA[0], CAMERA[1], CAMERA[2] + 1.0, "camera", "#e0e0e0" if self.step == "input" else "#202020")

    def target(self, p, corners, cols=6, rows=4) -> None:
        """The circle target on the quad ``corners`` (3D, in order around it)."""
        self.poly(p, corners, "#fbf6e8")
        a, b, _, d = (np.asarray(q, float) for q in corners)
        p.setPen(Qt.PenStyle.NoPen)
        p.setBrush(QColor("#303030"))
        for i in range(cols):
            for j in range(rows):
                q = a + (b - a) * (i + 0.5) / cols + (d - a) * (j + 0.5) / rows
                p.drawEllipse(self.at(*q), 1.6, 1.6)

    def objects(self, p) -> None:
        self.box(p, (0.45, 0.3, 0.0), (0.9, 0.7, 0.6), "#b070b0")
        self.poly(p, [(-0.9, -0.6, 0), (-0.1, -0.6, 0), (-0.1, -0.5, 0.9), (-0.9, -0.5, 0.9)], "#80a8e0")  # sheet
        self.box(p, (-0.3, 0.9, 0.0), (1.3, 0.1, 0.9), "#c8d8e0")  # mirror

    # -- one drawing per step --------------------------------------------------------------
    def _devices(self, p) -> None:
        self.box(p, (2.7, -1.6, 0.0), (1.0, 0.6, 0.35), "#207040")
        self.label(p, 2.7, -1.6, -0.6, "board (USB)")
        p.setPen(QPen(QColor("#404040"), 1.2))
        board = self.at(2.7, -1.6, 0.35)
        for end in [self.at(1.3, -0.4, 0.0)] + [self.at(*lamp) for lamp in LAMPS]:
            p.drawLine(board, end)
        self.label(p, 0, 0, -0.5, "turntable")

    def _calibrate_camera(self, p) -> None:
        self.target(p, [(-3.3, -2.0, 0), (-1.7, -2.0, 0), (-1.7, -1.0, 0), (-3.3, -1.0, 0)])
        self.label(p, -2.5, -2.0, -0.5, "1. flat")
        self.poly(p, [(-0.8, -0.5, 0), (0.8, -0.5, 0), (0.8, 0.5, 0.8), (-0.8, 0.5, 0.8)], "#c8a070")  # wedge
        self.target(p, [(-0.7, -0.45, 0.05), (0.7, -0.45, 0.05), (0.7, 0.45, 0.77), (-0.7, 0.45, 0.77)])
        self.label(p, 0.3, 0.5, 1.5, "2. on its wedge")
        self.turn_arrow(p, "each angle")

    def _calibrate_lights(self, p) -> None:
        self.poly(p, [(-3.2, 0.3, 0), (-2.1, 0.3, 0), (-2.1, 1.2, 0), (-3.2, 1.2, 0)], "#909090")
        self.label(p, -2.65, 0.3, -0.45, "grey card")
        foot, top = (0.8, -0.2, 0.0), (0.8, -0.2, 1.3)
        away = np.asarray(foot[:2]) - np.asarray(LAMPS[0][:2])
        tip = (*(np.asarray(foot[:2]) + 1.6 * away / np.linalg.norm(away)), 0.0)  # lamp 0's shadow of the rod
        p.setPen(QPen(QColor("#505050"), 3))
        p.drawLine(self.at(*foot), self.at(*tip))
        p.setPen(QPen(QColor("#7a4a20"), 3))
        p.drawLine(self.at(*foot), self.at(*top))
        self.label(p, 0.8, -0.2, 1.75, "rod, off the axis")
        self.label(p, tip[0], tip[1], -0.45, "shadow tip")

    def _sweep(self, p) -> None:
        self.objects(p)
        self.turn_arrow(p, "full circle")

    def _input(self, p) -> None:
        self.objects(p)
        self.label(p, 0.0, -1.5, -0.7, "back at the input pose", "#e0e0e0")


#: The steps that have something to set up at the rig, hence a picture.
SKETCHED = ("devices", "calibrate_camera", "calibrate_lights", "sweep", "input")
