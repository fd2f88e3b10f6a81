"""Simulated calibration captures: a printed circle target and rod shadows, rendered with Mitsuba 3.

The truth is an OpenCV camera (:class:`reflab.calibration.camera.Camera`, distortion included). Mitsuba
renders an undistorted pinhole image with a wider field of view and finer pixels; ``cv2.remap``
then samples it at the undistorted position of every output pixel, so the returned image is
exactly what the distorted OpenCV camera sees (up to the bilinear resampling of the fine render).

World frame as in docs/formats.md: metres, the ground/target plane is z = 0, +z up toward the
camera. Circle (column i, row j) of the target is at ``(i * spacing, -j * spacing, 0)``, the
order :func:`reflab.calibration.circles.detect_grid` returns (row by row, rows top to bottom).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reflab.calibration.camera import Camera
from reflab.calibration.rotations import axis_rotation, look_rotation
from reflab.calibration.target import target_points  # noqa: F401  (re-exported for the twin's users)


def target_texture(cols: int, rows: int, spacing: float, radius: float, texels_per_m: float = 8000.0):
    """Anti-aliased printed target (white paper, black discs) and its extent on the plane.

    Returns
    -------
    image : (H, W) float32 ndarray
        Reflectance, row 0 at the target's top edge (largest y).
    extent : tuple
        ``(xmin, xmax, ymin, ymax)`` of the printed sheet in world metres.
    """
    margin = spacing
    xmin, xmax = -margin, (cols - 1) * spacing + margin
    ymin, ymax = -(rows - 1) * spacing - margin, margin
    w = int(np.ceil((xmax - xmin) * texels_per_m))
    h = int(np.ceil((ymax - ymin) * texels_per_m))
    x = xmin + (np.arange(w) + 0.5) * (xmax - xmin) / w
    y = ymax - (np.arange(h) + 0.5) * (ymax - ymin) / h
    # Distance to the nearest grid centre, separably: the grid is axis-aligned.
    dx = np.abs(x - np.clip(np.round(x / spacing), 0, cols - 1) * spacing)
    dy = np.abs(y + np.clip(np.round(-y / spacing), 0, rows - 1) * spacing)
    d = np.sqrt(dx[None, :] ** 2 + dy[:, None] ** 2)
    texel = (xmax - xmin) / w
    ink = np.clip(0.5 - (d - radius) / texel, 0.0, 1.0)  # linear coverage ramp over one texel
    return (1.0 - 0.95 * ink).astype(np.float32), (xmin, xmax, ymin, ymax)


def _rectangle(extent, z=0.0):
    """Mitsuba ``to_world`` of a rectangle covering ``extent`` at height z (normal +z)."""
    from reflab.core.mitsuba_env import mitsuba

    mi = mitsuba()
    xmin, xmax, ymin, ymax = extent
    return mi.ScalarTransform4f().translate([(xmin + xmax) / 2, (ymin + ymax) / 2, z]).scale(
        [(xmax - xmin) / 2, (ymax - ymin) / 2, 1.0])


def render_view(camera: Camera, objects: dict, spp: int = 16, oversample: float = 1.5) -> np.ndarray:
    """Render Mitsuba ``objects`` (shapes, emitters, integrator) as seen by a distorted camera.

    Parameters
    ----------
    camera : Camera
        The true camera (OpenCV intrinsics, distortion and pose).
    objects : dict
        Mitsuba scene entries other than the sensor; an ``integrator`` entry is required.
    spp : int
        Samples per pixel of the fine render (box filter: exact pixel-area integration).
    oversample : float
        Fine-render focal length relative to the camera's, so the final remap blurs little.

    Returns
    -------
    (H, W, C) float32 ndarray, all channels the integrator writes.
    """
    return render_views([camera], objects, spp, oversample)[0]


def render_views(cameras: list[Camera], objects: dict, spp: int = 16, oversample: float = 1.5) -> list[np.ndarray]:
    """:func:`render_view` for several poses of one camera (same intrinsics): the scene loads once."""
    import cv2

    from reflab.core.mitsuba_env import mitsuba

    mi = mitsuba()
    camera = cameras[0]
    W, H = camera.width, camera.height
    v, u = np.mgrid[0:H, 0:W]
    xy = camera.undistort(np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
    f = oversample * max(camera.K[0, 0], camera.K[1, 1])
    half_w = np.abs(xy[:, 0]).max() * f + 2
    half_h = np.abs(xy[:, 1]).max() * f + 2
    rw, rh = int(2 * np.ceil(half_w)), int(2 * np.ceil(half_h))
    fov = np.degrees(2 * np.arctan(rw / 2 / f))
    # Fine pixel centre of normalised point (x, y): f * (x, y) + ((rw - 1) / 2, (rh - 1) / 2).
    map_u = (xy[:, 0] * f + (rw - 1) / 2).reshape(H, W).astype(np.float32)
    map_v = (xy[:, 1] * f + (rh - 1) / 2).reshape(H, W).astype(np.float32)

    def to_world(cam):
        C = cam.center
        return mi.ScalarTransform4f().look_at(origin=C.tolist(), target=(C + cam.R[2]).tolist(),
                                              up=(-cam.R[1]).tolist())

    scene = dict(objects, type="scene")
    scene["sensor"] = {
        "type": "perspective", "fov": float(fov), "fov_axis": "x", "to_world": to_world(camera),
        "near_clip": 1e-3, "far_clip": 1e3,
        "sampler": {"type": "independent", "sample_count": int(spp)},
        "film": {"type": "hdrfilm", "width": rw, "height": rh, "rfilter": {"type": "box"},
                 "pixel_format": "rgb"},
    }
    scene = mi.load_dict(scene, optimize=False)
    params = mi.traverse(scene)
    out = []
    for k, cam in enumerate(cameras):
        if not (np.allclose(cam.K, camera.K) and np.allclose(cam.dist, camera.dist)
                and (cam.width, cam.height) == (W, H)):
            raise ValueError("render_views: every camera must share the first one's intrinsics")
        params["sensor.to_world"] = to_world(cam)
        params.update()
        fine = np.array(mi.render(scene, seed=k), dtype=np.float32)
        out.append(np.stack([cv2.remap(np.ascontiguousarray(fine[:, :, c]), map_u, map_v, cv2.INTER_LINEAR,
                                       borderMode=cv2.BORDER_REPLICATE) for c in range(fine.shape[2])], axis=2))
    return out


def render_targets(cameras: list[Camera], cols: int, rows: int, spacing: float, radius: float, *,
                   noise: float = 0.005, spp: int = 16, seed: int = 0, background: float = 0.3) -> list[np.ndarray]:
    """Linear RGB images of the printed circle target lying on the plane z = 0, one per camera.

    The sheet is self-emitting (radiance = its reflectance), so the images have no lighting noise,
    over a uniform grey table of radiance ``background``; Gaussian sensor noise of std ``noise``.
    """
    from reflab.core.mitsuba_env import mitsuba

    mi = mitsuba()
    tex, extent = target_texture(cols, rows, spacing, radius)
    # Bitmap row 0 maps to uv v = 0, which Mitsuba's rectangle puts at y = -1: flip rows.
    bmp = mi.Bitmap(np.ascontiguousarray(tex[::-1, :, None]))
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    objects = {
        "integrator": {"type": "path", "max_depth": 1},  # emitters seen directly; nothing to sample
        "sheet": {"type": "rectangle", "to_world": _rectangle(extent, 0.0), "bsdf": black,
                  "emitter": {"type": "area", "radiance": {"type": "bitmap", "bitmap": bmp, "raw": True,
                                                           "filter_type": "bilinear"}}},
        "table": {"type": "rectangle", "to_world": _rectangle((-5, 5, -5, 5), -1e-4), "bsdf": black,
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [background] * 3}}},
    }
    rng = np.random.default_rng(seed)
    return [(img[:, :, :3] + rng.normal(0.0, noise, img[:, :, :3].shape)).astype(np.float32)
            for img in render_views(cameras, objects, spp=spp)]


def random_target_poses(n: int, cols: int, rows: int, spacing: float, seed: int = 0, *,
                        distance: float = 0.45, max_tilt_deg: float = 40.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` camera poses (R, t) looking at the target's centre from varied tilted directions.

    The camera sits ``distance`` (±10%) from the target centre, its axis ``max_tilt_deg`` at most
    off the target normal, rolled by up to ±20°: a spread of orientations that is not degenerate.
    """
    rng = np.random.default_rng(seed)
    centre = np.array([(cols - 1) * spacing / 2, -(rows - 1) * spacing / 2, 0.0])
    poses = []
    for k in range(n):
        tilt = np.radians(max_tilt_deg * (0.35 + 0.65 * rng.random()))
        azim = 2 * np.pi * (k / n) + rng.normal(0, 0.3)
        d = distance * (0.9 + 0.2 * rng.random())
        eye = centre + d * np.array([np.sin(tilt) * np.cos(azim), np.sin(tilt) * np.sin(azim), np.cos(tilt)])
        aim = centre + rng.normal(0, 0.01, 3) * np.array([1, 1, 0])
        roll = np.radians(rng.uniform(-20, 20))
        R = look_rotation(aim - eye, (np.sin(roll), np.cos(roll), 0.0))
        poses.append((R, -R @ eye))
    return poses


@dataclass
class RodScene:
    """A vertical rod on the ground plane lit by one point lamp; its true marks.

    Attributes
    ----------
    foot : (3,) ndarray
        Rod foot on z = 0.
    height, radius : float
        Rod height and radius (metres).
    lamp : (3,) ndarray
        Lamp position.
    """

    foot: np.ndarray
    height: float
    radius: float
    lamp: np.ndarray

    @property
    def tip(self) -> np.ndarray:
        """Shadow tip on z = 0: where the line lamp -> rod top meets the ground."""
        top = self.foot + np.array([0.0, 0.0, self.height])
        s = self.lamp[2] / (self.lamp[2] - self.height)
        return self.lamp + s * (top - self.lamp)


def render_rod(camera: Camera, rod: RodScene, *, intensity: float = 0.3, ambient: float = 0.05,
               ground_reflectance: float = 0.7, spp: int = 8, noise: float = 0.002, seed: int = 0) -> np.ndarray:
    """Linear RGB image of a red vertical rod on a grey ground lit by one point lamp.

    The ambient term (``ambient`` times each surface's reflectance, Mitsuba's albedo AOV) stands for
    the room's light: it keeps the rod's unlit side and the shadow distinguishable by colour.
    """
    from reflab.core.mitsuba_env import mitsuba

    mi = mitsuba()
    foot = np.asarray(rod.foot, dtype=np.float64)
    objects = {
        "integrator": {"type": "aov", "aovs": "albedo:albedo", "direct": {"type": "direct"}},
        "ground": {"type": "rectangle", "to_world": _rectangle((-3, 3, -3, 3), 0.0),
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [ground_reflectance] * 3}}},
        "rod": {"type": "cylinder", "p0": foot.tolist(), "p1": (foot + [0, 0, rod.height]).tolist(),
                "radius": float(rod.radius),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.04, 0.04]}}},
        "cap": {"type": "disk", "to_world": mi.ScalarTransform4f().translate((foot + [0, 0, rod.height]).tolist())
                .scale([rod.radius, rod.radius, 1.0]),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.04, 0.04]}}},
        "lamp": {"type": "point", "position": np.asarray(rod.lamp, float).tolist(),
                 "intensity": {"type": "rgb", "value": [intensity] * 3}},
    }
    img = render_view(camera, objects, spp=spp)
    out = img[:, :, :3] + ambient * img[:, :, 3:6]
    rng = np.random.default_rng(seed)
    return (out + rng.normal(0.0, noise, out.shape)).astype(np.float32)


def render_lit_ground(camera: Camera, lamp: np.ndarray, intensity, reflectance: float, *, spp: int = 4) -> np.ndarray:
    """Linear RGB image of a Lambertian ground (z = 0) of ``reflectance`` under one point lamp."""
    objects = {
        "integrator": {"type": "direct"},
        "ground": {"type": "rectangle", "to_world": _rectangle((-3, 3, -3, 3), 0.0),
                   "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [reflectance] * 3}}},
        "lamp": {"type": "point", "position": np.asarray(lamp, float).tolist(),
                 "intensity": {"type": "rgb", "value": np.broadcast_to(np.asarray(intensity, float), (3,)).tolist()}},
    }
    return render_view(camera, objects, spp=spp)[:, :, :3].astype(np.float32)


# ---------------------------------------------------------------- props in the simulated lab
# What the simulated user puts on the table for the calibration shots, rendered by the reference
# renderer together with the lab's ground (reflab.hardware.sim.camera.lab_renderer). The lab's objects
# are not on the table then: the camera and the lamps are calibrated on the empty table, before
# the scene is set up (docs/simulated-lab.md, "The procedure").

@dataclass(frozen=True)
class LabProps:
    """The printed target, the wedge it is tilted on, and the rod, as the simulated user has them.

    The target's first circle lies at the world origin in the flat (reference) shot, rows along
    +x, columns toward -y (:func:`reflab.calibration.target.target_points`); on the wedge it is centred on
    the turntable axis and tilted by ``wedge_deg`` toward the camera at angle 0. The rod stands
    on the turntable ``rod_offset`` from its axis.
    """

    cols: int = 9
    rows: int = 7
    spacing: float = 0.025
    radius: float = 0.0075
    paper: float = 0.2e-3          # printed sheet thickness: the flat target's plane is z = paper
    wedge_deg: float = 25.0
    rod_height: float = 0.12
    rod_radius: float = 0.003
    rod_offset: tuple = (0.04, 0.0)
    card: tuple = (-0.28, -0.18, 0.03, 0.10)   # grey card on the table during rod shots: xmin xmax ymin ymax
    card_reflectance: float = 0.9              # Lambertian reflectance: kd = reflectance / pi
    room_light: float = 0.04                   # intensity of the room light (a lamp at the camera) in rod shots

    @property
    def grid(self) -> str:
        return f"{self.cols}x{self.rows}"


def _rz(deg: float) -> np.ndarray:
    return axis_rotation((0.0, 0.0, 1.0), deg)


def _rx(deg: float) -> np.ndarray:
    return axis_rotation((1.0, 0.0, 0.0), deg)


def target_placement(props: LabProps, role: str, angle: float, centre=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Target-to-world (R, c) of the printed target in a calibration shot: world = R @ local + c.

    ``role`` "target flat": lying on the turntable, first circle at the origin (the frame the
    reference view defines); "target on wedge": centred on the axis, tilted toward the camera
    side by ``wedge_deg``; both then turned with the turntable by ``angle`` about the axis.
    """
    c_axis = np.array([centre[0], centre[1], 0.0])
    if role == "target flat":
        R, c = np.eye(3), np.array([0.0, 0.0, props.paper])
    else:
        mid = np.array([(props.cols - 1) * props.spacing / 2, -(props.rows - 1) * props.spacing / 2, 0.0])
        tilt = _rx(props.wedge_deg)
        half = ((props.rows - 1) * props.spacing / 2 + 1.5 * props.spacing) * np.sin(np.radians(props.wedge_deg))
        R = tilt
        c = -tilt @ mid + c_axis + np.array([0.0, 0.0, half + props.paper])
    turn = _rz(angle)
    return turn @ R, turn @ (c - c_axis) + c_axis


def target_albedo(props: LabProps, R: np.ndarray, c: np.ndarray, paper: float = 0.8, ink: float = 0.04):
    """``albedo(points) -> (N, 3)`` of the printed target placed by (R, c): white paper, black discs."""
    def albedo(points: np.ndarray) -> np.ndarray:
        local = (np.asarray(points, dtype=np.float64).reshape(-1, 3) - c) @ R
        s = props.spacing
        dx = local[:, 0] - np.clip(np.round(local[:, 0] / s), 0, props.cols - 1) * s
        dy = local[:, 1] + np.clip(np.round(-local[:, 1] / s), 0, props.rows - 1) * s
        disc = np.hypot(dx, dy) <= props.radius
        return np.repeat(np.where(disc, ink, paper)[:, None], 3, axis=1)
    return albedo


def _quad(corners: np.ndarray):
    from reflab.reconstruction.scene import Mesh

    return Mesh(corners, [[0, 1, 2], [0, 2, 3]])


def _wedge(sheet: np.ndarray):
    """A closed wedge under a tilted sheet (corners 0, 1 its high edge, 3, 2 its low edge), 1 mm below it."""
    from reflab.reconstruction.scene import Mesh

    H = sheet[[0, 1]] - [0.0, 0.0, 1e-3]
    ground = lambda p: p * [1.0, 1.0, 0.0]  # noqa: E731
    v = np.concatenate([ground(sheet[[3, 2]]), H, ground(sheet[[0, 1]])])  # l0 l1 H0 H1 h0 h1
    tris = [[0, 1, 3], [0, 3, 2], [4, 5, 3], [4, 3, 2], [0, 1, 5], [0, 5, 4], [0, 2, 4], [1, 3, 5]]
    return Mesh(v, tris)


def _prism(foot, height: float, radius: float, sides: int = 24):
    """A closed vertical n-sided prism (the rod) standing on ``foot``."""
    from reflab.reconstruction.scene import Mesh

    a = 2 * np.pi * np.arange(sides) / sides
    ring = np.stack([radius * np.cos(a), radius * np.sin(a), np.zeros(sides)], axis=1) + np.asarray(foot, float)
    top = ring + [0.0, 0.0, height]
    verts = np.concatenate([ring, top, [np.asarray(foot, float)], [np.asarray(foot, float) + [0, 0, height]]])
    b, t = 2 * sides, 2 * sides + 1
    tris = []
    for i in range(sides):
        j = (i + 1) % sides
        tris += [[i, j, sides + j], [i, sides + j, sides + i], [b, j, i], [t, sides + i, sides + j]]
    return Mesh(verts, tris)


def prop_surfaces(props: LabProps, role: str, angle: float, centre=(0.0, 0.0)):
    """The props a shot of ``role`` shows: a list of (Surface, albedo function or None).

    Roles (reflab.hardware.capture's plans): "target flat" and "target on wedge" (calibration shots),
    "lamp K" and "room light" (rod-shadow shots: the rod on the turntable and the grey card on the
    table); any other role shows no prop.
    """
    from reflab.reconstruction.scene import Material, Surface

    lambert = lambda kd: Material("lambert", {"kd": np.asarray(kd, float), "r": np.zeros(3), "t": np.zeros(3)}, None)  # noqa: E731
    out = []
    if role in ("target flat", "target on wedge"):
        R, c = target_placement(props, role, angle, centre)
        s, m = props.spacing, 1.5 * props.spacing
        local = np.array([[-m, m, 0], [(props.cols - 1) * s + m, m, 0],
                          [(props.cols - 1) * s + m, -(props.rows - 1) * s - m, 0], [-m, -(props.rows - 1) * s - m, 0]])
        out.append((Surface("target", "", lambert([0.8] * 3), True, _quad(local @ R.T + c)), target_albedo(props, R, c)))
        if role == "target on wedge":
            out.append((Surface("wedge", "", lambert([0.35, 0.33, 0.30]), False, _wedge(local @ R.T + c)), None))
    elif role.startswith("lamp") or role == "room light":
        foot = rod_foot(props, angle, centre)
        out.append((Surface("rod", "", lambert([0.6, 0.04, 0.04]), False, _prism(foot, props.rod_height, props.rod_radius)),
                    None))
        x0, x1, y0, y1 = props.card
        card = np.array([[x0, y0, props.paper], [x1, y0, props.paper], [x1, y1, props.paper], [x0, y1, props.paper]])
        out.append((Surface("card", "", lambert([props.card_reflectance / np.pi] * 3), False, _quad(card)), None))
    return out


def rod_foot(props: LabProps, angle: float, centre=(0.0, 0.0)) -> np.ndarray:
    """Where the rod stands in a rod shot at turntable ``angle`` (world, z = 0)."""
    return _rz(angle) @ np.array([props.rod_offset[0], props.rod_offset[1], 0.0]) + [centre[0], centre[1], 0.0]
