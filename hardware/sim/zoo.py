"""A seeded zoo of random scenes for judging the fit on scenes it was never tuned on (docs/fit.md, "The zoo").

:func:`random_scene` draws, from one integer seed, a table-top scene in the world frame of
docs/formats.md (metres, ground z = 0, +z up):

- a ground plane (matte lambert or faintly glossy phong) and 2–7 objects on it, together 3–8
  surfaces: boxes at any yaw, spheres, cylinders lying on their side (closed meshes, lifted 1 mm
  so that no face is shared with the ground), and at most one upright wall behind them;
- materials over the plausible range of each BRTDF (:mod:`reflab.inverse.fit.ranges`): phong
  mostly (lobe albedo 2–35 %, ns 5–300, sometimes a faint mirror term r), some ward and lambert;
  at most one mirror (r 0.7–0.95) and one glass object (index 1.4–1.6, closed mesh);
- each diffuse surface untextured, or textured by one to four inks (soft-edged regions) or by
  smooth noise; a textured surface's ``kd`` is its texture's mean;
- one to three lamps above, and a camera looking at the scene from a random direction above.

:func:`write_zoo_workspace` writes a scene as the workspace a user would have (camera, lamps,
geometry, brdf and ior only in scene.json; the photograph input.exr by the independent reference
renderer), with the truth beside it: truth.json (the true materials) and truth/ (the true scene,
a novel view and a relit view rendered by the same renderer). Everything is deterministic per seed.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reflab.calibration.camera import Camera
from reflab.calibration.lights import Lights, PointLight
from reflab.hardware.sim.lab import SimLab, _material, _rot_z, box_mesh, plane_mesh, write_lab
from reflab.hardware.sim.scenes import cylinder_mesh
from reflab.inverse.fit.problem import LOG2
from reflab.inverse.fit.ranges import phong_lobe_albedo
from reflab.reconstruction.scene import Mesh, Scene, Surface

#: Range of a texture's albedo per band (as the lab's textures).
ALBEDO = (0.05, 0.9)
#: Radius (m) of the disc on the ground the objects stand in.
SPREAD = 0.14
#: Degrees the novel view's camera turns about the vertical axis through the origin.
NOVEL_TURN = 35.0


#: A determined value is confidently wrong beyond this many σ plus :data:`SLACK` of its true value.
SIGMAS, SLACK = 3.0, 0.02
#: Recall: within this share of the true value (or :data:`ATTENUATION_FLOOR` for r and t).
RECALL, ATTENUATION_FLOOR = 0.10, 0.01


def sphere_mesh(radius: float, center, rings: int = 16, segments: int = 32) -> Mesh:
    """A closed UV sphere (one vertex at each pole, outward triangles) of ``radius`` at ``center``."""
    theta = np.pi * np.arange(1, rings) / rings  # polar angles of the inner rings
    phi = 2 * np.pi * np.arange(segments) / segments
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring = np.stack([st * np.cos(phi), st * np.sin(phi), ct * np.ones_like(phi)], axis=2).reshape(-1, 3)
    verts = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]])
    top, bottom = 0, len(verts) - 1
    j = np.arange(segments)
    k = (j + 1) % segments
    idx = lambda r, c: 1 + r * segments + c  # noqa: E731 -- vertex of inner ring r, column c
    tris = [np.stack([np.full(segments, top), idx(0, j), idx(0, k)], 1),
            np.stack([np.full(segments, bottom), idx(rings - 2, k), idx(rings - 2, j)], 1)]
    for r in range(rings - 2):
        tris += [np.stack([idx(r, j), idx(r + 1, j), idx(r + 1, k)], 1), np.stack([idx(r, j), idx(r + 1, k), idx(r, k)], 1)]
    tris = np.concatenate(tris)
    v = verts[tris]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flip = np.einsum("ij,ij->i", n, v.mean(axis=1)) < 0  # orient outward (the centre is the origin)
    tris[flip] = tris[flip][:, ::-1]
    return Mesh(radius * verts + np.asarray(center, dtype=np.float64), tris)


# ---------------------------------------------------------------- textures
def _waves(rng, scale: float, k: int = 6):
    """A smooth random field of world points, about N(0, 1): ``k`` plane waves of period ~``scale``."""
    dirs = rng.normal(size=(k, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    periods = scale * np.exp(rng.uniform(np.log(0.7), np.log(1.4), k))
    phases = rng.uniform(0, 2 * np.pi, k)
    w = dirs / periods[:, None]

    def field(p):
        return np.sin(2 * np.pi * np.asarray(p, dtype=np.float64).reshape(-1, 3) @ w.T + phases).sum(axis=1) * np.sqrt(2.0 / k)

    return field


def _colour(rng, lo: float = 0.1, hi: float = 0.8) -> np.ndarray:
    """A random colour: a brightness and a saturation, per band within [lo, hi]."""
    base = rng.uniform(lo, hi)
    return np.clip(base * (1.0 + rng.uniform(-0.5, 0.5, 3)), lo, hi)


def _inks(rng, n: int, scale: float):
    """``n`` inks in soft-edged regions (the largest of ``n`` smooth fields wins); one ink is uniform."""
    colours = np.array([_colour(rng) for _ in range(n)])
    fields = [_waves(rng, scale) for _ in range(n)]

    def tex(p):
        if n == 1:
            return np.broadcast_to(colours[0], (len(np.asarray(p).reshape(-1, 3)), 3)).copy()
        f = np.stack([fl(p) for fl in fields], axis=1)
        w = np.exp(6.0 * (f - f.max(axis=1, keepdims=True)))
        return np.clip((w / w.sum(axis=1, keepdims=True)) @ colours, *ALBEDO)

    return tex


def _noise(rng, scale: float):
    """Smooth noise about a base colour: each band its own field, ± 40 % of the base."""
    base = _colour(rng, 0.2, 0.7)
    fields = [_waves(rng, scale) for _ in range(3)]

    def tex(p):
        f = np.stack([fl(p) for fl in fields], axis=1)
        return np.clip(base * (1.0 + 0.4 * np.tanh(f)), *ALBEDO)

    return tex


def _texture(rng):
    """(kind, albedo function or None): none (half), inks (3 in 10) or smooth noise (1 in 5)."""
    u = rng.uniform()
    scale = rng.uniform(0.02, 0.05)
    if u < 0.5:
        return "none", None
    if u < 0.8:
        n = int(rng.integers(1, 5))
        return f"{n} ink{'s' if n > 1 else ''}", _inks(rng, n, scale)
    return "noise", _noise(rng, scale)


# ---------------------------------------------------------------- materials
def _phong(rng, kd, lobe=(0.02, 0.35), ns=(5.0, 300.0), mirror: float = 0.3):
    n = float(np.exp(rng.uniform(*np.log(ns))))
    ks = rng.uniform(*lobe) / float(phong_lobe_albedo(n))  # the lobe's albedo, not its peak, is drawn
    r = rng.uniform(0.02, 0.08) if rng.uniform() < mirror else 0.0
    return _material("phong", kd=kd, ks=ks, ns=n, r=r)


def _diffuse_material(rng, kd, brdf: str):
    if brdf == "lambert":
        return _material("lambert", kd=kd)
    if brdf == "ward":
        return _material("ward", kd=kd, ks=rng.uniform(0.03, 0.3), alpha=float(np.exp(rng.uniform(np.log(0.05), np.log(0.4)))))
    return _phong(rng, kd)


def _glass(rng):
    return _material("phong", ior=float(rng.uniform(1.4, 1.6)), kd=rng.uniform(0.002, 0.01, 3), ks=rng.uniform(0.1, 0.2),
                     ns=float(rng.uniform(150.0, 300.0)), r=1.0, t=rng.uniform(0.8, 0.95, 3))


# ---------------------------------------------------------------- the scene
@dataclass
class ZooScene(SimLab):
    """A :class:`reflab.hardware.sim.lab.SimLab` drawn by :func:`random_scene`, with its seed, its
    photograph's noise (of the peak) and a one-line description per surface."""

    seed: int = 0
    noise: float = 0.0
    description: tuple = ()


def _place(rng, placed: list, radius: float, tries: int = 50):
    """A ground point in the disc of :data:`SPREAD` whose footprint circle misses the placed ones."""
    for _ in range(tries):
        c = rng.uniform(-SPREAD, SPREAD, 2)
        if np.hypot(*c) <= SPREAD and all(np.hypot(*(c - q)) > radius + s + 0.005 for q, s in placed):
            placed.append((c, radius))
            return c
    return None


def random_scene(seed: int, width: int = 160, height: int = 120, *, noise: float = 0.0) -> ZooScene:
    """Draw the scene of ``seed`` (deterministic) for a ``width`` x ``height`` camera.

    Parameters
    ----------
    seed : int
    width, height : int
        Image size; the field of view is the 640x480 camera's at any size.
    noise : float
        Standard deviation of the photograph's Gaussian noise, relative to its peak
        (:func:`write_zoo_workspace` adds it, seeded by ``seed``).

    Returns
    -------
    ZooScene
    """
    if width < 2 or height < 2:
        raise ValueError(f"random_scene: image size must be at least 2x2, got {width}x{height}")
    rng = np.random.default_rng([35, int(seed)])
    azimuth = rng.uniform(0.0, 360.0)
    a = np.radians(azimuth)
    toward = np.array([np.cos(a), np.sin(a)])  # horizontal direction from the scene to the camera
    elevation, distance = np.radians(rng.uniform(30.0, 60.0)), rng.uniform(0.45, 0.6)
    eye = distance * np.array([np.cos(elevation) * toward[0], np.cos(elevation) * toward[1], np.sin(elevation)])
    camera = Camera.look_at(640, 480, fov_x_deg=40.0, eye=eye, target=(0.0, 0.0, 0.02))
    camera = camera.scaled(width, height) if (width, height) != (640, 480) else camera

    surfaces, textures, description = [], {}, []
    special = {"mirror": rng.uniform() < 0.35, "glass": rng.uniform() < 0.35}

    def add(name, mesh, material, tex=None, kind="none"):
        if tex is not None:
            material = _material(material.brdf, ior=material.ior,
                                 **dict(material.params, kd=tex(mesh.sample_points(20000)).mean(axis=0)))
            textures[len(surfaces)] = tex
        surfaces.append(Surface(name, f"meshes/{name}.ply", material, tex is not None, mesh))
        description.append(f"{name}: {material.brdf}{'' if material.ior is None else ' glass'}"
                           f"{' mirror' if material.brdf == 'phong' and material['r'].max() > 0.5 and material.ior is None else ''}"
                           f", texture {kind}")

    ground = plane_mesh((-0.8, 0.8), (-0.8, 0.8))
    kind, tex = _texture(rng)
    gmat = (_material("lambert", kd=_colour(rng, 0.2, 0.7)) if rng.uniform() < 0.6 else
            _phong(rng, _colour(rng, 0.2, 0.7), lobe=(0.02, 0.1), ns=(5.0, 30.0), mirror=0.0))
    add("ground", ground, gmat, tex, kind)

    n_objects = int(rng.integers(2, 8))
    placed = []
    if rng.uniform() < 0.4:  # an upright wall behind the objects, facing the camera
        n_objects -= 1
        yaw = azimuth - 90.0 + rng.uniform(-20.0, 20.0)
        size = (rng.uniform(0.18, 0.28), 0.006, rng.uniform(0.10, 0.16))
        c = -(SPREAD + 0.05) * toward
        mesh = box_mesh(size, (c[0], c[1], size[2] / 2 + 0.001), _rot_z(yaw))
        if special["mirror"]:
            special["mirror"] = False
            mat = _material("phong", kd=0.02, ks=0.3, ns=300.0, r=rng.uniform(0.7, 0.95))
            add("wall", mesh, mat)
        else:
            kind, tex = _texture(rng)
            add("wall", mesh, _diffuse_material(rng, _colour(rng), "phong"), tex, kind)
    for i in range(n_objects):
        shape = rng.choice(["box", "box", "sphere", "cylinder"])
        role = "glass" if special["glass"] else "mirror" if special["mirror"] and shape == "box" else "diffuse"
        if shape == "box":
            size = rng.uniform(0.04, 0.10, 3)
            size[2] = rng.uniform(0.02, 0.08)
            c = _place(rng, placed, 0.5 * np.hypot(size[0], size[1]))
            if c is None:
                continue
            mesh = box_mesh(size, (c[0], c[1], size[2] / 2 + 0.001), _rot_z(rng.uniform(0.0, 360.0)))
        elif shape == "sphere":
            radius = rng.uniform(0.025, 0.05)
            c = _place(rng, placed, radius)
            if c is None:
                continue
            mesh = sphere_mesh(radius, (c[0], c[1], radius + 0.001))
        else:
            radius, length = rng.uniform(0.02, 0.04), rng.uniform(0.08, 0.16)
            c = _place(rng, placed, 0.5 * np.hypot(length, 2 * radius))
            if c is None:
                continue
            mesh = cylinder_mesh(radius, length, (c[0], c[1], radius + 0.001), axis_deg=rng.uniform(0.0, 360.0))
        name = f"{shape}{i}"
        if role == "glass":
            special["glass"] = False
            add(name, mesh, _glass(rng))
        elif role == "mirror":
            special["mirror"] = False
            add(name, mesh, _material("phong", kd=0.02, ks=0.3, ns=300.0, r=rng.uniform(0.7, 0.95)))
        else:
            kind, tex = _texture(rng)
            brdf = rng.choice(["phong"] * 6 + ["ward"] * 2 + ["lambert"] * 2)
            add(name, mesh, _diffuse_material(rng, _colour(rng), str(brdf)), tex, kind)

    lamps = []
    n_lamps = int(rng.integers(1, 4))
    for _ in range(n_lamps):
        b = np.radians(azimuth + rng.uniform(-150.0, 150.0))  # not straight behind the camera's back
        el, d = np.radians(rng.uniform(35.0, 70.0)), rng.uniform(0.35, 0.6)
        pos = d * np.array([np.cos(el) * np.cos(b), np.cos(el) * np.sin(b), np.sin(el)])
        tint = np.array([1.0, rng.uniform(0.85, 1.0), rng.uniform(0.65, 1.0)])
        lamps.append(PointLight(pos, d * d * rng.uniform(0.3, 0.5) / np.sqrt(n_lamps) * tint))
    return ZooScene(camera, Lights(lamps), Scene(surfaces), textures, seed=int(seed), noise=float(noise),
                    description=tuple(description))


def _turned(camera: Camera, degrees: float) -> Camera:
    """``camera`` turned by ``degrees`` about the vertical axis through the origin."""
    from reflab.calibration.rotations import axis_rotation

    Rz = axis_rotation((0.0, 0.0, 1.0), degrees)
    R = camera.R @ Rz.T
    return Camera(camera.width, camera.height, camera.K.copy(), camera.dist.copy(), R, -R @ (Rz @ camera.center))


def views(zoo: ZooScene) -> dict:
    """The scoring views of a zoo scene: ``novel`` (camera, lights), the camera turned by
    :data:`NOVEL_TURN`, and ``relit`` (camera, lights), the input camera under other lamps
    (each lamp moved by 120° about the vertical axis)."""
    from reflab.calibration.rotations import axis_rotation

    Rz = axis_rotation((0.0, 0.0, 1.0), 120.0)
    relit = Lights([PointLight(Rz @ p, i) for p, i in zip(zoo.lights.positions, zoo.lights.intensities)])
    return {"novel": (_turned(zoo.camera, NOVEL_TURN), zoo.lights), "relit": (zoo.camera, relit)}


def photograph(zoo: ZooScene, depth: int = 3) -> np.ndarray:
    """The scene's photograph by the reference renderer, with its seeded Gaussian noise, not clipped
    at 0 (a dark-frame-subtracted photograph: clipping would lift dark pixels, a bias the fit's
    noise model does not hold, and it reads noise-level negative values as data)."""
    from reflab.hardware.sim.reference import render_reference

    img = render_reference(zoo.scene, zoo.camera, zoo.lights, depth=depth, albedo=zoo.albedo)
    if zoo.noise > 0:
        img = img + np.random.default_rng([35, zoo.seed, 1]).normal(0.0, zoo.noise * img.max(), img.shape)
    return img


def write_zoo_workspace(root, seed: int, width: int = 160, height: int = 120, *, noise: float = 0.0,
                        depth: int = 3, truth_views: bool = True) -> ZooScene:
    """Write the zoo scene of ``seed`` as a workspace at ``root``.

    The workspace holds what a user knows (camera.json, lights.json, meshes/, scene.json with
    brdf and ior only, ``r = 0`` on lambert surfaces) and the photograph input.exr (reference
    renderer, ``noise`` of the peak); the truth: truth.json (true materials, fit.json's layout),
    truth/ (scene.json with the true materials and meshes, zoo.json with the seed and the scene's
    description) and, with ``truth_views``, truth/novel_camera.json + novel.exr and
    truth/relit_lights.json + relit.exr (docs/formats.md, "The simulated lab's truth"). The true
    textures are procedural: :func:`random_scene` with the seed gives them back.

    Returns
    -------
    ZooScene
    """
    from reflab.core.images import write_image
    from reflab.core.workspace import Workspace, write_json
    from reflab.hardware.sim.reference import render_reference

    zoo = random_scene(seed, width, height, noise=noise)
    ws = Workspace(Path(root))
    write_lab(ws.root, zoo, materials=False)
    write_image(ws.root / "input.exr", photograph(zoo, depth))
    truth = Workspace(ws.truth)
    write_lab(truth.root, zoo, materials=True)
    write_json(truth.root / "zoo.json", {"seed": int(seed), "width": width, "height": height, "noise": noise,
                                         "depth": depth, "surfaces": list(zoo.description)})
    if truth_views:
        for which, (cam, lights) in views(zoo).items():
            pose, image = truth.view(which)
            (cam if which == "novel" else lights).save(pose)
            write_image(image, render_reference(zoo.scene, cam, lights, depth=depth, albedo=zoo.albedo))
    return zoo


def write_further_photographs(root, zoo: ZooScene, shots, depth: int = 3) -> None:
    """The further photographs ``shots`` (:func:`reflab.hardware.sim.lab.named_views`: ``Lk`` lamp k
    alone, ``TA`` the turntable turned by A degrees) of a zoo scene, by the reference renderer
    with the scene's noise share of each one's peak (seeded by its seed), written into ``root``'s
    inputs/ with their camera and lamps: the fit over several photographs on a random scene."""
    from reflab.hardware.sim.lab import named_views
    from reflab.hardware.sim.reference import render_reference
    from reflab.inverse.forward.photographs import write_input

    rng = np.random.default_rng([35, zoo.seed, 2])
    for name, cam, lights in named_views(zoo.camera, zoo.lights, shots):
        img = render_reference(zoo.scene, cam, lights, depth=depth, albedo=zoo.albedo)
        if zoo.noise > 0:
            img = img + rng.normal(0.0, zoo.noise * img.max(), img.shape)
        write_input(root, name, img, cam, lights)


# ---------------------------------------------------------------- scoring a fit
def seen_surfaces(report: dict) -> set:
    """Indices of the surfaces with a column in the fit (seen by the camera and lit)."""
    return {int(m) for name in report["columns"]["names"] for m in re.findall(r"[a-z]+(\d+)", name)}


def compare(report: dict, truth: dict, textured: list) -> list:
    """One row per visible parameter value: (surface, name, fitted, true, σ or None, determined).

    ``report``: fit.json, ``truth``: truth.json, ``textured``: per surface. Values the user gave
    (held: a lambert surface's r) and t of opaque surfaces are not fitted and not listed; nor is a
    textured surface's kd (its texture's mean, the texture stage's), unless the fit found its
    albedo uniform (fit.json's ``albedo_model``) and fitted it as one colour.
    """
    rows = []
    seen = seen_surfaces(report)
    for i, (item, true) in enumerate(zip(report["surfaces"], truth["surfaces"])):
        if i not in seen:
            continue
        fitted, sig, und = item["material"], item["sigma"], set(item["undetermined"])
        tm = true["material"]
        for name, value in fitted.items():
            if name in ("brdf", "ior") or (name == "kd" and textured[i] and item.get("albedo_model") != "uniform"):
                continue
            if name == "t" and tm.get("ior") is None or (name == "r" and tm["brdf"] == "lambert"):
                continue
            vals, tvals = np.atleast_1d(value), np.atleast_1d(tm[name])
            sigs = np.atleast_1d(sig.get(name, [None] * len(vals)))
            for c, (v, t, s) in enumerate(zip(vals, tvals, sigs)):
                label = f"{name}[{c}]" if len(vals) > 1 else name
                det = name not in und and label not in und and s is not None and np.isfinite(s) and s > 0
                rows.append((item["name"], label, float(v), float(t), None if s is None else float(s), bool(det)))
    return rows


def deviation(name: str, fitted: float, true: float, sigma: float) -> tuple[float, float]:
    """(|error| / σ, the error's margin beyond SIGMAS σ plus SLACK: > 0 is confidently wrong) of one
    determined value; a shape the fit searches in log2 (:data:`reflab.inverse.fit.problem.LOG2`) in
    log2 units, σ / (fitted ln 2) with slack log2(1 + SLACK), where the fit's σ is symmetric (a
    broad lobe's linear σ understates its upward tail: zoo seed 61, one photograph, a box's ns
    5.20 ± 1.65 for 11.03 is 3.5σ off linearly, 2.4σ in log2)."""
    if name in LOG2 and fitted > 0 and true > 0:
        err, sig = abs(np.log2(fitted / true)), sigma / (fitted * np.log(2.0))
        return err / sig, err - (SIGMAS * sig + np.log2(1.0 + SLACK))
    err = abs(fitted - true)
    return err / sigma, err - (SIGMAS * sigma + SLACK * abs(true))


def score(rows: list) -> dict:
    det = [r for r in rows if r[5]]
    judged = [deviation(b, v, t, s) for _, b, v, t, s, _ in det]
    z = np.array([j[0] for j in judged])
    wrong = [f"{a} {b} fit {v:.4g} true {t:.4g} σ {s:.3g}" for (a, b, v, t, s, _), j in zip(det, judged)
             if j[1] > 0]

    def close(r):
        floor = ATTENUATION_FLOOR if r[1][0] in "rt" else 0.0
        return r[5] and abs(r[2] - r[3]) <= max(RECALL * abs(r[3]), floor)

    return {"visible": len(rows), "determined": len(det), "recovered": int(sum(close(r) for r in rows)),
            "within_3sigma": int(np.sum(z <= SIGMAS)), "worst": float(z.max()) if len(z) else 0.0, "wrong": wrong}
