"""The rig as the window sees it: one controller and one camera, shared by the preview and the steps.

``port`` is a serial port or ``sim`` (hardware/sim/device.py's board on a pseudo-terminal);
``camera`` is ``sim`` (the simulated lab at the board's true angle and lamps), ``opencv:N`` or
``folder:PATH`` (hardware/cameras.py). Every use of the controller or the camera holds
:attr:`Rig.lock`, so the live preview never talks to the camera while a capture does; the
preview only *tries* the lock and skips a frame when a step holds it.
"""
from __future__ import annotations

import threading
from pathlib import Path

import numpy as np


class RigError(RuntimeError):
    """The rig is not connected, or a device refused (the message says which)."""


class Rig:
    """Connect, jog, switch lamps, preview and capture on one controller and one camera."""

    def __init__(self, workspace, port: str = "sim", camera: str = "sim", *, size=(320, 240), depth: int = 2,
                 grain: float = 0.2, log=None):
        self.workspace = Path(workspace)
        self.port_spec, self.camera_spec = port, camera
        self.size, self.depth, self.grain = tuple(size), int(depth), float(grain)
        self.log = log or (lambda msg: None)
        self.lock = threading.RLock()
        self.controller = self.camera = self.sim = self.config = None

    # ------------------------------------------------------------------ connection
    @property
    def connected(self) -> bool:
        return self.controller is not None

    def _load_config(self):
        from hardware.grbl import GrblConfig

        path = self.workspace / "hardware.json"
        return GrblConfig.load(path) if path.exists() else GrblConfig()

    def connect(self) -> str:
        """Open the board (starting the simulated one for ``sim``) and the camera; return the status line."""
        from hardware.grbl import GrblController

        with self.lock:
            if self.connected:
                return self.status()
            self.config = self._load_config()
            port = self.port_spec
            if port == "sim":
                from hardware.sim.device import SimulatedGrbl

                self.sim = SimulatedGrbl(time_scale=20.0).start()
                port = self.sim.port
                self.log(f"simulated GRBL board on {port}")
            ctl = GrblController(port, self.config, log=self.log)
            try:
                ctl.connect()
                self.camera = self._open_camera(ctl)
            except BaseException:
                ctl.close()
                self._stop_sim()
                raise
            self.controller = ctl
            return self.status()

    def _open_camera(self, ctl):
        if self.camera_spec != "sim":
            from hardware.cameras import open_camera

            return open_camera(self.camera_spec)
        from hardware.sim.camera import SimulatedCamera, lab_renderer
        from hardware.sim.lab import build_lab

        lab = build_lab(*self.size, grain=self.grain)
        if len(self.config.lamps) != len(lab.lights):
            raise RigError(f"the simulated lab has {len(lab.lights)} lamps but hardware.json maps {len(self.config.lamps)}")
        sim, axis = self.sim, self.config.axis
        if sim is not None:
            state = lambda: (sim.turntable(axis), self.config.lamp_states(sim.lamp_outputs()))  # noqa: E731
        else:
            state = lambda: (ctl.angle, ctl.lamps)  # noqa: E731
        return SimulatedCamera(lab_renderer(lab, depth=self.depth), state,
                               lab={"grain": self.grain, "fixed": ["ground"], "centre": [0.0, 0.0]})

    def _stop_sim(self) -> None:
        if self.sim is not None:
            self.sim.stop()
            self.sim = None

    def disconnect(self) -> None:
        with self.lock:
            if self.controller is not None:
                self.controller.close()
            if self.camera is not None:
                self.camera.close()
            self.controller = self.camera = None
            self._stop_sim()

    def require(self):
        if not self.connected:
            raise RigError("the rig is not connected: connect it on the Devices page first")
        return self.controller

    # ------------------------------------------------------------------ manual control
    def status(self) -> str:
        with self.lock:
            ctl = self.require()
            lamps = ", ".join(f"lamp {k} {'on' if on else 'off'}" for k, on in enumerate(ctl.lamps))
            return f"{ctl.status().state}, turntable {ctl.angle:.1f}°, {lamps} (GRBL {ctl.version} on {ctl.port})"

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
        """One frame from the camera, or None when a step holds the rig (never waits for it)."""
        if not self.lock.acquire(blocking=blocking):
            return None
        try:
            if self.camera is None:
                return None
            return np.asarray(self.camera.capture(None))
        finally:
            self.lock.release()

    def write_config(self) -> Path:
        """WORKSPACE/hardware.json: the configuration the captures of this workspace use."""
        from hardware.workspace import write_json

        return write_json(self.workspace / "hardware.json", self.config.to_json())
