"""Open the rig (GRBL board + camera) for a capture, on hardware or on the simulated lab.

``reflab.hardware.capture.run_capture`` takes opened devices; this is where ``--port sim`` and
``--camera sim`` become the simulated twin (``hardware/sim``), which product code never imports.
The CLI (``reflab capture``), the GUI and the demo open their devices here.
"""
from __future__ import annotations

from dataclasses import dataclass

from reflab.core.options import float_list, image_size, opt

#: The simulated camera's default image size: at 320x240 structure from motion registers too few
#: of the simulated sweep's shots (docs/reconstruction.md), so every default is 480x360.
SIM_SIZE = (480, 360)


def load_config(path):
    """The hardware configuration at ``path``, or the defaults when it is None."""
    from reflab.hardware.grbl import GrblConfig

    return GrblConfig.load(path) if path else GrblConfig()


def open_port(port: str, log=print):
    """(port name, simulated board or None) for ``--port``; 'sim' starts a simulated board."""
    if port != "sim":
        return port, None
    from reflab.hardware.sim.device import SimulatedGrbl

    sim = SimulatedGrbl(time_scale=20.0).start()
    log(f"simulated GRBL board on {sim.port}")
    return sim.port, sim


@dataclass
class SimOptions:
    """The simulated camera's knobs (``--camera sim``): image size, ray depth, turntable axis
    (x, y, metres), ambient radiance added to every pixel, print grain of the lab's textures."""

    size: tuple = opt(SIM_SIZE, "simulated camera image size WxH (at 320x240 structure from motion registers too "
                                "few sweep shots)", type=image_size, metavar="WxH")
    depth: int = opt(3, "maximum internal nodes per path of the simulated camera's renderer", flag="--sim-depth",
                     aliases=("--depth",))
    centre: list = opt(factory=lambda: [0.0, 0.0], help="where the turntable axis meets the ground, x,y",
                       unit="m", flag="--turntable-centre", aliases=("--centre",), type=float_list, metavar="X,Y")
    room_light: float = opt(0.0, "ambient radiance added to every pixel")
    grain: float = opt(0.2, "fine print grain of the lab's textures (as printed paper has; 0 = the plain procedural "
                            "lab, too poorly textured for structure from motion)")


class Devices:
    """A connected controller and camera (and the simulated board, when ``port`` is "sim").

    Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, port: str, camera: str, *, config=None, unlock: bool = False, sim: SimOptions | None = None,
                 trigger=None, camera_timeout: float = 60.0, log=print):
        from reflab.hardware.grbl import GrblAlarm, GrblController

        self.config = config if config is not None else load_config(None)
        self.camera = None
        name, self.board = open_port(port, log)
        self.controller = GrblController(name, self.config, log=log)
        try:
            try:
                self.controller.connect()
            except GrblAlarm:
                if not unlock:
                    raise
                self.controller.unlock()
                log(f"{name}: unlocked")
            self.camera = self._open_camera(camera, sim or SimOptions(), trigger, camera_timeout)
        except BaseException:
            self.close()
            raise

    def _open_camera(self, spec: str, sim: SimOptions, trigger, timeout_s: float):
        from reflab.hardware.cameras import open_camera

        if spec != "sim":
            if spec.startswith("folder:"):
                return open_camera(spec, trigger=trigger.split() if isinstance(trigger, str) else trigger,
                                   timeout_s=timeout_s)
            return open_camera(spec)
        from reflab.hardware.sim.camera import SimulatedCamera, lab_renderer
        from reflab.hardware.sim.lab import build_lab
        from reflab.hardware.sim.props import LabProps

        if not 0.0 <= sim.grain < 1.0:
            raise ValueError(f"--grain must be in [0, 1), got {sim.grain}")
        if len(sim.centre) != 2:
            raise ValueError(f"--turntable-centre takes x,y, got {sim.centre}")
        lab = build_lab(*sim.size, grain=sim.grain)
        if len(self.config.lamps) != len(lab.lights):
            raise ValueError(f"the simulated lab has {len(lab.lights)} lamps but the configuration "
                             f"maps {len(self.config.lamps)} ({self.config.lamps})")
        ctl, board, config = self.controller, self.board, self.config
        if board is not None:  # the simulated board's axis and outputs: the rig as it really is
            state = lambda: (board.turntable(config.axis), config.lamp_states(board.lamp_outputs()))  # noqa: E731
        else:
            state = lambda: (ctl.angle, ctl.lamps)  # noqa: E731
        # The simulated user shows the props a shot's role needs: the circle target (calibration),
        # the rod and grey card (lights); the bare scene otherwise (reflab.hardware.sim.props.LabProps).
        camera = SimulatedCamera(lab_renderer(lab, depth=sim.depth, centre=sim.centre, props=LabProps()), state,
                                 ambient=sim.room_light, lab={"grain": sim.grain, "fixed": ["ground"], "centre": list(sim.centre)})
        camera.sim_lab = lab  # for the simulated user's marks after a sweep (reflab.hardware.sim.user)
        return camera

    def close(self) -> None:
        self.controller.close()
        if self.camera is not None:
            self.camera.close()
            self.camera = None
        if self.board is not None:
            self.board.stop()
            self.board = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
