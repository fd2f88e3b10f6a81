"""GRBL 1.1h itself (gnea/grbl under grbl-sim) on a pseudo-terminal, for the firmware tests.

The sources are the project's ``../shared/third_party`` tarballs; the program is built once per
tarball pair into ``~/.cache/reflab-grbl-sim/<hash>/``. GRBL is not touched; grbl-sim's host glue
is patched (see ``_PATCHES``): stdin read unbuffered (stdio kept bytes back until the next line),
output flushed per line, 1 ms sleeps instead of busy loops, no sleep between a received line and
the cycle start (a stale ``Idle`` report otherwise), GRBL's serial.c at -O0 (at -O2 the TX head is
stored before the byte: garbled reports), and a *probe*: the step counters and the spindle and
coolant pins written into a shared file, read here as the rig physically is (the camera's truth).

The pseudo-terminal is bridged in Python: the firmware's stdin/stdout are pipes, a thread copies
bytes between them and the pty master, and the client opens the slave (``port``, a symlink).
"""
from __future__ import annotations

import hashlib
import mmap
import os
import select
import shutil
import struct
import subprocess
import tarfile
import tempfile
import threading
import time
from pathlib import Path

THIRD_PARTY = Path(__file__).resolve().parents[1].parent / "shared" / "third_party"
TARBALLS = ("gnea-grbl-1.1h.tar.gz", "grbl-sim.tar.gz")
PROBE_FORMAT = "<Iiiiiiii"  # seq, x, y, z steps, spindle, flood, mist pins, sys.state
PROBE_SIZE = struct.calcsize(PROBE_FORMAT)

_POLL_STDIN = r'''
uint8_t platform_poll_stdin() {
  uint8_t char_in = 0;
  struct timeval tv = {0};
  fd_set rdfs;
  FD_ZERO(&rdfs);
  FD_SET(STDIN_FILENO, &rdfs);
  if (select(STDIN_FILENO + 1, &rdfs, NULL, NULL, &tv) > 0 && read(STDIN_FILENO, &char_in, 1) != 1) {
    char_in = 0x06;  /* EOF: the bridge closed; ^F exits the simulator */
  }
  return char_in;
}
'''
_SERIAL_READ = r'''
uint8_t serial_read() {
  static uint8_t idle = 0;
  uint8_t c = orig_serial_read();
  if (c == SERIAL_NO_DATA) {
    if (idle) { platform_sleep(1000); }
    idle = 1;
  } else {
    idle = 0;
  }
  return c;
}
'''
_PROBE = r'''
#include <fcntl.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <unistd.h>
#include "../spindle_control.h"
#include "../coolant_control.h"
static volatile int32_t *probe_map = NULL;
static void probe_write(void) {
  static int tried = 0;
  if (!tried) {
    const char *path = getenv("REFLAB_GRBL_PROBE");
    tried = 1;
    if (path) {
      int fd = open(path, O_RDWR);
      if (fd >= 0) {
        void *m = mmap(NULL, 64, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
        if (m != MAP_FAILED) { probe_map = (volatile int32_t *)m; }
        close(fd);
      }
    }
  }
  if (!probe_map) { return; }
  probe_map[0]++;
  __sync_synchronize();
  probe_map[1] = sys_position[X_AXIS];
  probe_map[2] = sys_position[Y_AXIS];
  probe_map[3] = sys_position[Z_AXIS];
  probe_map[4] = spindle_get_state() != SPINDLE_STATE_DISABLE;
  probe_map[5] = (coolant_get_state() & COOLANT_STATE_FLOOD) != 0;
  probe_map[6] = (coolant_get_state() & COOLANT_STATE_MIST) != 0;
  probe_map[7] = sys.state;
  __sync_synchronize();
  probe_map[0]++;
}
'''
#: (file under grbl/grbl-sim, old text, new text); each must match exactly once.
_PATCHES = [
    ("platform_LINUX.c", "uint8_t platform_poll_stdin() {", "uint8_t platform_poll_stdin_stdio() {"),
    ("platform_LINUX.c", "#include \"platform.h\"\n", "#include \"platform.h\"\n#include <sys/select.h>\n" + _POLL_STDIN),
    ("serial.c", "uint8_t serial_read() {\n  platform_sleep(0);\n  return orig_serial_read();\n}", _SERIAL_READ),
    ("simulator.c", "fprintf(args.serial_out_file,\"%s\",buf);", "fprintf(args.serial_out_file,\"%s\",buf);\n   fflush(args.serial_out_file);"),
    ("simulator.c", "platform_sleep(0); //yield", "platform_sleep(1000); //yield"),
    ("grbl_interface.c", "void print_steps(bool force);", "void print_steps(bool force);\n" + _PROBE),
    ("grbl_interface.c", "  printBlock();\n", "  printBlock();\n  probe_write();\n"),
]
_BUILD_VERSION = "1"


def missing() -> str | None:
    """Why the firmware cannot be built here, or None."""
    for name in TARBALLS:
        if not (THIRD_PARTY / name).exists():
            return f"{THIRD_PARTY / name} is missing (the project's shared third_party folder)"
    if not (shutil.which("cc") or shutil.which("gcc")):
        return "no C compiler (cc/gcc) to build grbl-sim"
    if not shutil.which("make"):
        return "no make to build grbl-sim"
    return None


def build(cache: Path | None = None) -> Path:
    """The grbl-sim program for GRBL 1.1h, built once into the cache (keyed by the tarballs' hash)."""
    h = hashlib.sha256(_BUILD_VERSION.encode() + repr(_PATCHES).encode())
    for name in TARBALLS:
        h.update((THIRD_PARTY / name).read_bytes())
    cache = Path(cache or Path.home() / ".cache" / "reflab-grbl-sim") / h.hexdigest()[:16]
    exe = cache / "grbl_sim.exe"
    if exe.exists():
        return exe
    cache.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=cache.parent) as tmp:
        tmp = Path(tmp)
        with tarfile.open(THIRD_PARTY / TARBALLS[0]) as tar:
            tar.extractall(tmp, filter="data")
        grbl = next(p for p in tmp.glob("*/grbl") if p.is_dir())
        with tarfile.open(THIRD_PARTY / TARBALLS[1]) as tar:
            tar.extractall(grbl, filter="data")
        sim = grbl / "grbl-sim"
        for name, old, new in _PATCHES:
            text = (sim / name).read_text()
            if text.count(old) != 1:
                raise RuntimeError(f"grbl-sim patch does not apply to {name}: {old[:40]!r}")
            (sim / name).write_text(text.replace(old, new))
        env = dict(os.environ, MAKEFLAGS="")
        run = lambda *args: subprocess.run(["make", "-j2", *args], cwd=sim, env=env, check=True,  # noqa: E731
                                           capture_output=True, text=True)
        try:
            run("../serial.o", "serial.o", "FLAGS=-g -O0 -fcommon")
            run("main", "FLAGS=-g -O2 -fcommon")
        except subprocess.CalledProcessError as exc:
            raise RuntimeError(f"building grbl-sim failed: {exc.stderr[-2000:]}") from None
        cache.mkdir(parents=True, exist_ok=True)
        staged = cache / "grbl_sim.exe.tmp"
        shutil.copy2(sim / "grbl_sim.exe", staged)
        os.replace(staged, exe)
    return exe


class Firmware:
    """One GRBL 1.1h board: the firmware process, its pseudo-terminal and its probe.

    Parameters
    ----------
    exe : Path
    folder : Path
        Working folder (GRBL's EEPROM.DAT lives there: settings survive a restart in it).
    """

    def __init__(self, exe: Path, folder: Path):
        self.exe, self.folder = Path(exe), Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.port = str(self.folder / "ttyGRBL")
        self.probe_path = self.folder / "probe.bin"
        self.received = bytearray()  # what the host sent, for assertions
        self.proc = None
        self._master = self._slave = None
        self._threads = []
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ life cycle
    def start(self) -> "Firmware":
        self.probe_path.write_bytes(b"\0" * 64)
        self.proc = subprocess.Popen([str(self.exe), "-n", "-t", "1", "-s", "/dev/null", "-b", "/dev/null"],
                                     cwd=self.folder, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, env=dict(os.environ, REFLAB_GRBL_PROBE=str(self.probe_path)),
                                     bufsize=0)
        self._plug()
        return self

    def _plug(self) -> None:
        import tty

        master, slave = os.openpty()
        tty.setraw(slave)
        link = Path(self.port)
        tmp = link.with_name(link.name + ".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(slave))
        os.replace(tmp, link)
        self._master, self._slave = master, slave  # the slave stays open: the master never sees EIO
        self._running = True
        self._threads = [threading.Thread(target=self._to_board, daemon=True),
                         threading.Thread(target=self._to_host, daemon=True)]
        for t in self._threads:
            t.start()

    def _to_board(self) -> None:
        master = self._master
        while self._running:
            ready, _, _ = select.select([master], [], [], 0.05)
            if not ready:
                continue
            try:
                data = os.read(master, 4096)
            except OSError:
                return
            with self._lock:
                self.received.extend(data)
                self._feed(data)

    def _to_host(self) -> None:
        out = self.proc.stdout.fileno()
        while self._running:
            ready, _, _ = select.select([out], [], [], 0.05)
            if not ready:
                continue
            data = os.read(out, 4096)
            if not data:
                return
            try:
                os.write(self._master, data)
            except OSError:
                pass

    def _feed(self, data: bytes) -> None:
        try:
            self.proc.stdin.write(data)
        except (BrokenPipeError, OSError):
            pass

    def inject(self, data: bytes) -> None:
        """Bytes into the board as if from the host (a soft reset 0x18, a feed hold ``!``)."""
        with self._lock:
            self._feed(data)

    def stop(self) -> None:
        self._running = False
        for t in self._threads:
            t.join(timeout=1)
        if self.proc is not None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
            try:
                self.proc.wait(timeout=2)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            self.proc.stdout.close()
            self.proc = None
        Path(self.port).unlink(missing_ok=True)
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # ------------------------------------------------------------------ set-up and truth
    def configure(self, lines, timeout: float = 10.0, wait_banner: bool = True) -> list[str]:
        """Send lines (``$110=…``) over the port as a plain terminal would, one ``ok`` at a time
        (after the boot banner unless ``wait_banner`` is False)."""
        import serial

        answers = []
        with serial.Serial(self.port, 115200, timeout=0.05) as port:
            buf = b""
            deadline = time.monotonic() + timeout
            while wait_banner and b"['$' for help]" not in buf:  # boot: a fresh EEPROM prints error:7 and the defaults first
                buf += port.read(256)
                if time.monotonic() > deadline:
                    raise TimeoutError(f"no GRBL banner: {buf!r}")
            buf = b""
            for line in lines:
                port.write(line.encode() + b"\n")
                while True:
                    buf += port.read(256)
                    text = buf.decode("latin-1")
                    if "ok\r\n" in text or "error:" in text:
                        answers.append(text.strip())
                        buf = b""
                        break
                    if time.monotonic() > deadline:
                        raise TimeoutError(f"GRBL did not answer {line!r}: {text!r}")
        return answers

    def truth(self) -> dict:
        """The board as it physically is: step counters and output pins (read through the probe)."""
        with open(self.probe_path, "rb") as f:
            m = mmap.mmap(f.fileno(), 64, access=mmap.ACCESS_READ)
            try:
                for _ in range(1000):
                    raw = m[:PROBE_SIZE]
                    seq, x, y, z, spindle, flood, mist, state = struct.unpack(PROBE_FORMAT, raw)
                    if seq % 2 == 0 and struct.unpack("<I", m[:4])[0] == seq:
                        break
                    time.sleep(0.0001)
            finally:
                m.close()
        return {"steps": (x, y, z), "spindle": bool(spindle), "flood": bool(flood), "mist": bool(mist),
                "state": state, "seq": seq}
