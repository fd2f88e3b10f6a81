"""Long work off the UI thread: one :class:`Worker` per run, in its own ``QThread``.

The worker owns a :class:`reflab.core.task.Task`; the stage reports through ``task.step`` (emitted
as :attr:`Worker.progress`, queued to the UI thread) and the cancel button calls
:meth:`Worker.cancel`, which the stage sees at its next check. Exactly one of ``succeeded``,
``failed`` or ``cancelled`` is emitted, then ``finished``. A failure carries the stage's one-line
message and, separately, the details (the traceback) for the log pane: no dialog ever shows it.
"""
from __future__ import annotations

import traceback

from PySide6.QtCore import QObject, Qt, QThread, Signal, Slot

from reflab.core.task import Cancelled, Task


class StepFailed(RuntimeError):
    """A stage stopped with a message meant for the user (one line, says what to fix)."""


def one_line(exc: BaseException) -> str:
    """The first line of an exception's message, named by its type when it has none."""
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


class Box:
    """A result carried by a queued signal: PySide6 mis-counts references to a bare ``None`` sent
    through ``Signal(object)`` across threads (the interpreter aborts in ``none_dealloc``)."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value


class _Thread(QThread):
    def __init__(self, target):
        super().__init__()
        self.target = target

    def run(self) -> None:
        self.target()


class Worker(QObject):
    """Run ``fn(task)`` in a thread; ``fn`` returns a one-line summary (or any object).

    The thread emits only the private ``_event`` (queued to :meth:`_dispatch`, a ``@Slot`` of this
    object, which lives in the UI thread); the public signals are emitted from there. PySide6
    6.8+ crashes (refcount errors, PYSIDE-3124) when a signal emitted in another thread is
    delivered to a lambda or an undecorated method, which is what the window connects.
    """

    _event = Signal(str, object)

    progress = Signal(float, float, str)
    log = Signal(str)
    succeeded = Signal(object)  # a Box holding fn's return value
    failed = Signal(str, str)  # one-line message, details
    cancelled = Signal(str)
    finished = Signal()

    def __init__(self, fn, name: str = ""):
        super().__init__()
        self.fn, self.name = fn, name
        self.task = Task(progress=lambda done, total, msg: self.post("progress", done, total, msg))
        self._event.connect(self._dispatch, Qt.ConnectionType.QueuedConnection)
        # This object stays in the UI thread; only _run executes in the thread.
        self.thread = _Thread(self._run)
        self.thread.setObjectName(f"worker_{name}")

    def post(self, kind: str, *args) -> None:
        """From the thread: emit the public signal ``kind`` with ``args``, in the UI thread."""
        self._event.emit(kind, Box(args))

    @Slot(str, object)
    def _dispatch(self, kind: str, box) -> None:
        getattr(self, kind).emit(*box.value)

    def start(self) -> "Worker":
        self.thread.start()
        return self

    def cancel(self) -> None:
        self.task.cancel()

    @property
    def running(self) -> bool:
        return self.thread.isRunning()

    def wait(self, ms: int = -1) -> bool:
        return self.thread.wait() if ms < 0 else self.thread.wait(ms)

    def _run(self) -> None:
        from reflab.app.gui.rig import RigError
        from reflab.hardware.cameras import CameraError
        from reflab.hardware.capture import CaptureCancelled, CaptureError
        from reflab.hardware.grbl import GrblError
        from reflab.core.workspace import WorkspaceError

        expected = (StepFailed, WorkspaceError, CaptureError, GrblError, CameraError, RigError, ValueError)

        try:
            result = self.fn(self.task)
        except (Cancelled, CaptureCancelled, KeyboardInterrupt) as exc:
            self.post("log", str(exc))
            self.post("cancelled", one_line(exc))
        except expected as exc:  # the stage's own message names what to fix
            self.post("log", str(exc))
            self.post("failed", one_line(exc), str(exc))
        except Exception as exc:  # noqa: BLE001 -- any other error is shown in the page, not raised
            details = traceback.format_exc()
            self.post("log", details)
            self.post("failed", f"{type(exc).__name__}: {one_line(exc)}", details)
        else:
            if self.task.cancelled:
                self.post("cancelled", "cancelled")
            else:
                self.post("succeeded", Box(result))
        finally:
            self.post("finished")
