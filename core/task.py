"""One small task object for every long stage: progress, pause, cancel and deadline.

The CLI, the GUI and the demo hand a :class:`Task` to a stage function; the stage calls
:meth:`Task.step` (or :meth:`Task.check`) inside its long loops (tree levels, fit iterations,
texture CG, SfM, captures). Another thread (the GUI's cancel button, a signal handler) calls
:meth:`Task.pause`, :meth:`Task.resume` or :meth:`Task.cancel`; the stage sees it at its next
check, at most one loop iteration later. A cancelled stage raises :class:`Cancelled` before
writing anything half-done; its finished work (capture shots, cached trees) stays for a resume.

A deadline is not an error: :attr:`Task.out_of_time` tells a stage that can stop early with
a usable result (the fit) to do so, and say so in its output.

It lives in ``hardware`` because that is the lowest layer: every stage may import it.
"""
from __future__ import annotations

import threading
import time
from typing import Callable


class Cancelled(RuntimeError):
    """The user cancelled the running stage; nothing half-written was left behind."""


class Task:
    """Progress, pause, cancel and deadline for one running stage.

    Parameters
    ----------
    progress : callable, optional
        ``progress(done, total, message)`` after every :meth:`step` (from the stage's thread).
    max_seconds : float, optional
        Wall-clock budget from creation; :attr:`out_of_time` turns true once spent.
    """

    def __init__(self, progress: Callable[[float, float, str], None] | None = None,
                 max_seconds: float | None = None):
        self._progress = progress
        self._run = threading.Event()
        self._run.set()
        self._cancel = threading.Event()
        #: Set while the stage is held in :meth:`check` by a pause (the GUI and tests can tell
        #: "asked to pause" from "holding").
        self.holding = threading.Event()
        self.start = time.perf_counter()
        self.deadline = None if max_seconds is None else self.start + float(max_seconds)
        self.done, self.total, self.message = 0.0, 0.0, ""

    # -- called from another thread ---------------------------------------------------------
    def pause(self) -> None:
        self._run.clear()

    def resume(self) -> None:
        self._run.set()

    def cancel(self) -> None:
        self._cancel.set()
        self._run.set()

    @property
    def paused(self) -> bool:
        return not self._run.is_set()

    @property
    def cancelled(self) -> bool:
        return self._cancel.is_set()

    # -- called by the stage --------------------------------------------------------------
    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    @property
    def out_of_time(self) -> bool:
        return self.deadline is not None and time.perf_counter() > self.deadline

    def seconds_left(self) -> float | None:
        return None if self.deadline is None else self.deadline - time.perf_counter()

    def check(self) -> None:
        """Block while paused; raise :class:`Cancelled` once cancelled."""
        if not self._run.is_set():
            self.holding.set()
            while not self._run.wait(0.05):
                pass
            self.holding.clear()
        if self._cancel.is_set():
            raise Cancelled("cancelled")

    def step(self, done: float, total: float, message: str = "") -> None:
        """Record progress, tell the listener, then :meth:`check`."""
        self.done, self.total, self.message = float(done), float(total), message
        if self._progress is not None:
            self._progress(self.done, self.total, message)
        self.check()


def ensure(task: Task | None) -> Task:
    """The task a stage was given, or a silent one that never stops it."""
    return task if task is not None else Task()
