"""The simulated lab: a virtual copy of the dissertation's table-top set (docs/method.md §5).

World frame of docs/formats.md (metres, ground z = 0, +z up). The camera looks down at about 45°
from about 0.6 m, toward +y. Five surfaces, in scene order:

0. ``ground``: a table top with an A4 sheet of printed paper in its centre (one textured lambert
   plane, large enough to fill the view);
1. ``box``: a purple laminated paper box (closed box mesh, textured glossy phong);
2. ``sheet``: a blue transparent plastic sheet (index 1.46), a thin closed box standing in front of
   the purple box and leaning back, so that the camera sees part of the box through it;
3. ``mirror``: a box-shaped mirror behind the purple box. The real one is glass (index 1.52) with a
   silvered back; with depth D = 3 a ray entering the glass, reflecting on the silver and leaving
   again needs more internal nodes than D allows, so it is modelled as an opaque reflector
   (``ior`` null: F = 1) with ``r`` = 0.85 and a dark, glossy front;
4. ``tile``: a textured ceramic tile lying on the paper (glossy phong).

Two point lamps about 0.6 m away: one behind on the right (its highlight falls on the tile seen
by the camera), one in front on the left (it lights the mirror's face). The purple box's back face
is seen ONLY in the mirror. Ground-truth textures are smooth procedural functions of the surface
point (:meth:`SimLab.albedo`), values in [0.05, 0.9] per band; the ``kd`` in the scene's materials
is their mean over the surface (the homogeneous value).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.calibration.camera import Camera
from reflab.calibration.rotations import axis_rotation
from reflab.calibration.lights import Lights, PointLight
from reflab.core.workspace import write_json
from reflab.reconstruction.scene import Material, Mesh, Scene, Surface

#: Full resolution of the simulated camera (the dissertation's 640x480).
FULL_SIZE = (640, 480)
#: A4 paper, metres (x by y on the ground).
A4 = (0.297, 0.210)
#: Radial distortion of the simulated lens (k1, mild barrel).
K1 = -0.05
SHEET_IOR = 1.46
ALBEDO_RANGE = (0.05, 0.9)


# ---------------------------------------------------------------- geometry
def _rot_z(deg: float) -> np.ndarray:
    return axis_rotation((0.0, 0.0, 1.0), deg)


def _rot_x(deg: float) -> np.ndarray:
    return axis_rotation((1.0, 0.0, 0.0), deg)


def box_mesh(size, center, rotation=None) -> Mesh:
    """A closed box of edge lengths ``size`` centred at ``center``, turned by ``rotation``
    (box-to-world, identity when omitted): :func:`reflab.reconstruction.surfaces.box_mesh`."""
    from reflab.reconstruction.surfaces import box_mesh as box

    return box(center, np.eye(3) if rotation is None else rotation, size)


def plane_mesh(x_range, y_range, z: float = 0.0) -> Mesh:
    """A horizontal rectangle facing +z (an open mesh: two-sided)."""
    (x0, x1), (y0, y1) = x_range, y_range
    verts = [[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]
    return Mesh(verts, [[0, 1, 2], [0, 2, 3]])


# ---------------------------------------------------------------- textures
def _soft_checker(u: np.ndarray, v: np.ndarray, cell: float, sharpness: float = 6.0) -> np.ndarray:
    """A checkerboard in [0, 1] with smooth (tanh) edges; ``cell`` is the square's size."""
    s = np.sin(np.pi * u / cell) * np.sin(np.pi * v / cell)
    return 0.5 + 0.5 * np.tanh(sharpness * s)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _mix(a, b, w: np.ndarray) -> np.ndarray:
    """Per-point blend of two colours: ``a`` where w = 0, ``b`` where w = 1."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return a + (b - a) * w[:, None]


def _ground_albedo(local: np.ndarray) -> np.ndarray:
    """Wood-grain table with an A4 sheet printed with a soft checker and waves."""
    x, y = local[:, 0], local[:, 1]
    grain = 0.8 + 0.2 * np.sin(2 * np.pi * y / 0.013 + 3.0 * np.sin(2 * np.pi * x / 0.11))
    wood = np.array([0.45, 0.30, 0.18]) * grain[:, None]
    checker = _soft_checker(x + 0.01, y + 0.005, 0.035)
    waves = 0.5 + 0.5 * np.sin(2 * np.pi * (x + 0.6 * y) / 0.05)
    paper = _mix([0.82, 0.80, 0.76], [0.30, 0.42, 0.62], 0.6 * checker * (0.5 + 0.5 * waves))
    inside = _sigmoid((A4[0] / 2 - np.abs(x)) / 0.0015) * _sigmoid((A4[1] / 2 - np.abs(y)) / 0.0015)
    return wood + (paper - wood) * inside[:, None]


def _box_albedo(local: np.ndarray) -> np.ndarray:
    """Purple laminated print: oblique waves and soft stripes, in the box's own frame."""
    x, y, z = local[:, 0], local[:, 1], local[:, 2]
    waves = np.sin(2 * np.pi * (x + 0.5 * z) / 0.03) * np.sin(2 * np.pi * (y - 0.7 * z) / 0.025)
    stripes = _sigmoid(8.0 * np.sin(2 * np.pi * (x - y + z) / 0.04))
    base = _mix([0.36, 0.12, 0.46], [0.70, 0.52, 0.80], 0.5 + 0.5 * waves)
    return base * (0.7 + 0.3 * stripes)[:, None]


def _tile_albedo(local: np.ndarray) -> np.ndarray:
    """Cream and blue ceramic pattern: soft checker with a radial motif, in the tile's frame."""
    x, y = local[:, 0], local[:, 1]
    checker = _soft_checker(x, y, 0.03, sharpness=4.0)
    rings = 0.5 + 0.5 * np.cos(2 * np.pi * np.hypot(x, y) / 0.035)
    return _mix([0.85, 0.78, 0.62], [0.12, 0.22, 0.55], 0.8 * checker * (0.4 + 0.6 * rings))


def _grain(local: np.ndarray, amplitude: float) -> np.ndarray:
    """Multiplicative print grain in [1 - amplitude, 1 + amplitude]: 32 plane waves, periods 2-8 mm.

    Fixed directions, periods and phases (seed 1), in the surface's own frame; their sum is
    noise-like (not periodic over a surface), which is what feature matching needs.
    """
    rng = np.random.default_rng(1)
    k = 32
    angle, period, phase = rng.uniform(0, np.pi, k), rng.uniform(0.002, 0.008, k), rng.uniform(0, 2 * np.pi, k)
    waves = np.stack([np.cos(angle), np.sin(angle), 0.5 * rng.normal(size=k)], axis=1) / period[:, None]
    s = np.sin(2 * np.pi * local @ waves.T + phase).sum(axis=1) / np.sqrt(k / 2)
    return 1.0 + amplitude * np.tanh(s)


@dataclass
class _Texture:
    """A procedural albedo in a surface's own frame: ``fn((points - origin) @ frame)``, times the grain."""

    fn: object
    origin: np.ndarray
    frame: np.ndarray  # columns are the surface's own axes in world coordinates
    grain: float = 0.0

    def __call__(self, points: np.ndarray) -> np.ndarray:
        local = (np.asarray(points, dtype=np.float64).reshape(-1, 3) - self.origin) @ self.frame
        value = self.fn(local)
        if self.grain:
            value = value * _grain(local, self.grain)[:, None]
        return np.clip(value, *ALBEDO_RANGE)


# ---------------------------------------------------------------- the lab
@dataclass
class SimLab:
    """The simulated lab: camera, lights, scene with true materials, and the true albedo.

    Attributes
    ----------
    camera : Camera
    lights : Lights
    scene : Scene
        Surfaces with meshes loaded and the true materials (``kd`` = mean of the texture).
    textures : dict
        Surface index -> procedural albedo; surfaces not in it have the constant ``kd``.
    """

    camera: Camera
    lights: Lights
    scene: Scene
    textures: dict = field(default_factory=dict)

    def albedo(self, surface_index: int, points: np.ndarray) -> np.ndarray:
        """True diffuse albedo (N, 3) of surface ``surface_index`` at world points (N, 3)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        tex = self.textures.get(int(surface_index))
        if tex is None:
            return np.broadcast_to(self.scene[surface_index].material["kd"], points.shape).copy()
        return tex(points)

    def albedo_at(self, surfaces: np.ndarray, points: np.ndarray) -> np.ndarray:
        """True albedo (N, 3) at points (N, 3) on surfaces (N,) (e.g. every tree node)."""
        surfaces = np.asarray(surfaces).reshape(-1)
        out = np.zeros((len(surfaces), 3))
        for s in np.unique(surfaces):
            sel = surfaces == s
            out[sel] = self.albedo(int(s), points[sel])
        return out

    def homogeneous(self) -> "SimLab":
        """The same lab with every surface at its constant ``kd`` (no textures)."""
        return SimLab(self.camera, self.lights, self.scene, {})


def _surface_mean(mesh: Mesh, tex: _Texture, n: int = 20000) -> np.ndarray:
    """Area-weighted mean of a texture over a mesh (deterministic sample)."""
    return tex(mesh.sample_points(n)).mean(axis=0)


def _material(brdf: str, ior=None, **params) -> Material:
    full = {k: np.float64(v) if np.ndim(v) == 0 and k in ("ns", "alpha", "sigma") else
            np.broadcast_to(np.asarray(v, dtype=np.float64), (3,)).copy() for k, v in params.items()}
    full.setdefault("r", np.zeros(3))
    full.setdefault("t", np.zeros(3))
    return Material(brdf, full, ior)


def build_lab(width: int = FULL_SIZE[0], height: int = FULL_SIZE[1], *, textured: bool = True,
              grain: float = 0.0) -> SimLab:
    """Build the simulated lab at ``width`` x ``height`` (the 640x480 camera, scaled).

    Parameters
    ----------
    width, height : int
        Image size; any size keeps the full-resolution camera's field of view.
    textured : bool
        False gives the homogeneous variant (every surface its constant ``kd``).
    grain : float
        Amplitude of a fine print grain (2-8 mm) multiplying every texture, 0 = none. The
        procedural textures alone vary over centimetres and repeat: structure from motion finds
        too few distinctive features on them (docs/reconstruction.md); 0.2 is enough.

    Returns
    -------
    SimLab
    """
    if width < 2 or height < 2:
        raise ValueError(f"build_lab: image size must be at least 2x2, got {width}x{height}")
    camera = Camera.look_at(*FULL_SIZE, fov_x_deg=50.0, eye=(0.05, -0.39, 0.43), target=(0.0, 0.03, 0.0),
                            dist=np.array([K1, 0.0, 0.0, 0.0, 0.0]))
    if (width, height) != FULL_SIZE:
        camera = camera.scaled(width, height)

    R_box, R_tile, R_mirror = _rot_z(12.0), _rot_z(20.0), _rot_z(-5.0)
    R_sheet = _rot_z(8.0) @ _rot_x(-10.0)  # leaning back, away from the camera
    sheet_size = np.array([0.10, 0.003, 0.10])
    sheet_bottom = np.array([-0.12, -0.06, 0.001])  # lifted 1 mm: no face shared with the ground
    sheet_center = sheet_bottom + R_sheet @ np.array([0.0, 0.0, sheet_size[2] / 2])
    geometry = {
        "ground": plane_mesh((-0.70, 0.70), (-0.40, 1.20)),
        "box": box_mesh((0.10, 0.07, 0.06), (-0.07, 0.03, 0.03), R_box),
        "sheet": box_mesh(sheet_size, sheet_center, R_sheet),
        "mirror": box_mesh((0.26, 0.006, 0.13), (-0.02, 0.15, 0.065), R_mirror),
        "tile": box_mesh((0.12, 0.12, 0.008), (0.11, -0.06, 0.004), R_tile),
    }
    textures = {
        0: _Texture(_ground_albedo, np.zeros(3), np.eye(3), grain),
        1: _Texture(_box_albedo, np.array([-0.07, 0.03, 0.03]), R_box, grain),
        4: _Texture(_tile_albedo, np.array([0.11, -0.06, 0.008]), R_tile, grain),
    }
    kd = {i: _surface_mean(geometry[name], textures[i]) for i, name in ((0, "ground"), (1, "box"), (4, "tile"))}
    materials = {
        "ground": _material("lambert", kd=kd[0]),
        "box": _material("phong", kd=kd[1], ks=0.25, ns=30.0, r=0.04),
        "sheet": _material("phong", ior=SHEET_IOR, kd=[0.01, 0.015, 0.04], ks=0.2, ns=200.0,
                           r=1.0, t=[0.35, 0.60, 0.92]),
        "mirror": _material("phong", kd=0.02, ks=0.3, ns=300.0, r=0.85),
        "tile": _material("phong", kd=kd[4], ks=0.35, ns=60.0, r=0.06),
    }
    surfaces = [Surface(name, f"meshes/{name}.ply", materials[name], textured=name in ("ground", "box", "tile"),
                        mesh=geometry[name]) for name in geometry]
    # Halogen-like warm lamps; intensities put the image's brightest pixels near 0.8.
    warm = np.array([1.0, 0.86, 0.66])
    lights = Lights([PointLight([0.22, 0.36, 0.46], 0.24 * warm), PointLight([-0.40, -0.20, 0.45], 0.24 * warm)])
    return SimLab(camera, lights, Scene(surfaces), textures if textured else {})


def write_lab(workspace, lab: SimLab, *, materials: bool = True, photograph=None, further=()) -> dict[str, Path]:
    """Write the lab's camera.json, lights.json, scene.json and meshes/*.ply into ``workspace``,
    and its photographs when given.

    Parameters
    ----------
    workspace : path-like
    lab : SimLab
    materials : bool
        True: scene.json carries the true materials. False: only what a user knows before
        fitting — ``brdf``, ``ior``, and that a matte (``lambert``) surface such as the paper
        ground does not mirror (``r = 0``, so the trees leave out its reflections) — and the
        truth goes to ``truth.json`` (fit.json's "surfaces" layout) for comparison.
    photograph : (H, W, 3) array, optional
        The reference photograph, written as input.exr.
    further : iterable of (name, image, camera, lights)
        Further photographs, each written into inputs/ with its sidecar.

    Returns
    -------
    dict
        Name -> path of every file written.
    """
    root = Path(workspace)
    root.mkdir(parents=True, exist_ok=True)
    surfaces = lab.scene.surfaces
    if not materials:
        known = lambda m: {"r": np.zeros(3)} if m.brdf == "lambert" else {}  # noqa: E731 -- matte: no mirror
        surfaces = [Surface(s.name, s.mesh_path, Material(s.material.brdf, known(s.material), s.material.ior),
                            s.textured, s.mesh, s.extra) for s in surfaces]
    scene = Scene(surfaces, root)
    written = {"camera": lab.camera.save(root / "camera.json"), "lights": lab.lights.save(root / "lights.json"),
               "scene": scene.save(root / "scene.json")}
    if not materials:
        written["truth"] = write_json(root / "truth.json", {"surfaces": [
            {"name": s.name, "textured": s.textured, "material": s.material.to_json()} for s in lab.scene]})
    written.update({s.name: root / s.mesh_path for s in scene})
    if photograph is not None:
        from reflab.core.images import write_image

        written["input"] = write_image(root / "input.exr", photograph)
    if further:
        from reflab.inverse.forward.photographs import write_input

        for name, image, camera, lights in further:
            written[f"inputs/{name}"] = write_input(root, name, image, camera, lights)[0]
    return written


def photographed(workspace, lab: SimLab, shots="", *, noise: float = 0.01, seed: int = 0, materials: bool = False) -> SimLab:
    """Write ``lab`` (:func:`write_lab`) with its reference photograph and the further ``shots``
    (:func:`named_views`' names) by the independent reference renderer, each with Gaussian noise of
    ``noise`` × its peak from one generator seeded ``seed``. Returns ``lab``."""
    from reflab.hardware.sim.reference import render_reference

    rng = np.random.default_rng(seed)

    def photo(cam, lights):
        img = render_reference(lab.scene, cam, lights, albedo=lab.albedo)
        return img + rng.normal(0.0, noise * img.max(), img.shape)

    further = [(n, photo(cam, li), cam, li) for n, cam, li in named_views(lab.camera, lab.lights, shots)]
    write_lab(workspace, lab, materials=materials, photograph=photo(lab.camera, lab.lights), further=further)
    return lab


def user_workspace(root, width: int, height: int, *, textured: bool = True, noise: float = 0.0, seed: int = 0):
    """The lab written as a user's workspace (scene.json: only what a user knows, the truth in
    truth.json; untextured, no surface declared textured) with its input photograph made by the
    forward model from the true materials (``noise``: Gaussian σ as a fraction of each photograph's
    peak). Returns ``(lab, photo)``: ``photo(camera, lights)`` makes further photographs the same way."""
    import json

    from reflab.core.images import write_image
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees

    root = Path(root)
    lab = build_lab(width, height, textured=textured)
    write_lab(root, lab, materials=False)
    if not textured:
        scene = json.loads((root / "scene.json").read_text())
        for s in scene["surfaces"]:
            s["textured"] = False
        (root / "scene.json").write_text(json.dumps(scene))
    truth = [s.material for s in lab.scene]
    rng = np.random.default_rng(seed)

    def photo(camera, lights):
        trees = build_trees(lab.scene, camera, lights, depth=3)
        kd = lab.albedo_at(trees.surface, trees.point) if textured else None
        img = render(trees, truth, lights.intensities, kd_nodes=kd)
        return img + rng.normal(0.0, noise * img.max(), img.shape) if noise else img

    write_image(root / "input.exr", photo(lab.camera, lab.lights))
    return lab, photo


def named_views(camera, lights, shots, centre=(0.0, 0.0)) -> list:
    """``(name, camera, lights)`` of further photographs named as the benchmarks name them:
    ``Lk`` lamp k alone (left out where the set has fewer lamps), ``TA`` every lamp on with the
    turntable turned by A degrees about the vertical axis through ``centre``. ``shots``: a list
    or a comma-separated string; a name's ``-`` becomes ``m`` (a file name)."""
    from reflab.inverse.forward.photographs import turned_view

    out = []
    for shot in filter(None, shots.split(",") if isinstance(shots, str) else shots):
        lamp = shot[0] == "L"
        if lamp and int(shot[1:]) >= len(lights):
            continue
        cam, lit = turned_view(camera, lights, 0.0 if lamp else float(shot[1:]), centre,
                               lit=[int(shot[1:])] if lamp else None)
        out.append((shot.replace("-", "m"), cam, lit))
    return out
