"""Screenshots of every page of the guided lab window, for docs/gui.md.

    QT_QPA_PLATFORM=offscreen .venv/bin/python docs/figures/gui_screenshots.py WORKSPACE [OUTDIR (default docs/img)]

Drives ``reflab.app.gui.MainWindow`` through the whole acquisition on the simulated lab at 480x360, each
step by its Run button, from an empty WORKSPACE; no truth is handed to any stage. The one thing
not done through the window is the corner marking, which the simulated user
(hardware/sim/user.py) writes into marks.json as the sweep page would. Writes gui-<step>.png
(and gui-fit-1.png, gui-results-1.png: the pages' second tabs, gui-results-2.png: the results
page's Export tab after a glTF export, gui-sweep-running.png: the sweep while it runs) as 256-colour PNGs, and prints each step's time.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from PIL import Image  # noqa: E402
from PySide6.QtCore import QEventLoop, QTimer  # noqa: E402
from PySide6.QtWidgets import QApplication  # noqa: E402

SIZE = (480, 360)


def wait(signal, timeout_s: float = 900.0) -> tuple:
    """Run the event loop until ``signal`` fires; its arguments."""
    loop, got = QEventLoop(), []
    signal.connect(lambda *args: (got.append(args), loop.quit()))
    QTimer.singleShot(int(timeout_s * 1000), loop.quit)
    loop.exec()
    if not got:
        raise TimeoutError(f"no signal in {timeout_s} s")
    return got[0]


def main(ws: Path, out: Path) -> None:
    from reflab.app.gui import MainWindow
    from reflab.hardware.sim.lab import build_lab
    from reflab.hardware.sim.user import mark_sweep
    from reflab.core.workspace import Workspace, read_json

    app = QApplication.instance() or QApplication(sys.argv[:1])
    window = MainWindow(ws, "sim", "sim", size=SIZE, live_preview_ms=0)
    window.show()
    out.mkdir(parents=True, exist_ok=True)

    def shot(name: str) -> None:
        app.processEvents()
        path = out / f"gui-{name}.png"
        window.grab().save(str(path))
        Image.open(path).convert("RGB").quantize(256).save(path, optimize=True)

    def live(step: str) -> None:
        window.pages[step].preview.set_image(window.rig.preview(blocking=True))

    def run(step: str) -> None:
        window.go_to(step)
        start = time.monotonic()
        window.run_step(step)
        name, outcome = wait(window.step_finished)
        print(f"{step}: {outcome} in {time.monotonic() - start:.0f} s: {window.pages[step].status.text()}", flush=True)
        if outcome != "done":
            raise SystemExit(1)

    run("devices")
    window.hardware_action("lamp", 0, True)
    wait(window.hardware_done)
    live("devices")
    shot("devices")

    for step in ("calibrate_camera", "calibrate_lights"):
        run(step)
        live(step)
        shot(step)

    window.go_to("sweep")
    window.run_step("sweep")
    taken = []
    window.worker.progress.connect(lambda done, total, msg: done >= 12 and not taken and (taken.append(done),
                                                                                            shot("sweep-running")))
    start = time.monotonic()
    print(f"sweep: {wait(window.step_finished)[1]} in {time.monotonic() - start:.0f} s", flush=True)
    mark_sweep(ws, build_lab(*SIZE), read_json(Workspace(ws).manifest("sweep")))
    page = window.pages["sweep"]
    page.refresh()
    page.surface.setCurrentText("mirror")
    page.shots.setCurrentRow(1)
    live("sweep")
    shot("sweep")

    for step in ("reconstruct", "input", "fit"):
        run(step)
        live(step)
        window.pages[step].tabs.setCurrentIndex(0)
        shot(step)
    window.pages["fit"].tabs.setCurrentIndex(1)
    shot("fit-1")

    for step in ("texture", "results"):
        run(step)
        live(step)
        shot(step)
    page = window.pages["results"]
    page.tabs.setCurrentIndex(1)
    page.azimuth.setValue(-35)
    page.elevation.setValue(8)
    page.dimmers[1].setValue(20)
    page.render_novel()
    print(wait(page.novel_rendered)[1], flush=True)
    shot("results-1")
    page.tabs.setCurrentIndex(page.tabs.count() - 1)  # Export
    page.export_format.setCurrentText("gltf")
    page.run_export()
    print(wait(page.exported)[1], flush=True)
    shot("results-2")
    window.close()


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]) if len(sys.argv) > 2 else Path(__file__).resolve().parents[1] / "img")
