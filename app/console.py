"""The command line's output: one ``reflab`` logger, a progress bar, Ctrl-C as a cancel.

Messages go through ``LOG`` (``logging.getLogger("reflab")``): info to stdout as plain lines,
warnings and errors to stderr, each written to the stream current at that moment (so a caller's
``contextlib.redirect_stdout`` and pytest's capsys see them). ``-q`` leaves warnings and errors,
``-v`` adds debug lines.

:func:`running` hands a command a :class:`reflab.core.task.Task` for its stage: while stderr is a
terminal (and not ``-q``) the task's progress shows as a bar there once the stage has run a
second; Ctrl-C cancels the task, so the stage stops at its next check with nothing half-written
(a second Ctrl-C interrupts at once).
"""
from __future__ import annotations

import contextlib
import logging
import signal
import sys
import threading

LOG = logging.getLogger("reflab")


class _Handler(logging.Handler):
    """Info and debug to sys.stdout, warnings and errors to sys.stderr, looked up at each record."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            stream = sys.stderr if record.levelno >= logging.WARNING else sys.stdout
            stream.write(self.format(record) + "\n")
            stream.flush()
        except Exception:  # noqa: BLE001 - logging's own convention
            self.handleError(record)


def setup(verbosity: int = 0) -> logging.Logger:
    """Route ``LOG`` to stdout/stderr at the level ``verbosity`` asks: < 0 warnings, 0 info, > 0 debug."""
    if not any(isinstance(h, _Handler) for h in LOG.handlers):
        LOG.addHandler(_Handler())
        LOG.propagate = False
    LOG.setLevel(logging.WARNING if verbosity < 0 else logging.DEBUG if verbosity > 0 else logging.INFO)
    return LOG


def _bar(label: str):
    """A progress(done, total, message) callback drawing a tqdm bar on stderr, and a closer."""
    state = {"bar": None}
    show = sys.stderr.isatty() and LOG.getEffectiveLevel() <= logging.INFO

    def progress(done: float, total: float, message: str) -> None:
        if not show:
            return
        if state["bar"] is None:
            from tqdm import tqdm

            state["bar"] = tqdm(total=total or None, desc=label, file=sys.stderr, delay=1.0, leave=False,
                                dynamic_ncols=True, bar_format="{desc}: {percentage:3.0f}%|{bar}| {postfix}")
        bar = state["bar"]
        if total and bar.total != total:
            bar.total = total
        bar.set_postfix_str(message, refresh=False)
        bar.update(done - bar.n)

    def close() -> None:
        if state["bar"] is not None:
            state["bar"].close()

    return progress, close


@contextlib.contextmanager
def running(label: str, max_seconds: float | None = None):
    """A Task for one stage run from the command line: progress bar, Ctrl-C cancels it."""
    from reflab.core.task import Task

    progress, close = _bar(label)
    task = Task(progress, max_seconds)
    main = threading.current_thread() is threading.main_thread()
    previous = (signal.getsignal(signal.SIGINT) or signal.default_int_handler) if main else None

    def cancel(signum, frame):
        task.cancel()
        signal.signal(signal.SIGINT, previous)  # a second Ctrl-C interrupts at once

    if main:
        signal.signal(signal.SIGINT, cancel)
    LOG.debug(f"{label}: running (Ctrl-C cancels)")
    try:
        yield task
    finally:
        if main:
            signal.signal(signal.SIGINT, previous)
        close()
