"""A simulated GRBL 1.1 board on a pseudo-terminal, with fault injection.

The board serves the master side of ``os.openpty()`` from a thread; clients open the slave side
through pyserial like any serial port, so real bytes cross a real tty (``loop://`` only echoes).
``port`` is a symlink to the current slave: a simulated unplug closes the pty and removes the
link, a re-plug opens a new pty behind the same name, as a udev rule does for a real board.

The board keeps what a test needs to check the host's manners: the arrival time of every line
and of every ``?`` (status polled at most 5 Hz), and how many lines were unacknowledged when
each line arrived (send-response flow control keeps it at 1). Answers leave after ``latency_s``,
so a host that does not wait for ``ok`` is caught.

Where it matters to a driver it behaves as GRBL 1.1h does (checked against the firmware itself
under grbl-sim): ``Ov:`` and the accessory field ``A:`` come on about one status report in ten
(and on the next one after an output changes); ``M9`` clears flood and mist; ``M7`` is
``error:20`` unless built with ``m7=True``; in ``Hold`` lines wait unanswered until ``~`` or a
reset; a reset while moving gives ``ALARM:3``; ``power_up_alarm`` boots locked as ``$22=1`` does.
"""
from __future__ import annotations

import os
import re
import select
import tempfile
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

import numpy as np

VERSION = "1.1h"
BANNER = f"Grbl {VERSION} ['$' for help]"
#: Settings a turntable driver touches: steps per unit, max rate, acceleration, max travel.
DEFAULT_SETTINGS = {
    **{100 + i: 250.0 for i in range(3)},
    **{110 + i: 36000.0 for i in range(3)},
    **{120 + i: 100.0 for i in range(3)},
    **{130 + i: 10000.0 for i in range(3)},
}
FAULTS = ("garble", "error", "alarm", "silent", "disconnect")


@dataclass
class Fault:
    """A fault waiting for its line.

    Attributes
    ----------
    kind : str
        ``garble`` (the line is executed, its ``ok`` arrives as noise), ``error`` (answered
        ``error:code``, not executed), ``alarm`` (a move starts, then ``ALARM:code`` halfway; a
        critical alarm ignores everything but a soft reset), ``silent`` (no answer, not executed),
        ``disconnect`` (the port vanishes before the answer; it comes back after ``reappear_after``
        seconds, or never when None).
    match : str
        Regular expression searched in each received line; the fault fires on a match.
    skip : int
        Matching lines let through before the one that fires.
    code : int
        The error or alarm number.
    reappear_after : float or None
        For ``disconnect``.
    """

    kind: str
    match: str = r"^G"
    skip: int = 0
    code: int = 1
    reappear_after: float | None = None


class SimulatedGrbl:
    """A GRBL 1.1 board on a pty: one axis set in degrees or mm, spindle and coolant outputs.

    Parameters
    ----------
    folder : path-like, optional
        Where the ``ttyGRBL`` link is made (a temporary folder by default).
    time_scale : float
        Moves run this many times faster than their feed rate says (tests use 20–100).
    latency_s : float
        Delay before each answer leaves the board.
    m7 : bool
        Built with ENABLE_M7 (the mist output); stock GRBL answers ``M7`` with ``error:20``.
    power_up_alarm : bool
        Boot in Alarm, as GRBL does with homing enabled (``$22=1``).
    """

    def __init__(self, folder=None, *, time_scale: float = 1.0, latency_s: float = 0.005, m7: bool = False,
                 power_up_alarm: bool = False):
        self._tmp = None if folder else tempfile.TemporaryDirectory(prefix="simgrbl-")
        self.port = str(Path(folder or self._tmp.name) / "ttyGRBL")
        self.time_scale, self.latency_s = float(time_scale), float(latency_s)
        self.settings = dict(DEFAULT_SETTINGS)
        self.setting_writes = 0
        self.position = np.zeros(3)
        self.outputs = {"spindle": False, "flood": False, "mist": False}
        self.spindle_speed = 0.0
        self.m7 = bool(m7)
        self.state = "Alarm" if power_up_alarm else "Idle"
        self.alarm_code: int | None = None
        self._ovr_counter = 0  # reports until the next Ov:/A: (GRBL: 10 idle, 20 busy)
        self._held_lines: list[str] = []  # lines received in Hold: GRBL answers them after ~
        self.critical = False
        self.faults: list[Fault] = []
        # What the host did, for conformance tests.
        self.lines: list[tuple[float, str]] = []
        self.polls: list[float] = []
        self.realtime: list[tuple[float, bytes]] = []  # !, ~ and 0x18 as received
        self.max_in_flight = 0
        self.resets = 0
        self._unacked = 0
        self._moves: list[tuple[np.ndarray, float]] = []  # planned (target, feed per minute)
        self._motion = None  # (start, target, t0, duration, feed) of the block being executed
        self._deferred_ok = 0  # G4 dwell answers wait until motion ends
        self._modal = {"absolute": True, "feed": None}
        self._outbox: list[tuple[float, bytes, int]] = []
        self._rx = bytearray()
        self._lock = threading.RLock()
        self._fd = self._slave = None
        self._reappear_at: float | None = None
        self._running = False
        self._thread = None

    # ------------------------------------------------------------------ life cycle
    def __enter__(self) -> "SimulatedGrbl":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> "SimulatedGrbl":
        self._plug()
        self._running = True
        self._thread = threading.Thread(target=self._serve, name="SimulatedGrbl", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2)
        self._unplug()
        if self._tmp is not None:
            self._tmp.cleanup()

    def inject(self, kind: str, **kw) -> Fault:
        """Queue a fault (see :class:`Fault`); faults fire in the order queued."""
        if kind not in FAULTS:
            raise ValueError(f"unknown fault {kind!r}; one of {FAULTS}")
        fault = Fault(kind, **kw)
        with self._lock:
            self.faults.append(fault)
        return fault

    def replug(self) -> None:
        """Plug the board back in after a ``disconnect`` fault that did not come back by itself."""
        with self._lock:
            if self._fd is None:
                self._plug()

    @property
    def plugged(self) -> bool:
        return self._fd is not None

    def _plug(self) -> None:
        """A fresh pty behind ``port``; the board prints its banner as after power-up."""
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        link = Path(self.port)
        tmp = link.with_name(link.name + ".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(slave))
        os.replace(tmp, link)
        self._fd, self._slave = master, slave  # the slave stays open so the master never sees EIO
        self._rx.clear()
        self._outbox.clear()
        self._unacked = 0
        self._reappear_at = None
        self._send(f"\r\n{BANNER}\r\n", delay=0)
        if self.state == "Alarm":
            self._send("[MSG:'$H'|'$X' to unlock]\r\n", delay=0)

    def _unplug(self) -> None:
        Path(self.port).unlink(missing_ok=True)
        for fd in (self._fd, self._slave):
            if fd is not None:
                os.close(fd)
        self._fd = self._slave = None

    # ------------------------------------------------------------------ the physical rig
    def turntable(self, axis: str = "X") -> float:
        """The true turntable angle (degrees) on ``axis``, mid-move included."""
        with self._lock:
            self._advance(time.monotonic())
            return float(self.position["XYZ".index(axis)])

    def press(self, byte: bytes) -> None:
        """A button on the board: ``b"!"`` feed hold, ``b"~"`` cycle start, ``b"\\x18"`` reset."""
        with self._lock:
            now = time.monotonic()
            {b"!": self._feed_hold, b"~": self._cycle_start, b"\x18": self._reset}[byte](now)

    def lamp_outputs(self) -> dict:
        """The true state of each output (``spindle``, ``flood``, ``mist``)."""
        with self._lock:
            return dict(self.outputs)

    # ------------------------------------------------------------------ serving
    def _serve(self) -> None:
        while self._running:
            now = time.monotonic()
            with self._lock:
                if self._fd is None:
                    if self._reappear_at is not None and now >= self._reappear_at:
                        self._plug()
                    fd = None
                else:
                    fd = self._fd
                    self._advance(now)
                    self._flush(now)
            if fd is None:
                time.sleep(0.005)
                continue
            try:
                ready, _, _ = select.select([fd], [], [], 0.002)
                data = os.read(fd, 4096) if ready else b""
            except OSError:
                data = b""
            if data:
                with self._lock:
                    if self._fd == fd:
                        self._receive(data, time.monotonic())

    def _send(self, text: str, delay: float | None = None, acks: int = 0) -> None:
        """Queue bytes to leave after ``latency_s``; ``acks`` lines count as answered then."""
        when = time.monotonic() + (self.latency_s if delay is None else delay)
        self._outbox.append((when, text.encode("latin-1"), acks))

    def _flush(self, now: float) -> None:
        while self._outbox and self._outbox[0][0] <= now and self._fd is not None:
            _, data, acks = self._outbox.pop(0)
            try:
                os.write(self._fd, data)
            except OSError:
                pass  # nobody reads: bytes a real board would also lose
            self._unacked -= acks

    def _receive(self, data: bytes, now: float) -> None:
        lines = []
        for b in data:
            c = bytes([b])
            if c == b"?":
                self.polls.append(now)
                self._send(self._report())
            elif c in (b"!", b"~", b"\x18"):
                self.realtime.append((now, c))
                if c == b"!":
                    self._feed_hold(now)
                elif c == b"~":
                    self._cycle_start(now)
                else:
                    self._reset(now)
                    lines.clear()
            elif c == b"\n":
                lines.append(self._rx.decode("latin-1").strip())
                self._rx.clear()
            elif c != b"\r":
                self._rx.extend(c)
        # Count every line of this read as arrived before any is answered.
        for line in lines:
            self._unacked += 1
            self.max_in_flight = max(self.max_in_flight, self._unacked)
            self.lines.append((now, line))
        for line in lines:
            if self._fd is None:
                break
            self._line(line, now)

    def _line(self, line: str, now: float) -> None:
        if self.state.startswith("Hold"):
            self._held_lines.append(line)  # GRBL's main loop runs no line while held
            return
        if self.critical:
            self._unacked -= 1  # ignored until reset, as GRBL does after a critical alarm
            return
        fault = self._fault_for(line)
        if fault is not None:
            if fault.kind == "silent":
                self._unacked -= 1
                return
            if fault.kind == "error":
                self._send(f"error:{fault.code}\r\n", acks=1)
                return
            if fault.kind == "disconnect":
                self._unplug()
                if fault.reappear_after is not None:
                    self._reappear_at = now + fault.reappear_after
                return
        answer = self._execute(line, now)
        if fault is not None and fault.kind == "garble":
            answer = "o\x8b\x00k\xfe\r\n"
        elif fault is not None and fault.kind == "alarm":
            self._alarm_at = (now + (self._motion[3] / 2 if self._motion else 0.0), fault.code)
        if answer is None:
            self._deferred_ok += 1
            return
        self._send(answer, acks=1)

    def _fault_for(self, line: str) -> Fault | None:
        for fault in self.faults:
            if re.search(fault.match, line):
                if fault.skip > 0:
                    fault.skip -= 1
                    return None
                self.faults.remove(fault)
                return fault
            break  # faults fire in order: only the first one waits
        return None

    # ------------------------------------------------------------------ commands
    def _execute(self, line: str, now: float) -> str | None:
        """Run one line; return its answer (``ok``, ``error:N`` …), or None for a deferred ``ok``."""
        if len(line) > 80:
            return "error:11\r\n"
        if line.startswith("$"):
            return self._system(line)
        if self.state == "Alarm":
            return "error:9\r\n"
        words = re.findall(r"([A-Z])\s*([-+]?[0-9]*\.?[0-9]+)", line.upper().replace(" ", ""))
        if "".join(l + v for l, v in words) != line.upper().replace(" ", ""):
            return "error:1\r\n"
        target = self._planned_end().copy()
        axes = False
        dwell = None
        motion = None
        for letter, value in words:
            v = float(value)
            if letter == "G":
                if v in (0, 1):
                    motion = int(v)
                elif v == 90:
                    self._modal["absolute"] = True
                elif v == 91:
                    self._modal["absolute"] = False
                elif v == 4:
                    dwell = 0.0
                else:
                    return "error:20\r\n"
            elif letter == "M":
                self._ovr_counter = 0  # GRBL reports an output change on the next status report
                if v in (3, 4):
                    self.outputs["spindle"] = True
                elif v == 5:
                    self.outputs["spindle"] = False
                elif v == 7:
                    if not self.m7:
                        return "error:20\r\n"
                    self.outputs["mist"] = True
                elif v == 8:
                    self.outputs["flood"] = True
                elif v == 9:
                    self.outputs["flood"] = self.outputs["mist"] = False
                else:
                    return "error:20\r\n"
            elif letter == "S":
                self.spindle_speed = v
            elif letter == "F":
                self._modal["feed"] = v
            elif letter == "P" and dwell is not None:
                dwell = v
            elif letter in "XYZ":
                i = "XYZ".index(letter)
                target[i] = v if self._modal["absolute"] else target[i] + v
                axes = True
            else:
                return "error:20\r\n"
        if dwell is not None:
            return None if self._moves or self._motion else "ok\r\n"
        if axes:
            feed = self.settings[110] if motion == 0 else self._modal["feed"]
            if motion is None:
                return "error:20\r\n"
            if not feed:
                return "error:22\r\n"
            self._moves.append((target, feed))
            self._advance(now)
        return "ok\r\n"

    def _system(self, line: str) -> str:
        if line == "$$":
            return "".join(f"${k}={v:.3f}\r\n" for k, v in sorted(self.settings.items())) + "ok\r\n"
        if line == "$X":
            if self.state == "Alarm":
                self.state, self.alarm_code = "Idle", None
                return "[MSG:Caution: Unlocked]\r\nok\r\n"
            return "ok\r\n"
        if line == "$I":
            return f"[VER:{VERSION}.20190830:]\r\n[OPT:V{'M' if self.m7 else ''},15,128]\r\nok\r\n"
        if line == "$G":
            o = self.outputs
            spindle = "M3" if o["spindle"] else "M5"
            coolant = " ".join(m for m, on in (("M7", o["mist"]), ("M8", o["flood"])) if on) or "M9"
            dist = "G90" if self._modal["absolute"] else "G91"
            return (f"[GC:G1 G54 G17 G21 {dist} G94 {spindle} {coolant} T0 F{self._modal['feed'] or 0:g} "
                    f"S{self.spindle_speed:g}]\r\nok\r\n")
        m = re.fullmatch(r"\$(\d+)=([-+]?[0-9.]+)", line)
        if m:
            if self.state != "Idle":
                return "error:8\r\n"
            if int(m.group(1)) not in self.settings:
                return "error:3\r\n"
            self.settings[int(m.group(1))] = float(m.group(2))
            self.setting_writes += 1
            return "ok\r\n"
        return "error:3\r\n"

    # ------------------------------------------------------------------ motion
    _alarm_at: tuple[float, int] | None = None

    def _planned_end(self) -> np.ndarray:
        if self._moves:
            return self._moves[-1][0]
        return self._motion[1] if self._motion else self.position

    def _advance(self, now: float) -> None:
        """Move the axes along the planned blocks up to time ``now`` (constant feed, no ramps)."""
        if self._alarm_at is not None and now >= self._alarm_at[0]:
            self._trigger_alarm()
        while True:
            if self._motion is None:
                if not self._moves or self.state not in ("Idle", "Run"):
                    break
                target, feed = self._moves.pop(0)
                dist = float(np.linalg.norm(target - self.position))
                duration = dist / (feed / 60.0) / self.time_scale
                self._motion = (self.position.copy(), target, now, duration, feed)
                self.state = "Run"
            start, target, t0, duration, _ = self._motion
            if self.state != "Run":
                break
            if now - t0 >= duration:
                self.position = target.copy()
                self._motion = None
                if not self._moves:
                    self.state = "Idle"
                    while self._deferred_ok:
                        self._deferred_ok -= 1
                        self._send("ok\r\n", acks=1)
                continue
            self.position = start + (target - start) * ((now - t0) / max(duration, 1e-12))
            break

    def _trigger_alarm(self) -> None:
        when, code = self._alarm_at
        self._alarm_at = None
        if self._motion is not None:
            start, target, t0, duration, _ = self._motion
            self.position = start + (target - start) * min(1.0, (when - t0) / max(duration, 1e-12))
        self._motion, self._moves = None, []
        self.state, self.alarm_code = "Alarm", code
        self.critical = code in (1, 2)
        self._send(f"ALARM:{code}\r\n", delay=0)
        if self.critical:
            self._send("[MSG:Reset to continue]\r\n", delay=0)

    def _feed_hold(self, now: float) -> None:
        if self.state == "Run":
            self._advance(now)
            if self._motion is not None:
                # The rest of the block runs after ~, from where it stopped.
                self._moves.insert(0, (self._motion[1], self._motion[4]))
                self._motion = None
            self.state = "Hold:0"

    def _cycle_start(self, now: float) -> None:
        if self.state.startswith("Hold"):
            self.state = "Idle"
            self._advance(now)
            held, self._held_lines = self._held_lines, []
            for line in held:
                self._line(line, now)

    def _reset(self, now: float) -> None:
        """0x18: stop, outputs off, answer pending lines no more, print the banner."""
        self._advance(now)
        if self.state == "Run":
            self.state, self.alarm_code = "Alarm", 3
            self._send("ALARM:3\r\n", delay=0)
        self._motion, self._moves, self._alarm_at = None, [], None
        self._held_lines = []
        if self.state.startswith("Hold"):
            self.state = "Idle"
        self.critical = False
        self.outputs = {k: False for k in self.outputs}
        self._rx.clear()
        self._outbox = [o for o in self._outbox if o[2] == 0]
        self._unacked, self._deferred_ok = 0, 0
        self.resets += 1
        self._send(f"\r\n{BANNER}\r\n", delay=0)
        if self.state == "Alarm":
            self._send("[MSG:'$H'|'$X' to unlock]\r\n", delay=0)

    def _report(self) -> str:
        self._advance(time.monotonic())
        x, y, z = self.position
        acc = ("S" if self.outputs["spindle"] else "") + ("F" if self.outputs["flood"] else "") + ("M" if self.outputs["mist"] else "")
        feed = self._motion[4] if self._motion else 0
        text = f"<{self.state}|MPos:{x:.3f},{y:.3f},{z:.3f}|FS:{feed:g},{self.spindle_speed:g}"
        if self._ovr_counter > 0:  # GRBL 1.1: overrides and accessories only every 10th (idle) report
            self._ovr_counter -= 1
            return text + ">\r\n"
        self._ovr_counter = 19 if self.state in ("Run", "Hold:0") else 9
        return text + "|Ov:100,100,100" + (f"|A:{acc}" if acc else "") + ">\r\n"
