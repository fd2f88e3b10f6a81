"""Write the recovered model as a Mitsuba 3 scene: scene.xml, meshes/*.ply with UVs, textures/*.exr.

Native plugins only (docs/export.md lists each approximation and its measured error):

- the lamps are ``point`` emitters of π times lights.json's intensity and the diffuse term
  ``kd (n·l)`` a ``diffuse`` BSDF of reflectance ``kd`` (a bitmap for a textured surface): reflab's
  kd has no 1/π, Mitsuba's reflectance has (``reflab.inverse.export.model``);
- the Phong lobe ``ks (n·h)^ns`` is a ``roughconductor`` (material ``none``, Beckmann) with
  ``alpha = sqrt(2 / (ns + 2))`` (Blinn-Phong's normalised lobe ≈ Beckmann's) and
  ``specular_reflectance = ks · 8 c / (ns + 2)`` (the lamps' π taken out), ``c`` the surface's mean view cosine (the
  microfacet lobe divides by ``4 n·v``, Phong's does not); Ward's lobe maps to Beckmann with its
  own ``alpha`` and ``ks · c / π``;
- an opaque surface's ideal reflection ``r`` is a ``conductor`` (material ``none``,
  ``specular_reflectance = r``); a transparent one's ``r F`` and ``t (1 − F)`` are a
  ``dielectric`` (``int_ior = ior``, ``specular_reflectance = r``, ``specular_transmittance = t``);
- the terms are mixed by nested ``blendbsdf``: term i gets weight ``a_i = m_i / Σ m`` (``m_i`` its
  largest value) and its values are divided by ``a_i`` (``srgb`` textures marked unbounded, as a
  value passes 1 where ``Σ m > 1``);
  opaque surfaces are ``twosided`` (reflab shades the side the viewer sees);
- the camera is a ``perspective`` sensor (fov from fx; principal point offset); camera.json's lens
  distortion is left out (Mitsuba's pinhole has none);
- the integrator is ``path`` with
  ``max_depth = depth + 1`` (reflab's depth counts surface nodes, Mitsuba's the emitter too).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _f(x) -> str:
    return f"{float(x):.9g}"


def _v(x) -> str:
    return ", ".join(_f(v) for v in np.ravel(x))


def _rgb(name: str, value) -> str:
    return f'<rgb name="{name}" value="{_v(np.broadcast_to(np.asarray(value, float), (3,)))}"/>'


def _colour(name: str, value) -> str:
    """An RGB parameter that may pass 1 (a blended term's value divided by its weight)."""
    return f'<texture type="srgb" name="{name}">{_rgb("color", value)}<boolean name="unbounded" value="true"/></texture>'


def lobe_parameters(material, facing: float):
    """(alpha, specular_reflectance (3,)) of the Beckmann lobe standing in for the surface's
    Phong or Ward lobe, or None when it has none."""
    if material.brdf == "phong":
        ns = float(material["ns"])
        return float(np.sqrt(2.0 / (ns + 2.0))), np.asarray(material["ks"], float) * 8 * facing / (ns + 2.0)
    if material.brdf == "ward":
        return float(material["alpha"]), np.asarray(material["ks"], float) * facing / np.pi
    return None


def _terms(surface, texture_file: str | None) -> list:
    """(largest value, xml builder taking the scale 1/a) of each term of the surface's BSDF."""
    m = surface.material
    terms = []
    if surface.textured:
        peak = float(surface.albedo.max())
        terms.append((peak, lambda k: (
            '<bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
            f'<string name="filename" value="{texture_file}"/><boolean name="raw" value="true"/>'
            '<string name="wrap_mode" value="clamp"/></texture></bsdf>', k)))
    elif np.max(surface.albedo_constant) > 0:
        terms.append((float(np.max(surface.albedo_constant)),
                      lambda k: (f'<bsdf type="diffuse">{_colour("reflectance", surface.albedo_constant * k)}</bsdf>', k)))
    lobe = lobe_parameters(m, surface.facing)
    if lobe is not None and np.max(lobe[1]) > 0:
        alpha, spec = lobe
        terms.append((float(np.max(spec)), lambda k: (
            '<bsdf type="roughconductor"><string name="material" value="none"/>'
            f'<string name="distribution" value="beckmann"/><float name="alpha" value="{_f(alpha)}"/>'
            f'{_colour("specular_reflectance", spec * k)}</bsdf>', k)))
    r, t = np.asarray(m["r"], float), np.asarray(m["t"], float)
    if m.transparent:
        terms.append((float(max(r.max(), t.max(), 1e-6)), lambda k: (
            f'<bsdf type="dielectric"><float name="int_ior" value="{_f(m.ior)}"/>'
            '<float name="ext_ior" value="1"/>'
            f'{_colour("specular_reflectance", r * k)}{_colour("specular_transmittance", t * k)}</bsdf>', k)))
    elif r.max() > 0:
        terms.append((float(r.max()), lambda k: (
            '<bsdf type="conductor"><string name="material" value="none"/>'
            f'{_colour("specular_reflectance", r * k)}</bsdf>', k)))
    return terms


def bsdf_xml(surface, texture_file: str | None) -> tuple[str, dict]:
    """The surface's BSDF as Mitsuba XML, and how its terms were weighted (``weights``,
    ``diffuse_scale``: what the bitmap's texels are multiplied by)."""
    terms = _terms(surface, texture_file)
    info = {"weights": [], "diffuse_scale": 1.0}
    if not terms:
        xml = '<bsdf type="diffuse"><rgb name="reflectance" value="0, 0, 0"/></bsdf>'
    else:
        total = sum(peak for peak, _ in terms)
        weights = [peak / total for peak, _ in terms]
        parts = [build(1.0 / a)[0] for (_, build), a in zip(terms, weights)]
        if surface.textured:
            info["diffuse_scale"] = 1.0 / weights[0]
        info["weights"] = weights
        xml, acc = parts[0], weights[0]
        for part, a in zip(parts[1:], weights[1:]):
            xml = (f'<bsdf type="blendbsdf"><float name="weight" value="{_f(a / (acc + a))}"/>'
                   f"{xml}{part}</bsdf>")
            acc += a
    if not surface.material.transparent:
        xml = f'<bsdf type="twosided">{xml}</bsdf>'
    return xml, info


def sensor_xml(camera) -> str:
    """A perspective sensor at the input camera (OpenCV K, R, t; pixel centres at integers); its
    film's size and sample count are the scene's parameters ``width``, ``height``, ``spp`` (a
    multiple of the size keeps the view)."""
    K, W, H = camera.K, int(camera.width), int(camera.height)
    fov = np.degrees(2 * np.arctan(W / (2 * K[0, 0])))
    C = camera.center
    # Mitsuba's film centre is pixel (W - 1) / 2 in reflab's convention; its offsets are film
    # fractions, positive toward the image's left and top (checked against reflab render).
    ox, oy = ((W - 1) / 2 - K[0, 2]) / W, ((H - 1) / 2 - K[1, 2]) / H
    return (
        '<sensor type="perspective"><string name="fov_axis" value="x"/>'
        f'<float name="fov" value="{_f(fov)}"/>'
        f'<float name="principal_point_offset_x" value="{_f(ox)}"/>'
        f'<float name="principal_point_offset_y" value="{_f(oy)}"/>'
        '<float name="near_clip" value="0.001"/><float name="far_clip" value="1000"/>'
        f'<transform name="to_world"><lookat origin="{_v(C)}" target="{_v(C + camera.R[2])}" '
        f'up="{_v(-camera.R[1])}"/></transform>'
        '<sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>'
        '<film type="hdrfilm"><integer name="width" value="$width"/><integer name="height" value="$height"/>'
        '<rfilter type="box"/><string name="pixel_format" value="rgb"/></film></sensor>')


def write_mitsuba(model, out, *, depth: int = 3, spp: int = 64, task=None) -> tuple[list, dict]:
    """Write ``out/scene.xml`` (last), ``out/meshes/<surface>.ply`` and ``out/textures/<surface>.exr``.

    Returns the written paths and per-surface notes (term weights, the bitmap's scale).
    """
    from reflab.core.images import write_image
    from reflab.core.workspace import Workspace, atomic_write
    from reflab.inverse.export.model import LAMP_SCALE
    from reflab.inverse.export.ply import write_ply

    out = Path(out)
    layout = Workspace(out)
    written, notes, shapes = [], {}, []
    for i, s in enumerate(model.surfaces):
        if task is not None:
            task.step(i, len(model.surfaces), f"surface {s.name}")
        # The export's folder is laid out as a workspace's: meshes/<surface>.ply, textures/<surface>.exr.
        texture = layout.textures / f"{s.name}.exr"
        mesh = layout.mesh(s.name)
        bsdf, info = bsdf_xml(s, texture.relative_to(out).as_posix() if s.textured else None)
        if s.textured:
            written.append(write_image(texture, s.albedo * info["diffuse_scale"]))
        # Mitsuba's PLY reader and bitmap put row 0 at v = 0: reflab's v-down coordinates as they are.
        written.append(write_ply(mesh, s.vertices, s.triangles, normals=s.normals, uv=s.uv))
        # Without normals in the file Mitsuba would smooth them over a box's corners: flat, as reflab.
        flat = '<boolean name="face_normals" value="true"/>' if s.normals is None else ""
        shapes.append(f'<shape type="ply" id="{s.name}"><string name="filename" value="{mesh.relative_to(out).as_posix()}"/>'
                      f'{flat}{bsdf}</shape>')
        notes[s.name] = info
    emitters = [f'<emitter type="point"><point name="position" x="{_f(p.position[0])}" y="{_f(p.position[1])}" '
                f'z="{_f(p.position[2])}"/>{_rgb("intensity", p.intensity * LAMP_SCALE)}</emitter>' for p in model.lights.lights]
    dist = np.asarray(model.camera.dist, float)
    lines = ['<?xml version="1.0" encoding="utf-8"?>',
             "<!-- reflab export: the recovered model; approximations in reflab's docs/export.md -->",
             *(["<!-- camera.json's lens distortion "
                f"({_v(dist)}) is not exported: Mitsuba's perspective sensor is a pinhole -->"] if np.any(dist) else []),
             '<scene version="3.0.0">',
             f'<default name="spp" value="{int(spp)}"/>',
             f'<default name="width" value="{int(model.camera.width)}"/>',
             f'<default name="height" value="{int(model.camera.height)}"/>',
             f'<integrator type="path"><integer name="max_depth" value="{int(depth) + 1}"/>'
             f'<integer name="rr_depth" value="{int(depth) + 2}"/></integrator>',
             sensor_xml(model.camera), *emitters, *shapes, "</scene>", ""]
    with atomic_write(out / "scene.xml", "w") as f:
        f.write("\n".join(lines))
    written.append(out / "scene.xml")
    return written, notes
