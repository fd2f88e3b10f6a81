"""Image view with zoom and click-to-mark, an error-against-time plot, and small helpers."""
from __future__ import annotations

import numpy as np
from PySide6.QtCore import QPointF, QRectF, Qt, Signal
from PySide6.QtGui import QBrush, QColor, QFont, QImage, QPainter, QPainterPath, QPen, QPixmap
from PySide6.QtWidgets import (QGraphicsEllipseItem, QGraphicsItem, QGraphicsPixmapItem, QGraphicsScene,
                               QGraphicsSimpleTextItem, QGraphicsView, QLabel, QWidget)


def to_qimage(img: np.ndarray, exposure: float | None = None) -> QImage:
    """A QImage of a linear float image (sRGB-encoded for display) or of an 8-bit one."""
    from reflab.core.images import to_display

    a = np.asarray(img)
    if a.dtype != np.uint8:
        a = to_display(a, exposure)
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    a = np.ascontiguousarray(a[:, :, :3])
    h, w = a.shape[:2]
    return QImage(a.data, w, h, 3 * w, QImage.Format.Format_RGB888).copy()


class _Mark(QGraphicsEllipseItem):
    """A draggable mark centred on a pixel; tells its view when it was dropped."""

    def __init__(self, view: "ImageView", key, colour: str, label: str):
        r = 4.0
        super().__init__(-r, -r, 2 * r, 2 * r)
        self.view, self.key = view, key
        self.setPen(QPen(QColor(colour), 2))
        self.setBrush(QBrush(QColor(0, 0, 0, 0)))
        self.setFlags(QGraphicsItem.GraphicsItemFlag.ItemIsMovable | QGraphicsItem.GraphicsItemFlag.ItemIgnoresTransformations
                      | QGraphicsItem.GraphicsItemFlag.ItemSendsGeometryChanges)
        self.setCursor(Qt.CursorShape.SizeAllCursor)
        self.text = QGraphicsSimpleTextItem(label, self)
        self.text.setBrush(QBrush(QColor(colour)))
        self.text.setPos(6, -16)

    def mouseReleaseEvent(self, event):
        super().mouseReleaseEvent(event)
        u, v = self.view.pixel_of(self.pos())
        self.view.mark_moved.emit(self.key, u, v)


class ImageView(QGraphicsView):
    """An image (numpy, linear or 8-bit) with wheel zoom, drag to pan, and marks.

    Pixel coordinates follow docs/formats.md: (0, 0) is the centre of the top-left pixel. A left
    click on the image (not on a mark) emits ``clicked(u, v)``; dropping a mark emits
    ``mark_moved(key, u, v)``.
    """

    clicked = Signal(float, float)
    mark_moved = Signal(object, float, float)

    def __init__(self, parent=None, placeholder: str = "no image yet"):
        super().__init__(parent)
        self.setScene(QGraphicsScene(self))
        self.setRenderHint(QPainter.RenderHint.Antialiasing)
        self.setTransformationAnchor(QGraphicsView.ViewportAnchor.AnchorUnderMouse)
        self.setDragMode(QGraphicsView.DragMode.ScrollHandDrag)
        self.setBackgroundBrush(QColor(40, 40, 40))
        self.pixmap = QGraphicsPixmapItem()
        self.pixmap.setTransformationMode(Qt.TransformationMode.FastTransformation)
        self.scene().addItem(self.pixmap)
        self.placeholder = self.scene().addSimpleText(placeholder)
        self.placeholder.setBrush(QBrush(QColor(200, 200, 200)))
        self.marks: dict = {}
        self.array = None
        self._zoomed = False
        self.banner = ""  # drawn over the view's top-left corner (the rig's state: "all lamps off")
        self.setMinimumSize(160, 120)

    #: The banner's colours: black on amber, readable over any image.
    BANNER_BACK = QColor(255, 190, 0)

    def set_banner(self, text: str) -> None:
        """Draw ``text`` over the view (fixed to its corner whatever the zoom); '' removes it."""
        if text != self.banner:
            self.banner = text
            self.viewport().update()

    def set_placeholder(self, text: str) -> None:
        """The text shown while there is no image."""
        self.placeholder.setText(text)

    def drawForeground(self, painter, rect):
        super().drawForeground(painter, rect)
        if not self.banner:
            return
        painter.save()
        painter.resetTransform()
        metrics = painter.fontMetrics()
        box = QRectF(6, 6, metrics.horizontalAdvance(self.banner) + 16, metrics.height() + 8)
        painter.fillRect(box, self.BANNER_BACK)
        painter.setPen(QColor(0, 0, 0))
        painter.drawText(box, Qt.AlignmentFlag.AlignCenter, self.banner)
        painter.restore()

    # -- image --------------------------------------------------------------------------
    def set_image(self, img, exposure: float | None = None) -> None:
        first = self.array is None or np.shape(img)[:2] != np.shape(self.array)[:2]
        self.array = np.asarray(img)
        self.pixmap.setPixmap(QPixmap.fromImage(to_qimage(img, exposure)))
        self.placeholder.setVisible(False)
        self.scene().setSceneRect(self.pixmap.boundingRect())
        if first or not self._zoomed:
            self.fit()

    def fit(self) -> None:
        self._zoomed = False
        if self.array is not None:
            self.fitInView(self.pixmap, Qt.AspectRatioMode.KeepAspectRatio)

    def zoom(self, factor: float) -> None:
        self._zoomed = True
        self.scale(factor, factor)

    def wheelEvent(self, event):
        self.zoom(1.25 if event.angleDelta().y() > 0 else 0.8)

    def resizeEvent(self, event):
        super().resizeEvent(event)
        if not self._zoomed:
            self.fit()

    def mouseDoubleClickEvent(self, event):
        self.fit()

    # -- marks --------------------------------------------------------------------------
    @staticmethod
    def pixel_of(pos: QPointF) -> tuple[float, float]:
        return pos.x() - 0.5, pos.y() - 0.5

    def set_mark(self, key, u: float, v: float, colour: str = "#ffcc00", label: str = "") -> None:
        item = self.marks.get(key)
        if item is None:
            item = self.marks[key] = _Mark(self, key, colour, label)
            self.scene().addItem(item)
        item.setPos(u + 0.5, v + 0.5)

    def clear_marks(self) -> None:
        for item in self.marks.values():
            self.scene().removeItem(item)
        self.marks = {}

    def mark_positions(self) -> dict:
        return {k: self.pixel_of(item.pos()) for k, item in self.marks.items()}

    def mousePressEvent(self, event):
        item = self.itemAt(event.position().toPoint())
        if event.button() == Qt.MouseButton.LeftButton and self.array is not None and not isinstance(item, _Mark) \
                and not isinstance(getattr(item, "parentItem", lambda: None)(), _Mark):
            if event.modifiers() & Qt.KeyboardModifier.ShiftModifier:  # shift-drag pans
                return super().mousePressEvent(event)
            pos = self.mapToScene(event.position().toPoint())
            h, w = self.array.shape[:2]
            u, v = self.pixel_of(pos)
            if -0.5 <= u < w - 0.5 and -0.5 <= v < h - 0.5:
                self.clicked.emit(u, v)
                return
        super().mousePressEvent(event)


class Curve(QWidget):
    """A small line plot of (x, y) series with a log y axis: the fit's error against time."""

    def __init__(self, xlabel: str = "seconds", ylabel: str = "RMS error", parent=None):
        super().__init__(parent)
        self.xlabel, self.ylabel = xlabel, ylabel
        self.series: list[tuple[str, QColor, np.ndarray]] = []
        self.setMinimumSize(240, 160)

    def set_series(self, series) -> None:
        """``series``: list of (label, colour, (N, 2) points)."""
        self.series = [(label, QColor(colour), np.asarray(pts, float).reshape(-1, 2)) for label, colour, pts in series]
        self.update()

    def paintEvent(self, event):
        p = QPainter(self)
        p.setRenderHint(QPainter.RenderHint.Antialiasing)
        p.fillRect(self.rect(), QColor("white"))
        pts = [s[2] for s in self.series if len(s[2])]
        left, right, top, bottom = 56, 12, 12, 30
        plot = QRectF(left, top, max(self.width() - left - right, 10), max(self.height() - top - bottom, 10))
        p.setPen(QPen(QColor("#888")))
        p.drawRect(plot)
        p.setFont(QFont(p.font().family(), 8))
        p.drawText(QRectF(left, self.height() - 16, plot.width(), 14), Qt.AlignmentFlag.AlignCenter, self.xlabel)
        if not pts:
            p.drawText(plot, Qt.AlignmentFlag.AlignCenter, "no data yet")
            return
        allp = np.concatenate(pts)
        allp = allp[np.isfinite(allp).all(axis=1) & (allp[:, 1] > 0)]
        if not len(allp):
            return
        x0, x1 = float(allp[:, 0].min()), float(allp[:, 0].max())
        y0, y1 = np.log10(allp[:, 1].min()), np.log10(allp[:, 1].max())
        x1, y1 = (x1 if x1 > x0 else x0 + 1.0), (y1 if y1 > y0 + 1e-9 else y0 + 0.5)

        def at(x, y):
            return QPointF(plot.left() + (x - x0) / (x1 - x0) * plot.width(),
                           plot.bottom() - (np.log10(y) - y0) / (y1 - y0) * plot.height())

        p.drawText(QRectF(0, top - 6, left - 4, 14), Qt.AlignmentFlag.AlignRight, f"{10 ** y1:.3g}")
        p.drawText(QRectF(0, plot.bottom() - 8, left - 4, 14), Qt.AlignmentFlag.AlignRight, f"{10 ** y0:.3g}")
        p.drawText(QRectF(plot.left(), plot.bottom() + 1, 60, 14), Qt.AlignmentFlag.AlignLeft, f"{x0:.3g}")
        p.drawText(QRectF(plot.right() - 60, plot.bottom() + 1, 60, 14), Qt.AlignmentFlag.AlignRight, f"{x1:.3g}")
        p.save()
        p.translate(10, plot.center().y())
        p.rotate(-90)
        p.drawText(QRectF(-60, -8, 120, 14), Qt.AlignmentFlag.AlignCenter, self.ylabel)
        p.restore()
        for i, (label, colour, s) in enumerate(self.series):
            s = s[np.isfinite(s).all(axis=1) & (s[:, 1] > 0)]
            if not len(s):
                continue
            path = QPainterPath(at(*s[0]))
            for x, y in s[1:]:
                path.lineTo(at(x, y))
            p.setPen(QPen(colour, 2))
            p.drawPath(path)
            p.drawText(QPointF(plot.right() - 110, plot.top() + 14 + 14 * i), label)


def text_label(text: str = "", name: str | None = None, wrap: bool = True) -> QLabel:
    label = QLabel(text)
    label.setWordWrap(wrap)
    label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
    if name:
        label.setObjectName(name)
    return label
