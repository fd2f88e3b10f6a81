"""The simulated camera: the virtual lab rendered at the simulated rig's turntable angle and lamps."""
from __future__ import annotations

import numpy as np


class SimulatedCamera:
    """The virtual lab seen at the rig's current turntable angle and lamp states.

    Parameters
    ----------
    render : callable
        ``render(angle_deg, lamps) -> (H, W, 3)`` linear radiance (see :func:`lab_renderer`).
    state : callable
        ``state() -> (angle_deg, lamps)``: the rig as it physically is (the simulated board's
        axis and outputs), so that a move or lamp command that did not happen shows in the image.
    ambient : float
        Room light added to every pixel, lamps on or off (what a lamps-off frame removes).
    reference_exposure : float
        The exposure at which a pixel holds the radiance itself; pixels scale with exposure.
    lab : dict, optional
        How the lab was built (e.g. its print grain, what stays still), recorded by :meth:`describe`.

    The image size is a setting, as a real camera's resolution is (:meth:`set_size`): a capture
    session sets the size its shots must have, and ``render`` is asked for it when it takes ``size``.
    """

    def __init__(self, render, state, *, ambient: float = 0.0, reference_exposure: float = 1.0, lab: dict | None = None):
        self.render, self.state, self.lab = render, state, lab
        self.ambient, self.reference_exposure = float(ambient), float(reference_exposure)
        self.last_state = None
        self.role = None
        self.size = None  # None: the renderer's own size
        import inspect

        try:
            params = inspect.signature(render).parameters
        except (TypeError, ValueError):
            params = {}
        self._takes_role, self._takes_size = "role" in params, "size" in params

    def set_size(self, size) -> None:
        """Shoot at ``size`` (width, height) from now on (None: the renderer's own size); a
        renderer that cannot change its size keeps it, and the session's size check says so."""
        self.size = None if size is None else (int(size[0]), int(size[1]))

    def prepare(self, shot) -> None:
        """Told by the capture session what the next shot is for (its plan role): the simulated
        user puts the props that role needs in front of the camera (reflab.hardware.sim.props)."""
        self.role = getattr(shot, "role", None) or None

    def capture(self, exposure: float | None = None) -> np.ndarray:
        angle, lamps = self.state()
        self.last_state = (float(angle), [bool(x) for x in lamps])
        scale = (self.reference_exposure if exposure is None else float(exposure)) / self.reference_exposure
        extra = {"role": self.role} if self._takes_role else {}
        if self._takes_size and self.size is not None:
            extra["size"] = self.size
        image = self.render(angle, lamps, **extra)
        img = (np.asarray(image, dtype=np.float64) + self.ambient) * scale
        return img.astype(np.float32)

    def describe(self) -> dict:
        out = {"type": "simulated", "ambient": self.ambient, "reference_exposure": self.reference_exposure}
        if self.size is not None:
            out["size"] = list(self.size)
        return out if self.lab is None else dict(out, lab=self.lab)

    def close(self) -> None:
        pass


def rotate_about_z(points: np.ndarray, degrees: float, centre) -> np.ndarray:
    """Points (N, 3) turned by ``degrees`` (counter-clockwise seen from +z) about the vertical axis through ``centre``."""
    from reflab.calibration.rotations import axis_rotation

    R = axis_rotation((0.0, 0.0, 1.0), degrees)
    c = np.array([centre[0], centre[1], 0.0], dtype=np.float64)
    return (np.asarray(points, dtype=np.float64) - c) @ R.T + c


def lab_renderer(lab, *, depth: int = 2, centre=(0.0, 0.0), fixed=("ground",), props=None, supersample: int = 4):
    """A ``render(angle, lamps, role=None, size=None)`` for :class:`SimulatedCamera` from a :class:`reflab.hardware.sim.lab.SimLab`.

    The surfaces not named in ``fixed`` stand on the turntable: their meshes and textures turn
    with it about the vertical axis through ``centre`` (x, y in metres); for a further input
    photograph (role ``"further input"``) every surface does. Lamps that are off are
    left out; with every lamp off the image is black. ``size`` (width, height): the lab's camera at
    that resolution (:meth:`reflab.calibration.camera.Camera.scaled`: the same field of view), as a
    camera shooting at its full resolution instead of the size it was calibrated at.

    ``props`` (a :class:`reflab.hardware.sim.props.LabProps`): a shot whose ``role`` needs a prop (the
    circle target for "target flat"/"target on wedge", the rod for "lamp K") shows the fixed
    surfaces and that prop only (the objects are not on the table while the camera and lamps are
    calibrated), with ray depth 1. The target's shots are rendered at ``supersample`` times the
    size and box-filtered down, the pixel-area integration a sensor does: one ray per pixel
    aliases the circles' edges into 0.06 px of noise on their centres (focal 0.05 % off, sigma
    0.21 %, at 480x360), 4 x 4 rays bring it to 0.01 px (focal 0.015 %, sigma 0.03 %). The rod's
    shots keep one ray per pixel (4 x 4 took 80 s at 480x360 and moved no lamp closer).
    """
    from reflab.calibration.lights import Lights
    from reflab.hardware.sim.reference import render_reference
    from reflab.reconstruction.scene import Mesh, Scene, Surface

    unknown = set(fixed) - set(lab.scene.names)
    if unknown:
        raise ValueError(f"lab_renderer: no surface named {sorted(unknown)} (surfaces: {lab.scene.names})")
    turning = [s.name not in fixed for s in lab.scene]

    def render_props(angle: float, on, role: str, base):
        from reflab.hardware.sim.props import prop_surfaces

        shown = prop_surfaces(props, role, angle, centre)
        still = [i for i, s in enumerate(lab.scene) if not turning[i]]
        surfaces = [lab.scene[i] for i in still] + [s for s, _ in shown]
        fns = [None] * len(still) + [fn for _, fn in shown]

        def albedo(index: int, points: np.ndarray) -> np.ndarray:
            if index < len(still):
                return lab.albedo(still[index], points)
            fn = fns[index]
            return fn(points) if fn is not None else np.broadcast_to(surfaces[index].material["kd"], points.shape).copy()

        k = int(supersample) if role.startswith("target") else 1
        cam = base.scaled(k * base.width, k * base.height)
        if role.startswith("lamp") or role == "room light":  # the room light stays on: a dim lamp at the camera
            from reflab.calibration.lights import PointLight

            on = on + [PointLight(base.center + [0.0, 0.0, 0.02], np.full(3, props.room_light))]
        fine = render_reference(Scene(surfaces), cam, Lights(on), 1, albedo)
        return fine.reshape(base.height, k, base.width, k, 3).mean(axis=(1, 3))

    def render(angle: float, lamps, role: str | None = None, size=None) -> np.ndarray:
        lamps = list(lamps)
        if len(lamps) != len(lab.lights):
            raise ValueError(f"{len(lamps)} lamp states for a lab with {len(lab.lights)} lamps")
        on = [light for light, state in zip(lab.lights, lamps) if state]
        camera = lab.camera
        if size is not None and tuple(size) != (camera.width, camera.height):
            camera = camera.scaled(int(size[0]), int(size[1]))
        if props is not None and role is not None and role.startswith(("target", "lamp", "room light")):
            return render_props(angle, on, role, camera)
        if not on:
            return np.zeros((camera.height, camera.width, 3))
        # A further photograph of the scene (reflab capture inputs): the whole set stands on the
        # turntable's plate, table top included, as docs/formats.md's inputs/ assumes.
        turns = [True] * len(turning) if role == "further input" else turning
        surfaces = [Surface(s.name, s.mesh_path, s.material, s.textured,
                            Mesh(rotate_about_z(s.mesh.vertices, angle, centre), s.mesh.triangles) if moves else s.mesh)
                    for s, moves in zip(lab.scene, turns)]

        def albedo(index: int, points: np.ndarray) -> np.ndarray:
            # A turned surface shows at p the texture its unturned self has at R^-1 p.
            return lab.albedo(index, rotate_about_z(points, -angle, centre) if turns[index] else points)

        return render_reference(Scene(surfaces), camera, Lights(on), depth, albedo)

    return render
