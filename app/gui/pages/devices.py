"""The devices page: connect the rig, turn the turntable, switch the lamps."""
from __future__ import annotations

from PySide6.QtWidgets import (QCheckBox, QGridLayout, QGroupBox, QHBoxLayout, QLabel, QPushButton, QVBoxLayout,
                               QWidget)

from reflab.app.gui.pages.page import StepPage, spin
from reflab.app.gui.widgets import text_label


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
                box.setChecked(bool(on))

    def refresh(self):
        self.show_connection(self.window.rig.status() if self.window.rig.connected else None)
