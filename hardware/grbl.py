"""A GRBL 1.1 controller over pyserial: the turntable (a rotary axis in degrees) and the lamps.

Protocol (gnea/grbl, doc/markdown/interface.md): the board prints a banner ``Grbl 1.1h ['$' for
help]`` after boot and after a soft reset (0x18). Every line sent is answered by ``ok`` or
``error:N``; this driver keeps at most one unacknowledged line in flight (send-response flow
control). ``?``, ``!``, ``~`` and 0x18 are real-time bytes, never acknowledged. ``?`` is answered
by a status report ``<Idle|MPos:0.000,0.000,0.000|FS:0,0|A:SF>``. ``ALARM:N`` and ``[MSG:…]``
arrive unsolicited. docs/hardware.md describes the configuration and the fault handling.

Every command this driver sends is idempotent (absolute moves ``G90 G1``, ``M3``/``M5``/``M7``/
``M8``/``M9``), so a line whose answer was lost to a disconnect is sent again after reconnecting.

GRBL 1.1 facts the driver is built on (checked against 1.1h itself under grbl-sim): the status
report carries the accessory field ``A:`` only with ``Ov:``, about one report in ten, so the lamps
are read from ``$G`` (the modal ``M3``/``M5``, ``M7``/``M8``/``M9``); ``M9`` switches flood AND mist
off, and stock builds refuse ``M7`` (``error:20``); in ``Hold`` no line is processed until ``~`` or a
soft reset; a soft reset while moving gives ``ALARM:3``, while held or idle it keeps the position;
every reset prints the banner, which is how a reset from elsewhere is noticed.
"""
from __future__ import annotations

import re
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import serial

from reflab.core.workspace import WorkspaceError, read_json

try:  # pyserial lets termios and ioctl errors of a vanished tty through unwrapped
    import termios

    _PORT_ERRORS: tuple = (OSError, termios.error)
except ImportError:  # Windows
    _PORT_ERRORS = (OSError,)

#: GRBL 1.1 error codes (doc/csv/error_codes_en_US.csv), the ones a turntable can meet.
ERRORS = {
    1: "G-code words consist of a letter and a value; letter was not found",
    2: "numeric value format is not valid or missing an expected value",
    3: "'$' system command was not recognized or supported",
    4: "negative value received for an expected positive value",
    5: "homing cycle is not enabled via settings",
    8: "'$' command only valid when Idle",
    9: "G-code locked out during alarm or jog state",
    11: "max characters per line exceeded; line was not processed",
    15: "jog target exceeds machine travel",
    20: "unsupported or invalid G-code command found in block",
    22: "feed rate has not yet been set or is undefined",
    24: "two G-code commands that both require the use of the XYZ axis words were detected",
    26: "no axis words found in block for a command that requires them",
    33: "motion command target is invalid",
}
#: GRBL 1.1 alarm codes (doc/csv/alarm_codes_en_US.csv).
ALARMS = {
    1: "hard limit triggered; machine position is likely lost",
    2: "soft limit: motion target exceeds machine travel",
    3: "reset while in motion; position is likely lost",
    4: "probe fail: probe not in the expected initial state",
    5: "probe fail: probe did not contact the workpiece",
    6: "homing fail: reset during active homing cycle",
    7: "homing fail: safety door opened during homing",
    8: "homing fail: cycle failed to clear limit switch",
    9: "homing fail: could not find limit switch",
}
#: Lamp outputs of the controller: spindle PWM (M3 S… / M5), flood (M8) and mist (M7) coolant.
OUTPUTS = ("spindle", "flood", "mist")
#: Letters of the status report's accessory field ``A:`` for each output.
_ACCESSORY = {"spindle": "S", "flood": "F", "mist": "M"}
_BANNER = re.compile(r"^Grbl (\S+) \[.*\]$")


class GrblError(RuntimeError):
    """The controller refused, stopped or could not be reached; the message says what to check.

    ``bad_input``: the error is the user's input (a port that cannot be opened, a configuration the
    board cannot follow), exit status 2 as for every other bad input; else a device fault (1).
    """

    bad_input = False


class GrblTimeout(GrblError):
    """No answer within the configured time."""


class GrblProtocolError(GrblError):
    """A line that GRBL 1.1 never sends (noise on the line, wrong baud rate, another firmware)."""


class GrblCommandError(GrblError):
    """``error:N`` in answer to a line."""

    def __init__(self, line: str, code: int):
        self.code = code
        super().__init__(f"GRBL refused {line!r}: error:{code} ({ERRORS.get(code, 'see GRBL error codes')})")


class GrblAlarm(GrblError):
    """``ALARM:N`` or a status report in the Alarm state: motion is locked until unlocked."""

    def __init__(self, code: int | None, context: str = ""):
        self.code = code
        what = f"ALARM:{code} ({ALARMS.get(code, 'see GRBL alarm codes')})" if code else "the Alarm state"
        super().__init__(
            f"GRBL is in {what}{context}. Check the turntable moves freely and the limit wiring, "
            "then unlock it (`reflab hardware --port PORT unlock`, which soft-resets and sends $X)."
        )


class BoardReset(GrblError):
    """The board reset on its own (reset button, power dip, another program): its outputs are off."""


class BoardHeld(GrblError):
    """The board went into feed hold without this driver asking (hold button, another program)."""


class MoveCancelled(GrblError):
    """A move abandoned at the caller's request (the board was soft-reset while held)."""


class DeviceLost(GrblError):
    """The serial port vanished and reconnecting failed."""


class PortUnavailable(DeviceLost):
    """The port named cannot be opened (no such device, held by another program, no permission)."""

    bad_input = True


class WiringError(GrblError):
    """The configuration's lamp outputs cannot work on this board (hardware.json or the firmware)."""

    bad_input = True


@dataclass
class GrblConfig:
    """How the rig is wired to the controller; read from a JSON file (docs/hardware.md).

    Attributes
    ----------
    axis : str
        The GRBL axis letter (``X``, ``Y`` or ``Z``) that drives the turntable; its unit is degrees.
    steps_per_degree : float or None
        Written to ``$100``/``$101``/``$102`` when it differs from the board's value; None leaves it.
    feed_deg_per_min : float
        Feed rate of turntable moves.
    lamps : list of str
        The controller output that switches lamp k: ``spindle``, ``flood`` or ``mist``.
    spindle_power : float
        The ``S`` word sent with ``M3`` for a lamp on the spindle output.
    baudrate : int
        Serial speed (GRBL 1.1: 115200).
    timeout_s : float
        Longest wait for the answer to one line, and for a serial write.
    move_timeout_s : float
        Longest wait for the turntable to reach ``Idle`` after a move (time in feed hold excluded).
    poll_interval_s : float
        Interval between ``?`` status requests; GRBL recommends at most 5 Hz, so never below 0.2.
    boot_wait_s : float
        How long to wait for the banner or a status report after opening the port (boards that
        reset when the port opens print their banner after about 1–2 s).
    reconnects : int
        Reconnect attempts after the port vanishes, before giving up.
    reconnect_delay_s : float
        Pause before each reconnect attempt.
    angle_tolerance_deg : float
        Largest difference between the commanded and reported angle that counts as arrived.
    """

    axis: str = "X"
    steps_per_degree: float | None = None
    feed_deg_per_min: float = 3600.0
    lamps: list = field(default_factory=lambda: ["spindle", "flood"])
    spindle_power: float = 1000.0
    baudrate: int = 115200
    timeout_s: float = 2.0
    move_timeout_s: float = 60.0
    poll_interval_s: float = 0.25
    boot_wait_s: float = 2.5
    reconnects: int = 3
    reconnect_delay_s: float = 1.0
    angle_tolerance_deg: float = 0.01

    def __post_init__(self):
        self.validate("GrblConfig")

    def validate(self, path) -> None:
        """Raise :class:`WorkspaceError` naming the first field out of range."""
        if self.axis not in ("X", "Y", "Z"):
            raise WorkspaceError(path, "axis", "one of 'X', 'Y', 'Z'", got=self.axis)
        if not isinstance(self.lamps, list) or any(o not in OUTPUTS for o in self.lamps):
            raise WorkspaceError(path, "lamps", f"a list of outputs from {list(OUTPUTS)}", got=self.lamps)
        if len(set(self.lamps)) != len(self.lamps):
            raise WorkspaceError(path, "lamps", "each output at most once", got=self.lamps)
        if self.poll_interval_s < 0.2:
            raise WorkspaceError(path, "poll_interval_s", "at least 0.2 (GRBL: status at most 5 Hz)", got=self.poll_interval_s)
        positive = ["feed_deg_per_min", "spindle_power", "timeout_s", "move_timeout_s", "boot_wait_s", "angle_tolerance_deg"]
        if self.steps_per_degree is not None:
            positive.append("steps_per_degree")
        for name in positive:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
                raise WorkspaceError(path, name, "a positive number", got=value)
        if not isinstance(self.reconnects, int) or self.reconnects < 0:
            raise WorkspaceError(path, "reconnects", "a non-negative integer", got=self.reconnects)
        if not isinstance(self.baudrate, int) or self.baudrate <= 0:
            raise WorkspaceError(path, "baudrate", "a positive integer", got=self.baudrate)

    @classmethod
    def load(cls, path) -> "GrblConfig":
        """Read a configuration file; unknown fields are an error (they are usually typos)."""
        obj = read_json(path)
        known = set(cls.__dataclass_fields__)
        for key in obj:
            if key not in known:
                raise WorkspaceError(path, key, f"one of {sorted(known)}", got=key)
        try:
            return cls(**obj)
        except WorkspaceError as exc:
            raise WorkspaceError(path, exc.field, exc.expected, exc.got) from None

    def to_json(self) -> dict:
        return asdict(self)

    def lamp_states(self, outputs: dict) -> list[bool]:
        """Lamp on/off states from the controller's output states (``{"spindle": bool, …}``)."""
        return [bool(outputs.get(o, False)) for o in self.lamps]

    def check_firmware(self, options: str, settings: dict) -> None:
        """Raise :class:`WiringError` when the board cannot switch these lamps independently.

        ``options`` is the letter field of ``$I``'s ``[OPT:…]`` (``M``: built with ENABLE_M7),
        ``settings`` the ``$$`` values (``$32``: laser mode).
        """
        where = {o: k for k, o in enumerate(self.lamps)}
        if "flood" in where and "mist" in where:
            raise WiringError(
                f"lamps {where['flood']} (flood) and {where['mist']} (mist) cannot both be used: GRBL's only "
                "coolant-off command, M9, switches flood AND mist off, so one lamp cannot be switched off alone. "
                "Put one of them on the spindle output (hardware.json 'lamps').")
        if "mist" in where and "M" not in options:
            raise WiringError(
                f"lamp {where['mist']} is on the mist output, but this GRBL build has no M7 (it answers error:20; "
                "its $I options lack 'M'). Rebuild GRBL with ENABLE_M7 in config.h, or move the lamp to the "
                "flood or spindle output (hardware.json 'lamps').")
        if "spindle" in where and float(settings.get("$32", 0)) != 0:
            raise WiringError(
                f"lamp {where['spindle']} is on the spindle output, but the board is in laser mode ($32=1), which "
                "keeps that output off while the axes stand still. Send $32=0 to the board.")


@dataclass
class Confirmed:
    """The board's own word at one moment: state, turntable angle (degrees), lamp states."""

    state: str
    angle: float
    lamps: list

    def to_json(self) -> dict:
        return {"state": self.state, "angle": round(float(self.angle), 6), "lamps": [bool(x) for x in self.lamps]}


@dataclass
class Status:
    """One parsed status report."""

    state: str
    position: np.ndarray
    fields: dict
    outputs: dict | None  # None when this report carries no accessory field

    @property
    def idle(self) -> bool:
        return self.state == "Idle"

    @classmethod
    def parse(cls, line: str) -> "Status":
        """Parse ``<State|MPos:x,y,z|…>`` (``WPos`` is accepted as well, offsets ignored)."""
        parts = line[1:-1].split("|")
        fields = {}
        for part in parts[1:]:
            key, sep, value = part.partition(":")
            if not sep:
                raise GrblProtocolError(f"garbled status report {line!r}")
            fields[key] = value
        pos = fields.get("MPos", fields.get("WPos"))
        try:
            position = np.array([float(x) for x in pos.split(",")], dtype=np.float64)
        except (AttributeError, ValueError):
            raise GrblProtocolError(f"status report without a readable position: {line!r}") from None
        # GRBL reports accessories (A:) only alongside overrides (Ov:), and omits A: when all are off.
        outputs = None
        if "Ov" in fields:
            outputs = {o: _ACCESSORY[o] in fields.get("A", "") for o in OUTPUTS}
        return cls(parts[0], position, fields, outputs)


def _classify(line: str) -> str:
    """The kind of a received line, or ``garbled`` for anything GRBL 1.1 does not send."""
    if line == "ok":
        return "ok"
    if re.fullmatch(r"error:\d+", line):
        return "error"
    if re.fullmatch(r"ALARM:\d+", line):
        return "alarm"
    if line.startswith("<") and line.endswith(">"):
        return "status"
    if line.startswith("[") and line.endswith("]"):
        return "message"
    if _BANNER.match(line):
        return "banner"
    if re.fullmatch(r"\$\d+=[-0-9.]+", line) or re.fullmatch(r"\$N\d=.*", line) or line.startswith(">"):
        return "setting"
    return "garbled"


class GrblController:
    """The turntable and lamps behind one GRBL 1.1 board.

    Parameters
    ----------
    port : str
        Serial device (``/dev/ttyUSB0``, ``COM3``) or any URL pyserial's ``serial_for_url`` takes.
    config : GrblConfig, optional
    log : callable, optional
        Called with each informational line (``[MSG:…]``, reconnects).

    Notes
    -----
    Use as a context manager; :meth:`connect` is called on entry. A timeout, a garbled answer,
    ``error:N`` or an alarm raises a :class:`GrblError` subclass and sends nothing further; a
    vanished port is reopened up to ``config.reconnects`` times before :class:`DeviceLost`.
    """

    def __init__(self, port: str, config: GrblConfig | None = None, log=None):
        self.port = str(port)
        self.config = config or GrblConfig()
        self.log = log or (lambda msg: None)
        self.serial = None
        self.version = None
        self.reconnect_count = 0
        self.position: np.ndarray | None = None
        self.outputs: dict = {o: None for o in OUTPUTS}  # None: not known yet
        self._buffer = bytearray()
        self._last_poll = -np.inf
        self._pending_alarm: int | None = None
        self.options = ""  # $I's [OPT:…] letters
        self.resets_seen = 0  # banners seen outside a reset this driver asked for

    # ------------------------------------------------------------------ connection
    def __enter__(self) -> "GrblController":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def connect(self) -> "GrblController":
        """Open the port, wait for GRBL, read its state; raise :class:`GrblAlarm` if it is in Alarm."""
        self._open()
        try:
            status = self._handshake()
        except _PORT_ERRORS as exc:
            raise DeviceLost(f"{self.port} failed while connecting ({exc}); check the USB cable and the board's power") from None
        self.position = status.position
        if status.state not in ("Idle", "Alarm"):  # left moving or held (no line is processed in Hold)
            self.log(f"{self.port}: the board was in state {status.state}; stopping it (feed hold, soft reset)")
            status = self.halt()
        if status.state == "Alarm":  # after a critical alarm GRBL answers no line until reset: unlock()
            raise GrblAlarm(self._pending_alarm, f" on {self.port}")
        self._identify()
        self.confirm()
        return self

    def _identify(self) -> None:
        """``$I`` and ``$$``: the version, the build options and settings the lamps depend on."""
        for line in self.send("$I"):
            if line.startswith("[VER:"):
                self.version = line[5:-1].split(".20")[0].split(":")[0]
            elif line.startswith("[OPT:"):
                self.options = line[5:-1].split(",")[0]
        settings = {k: v for k, _, v in (s.partition("=") for s in self.send("$$"))}
        self.config.check_firmware(self.options, settings)
        if self.config.steps_per_degree is not None:
            self._ensure_steps_per_degree(settings)

    def close(self) -> None:
        if self.serial is not None:
            try:
                self.serial.close()
            except Exception:  # noqa: BLE001 - closing a vanished port must not mask the real error
                pass
            self.serial = None

    def _open(self) -> None:
        self.close()
        try:
            self.serial = serial.serial_for_url(
                self.port, baudrate=self.config.baudrate, timeout=0.05, write_timeout=self.config.timeout_s
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise PortUnavailable(
                f"cannot open {self.port} ({exc}). Check the USB cable and the board's power, that the port "
                "name is right and that no other program (a G-code sender) holds it."
            ) from None
        self._buffer.clear()

    def _handshake(self) -> Status:
        """Wait for the banner or a status report; as a last resort soft-reset and wait for the banner."""
        deadline = time.monotonic() + self.config.boot_wait_s
        while time.monotonic() < deadline:
            self._poll_status_byte()
            line = self._readline(min(deadline, time.monotonic() + self.config.poll_interval_s))
            if line is None:
                continue
            kind = _classify(line)
            if kind == "banner":
                self.version = _BANNER.match(line).group(1)
                self.outputs = {o: False for o in OUTPUTS}
                return self.status()
            if kind == "status":
                status = Status.parse(line)
                if status.outputs is not None:
                    self.outputs = dict(status.outputs)
                return status
            self._note(line, kind, "the banner")
        self._write(b"\x18")
        self._wait_banner()
        return self.status()

    def _wait_banner(self) -> None:
        deadline = time.monotonic() + self.config.timeout_s
        while True:
            line = self._readline(deadline)
            if line is None:
                raise GrblTimeout(
                    f"no GRBL banner on {self.port} within {self.config.timeout_s:g} s. Check the port, the baud "
                    f"rate ({self.config.baudrate}) and that the board runs GRBL 1.1."
                )
            kind = _classify(line)
            if kind == "banner":
                self.version = _BANNER.match(line).group(1)
                return
            if kind == "alarm":  # ALARM:3 precedes the banner of a reset during motion
                self._pending_alarm = int(line.split(":")[1])
                continue
            self._note(line, kind, "the banner")

    def _reconnect(self, cause: Exception) -> None:
        """Reopen a vanished port; raise :class:`DeviceLost` after ``config.reconnects`` tries."""
        self.close()
        for attempt in range(1, self.config.reconnects + 1):
            time.sleep(self.config.reconnect_delay_s)
            self.log(f"{self.port}: lost ({cause}); reconnect attempt {attempt} of {self.config.reconnects}")
            try:
                self._open()
                status = self._handshake()
            except (DeviceLost, *_PORT_ERRORS) as exc:
                cause = exc
                continue
            self.reconnect_count += 1
            if status.state == "Alarm":
                raise GrblAlarm(self._pending_alarm, f" after reconnecting to {self.port}")
            if self.position is not None and not np.allclose(status.position, self.position, atol=self.config.angle_tolerance_deg):
                raise GrblError(
                    f"{self.port}: the machine position changed across the reconnect ({self.position.tolist()} -> "
                    f"{status.position.tolist()}); the board probably reset. Re-zero the turntable, then resume."
                )
            return
        raise DeviceLost(
            f"lost {self.port} ({cause}) and {self.config.reconnects} reconnect attempts failed. Check the USB "
            "cable, the board's power and that the port name has not changed."
        )

    # ------------------------------------------------------------------ bytes
    def _write(self, data: bytes) -> None:
        if self.serial is None:
            raise DeviceLost(f"{self.port} is not open")
        try:
            self.serial.write(data)
            self.serial.flush()
        except serial.SerialTimeoutException:
            raise GrblTimeout(
                f"writing to {self.port} did not finish within {self.config.timeout_s:g} s. Check that the board "
                "is powered and not halted."
            ) from None

    def _readline(self, deadline: float) -> str | None:
        """One received line without its line end, or None at the deadline."""
        while True:
            end = self._buffer.find(b"\n")
            if end >= 0:
                raw = bytes(self._buffer[:end]).rstrip(b"\r")
                del self._buffer[: end + 1]
                if not raw:
                    continue
                try:
                    return raw.decode("ascii")
                except UnicodeDecodeError:
                    return raw.decode("ascii", "backslashreplace")  # classified as garbled
            if time.monotonic() >= deadline:
                return None
            chunk = self.serial.read(max(1, self.serial.in_waiting))
            self._buffer.extend(chunk)

    def _retrying(self, fn, *args):
        """Run ``fn``; when the port vanishes, reconnect (bounded) and run it again.

        Safe because every line this driver sends is idempotent.
        """
        while True:
            try:
                return fn(*args)
            except _PORT_ERRORS as exc:  # SerialException is an OSError
                self._reconnect(exc)

    def _note(self, line: str, kind: str, waiting_for: str) -> None:
        """Handle an unsolicited line; raise on the ones that end the operation."""
        if kind == "message" or kind == "setting":
            self.log(f"{self.port}: {line}")
        elif kind == "alarm":
            self._pending_alarm = int(line.split(":")[1])
            raise GrblAlarm(self._pending_alarm, f" while waiting for {waiting_for}")
        elif kind == "banner":
            self.resets_seen += 1
            self.outputs = {o: False for o in OUTPUTS}
            raise BoardReset(
                f"{self.port} reset while waiting for {waiting_for} (reset button, power dip or another program): "
                "its lamps are off and any move was abandoned")
        elif kind == "garbled":
            raise GrblProtocolError(
                f"garbled reply from {self.port} while waiting for {waiting_for}: {line!r}. Check the baud rate "
                f"({self.config.baudrate}), the cable (noise) and that the board runs GRBL 1.1; nothing further was sent."
            )
        # A stray ok/error/status outside a request (left from before a reconnect) is dropped.

    # ------------------------------------------------------------------ protocol
    def send(self, line: str) -> list[str]:
        """Send one G-code or ``$`` line and wait for ``ok``; return the lines that came before it.

        At most one line is ever unacknowledged. ``error:N`` raises :class:`GrblCommandError`.
        """
        line = line.strip()
        if "\n" in line or len(line) > 70:
            raise ValueError(f"one line of at most 70 characters (GRBL's limit is 80 with its buffer), got {line!r}")
        return self._retrying(self._exchange, line)

    def _exchange(self, line: str) -> list[str]:
        self._write((line + "\n").encode("ascii"))
        return self._await_ok(line)

    def _await_ok(self, line: str) -> list[str]:
        deadline = time.monotonic() + self.config.timeout_s
        info = []
        while True:
            got = self._readline(deadline)
            if got is None:
                raise GrblTimeout(
                    f"no answer to {line!r} from {self.port} within {self.config.timeout_s:g} s. Check that the board "
                    "is powered, runs GRBL 1.1 and is not halted; the session stopped before the next command."
                )
            kind = _classify(got)
            if kind == "ok":
                return info
            if kind == "error":
                raise GrblCommandError(line, int(got.split(":")[1]))
            if kind in ("setting", "message"):
                info.append(got)
                continue
            if kind == "status":
                continue
            self._note(got, kind, f"the answer to {line!r}")

    def _poll_status_byte(self) -> None:
        """Send ``?`` unless one went out less than ``poll_interval_s`` ago (GRBL: at most 5 Hz)."""
        wait = self._last_poll + self.config.poll_interval_s - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        self._last_poll = time.monotonic()
        self._write(b"?")

    def status(self) -> Status:
        """Ask for and parse one status report."""
        return self._retrying(self._status)

    def _status(self) -> Status:
        self._poll_status_byte()
        deadline = time.monotonic() + self.config.timeout_s
        while True:
            got = self._readline(deadline)
            if got is None:
                raise GrblTimeout(
                    f"no status report from {self.port} within {self.config.timeout_s:g} s. Check that the board "
                    "is powered and runs GRBL 1.1."
                )
            kind = _classify(got)
            if kind == "status":
                status = Status.parse(got)
                self.position = status.position
                if status.outputs is not None:
                    self.outputs = dict(status.outputs)
                return status
            self._note(got, kind, "a status report")

    def realtime(self, byte: bytes) -> None:
        """Send a real-time command: ``b"!"`` feed hold, ``b"~"`` cycle start, ``b"\\x18"`` soft reset."""
        if byte not in (b"!", b"~", b"\x18", b"?"):
            raise ValueError(f"not a GRBL real-time command: {byte!r}")
        self._retrying(self._write, byte)

    def soft_reset(self) -> None:
        """0x18: stop everything and wait for the banner (outputs off; motion discarded)."""
        self.realtime(b"\x18")
        self._wait_banner()
        self.outputs = {o: False for o in OUTPUTS}

    def halt(self) -> Status:
        """Stop the turntable and switch every output off, keeping the position where possible.

        A feed hold ``!`` first, then, once the axes stand still (``Hold:0``, ``Idle``), a soft reset:
        GRBL keeps the position after a reset in a completed hold, and gives ``ALARM:3`` (position
        probably lost) only when reset while still moving, which happens here only after
        ``move_timeout_s``.
        """
        self.realtime(b"!")
        deadline = time.monotonic() + self.config.move_timeout_s
        status = None
        while time.monotonic() < deadline:
            try:
                status = self.status()
            except (BoardReset, GrblAlarm):
                break  # it already reset: outputs off, motion discarded
            if status.state in ("Idle", "Hold:0", "Alarm") or status.state.startswith("Door"):
                break
        self._pending_alarm = None
        self.soft_reset()
        return self.status()

    def safe_stop(self) -> None:
        """Best effort after a fault: the board stopped and the lamps off; never raises ``GrblError``."""
        try:
            status = self.status()
            if status.state == "Idle":
                self._pending_alarm = None
                self.send("M5")
                self.send("M9")
                self.outputs = {o: False for o in OUTPUTS}
            elif status.state != "Alarm":  # an alarm's reset already switched every output off
                self.halt()
        except (GrblError, *_PORT_ERRORS):
            try:
                self.halt()
            except (GrblError, *_PORT_ERRORS):
                pass

    def confirm(self) -> "Confirmed":
        """What the board itself says now: its state and angle (``?``) and the lamps (``$G``).

        Raises :class:`BoardHeld` in a hold this driver did not ask for (no line is answered
        there), :class:`GrblAlarm` in Alarm, :class:`BoardReset` when a banner arrives.
        """
        status = self.status()
        if status.state == "Alarm":
            raise GrblAlarm(self._pending_alarm, f" on {self.port}")
        if status.state.startswith(("Hold", "Door")):
            self._stop_held(status)
        modes = [line for line in self.send("$G") if line.startswith("[GC:")]
        if not modes:
            raise GrblProtocolError(f"{self.port} answered $G without its [GC:…] line")
        words = modes[-1][4:-1].split()
        self.outputs = {"spindle": bool({"M3", "M4"} & set(words)),
                        "flood": "M8" in words, "mist": "M7" in words}
        # A reset or alarm after the report shows as its banner or ALARM line before $G's ok.
        return Confirmed(status.state, self.angle, self.lamps)

    def _stop_held(self, status: Status) -> None:
        """A hold this driver did not ask for: stop for good (reset keeps the position), then raise."""
        self.halt()
        raise BoardHeld(
            f"{self.port} went into {status.state} without reflab asking (the hold button or another program). "
            f"It was stopped at {self.angle:.3f} deg with a soft reset, lamps off; run again (with --resume) "
            "to go on.")

    def unlock(self) -> list[str]:
        """Leave the Alarm state: soft reset (critical alarms need it), then ``$X``."""
        self._pending_alarm = None
        self.soft_reset()
        info = self.send("$X")
        self._identify()
        self.confirm()
        return info

    def _ensure_steps_per_degree(self, current: dict) -> None:
        """Write ``$10N`` only when it differs: GRBL stores settings in EEPROM."""
        key = f"$10{'XYZ'.index(self.config.axis)}"
        want = float(self.config.steps_per_degree)
        if key not in current or abs(float(current[key]) - want) > 1e-3:
            self.send(f"{key}={want:.3f}")

    # ------------------------------------------------------------------ the rig
    @property
    def axis_index(self) -> int:
        return "XYZ".index(self.config.axis)

    @property
    def angle(self) -> float:
        """The turntable angle (degrees) in the last status report."""
        return float(self.position[self.axis_index])

    @property
    def lamps(self) -> list:
        """Lamp states as last confirmed (``$G``, an ``A:`` field) or commanded; None where unknown."""
        return [None if self.outputs.get(o) is None else bool(self.outputs[o]) for o in self.config.lamps]

    def rotate_to(self, degrees: float, hold=None, cancelled=None) -> Status:
        """Turn the turntable to an absolute angle and wait for ``Idle`` there.

        Parameters
        ----------
        degrees : float
        hold : callable, optional
            Returns True while the caller wants the motion paused: a feed hold ``!`` is sent, and
            ``~`` once it returns False. Time in hold does not count toward ``move_timeout_s``.
        cancelled : callable, optional
            Returns True to abandon the move: while held the board is soft-reset (position kept,
            the rest of the move discarded) and :class:`MoveCancelled` is raised.
        """
        if not np.isfinite(degrees):
            raise ValueError(f"turntable angle must be finite, got {degrees!r}")
        self.send(f"G90 G1 {self.config.axis}{degrees:.3f} F{self.config.feed_deg_per_min:.1f}")
        return self.wait_idle(degrees, hold, cancelled)

    def wait_idle(self, degrees: float | None = None, hold=None, cancelled=None) -> Status:
        """Poll status (at most 1 / ``poll_interval_s``) until ``Idle``; check the angle reached."""
        budget = self.config.move_timeout_s
        held = False
        last = time.monotonic()
        stale = 1  # one Idle report at the old place is let through: the cycle may not have started yet
        while True:
            status = self.status()
            now = time.monotonic()
            if not held:
                budget -= now - last
            last = now
            if status.state == "Alarm":
                raise GrblAlarm(self._pending_alarm, " during a turntable move")
            if not held and status.state.startswith(("Hold", "Door")):
                self._stop_held(status)
            if (status.idle and not held and stale and degrees is not None
                    and abs(self.angle - degrees) > self.config.angle_tolerance_deg):
                stale -= 1
                continue
            want_hold = bool(hold and hold())
            if want_hold and not held:
                self.realtime(b"!")
                held = True
            elif held and not want_hold:
                self.realtime(b"~")
                held = False
            if held and cancelled and cancelled():
                self.soft_reset()
                raise MoveCancelled(f"move to {degrees} deg cancelled during feed hold")
            if status.idle and not held:
                break
            if budget <= 0:
                raise GrblTimeout(
                    f"the turntable did not reach Idle within {self.config.move_timeout_s:g} s (state {status.state}). "
                    "Check the motor driver and the feed rate in the configuration."
                )
        if degrees is not None and abs(self.angle - degrees) > self.config.angle_tolerance_deg:
            raise GrblError(
                f"the turntable stopped at {self.angle:.3f} deg instead of {degrees:.3f} deg. Check the "
                f"{self.config.axis} axis configuration (soft limits, max travel)."
            )
        return status

    def set_lamp(self, index: int, on: bool) -> None:
        """Switch lamp ``index`` (position in ``config.lamps``) on or off."""
        if not 0 <= index < len(self.config.lamps):
            raise ValueError(f"lamp {index} is not configured (lamps: 0..{len(self.config.lamps) - 1})")
        output = self.config.lamps[index]
        self._set_output(output, bool(on))

    def set_lamps(self, states) -> None:
        """Switch every lamp to ``states[k]``, sending only the changes."""
        states = [bool(s) for s in states]
        if len(states) != len(self.config.lamps):
            raise ValueError(f"{len(states)} lamp states for {len(self.config.lamps)} configured lamps")
        for k, on in enumerate(states):
            if self.outputs[self.config.lamps[k]] is not on:
                self.set_lamp(k, on)

    def _set_output(self, output: str, on: bool) -> None:
        # check_firmware refused flood and mist together: M9 here switches only this lamp's output.
        if output == "spindle":
            self.send(f"M3 S{self.config.spindle_power:g}" if on else "M5")
        elif on:
            self.send("M8" if output == "flood" else "M7")
        else:
            self.send("M9")
            self.outputs["mist" if output == "flood" else "flood"] = False
        self.outputs[output] = on
