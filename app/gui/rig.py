"""The rig as the window sees it: one controller and one camera, shared by the preview and the steps.

``port`` is a serial port or ``sim`` (hardware/sim/device.py's board on a pseudo-terminal);
``camera`` is ``sim`` (the simulated lab at the board's true angle and lamps), ``opencv:N`` or
``folder:PATH`` (hardware/cameras.py), opened by app/devices.py. Every use of the controller or the camera holds
:attr:`Rig.lock`, so the live preview never talks to the camera while a capture does; the
preview only *tries* the lock and skips a frame when a step holds it.
"""
from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from reflab.app.devices import SIM_SIZE
from reflab.core.workspace import Workspace


class RigError(RuntimeError):
    """The rig is not connected, or a device refused (the message says which)."""


class Rig:
    """Connect, jog, switch lamps, preview and capture on one controller and one camera."""

    def __init__(self, workspace, port: str = "sim", camera: str = "sim", *, size=SIM_SIZE, log=None):
        self.workspace = Path(workspace)
        self.port_spec, self.camera_spec, self.size = port, camera, tuple(size)
        self.log = log or (lambda msg: None)
        self.lock = threading.RLock()
        self.devices = None  # reflab.app.devices.Devices while connected
        self._shown = (None, None)  # (file, mtime, size) and image of a tethered camera's newest shot

    # ------------------------------------------------------------------ connection
    @property
    def connected(self) -> bool:
        return self.devices is not None

    controller = property(lambda self: self.devices.controller if self.devices else None)
    camera = property(lambda self: self.devices.camera if self.devices else None)
    sim = property(lambda self: self.devices.board if self.devices else None)  # the simulated board, if any

    @property
    def config(self):
        from reflab.app.devices import load_config

        if self.devices is not None:
            return self.devices.config
        path = Workspace(self.workspace).hardware
        return load_config(path if path.exists() else None)

    def connect(self) -> str:
        """Open the board (starting the simulated one for ``sim``) and the camera (app/devices.py); the status line."""
        from reflab.app.devices import Devices, SimOptions

        with self.lock:
            if not self.connected:
                self.devices = Devices(self.port_spec, self.camera_spec, config=self.config,
                                       sim=SimOptions(size=self.size), log=self.log)
            return self.status()

    def disconnect(self) -> None:
        with self.lock:
            if self.devices is not None:
                self.devices.close()
            self.devices = None

    def require(self):
        if not self.connected:
            raise RigError("the rig is not connected: connect it on the Devices page first")
        return self.controller

    # ------------------------------------------------------------------ manual control
    def status(self) -> str:
        with self.lock:
            ctl = self.require()
            now = ctl.confirm()  # the lamps from $G: a status report's A: field is usually absent
            lamps = ", ".join(f"lamp {k} {'on' if on else 'off'}" for k, on in enumerate(now.lamps))
            return f"{now.state}, turntable {now.angle:.1f}°, {lamps} (GRBL {ctl.version} on {ctl.port})"

    def rotate(self, degrees: float, relative: bool = True) -> str:
        with self.lock:
            ctl = self.require()
            ctl.rotate_to(ctl.angle + degrees if relative else degrees)
            return self.status()

    def set_lamp(self, index: int, on: bool) -> str:
        with self.lock:
            self.require().set_lamp(index, on)
            return self.status()

    def preview(self, blocking: bool = False):
        """One frame from the camera, or None when a step holds the rig (never waits for it).

        A tethered camera (``folder:``) has no live view: its newest image in the folder stands in,
        so a preview never fires its shutter nor waits for a shot."""
        from reflab.hardware.cameras import FolderCamera

        if not self.lock.acquire(blocking=blocking):
            return None
        try:
            if self.camera is None:
                return None
            if isinstance(self.camera, FolderCamera):
                return self._newest(self.camera.folder)
            return np.asarray(self.camera.capture(None))
        finally:
            self.lock.release()

    def _newest(self, folder: Path):
        """The newest complete image in ``folder`` (read again only when it changes), or None."""
        from reflab.hardware.cameras import FOLDER_SUFFIXES
        from reflab.core.images import read_image
        from reflab.core.workspace import WorkspaceError

        files = [p for p in folder.iterdir() if p.suffix.lower() in FOLDER_SUFFIXES and not p.name.startswith(".")]
        if not files:
            return None
        path = max(files, key=lambda p: p.stat().st_mtime)
        key = (path, path.stat().st_mtime, path.stat().st_size)
        if self._shown[0] != key:
            try:
                self._shown = (key, read_image(path))
            except WorkspaceError:  # still being written: the last one shown stays
                return self._shown[1]
        return self._shown[1]

    def write_config(self) -> Path:
        """WORKSPACE/hardware.json: the configuration the captures of this workspace use."""
        from reflab.core.workspace import write_json

        return write_json(Workspace(self.workspace).hardware, self.config.to_json())
