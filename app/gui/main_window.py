"""The guided lab window: a step list, one page per step, progress, cancel and a log pane.

Object names are part of docs/formats.md's contract (GUI): ``steps``, ``page_<step>``,
``run_<step>``, ``status_<step>``, ``progress``, ``cancel``. One step runs at a time, in a
:class:`reflab.app.gui.worker.Worker` thread; its Task is what ``cancel`` stops. The window emits
:attr:`MainWindow.step_finished` ``(step, outcome)`` with outcome ``done``, ``failed`` or
``cancelled`` once a step's thread has ended (tests wait on it).
"""
from __future__ import annotations

import re
import time
from pathlib import Path

from PySide6.QtCore import Qt, QTimer, Signal, Slot
from PySide6.QtGui import QColor, QFont, QKeySequence, QShortcut
from PySide6.QtWidgets import (QHBoxLayout, QLabel, QListWidget, QListWidgetItem, QMainWindow, QMessageBox,
                               QPlainTextEdit, QProgressBar, QPushButton, QSplitter, QStackedWidget, QVBoxLayout,
                               QWidget)

from reflab.app.devices import SIM_SIZE
from reflab.app.gui import stages
from reflab.app.gui.pages.calibrate_camera import CameraPage
from reflab.app.gui.pages.calibrate_lights import LightsPage
from reflab.app.gui.pages.devices import DevicesPage
from reflab.app.gui.pages.fit import FitPage
from reflab.app.gui.pages.input import InputPage
from reflab.app.gui.pages.reconstruct import ReconstructPage
from reflab.app.gui.pages.results import ResultsPage
from reflab.app.gui.pages.sweep import SweepPage
from reflab.app.gui.pages.texture import TexturePage
from reflab.app.gui.rig import Rig
from reflab.app.gui.worker import Worker


#: "…, RMS per band [a, b, c]" in a stage's progress message (the fit's iterations).
#: Each step's page.
PAGES = {"devices": DevicesPage, "calibrate_camera": CameraPage, "calibrate_lights": LightsPage, "sweep": SweepPage,
         "reconstruct": ReconstructPage, "input": InputPage, "fit": FitPage, "texture": TexturePage,
         "results": ResultsPage}
RMS_IN_MESSAGE = re.compile(r"RMS per band \[([^\]]+)\]")


def progress_text(done: float, total: float, message: str) -> str:
    """The progress bar's text: a capture's "<kind>: <file>" as "<kind>: shot 3 of 36 (<file>)", another
    stage's message with its count."""
    from reflab.hardware.capture import FOLDERS

    kind, _, file = (message or "").partition(": ")
    if kind in FOLDERS and file and " " not in file and total > 0:
        return f"{kind}: shot {done:.0f} of {total:.0f} ({file})"
    return f"{message} ({done:.0f} of {total:.0f})" if message and total > 0 else message or "%p%"


class MainWindow(QMainWindow):
    """``MainWindow(workspace, port="sim", camera="sim")``: the wizard over one workspace.

    Parameters
    ----------
    workspace : path-like
        Created when missing; an existing one reopens at its first missing step.
    port, camera : str
        As ``reflab capture``'s ``--port`` and ``--camera`` (``sim`` = the simulated lab).
    size : (int, int)
        Image size of the simulated camera.
    live_preview_ms : int
        Interval of the live camera view (0 turns it off).
    options : dict, optional
        ``{step: {option: value}}`` set on the pages' option widgets (tests, scripts).
    """

    step_finished = Signal(str, str)
    hardware_done = Signal(bool, str)  # a jog or lamp switch ended: (ok, status line or message)
    log_line = Signal(str)

    def __init__(self, workspace, port: str = "sim", camera: str = "sim", *, size=SIM_SIZE,
                 live_preview_ms: int = 1500, options: dict | None = None):
        super().__init__()
        self.workspace = Path(workspace)
        self.workspace.mkdir(parents=True, exist_ok=True)
        self.port, self.camera = port, camera
        self.rig = Rig(self.workspace, port, camera, size=size, log=self.log_line.emit)
        self.worker: Worker | None = None
        self.running: str | None = None
        self._background: list[Worker] = []
        self._preview: Worker | None = None
        self._last_message = ""
        self._preview_next = 0.0
        self.setWindowTitle(f"reflab — {self.workspace}")
        self.log_line.connect(self._append_log)

        self.step_list = QListWidget()
        self.step_list.setObjectName("steps")
        self.step_list.setMinimumWidth(200)
        self.step_list.setMaximumWidth(260)
        self.stack = QStackedWidget()
        self.stack.setObjectName("pages")
        self.pages = {}
        for step in stages.STEPS:
            item = QListWidgetItem(step.title)
            item.setData(Qt.ItemDataRole.UserRole, step.name)
            self.step_list.addItem(item)
            page = PAGES[step.name](step, self)
            self.pages[step.name] = page
            self.stack.addWidget(page)
        self.step_list.currentRowChanged.connect(self._show_page)

        self.progress = QProgressBar()
        self.progress.setObjectName("progress")
        self.progress.setRange(0, 1000)
        self.progress.setValue(0)
        self.progress.setFormat("idle")
        self.progress.setTextVisible(True)
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setObjectName("cancel")
        self.cancel_button.setEnabled(False)
        self.cancel_button.clicked.connect(self.cancel)
        self.pause_button = QPushButton("Pause")
        self.pause_button.setObjectName("pause")
        self.pause_button.setCheckable(True)
        self.pause_button.setEnabled(False)
        self.pause_button.toggled.connect(self.pause)
        self.log_pane = QPlainTextEdit()
        self.log_pane.setObjectName("log")
        self.log_pane.setReadOnly(True)
        self.log_pane.setMaximumBlockCount(5000)
        self.log_pane.setFont(QFont("monospace", 8))

        top = QSplitter(Qt.Orientation.Horizontal)
        top.addWidget(self.step_list)
        top.addWidget(self.stack)
        top.setStretchFactor(1, 1)
        bar = QHBoxLayout()
        bar.addWidget(self.progress, 1)
        bar.addWidget(self.pause_button)
        bar.addWidget(self.cancel_button)
        bottom = QWidget()
        bl = QVBoxLayout(bottom)
        bl.setContentsMargins(0, 0, 0, 0)
        bl.addLayout(bar)
        bl.addWidget(QLabel("Log"))
        bl.addWidget(self.log_pane)
        vsplit = QSplitter(Qt.Orientation.Vertical)
        vsplit.addWidget(top)
        vsplit.addWidget(bottom)
        vsplit.setStretchFactor(0, 5)
        vsplit.setStretchFactor(1, 1)
        central = QWidget()
        QVBoxLayout(central).addWidget(vsplit)
        self.setCentralWidget(central)
        self.resize(1280, 860)

        defaults = stages.sim_defaults() if camera == "sim" else {}
        for name, values in list(defaults.items()) + list((options or {}).items()):
            self.set_options(name, **values)
        self.refresh_steps()
        for page in self.pages.values():
            page.refresh()
        self.step_list.setCurrentRow(stages.resume_index(self.workspace))

        # Standard shortcuts: Ctrl+Q quits (asking first while a step runs), Esc cancels the running step.
        self.quit_shortcut = QShortcut(QKeySequence("Ctrl+Q"), self, self.close)
        self.cancel_shortcut = QShortcut(QKeySequence(Qt.Key.Key_Escape), self, self.cancel)

        self.preview_timer = QTimer(self)
        self.preview_timer.timeout.connect(self._tick_preview)
        if live_preview_ms:
            self.preview_timer.start(live_preview_ms)

    # ------------------------------------------------------------------ pages and steps
    def page(self, name: str):
        return self.pages[name]

    def current_step(self) -> str:
        return stages.NAMES[self.step_list.currentRow()]

    def go_to(self, name: str) -> None:
        self.step_list.setCurrentRow(stages.NAMES.index(name))

    def _show_page(self, row: int) -> None:
        if row >= 0:
            self.stack.setCurrentIndex(row)

    def set_options(self, name: str, **values) -> None:
        """Set a page's option widgets (``spin``, ``line edit``, ``check box``) by key."""
        from PySide6.QtWidgets import QCheckBox, QComboBox, QDoubleSpinBox, QSpinBox

        widgets = self.pages[name]._options
        for key, value in values.items():
            w = widgets[key]
            if isinstance(w, QCheckBox):
                w.setChecked(bool(value))
            elif isinstance(w, (QSpinBox, QDoubleSpinBox)):
                w.setValue(value)
            elif isinstance(w, QComboBox):
                w.setCurrentText(str(value))
            else:
                w.setText(str(value))

    def refresh_steps(self) -> None:
        """Tick the steps that are done, from the workspace's files."""
        for i, step in enumerate(stages.STEPS):
            item = self.step_list.item(i)
            done = step.done(self.workspace)
            running = step.name == self.running
            item.setText(("▶ " if running else "✓ " if done else "   ") + f"{i + 1}. {step.title}")
            item.setForeground(QColor("#2050a0" if running else "#207020" if done else "#222"))

    def run_step(self, name: str) -> bool:
        """Start step ``name`` in a worker thread; False when another step is running."""
        if self.running is not None:
            self.log(f"{self.running} is running: wait for it or cancel it first")
            return False
        step = stages.STEPS[stages.NAMES.index(name)]
        page = self.pages[name]
        page.before_run()
        ctx = stages.Context(self.workspace, self.rig, page.options(), log=self.log_line.emit)
        worker = Worker(lambda task: step.run(ctx, task), name)
        worker.progress.connect(self._progress)
        worker.succeeded.connect(lambda box: self._ended(name, "done", str(box.value)))
        worker.failed.connect(lambda msg, details: self._ended(name, "failed", msg))
        worker.cancelled.connect(lambda msg: self._ended(name, "cancelled", "stopped; Run again resumes"))
        worker.finished.connect(lambda: self._thread_done(name))
        self.worker, self.running = worker, name
        self._started = time.monotonic()
        page.set_status("running…")
        if not step.done(self.workspace):  # "press <button>" becomes "<button> is running…"
            try:
                page.refresh()
            except Exception as exc:  # noqa: BLE001 -- a page that cannot be shown is logged, not raised
                self.log(f"could not refresh {name}: {exc}")
        self.progress.setValue(0)
        self.progress.setFormat(f"{step.title}: starting")
        self.progress.setRange(0, 0)  # busy until the stage reports progress
        self.cancel_button.setEnabled(True)
        self.pause_button.setEnabled(True)
        for p in self.pages.values():
            p.run_button.setEnabled(False)
        self.refresh_steps()
        self.log(f"--- {step.title}: started")
        worker.start()
        return True

    def pause(self, paused: bool) -> None:
        """Hold the running step at its next check (a turntable move holds at once), or let it go on."""
        if self.worker is None:
            return
        title = stages.STEPS[stages.NAMES.index(self.running)].title
        if paused:
            self.worker.task.pause()
            self.log(f"{title} paused (no further shot or iteration until then): press Resume to go on")
            self.pages[self.running].set_status("paused: press Resume to go on, Cancel to stop")
        else:
            self.worker.task.resume()
            self.log(f"{title} goes on")
            self.pages[self.running].set_status("running…")
        self.progress.setFormat(("paused — " if paused else "") + self.progress.format().removeprefix("paused — "))
        self.pause_button.setText("Resume" if paused else "Pause")

    def cancel(self) -> None:
        if self.worker is not None:
            self.log(f"cancelling {self.running}…")
            self.cancel_button.setEnabled(False)
            self.worker.cancel()  # also ends a pause

    def _progress(self, done: float, total: float, message: str) -> None:
        if total > 0:
            self.progress.setRange(0, 1000)
            self.progress.setValue(int(1000 * min(done / total, 1.0)))
        self.progress.setFormat(("paused — " if self.worker is not None and self.worker.task.paused else "")
                                + progress_text(done, total, message))
        self._show_shot(message)
        rms = RMS_IN_MESSAGE.search(message or "")
        if rms and hasattr(self.pages[self.running], "live_point"):  # the fit's error as it falls
            self.pages[self.running].live_point(time.monotonic() - self._started, [float(v) for v in rms.group(1).split(",")])
        if message and message.split(",")[0] != self._last_message.split(",")[0]:  # one log line per phase
            self.log(message)
        self._last_message = message

    def show_rig_state(self) -> None:
        """What the rig is doing, on every page: the live views say when every lamp is off (drawn on
        the view) and, connected, that the camera's frame is coming; the devices page's lines follow the board."""
        connected = self.rig.connected
        lamps = list(getattr(self.rig.controller, "lamps", []) or []) if connected else []
        banner = "all lamps off" if connected and lamps and not any(lamps) else ""
        for page in self.pages.values():
            page.preview.set_banner(banner)
            page.preview.set_placeholder("connected: waiting for the camera's first frame" if connected else
                                         "live view" if page.preview_stretch == 0 else
                                         "the camera shows here\nonce the rig is connected\n(Devices)")

    def _show_shot(self, message: str) -> None:
        """A capture steps its task with "<kind>: <file>": show that shot in the running page's live view."""
        from reflab.hardware.capture import FOLDERS
        from reflab.core.workspace import Workspace

        kind, _, file = message.partition(": ")
        if kind in FOLDERS and file and " " not in file:
            path = Workspace(self.workspace).captures_of(kind) / file
            if path.exists():
                from reflab.core.images import read_image

                self.pages[self.running].preview.set_image(read_image(path))
                self.show_rig_state()

    def _ended(self, name: str, outcome: str, text: str) -> None:
        self.pages[name].set_status(f"{outcome}: {text}")
        self.log(f"--- {stages.STEPS[stages.NAMES.index(name)].title}: {outcome}: {text}")
        self._outcome = outcome

    def _thread_done(self, name: str) -> None:
        outcome = getattr(self, "_outcome", "failed")
        self.worker.wait(10000)  # the stage has returned; let its thread end
        self._reap()
        self._background.append(self.worker)  # dropped once its thread is finished, never inside its signals
        self.worker, self.running = None, None
        self.progress.setRange(0, 1000)
        self.progress.setValue(1000 if outcome == "done" else 0)
        self.progress.setFormat(f"{outcome}")
        self.cancel_button.setEnabled(False)
        self.pause_button.blockSignals(True)
        self.pause_button.setChecked(False)
        self.pause_button.setText("Pause")
        self.pause_button.blockSignals(False)
        self.pause_button.setEnabled(False)
        for p in self.pages.values():
            p.run_button.setEnabled(True)
        self.refresh_steps()
        try:
            self.pages[name].refresh()
            if name == "devices" or not self.rig.connected:
                self.pages["devices"].refresh()
            self.show_rig_state()
        except Exception as exc:  # noqa: BLE001 -- a result that cannot be shown is logged, not raised
            self.log(f"could not show the result of {name}: {exc}")
        self.step_finished.emit(name, outcome)

    # ------------------------------------------------------------------ hardware page actions
    def hardware_action(self, what: str, *args) -> None:
        """Jog or switch a lamp in a background thread (never while a step runs)."""
        if self.running is not None:
            self.log("a step is using the rig")
            return
        fn = {"rotate": self.rig.rotate, "lamp": self.rig.set_lamp}[what]
        self.background(lambda task: fn(*args), self._hardware_done, "hardware")

    def _hardware_done(self, ok: bool, result) -> None:
        self.pages["devices"].show_connection(str(result) if ok else f"failed: {result}")
        if ok:  # the step's status line follows the board too, not the state it was connected in
            self.pages["devices"].set_status(f"done: connected — {result}")
        self.show_rig_state()
        self.hardware_done.emit(ok, str(result))

    def disconnect_rig(self) -> None:
        if self.running is not None:
            self.log("a step is using the rig: cancel it first")
            return
        self.rig.disconnect()
        self.pages["devices"].show_connection("disconnected")
        self.pages["devices"].set_status("disconnected: Connect to use the rig again")
        self.show_rig_state()
        self.log("rig disconnected")

    def background(self, fn, done, name: str = "background") -> Worker:
        """Run ``fn(task)`` off the UI thread; ``done(ok, result_or_message)`` on the UI thread."""
        worker = Worker(fn, name)
        worker.log.connect(self.log)
        worker.succeeded.connect(lambda box: done(True, box.value))
        worker.failed.connect(lambda msg, details: done(False, msg))
        worker.cancelled.connect(lambda msg: done(False, msg))
        self._reap()
        self._background.append(worker)
        return worker.start()

    def _reap(self) -> None:
        """Drop the background workers whose thread has ended (never inside their own signals)."""
        self._background = [w for w in self._background if not w.thread.isFinished()]

    # ------------------------------------------------------------------ live camera view
    def _tick_preview(self) -> None:
        """Take one frame off the UI thread; a slow camera (the simulated one renders the lab) is
        asked at most every other frame time, so the live view never eats more than half a core."""
        if (not self.rig.connected or self.running is not None or self._preview is not None or not self.isVisible()
                or time.monotonic() < self._preview_next):
            return
        page = self.pages[self.current_step()]
        start = time.monotonic()

        def done(ok, img):
            self._preview = None
            self._preview_next = time.monotonic() + (time.monotonic() - start)
            if ok and img is not None:
                page.preview.set_image(img)
                self.show_rig_state()

        self._preview = self.background(lambda task: self.rig.preview(), done, "preview")

    # ------------------------------------------------------------------ log and closing
    def log(self, text: str) -> None:
        self.log_line.emit(str(text))

    @Slot(str)
    def _append_log(self, text: str) -> None:  # also reached from worker threads (queued)
        self.log_pane.appendPlainText(text)

    def ask_close(self) -> bool:
        """Ask before closing while a step runs (tests replace this)."""
        title = stages.STEPS[stages.NAMES.index(self.running)].title
        answer = QMessageBox.question(self, "A step is running",
                                      f"“{title}” is still running. Cancel it and close? Its finished work is kept "
                                      "and Run resumes it next time.")
        return answer == QMessageBox.StandardButton.Yes

    def closeEvent(self, event) -> None:
        if self.running is not None:
            if not self.ask_close():
                event.ignore()
                return
            self.cancel()
            if self.worker is not None:
                self.worker.wait(10000)
        self.preview_timer.stop()
        for w in list(self._background):
            w.cancel()
            w.wait(10000)
        self.rig.disconnect()
        event.accept()
