"""The task object every long stage checks: cancel from another thread, pause, deadline."""
import threading
import time

import pytest

from reflab.core.task import Cancelled, Task, ensure


def test_cancel_from_another_thread_stops_the_loop_within_a_second():
    task = Task()
    seen = []
    threading.Timer(0.2, task.cancel).start()
    start = time.perf_counter()
    with pytest.raises(Cancelled):
        for i in range(10_000):
            time.sleep(0.01)
            task.step(i, 10_000, "working")
            seen.append(i)
    assert time.perf_counter() - start < 1.0
    assert 5 < len(seen) < 100


def test_pause_blocks_until_resumed_and_progress_is_reported():
    calls = []
    task = Task(progress=lambda d, t, m: calls.append((d, t, m)))
    task.pause()
    threading.Timer(0.3, task.resume).start()
    start = time.perf_counter()
    task.step(1, 4, "one")
    assert time.perf_counter() - start >= 0.25
    assert calls == [(1.0, 4.0, "one")]
    assert (task.done, task.total, task.message) == (1.0, 4.0, "one")


def test_deadline_is_not_an_error():
    task = Task(max_seconds=0.05)
    assert not task.out_of_time
    time.sleep(0.1)
    assert task.out_of_time and task.seconds_left() < 0
    task.check()  # a spent budget does not raise
    assert ensure(None).deadline is None and ensure(task) is task
