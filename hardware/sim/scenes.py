"""Textured test scenes for the fit, other than the demo lab (docs/fit.md, "Textured scenes").

Each is built from :mod:`reflab.reconstruction.scene` types with a known per-point albedo, for the
independent renderer (:func:`reflab.hardware.sim.reference.render_reference`):

- ``shiny_box``: a shiny textured box (phong, ks 0.3, ns 40) on a plain matte ground, two lamps
  whose highlights fall on its top at different places;
- ``floor_mirror``: a matte textured floor (phong ks 0.04, ns 12) seen directly and in an upright
  mirror (r 0.85), one lamp;
- ``curved``: a textured cylinder (curved mesh, phong ks 0.2, ns 20) lying on a plain matte
  ground, two lamps;
- ``glass_block``: a thick glass block (index 1.5, 2.5 cm, faintly green) standing on a matte
  textured floor, which the camera sees directly, through the block (refracted twice, displaced)
  and in the block's faces; two lamps.

:data:`MORE` are further designs, each stressing one thing (docs/fit.md, "Other designs"):
``ward_tile`` (a textured Ward tile beside a plain glossy box), ``near_lamp`` (a lamp 3 cm above
a textured floor), ``oren_mirror`` (a textured Oren–Nayar box before a mirror), ``sheet_flat``
(a thin transparent sheet held flat over a textured floor), ``high_ns`` (a plain tile of
shininess 3000 whose highlight is in view, on a textured floor), ``two_textured`` (a glossy
textured box on a glossy textured floor), ``tile_mirror`` (a glossy textured tile seen directly
and in a mirror), ``glossy_floor_mirror`` (a glossy textured floor seen directly and in a
mirror) — those two, a textured lobe whose texels are seen twice — and ``print_can`` (curved's
can printed in full colour, each band its own pattern: no colour set for
:mod:`reflab.inverse.fit.dichromatic`, its lobe seen once).

Every other texture is two inks (:func:`_pattern`): its colours on a line in RGB.

The camera looks down at about 40° from 0.5 m (like the lab's); textures are smooth procedural
functions of the surface point in [0.1, 0.9] with features of 1–3 cm.
"""
from __future__ import annotations

import numpy as np

from reflab.calibration.camera import Camera
from reflab.calibration.lights import Lights, PointLight
from reflab.hardware.sim.lab import SimLab, _material, _rot_x, _rot_z, box_mesh, plane_mesh
from reflab.reconstruction.scene import Material, Mesh, Scene, Surface

NAMES = ("shiny_box", "floor_mirror", "curved", "glass_block")
MORE = ("ward_tile", "near_lamp", "oren_mirror", "sheet_flat", "high_ns", "two_textured", "tile_mirror",
        "glossy_floor_mirror", "print_can")


def _pattern(points, scale: float, colours, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    """A smooth two-colour pattern (waves and soft blobs) of world points, features ~``scale``,
    moved by ``shift`` (metres)."""
    x, y, z = (points - np.asarray(shift, dtype=np.float64)).T
    w = 0.5 + 0.5 * np.sin(2 * np.pi * (x + 0.4 * y) / scale) * np.cos(2 * np.pi * (y - 0.3 * z) / (1.3 * scale))
    w = 0.5 + 0.5 * np.tanh(3.0 * (w - 0.5) + np.sin(2 * np.pi * z / (0.9 * scale)))
    a, b = (np.asarray(c, dtype=np.float64) for c in colours)
    return np.clip(a + (b - a) * w[:, None], 0.1, 0.9)


def _full_colour(points, scale: float, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    """A full-colour print: each band its own wave pattern (no line or plane holds its colours)."""
    p = points - np.asarray(shift, dtype=np.float64)
    dirs = np.array([[1.0, 0.4, 0.2], [-0.3, 1.0, 0.5], [0.6, -0.7, 1.0]])
    return np.clip(0.5 + 0.3 * np.sin(2 * np.pi * p @ dirs.T / (scale * np.array([1.0, 1.3, 0.8]))), 0.1, 0.9)


def cylinder_mesh(radius: float, length: float, center, axis_deg: float = 0.0, segments: int = 48) -> Mesh:
    """A closed cylinder lying along the rotated x axis (flat facets, capped, outward triangles)."""
    ang = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([np.zeros(segments), radius * np.cos(ang), radius * np.sin(ang)], axis=1)
    left, right = ring + [-length / 2, 0, 0], ring + [length / 2, 0, 0]
    verts = np.concatenate([left, right, [[-length / 2, 0, 0], [length / 2, 0, 0]]])
    i = np.arange(segments)
    j = (i + 1) % segments
    cl, cr = 2 * segments, 2 * segments + 1
    side = np.concatenate([np.stack([i, j, segments + j], 1), np.stack([i, segments + j, segments + i], 1)])
    caps = np.concatenate([np.stack([np.full(segments, cl), j, i], 1), np.stack([np.full(segments, cr), segments + i, segments + j], 1)])
    tris = np.concatenate([side, caps])
    # Orient every triangle outward (its normal away from the axis or along the cap's side).
    v = verts[tris]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    c = v.mean(axis=1)
    out = c.copy()
    out[:, 1:] = np.where(np.abs(c[:, :1]) > length / 2 - 1e-9, 0.0, c[:, 1:])
    out[:, 0] = np.where(np.abs(c[:, 0]) > length / 2 - 1e-9, c[:, 0], 0.0)
    flip = np.einsum("ij,ij->i", n, out) < 0
    tris[flip] = tris[flip][:, ::-1]
    R = _rot_z(axis_deg)
    return Mesh(verts @ R.T + np.asarray(center, dtype=np.float64), tris)


def _mean(mesh: Mesh, fn) -> np.ndarray:
    return fn(mesh.sample_points(20000)).mean(axis=0)


def _realisation(scale: float, colours, seed: int | None):
    """The albedo function of one texture realisation: ``seed`` None gives the scenes' own; else
    the pattern moved by up to three features, its features 0.8–1.25× as large and its colours
    moved by up to ±0.08 (docs/figures/fit_calibration.py's texture realisations)."""
    if seed is None:
        return lambda p: _pattern(p, scale, colours)
    rng = np.random.default_rng(seed)
    shift = rng.uniform(0.0, 3.0 * scale, 3)
    scale = scale * float(np.exp(rng.uniform(np.log(0.8), np.log(1.25))))
    colours = [np.clip(np.asarray(c) + rng.uniform(-0.08, 0.08, 3), 0.1, 0.9) for c in colours]
    return lambda p: _pattern(p, scale, colours, shift)


# Each design: (surfaces, lights, textures) from the shared ground plane, lamp colour and texture seed.
def _shiny_box(ground, lamp, texture_seed):
    box = box_mesh((0.14, 0.10, 0.05), (0.0, 0.03, 0.025), _rot_z(15.0))
    tex = _realisation(0.03, ([0.65, 0.25, 0.2], [0.2, 0.45, 0.7]), texture_seed)
    surfaces = [Surface("ground", "meshes/ground.ply", _material("lambert", kd=[0.45, 0.42, 0.38]), False, ground),
                Surface("box", "meshes/box.ply", _material("phong", kd=_mean(box, tex), ks=0.3, ns=40.0), True, box)]
    lights = [PointLight([0.07, 0.42, 0.40], 0.12 * lamp), PointLight([-0.30, -0.25, 0.30], 0.08 * lamp)]
    textures = {1: tex}
    return surfaces, lights, textures


def _floor_mirror(ground, lamp, texture_seed):
    mirror = box_mesh((0.22, 0.006, 0.16), (0.05, 0.10, 0.08), _rot_z(-8.0))
    tex = _realisation(0.04, ([0.8, 0.7, 0.5], [0.15, 0.3, 0.35]), texture_seed)
    surfaces = [Surface("floor", "meshes/floor.ply", _material("phong", kd=_mean(ground, tex), ks=0.04, ns=12.0), True, ground),
                Surface("mirror", "meshes/mirror.ply", _material("phong", kd=0.02, ks=0.3, ns=300.0, r=0.85), False, mirror)]
    lights = [PointLight([-0.15, -0.2, 0.35], 0.1 * lamp)]
    textures = {0: tex}
    return surfaces, lights, textures


def _curved(ground, lamp, texture_seed):
    cyl = cylinder_mesh(0.04, 0.18, (0.0, 0.03, 0.0401), axis_deg=20.0)
    tex = _realisation(0.025, ([0.75, 0.7, 0.3], [0.2, 0.25, 0.6]), texture_seed)
    surfaces = [Surface("ground", "meshes/ground.ply", _material("lambert", kd=[0.4, 0.4, 0.42]), False, ground),
                Surface("can", "meshes/can.ply", _material("phong", kd=_mean(cyl, tex), ks=0.2, ns=20.0), True, cyl)]
    lights = [PointLight([0.10, 0.30, 0.40], 0.12 * lamp), PointLight([-0.25, -0.20, 0.35], 0.08 * lamp)]
    textures = {1: tex}
    return surfaces, lights, textures


def _glass_block(ground, lamp, texture_seed):
    block = box_mesh((0.14, 0.025, 0.07), (0.0, 0.06, 0.036), _rot_z(10.0))  # lifted 1 mm off the floor
    tex = _realisation(0.03, ([0.85, 0.8, 0.7], [0.25, 0.2, 0.45]), texture_seed)
    surfaces = [Surface("floor", "meshes/floor.ply", _material("lambert", kd=_mean(ground, tex)), True, ground),
                Surface("block", "meshes/block.ply", _material("phong", ior=1.5, kd=[0.004, 0.006, 0.004], ks=0.15,
                                                               ns=250.0, r=1.0, t=[0.88, 0.93, 0.90]), False, block)]
    lights = [PointLight([0.15, 0.35, 0.40], 0.12 * lamp), PointLight([-0.25, -0.20, 0.35], 0.08 * lamp)]
    textures = {0: tex}
    return surfaces, lights, textures


def _ward_tile(ground, lamp, texture_seed):
    tile = box_mesh((0.12, 0.12, 0.008), (0.02, 0.02, 0.0041), _rot_z(20.0))
    box = box_mesh((0.06, 0.06, 0.06), (-0.12, 0.10, 0.0301), _rot_z(-25.0))
    tex = _realisation(0.03, ([0.8, 0.75, 0.6], [0.15, 0.3, 0.5]), texture_seed)
    surfaces = [Surface("ground", "meshes/ground.ply", _material("lambert", kd=[0.35, 0.35, 0.33]), False, ground),
                Surface("tile", "meshes/tile.ply", _material("ward", kd=_mean(tile, tex), ks=0.15, alpha=0.12), True, tile),
                Surface("box", "meshes/box.ply", _material("phong", kd=[0.6, 0.2, 0.15], ks=0.4, ns=80.0), False, box)]
    lights = [PointLight([0.10, 0.35, 0.35], 0.12 * lamp), PointLight([-0.30, -0.10, 0.30], 0.08 * lamp)]
    textures = {1: tex}
    return surfaces, lights, textures


def _near_lamp(ground, lamp, texture_seed):
    box = box_mesh((0.08, 0.08, 0.05), (0.06, 0.05, 0.0251), _rot_z(30.0))
    tex = _realisation(0.03, ([0.85, 0.8, 0.7], [0.3, 0.2, 0.4]), texture_seed)
    surfaces = [Surface("floor", "meshes/floor.ply", _material("lambert", kd=_mean(ground, tex)), True, ground),
                Surface("box", "meshes/box.ply", _material("phong", kd=[0.2, 0.5, 0.3], ks=0.3, ns=60.0), False, box)]
    lights = [PointLight([-0.06, 0.0, 0.03], 0.004 * lamp), PointLight([0.2, 0.3, 0.4], 0.1 * lamp)]
    textures = {0: tex}
    return surfaces, lights, textures


def _upright_mirror(r: float) -> Surface:
    """The upright mirror behind the scene of oren_mirror, tile_mirror and glossy_floor_mirror."""
    mirror = box_mesh((0.25, 0.006, 0.15), (0.0, 0.12, 0.075), _rot_z(-5.0))
    return Surface("mirror", "meshes/mirror.ply", _material("phong", kd=0.02, ks=0.3, ns=300.0, r=r), False, mirror)


def _oren_mirror(ground, lamp, texture_seed):
    box = box_mesh((0.10, 0.07, 0.06), (0.0, 0.0, 0.0301), _rot_z(25.0))
    tex = _realisation(0.025, ([0.7, 0.5, 0.3], [0.2, 0.35, 0.6]), texture_seed)
    surfaces = [Surface("ground", "meshes/ground.ply", _material("lambert", kd=[0.4, 0.4, 0.4]), False, ground),
                Surface("box", "meshes/box.ply", _material("oren-nayar", kd=_mean(box, tex), sigma=0.4), True, box),
                _upright_mirror(0.8)]
    lights = [PointLight([0.25, -0.2, 0.35], 0.1 * lamp), PointLight([-0.25, -0.15, 0.3], 0.07 * lamp)]
    textures = {1: tex}
    return surfaces, lights, textures


def _sheet_flat(ground, lamp, texture_seed):
    sheet = box_mesh((0.16, 0.12, 0.003), (0.0, 0.04, 0.04), _rot_z(5.0) @ _rot_x(8.0))
    tex = _realisation(0.03, ([0.8, 0.7, 0.55], [0.2, 0.3, 0.5]), texture_seed)
    surfaces = [Surface("floor", "meshes/floor.ply", _material("lambert", kd=_mean(ground, tex)), True, ground),
                Surface("sheet", "meshes/sheet.ply", _material("phong", ior=1.49, kd=[0.01, 0.01, 0.03], ks=0.2, ns=300.0,
                                                               r=1.0, t=[0.7, 0.85, 0.95]), False, sheet)]
    lights = [PointLight([0.3, -0.1, 0.25], 0.1 * lamp), PointLight([-0.3, 0.3, 0.3], 0.1 * lamp)]
    textures = {0: tex}
    return surfaces, lights, textures


def _high_ns(ground, lamp, texture_seed):
    tile = box_mesh((0.10, 0.10, 0.006), (0.0, 0.04, 0.0031), _rot_z(10.0))
    tex = _realisation(0.03, ([0.8, 0.75, 0.6], [0.2, 0.25, 0.45]), texture_seed)
    surfaces = [Surface("floor", "meshes/floor.ply", _material("lambert", kd=_mean(ground, tex)), True, ground),
                Surface("tile", "meshes/tile.ply", _material("phong", kd=[0.05, 0.05, 0.06], ks=0.5, ns=3000.0), False, tile)]
    lights = [PointLight([0.0, 0.40, 0.33], 0.1 * lamp), PointLight([-0.3, -0.2, 0.3], 0.06 * lamp)]
    textures = {0: tex}
    return surfaces, lights, textures


def _two_textured(ground, lamp, texture_seed):
    box = box_mesh((0.10, 0.08, 0.05), (0.0, 0.03, 0.0251), _rot_z(15.0))
    tex_box = _realisation(0.03, ([0.65, 0.25, 0.2], [0.2, 0.45, 0.7]), texture_seed)
    tex_floor = _realisation(0.04, ([0.8, 0.75, 0.6], [0.3, 0.3, 0.2]), None if texture_seed is None else texture_seed + 100)
    surfaces = [Surface("floor", "meshes/floor.ply", _material("phong", kd=_mean(ground, tex_floor), ks=0.05, ns=15.0), True, ground),
                Surface("box", "meshes/box.ply", _material("phong", kd=_mean(box, tex_box), ks=0.25, ns=50.0), True, box)]
    lights = [PointLight([0.07, 0.42, 0.40], 0.12 * lamp), PointLight([-0.30, -0.25, 0.30], 0.08 * lamp)]
    textures = {0: tex_floor, 1: tex_box}
    return surfaces, lights, textures


def _print_can(ground, lamp, texture_seed):
    """curved's can and lamps, the can printed in full colour (:func:`_full_colour`)."""
    surfaces, lights, _ = _curved(ground, lamp, None)
    shift = (0.0, 0.0, 0.0) if texture_seed is None else np.random.default_rng(texture_seed).uniform(0.0, 0.075, 3)

    def tex(p):
        return _full_colour(p, 0.025, shift)

    can = surfaces[1]
    surfaces[1] = Surface(can.name, can.mesh_path, _material("phong", kd=_mean(can.mesh, tex), ks=0.2, ns=20.0), True, can.mesh)
    return surfaces, lights, {1: tex}


def _tile_mirror(ground, lamp, texture_seed):
    tile = box_mesh((0.14, 0.10, 0.006), (0.0, 0.02, 0.0031), _rot_z(8.0))
    tex = _realisation(0.025, ([0.75, 0.6, 0.35], [0.25, 0.3, 0.55]), texture_seed)
    surfaces = [Surface("ground", "meshes/ground.ply", _material("lambert", kd=[0.4, 0.4, 0.4]), False, ground),
                Surface("tile", "meshes/tile.ply", _material("phong", kd=_mean(tile, tex), ks=0.15, ns=25.0), True, tile),
                _upright_mirror(0.85)]
    lights = [PointLight([0.2, -0.25, 0.35], 0.1 * lamp), PointLight([-0.25, 0.0, 0.3], 0.08 * lamp)]
    return surfaces, lights, {1: tex}


def _glossy_floor_mirror(ground, lamp, texture_seed):
    tex = _realisation(0.03, ([0.8, 0.7, 0.5], [0.3, 0.35, 0.5]), texture_seed)
    surfaces = [Surface("floor", "meshes/floor.ply", _material("phong", kd=_mean(ground, tex), ks=0.12, ns=20.0), True, ground),
                _upright_mirror(0.9)]
    lights = [PointLight([0.15, -0.3, 0.3], 0.1 * lamp), PointLight([-0.3, 0.05, 0.35], 0.08 * lamp)]
    return surfaces, lights, {0: tex}


_DESIGNS = {"shiny_box": _shiny_box, "floor_mirror": _floor_mirror, "curved": _curved, "glass_block": _glass_block,
            "ward_tile": _ward_tile, "near_lamp": _near_lamp, "oren_mirror": _oren_mirror, "sheet_flat": _sheet_flat,
            "high_ns": _high_ns, "two_textured": _two_textured, "tile_mirror": _tile_mirror,
            "glossy_floor_mirror": _glossy_floor_mirror, "print_can": _print_can}


def build(name: str, width: int = 160, height: int = 120, texture_seed: int | None = None) -> SimLab:
    """One of :data:`NAMES` or :data:`MORE` at ``width`` x ``height`` (camera, lamps, true materials, true albedo);
    ``texture_seed`` picks another realisation of its texture (:func:`_realisation`)."""
    camera = Camera.look_at(640, 480, fov_x_deg=36.0, eye=(0.0, -0.38, 0.36), target=(0.0, 0.02, 0.02))
    camera = camera.scaled(width, height) if (width, height) != (640, 480) else camera
    ground = plane_mesh((-0.8, 0.8), (-0.5, 1.2))
    lamp = np.array([1.0, 0.92, 0.8])
    try:
        design = _DESIGNS[name]
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; one of {NAMES + MORE}") from None
    surfaces, lights, textures = design(ground, lamp, texture_seed)
    return SimLab(camera, Lights(lights), Scene(surfaces), textures)


def render(ts: SimLab, depth: int = 3) -> np.ndarray:
    """The photograph of ``ts`` by the independent reference renderer (noise-free, float64)."""
    from reflab.hardware.sim.reference import render_reference

    return render_reference(ts.scene, ts.camera, ts.lights, depth=depth, albedo=ts.albedo)


def user_materials(scene: Scene) -> list:
    """What a user knows before fitting: brdf, ior, and that a lambert surface does not mirror."""
    return [Material.from_json({"brdf": s.material.brdf, "ior": s.material.ior,
                                **({"r": 0.0} if s.material.brdf == "lambert" else {})}, "scene.json", f"s{i}")
            for i, s in enumerate(scene)]


def determined(result, fac, truth: list, scene: Scene) -> list:
    """(surface, name, fitted, true, σ) of every parameter ``result`` (a FitSolution) fitted and did
    not report undetermined; a textured surface's kd (its texture's mean) is left to the texture
    stage, unless the fit found its albedo uniform (``stats["albedo_models"]``) and fitted it as one
    colour. ``fac``: the scene's Factorization, ``truth``: the true materials."""
    from reflab.inverse.fit.rounds import params_of

    p, t, sig, free, lay = result.params, params_of(fac, truth), result.sigma, result.free, fac.layout
    chosen = result.stats.get("albedo_models") or {}
    textured = [s.textured and (chosen.get(s.name) or {}).get("model") != "uniform" for s in scene]
    out = []
    for k, (s, n) in enumerate(lay.x_names):
        out += [(s, f"{n}[{c}]", p.x[k, c], t.x[k, c], sig.x[k, c]) for c in range(3)
                if free.x[k, c] and not (n == "kd" and textured[s])]
    for f in range(lay.n_factors):
        out += [(f // 2, f"{'rt'[f % 2]}[{c}]", p.s[f, c], t.s[f, c], sig.s[f, c]) for c in range(3) if free.s[f, c]]
    out += [(s, n, p.theta[q], t.theta[q], sig.theta[q]) for q, (s, n) in enumerate(lay.theta_names) if free.theta[q]]
    und = result.undetermined
    return [r for r in out if r[1] not in und[r[0]] and r[1].split("[")[0] not in und[r[0]]]
