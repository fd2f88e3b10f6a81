"""Open the guided lab window over WORKSPACE: one page per step from devices to the model.

`--port sim --camera sim` runs it on the simulated lab (hardware/sim/). An existing workspace
reopens at its first missing step. docs/gui.md shows every page.
"""
from __future__ import annotations

import argparse

from reflab.app.commands._args import image_size
from reflab.app.devices import SIM_SIZE

HELP = "the guided lab window: devices, calibration, sweep, reconstruction, input, fit, texture, results"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("workspace", nargs="?", default="workspace", help="workspace folder (default ./workspace)")
    parser.add_argument("--port", default="sim", help="serial port of the GRBL board, or 'sim' (default)")
    parser.add_argument("--camera", default="sim", help="sim (default) | opencv:N | folder:PATH")
    parser.add_argument("--size", type=image_size, default=SIM_SIZE,
                        help="simulated camera image size (480x360: at 320x240 the simulated sweep does not reconstruct)")


def run(args) -> int:
    import sys

    from PySide6.QtWidgets import QApplication

    from reflab.app.gui import MainWindow

    app = QApplication.instance() or QApplication(sys.argv[:1])
    window = MainWindow(args.workspace, port=args.port, camera=args.camera, size=args.size)
    window.show()
    return app.exec()
