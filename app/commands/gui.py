"""Open the guided lab window over WORKSPACE: one page per step from devices to the model.

`--port sim --camera sim` runs it on the simulated lab (hardware/sim/). An existing workspace
reopens at its first missing step. docs/gui.md shows every page.
"""
from __future__ import annotations

import argparse

HELP = "the guided lab window: devices, calibration, sweep, reconstruction, input, fit, texture, results"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("workspace", nargs="?", default="workspace", help="workspace folder (default ./workspace)")
    parser.add_argument("--port", default="sim", help="serial port of the GRBL board, or 'sim' (default)")
    parser.add_argument("--camera", default="sim", help="the camera to photograph with: sim (default) | opencv:N | folder:PATH")
    from reflab.app.devices import SimOptions
    from reflab.core.options import add_arguments as table_arguments

    table_arguments(parser, SimOptions, only=("size",))


def run(args) -> int:
    import sys

    from PySide6.QtWidgets import QApplication

    from reflab.app.gui import MainWindow

    app = QApplication.instance() or QApplication(sys.argv[:1])
    window = MainWindow(args.workspace, port=args.port, camera=args.camera, size=args.size)
    window.show()
    return app.exec()
