"""Write the recovered model as a glTF 2.0 binary (.glb) or as PLY meshes with their textures.

glTF (numpy, struct and json only; docs/export.md):

- one mesh and node per surface, named as in scene.json: POSITION, NORMAL (the mesh's, or flat:
  vertices split per face), TEXCOORD_0 (v down, glTF's convention), uint32 indices;
- the material: ``baseColorTexture`` (the recovered kd as an sRGB PNG, embedded) or
  ``baseColorFactor`` (kd), metallic 0; the Phong lobe as GGX ``roughnessFactor = sqrt(alpha)``
  (alpha the Beckmann width of :func:`reflab.inverse.export.mitsuba.lobe_parameters`) and its
  strength as KHR_materials_specular's ``specularColorFactor`` (F0 over glTF's 0.04, clamped to
  1); an opaque surface whose r passes its kd (a mirror) is metallic with ``baseColorFactor = r``,
  roughness 0; a transparent one has KHR_materials_transmission (``transmissionFactor = max t``,
  ``baseColor`` the tint ``t / max t``), KHR_materials_ior and ``specularFactor = r``;
- the lamps as KHR_lights_punctual point lights of π times lights.json's intensity (reflab's kd
  has no 1/π, glTF's baseColor has; ``color`` the normalised RGB, ``intensity`` its peak);
- the input camera as a perspective camera node (yfov from fy);
- everything under one root node turning reflab's z-up world into glTF's y-up.
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

_ARRAY, _ELEMENTS = 34962, 34963
_FLOAT, _UINT = 5126, 5125
_EXTENSIONS = ["KHR_lights_punctual", "KHR_materials_ior", "KHR_materials_specular", "KHR_materials_transmission"]


def _png(albedo: np.ndarray) -> bytes:
    """The albedo (linear, (H, W, 3)) as an 8-bit sRGB PNG."""
    import cv2

    from reflab.core.images import linear_to_srgb

    img = (linear_to_srgb(np.clip(albedo, 0.0, 1.0)) * 255 + 0.5).astype(np.uint8)
    ok, data = cv2.imencode(".png", np.ascontiguousarray(img[:, :, ::-1]))
    if not ok:
        raise OSError("OpenCV could not encode a PNG texture")
    return data.tobytes()


def corner_mesh(surface) -> tuple:
    """(positions, normals, uv or None, indices) with flat normals where the mesh has none:
    one vertex per distinct (vertex, normal, uv) over the triangles' corners."""
    tris = surface.triangles
    corners = tris.reshape(-1)
    if surface.normals is None:
        v = surface.vertices[tris]
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        normals = np.repeat(n, 3, axis=0)
    else:
        normals = surface.normals[corners]
    key = np.column_stack([corners, np.round(normals * 1e6).astype(np.int64)])
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    pick = corners[first]
    uv = None if surface.uv is None else surface.uv[pick]
    return surface.vertices[pick], normals[first], uv, inverse.reshape(-1, 3)


def material_json(surface, texture: int | None) -> dict:
    """The glTF material of one surface (see the module's description)."""
    from reflab.inverse.export.mitsuba import lobe_parameters

    m = surface.material
    kd = np.clip(surface.albedo_constant, 0.0, 1.0)
    r, t = np.asarray(m["r"], float), np.asarray(m["t"], float)
    pbr = {"metallicFactor": 0.0, "roughnessFactor": 1.0}
    ext = {}
    if texture is not None:
        pbr["baseColorTexture"] = {"index": texture}
    else:
        pbr["baseColorFactor"] = [*map(float, kd), 1.0]
    lobe = lobe_parameters(m, surface.facing)
    if lobe is not None and np.max(lobe[1]) > 0:
        alpha, spec = lobe
        pbr["roughnessFactor"] = float(np.sqrt(alpha))
        ext["KHR_materials_specular"] = {"specularColorFactor": [float(x) for x in np.clip(spec / 0.04, 0, 1)]}
    if m.transparent:
        peak = float(max(t.max(), 1e-6))
        pbr.update(baseColorFactor=[*map(float, t / peak), 1.0], roughnessFactor=0.0)
        pbr.pop("baseColorTexture", None)
        ext["KHR_materials_transmission"] = {"transmissionFactor": peak}
        ext["KHR_materials_ior"] = {"ior": float(m.ior)}
        ext.setdefault("KHR_materials_specular", {})["specularFactor"] = float(r.max())
    elif r.max() > kd.max():
        pbr.update(baseColorFactor=[*map(float, r), 1.0], metallicFactor=1.0, roughnessFactor=0.0)
        pbr.pop("baseColorTexture", None)
    out = {"name": surface.name, "pbrMetallicRoughness": pbr, "doubleSided": not m.transparent}
    if ext:
        out["extensions"] = ext
    return out


def write_glb(model, path) -> tuple[list, dict]:
    """Write the model as one .glb (atomically). Returns ([path], per-surface notes)."""
    from reflab.core.workspace import atomic_write
    from reflab.inverse.export.model import LAMP_SCALE

    blob = bytearray()
    doc = {"asset": {"version": "2.0", "generator": "reflab export"}, "extensionsUsed": _EXTENSIONS,
           "buffers": [], "bufferViews": [], "accessors": [], "meshes": [], "materials": [], "nodes": [],
           "images": [], "textures": [], "samplers": [{"magFilter": 9729, "minFilter": 9729,
                                                      "wrapS": 33071, "wrapT": 33071}]}

    def view(data: bytes, target=None) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data),
                                   **({"target": target} if target else {})})
        blob.extend(data)
        return len(doc["bufferViews"]) - 1

    def accessor(array: np.ndarray, kind: str, component: int, target: int, bounds: bool = False) -> int:
        dtype = np.float32 if component == _FLOAT else np.uint32
        data = np.ascontiguousarray(array, dtype=dtype)
        acc = {"bufferView": view(data.tobytes(), target), "componentType": component, "count": int(len(data)),
               "type": kind}
        if bounds:
            acc.update(min=[float(x) for x in data.min(0)], max=[float(x) for x in data.max(0)])
        doc["accessors"].append(acc)
        return len(doc["accessors"]) - 1

    notes, children = {}, []
    for s in model.surfaces:
        pos, nor, uv, idx = corner_mesh(s)
        attrs = {"POSITION": accessor(pos, "VEC3", _FLOAT, _ARRAY, bounds=True),
                 "NORMAL": accessor(nor, "VEC3", _FLOAT, _ARRAY)}
        if uv is not None:
            attrs["TEXCOORD_0"] = accessor(uv, "VEC2", _FLOAT, _ARRAY)
        texture = None
        if s.textured:
            doc["images"].append({"bufferView": view(_png(s.albedo)), "mimeType": "image/png", "name": s.name})
            doc["textures"].append({"source": len(doc["images"]) - 1, "sampler": 0})
            texture = len(doc["textures"]) - 1
        doc["materials"].append(material_json(s, texture))
        doc["meshes"].append({"name": s.name, "primitives": [{
            "attributes": attrs, "indices": accessor(idx.reshape(-1), "SCALAR", _UINT, _ELEMENTS),
            "material": len(doc["materials"]) - 1, "mode": 4}]})
        doc["nodes"].append({"name": s.name, "mesh": len(doc["meshes"]) - 1})
        children.append(len(doc["nodes"]) - 1)
        notes[s.name] = {"vertices": int(len(pos)), "triangles": int(len(idx)), "texture": texture is not None}
    lights = []
    for k, light in enumerate(model.lights.lights):
        power = np.asarray(light.intensity, float) * LAMP_SCALE
        peak = float(max(power.max(), 1e-300))
        lights.append({"name": f"lamp{k}", "type": "point", "color": [float(x) for x in power / peak],
                       "intensity": peak})
        doc["nodes"].append({"name": f"lamp{k}", "translation": [float(x) for x in light.position],
                             "extensions": {"KHR_lights_punctual": {"light": k}}})
        children.append(len(doc["nodes"]) - 1)
    doc["extensions"] = {"KHR_lights_punctual": {"lights": lights}}
    cam = model.camera
    doc["cameras"] = [{"name": "input", "type": "perspective", "perspective": {
        "yfov": float(2 * np.arctan(cam.height / (2 * cam.K[1, 1]))), "aspectRatio": cam.width / cam.height,
        "znear": 0.001, "zfar": 1000.0}}]
    # glTF's camera looks down its -z with +y up; OpenCV's down +z with +y down.
    to_world = np.eye(4)
    to_world[:3, 0], to_world[:3, 1], to_world[:3, 2], to_world[:3, 3] = cam.R[0], -cam.R[1], -cam.R[2], cam.center
    doc["nodes"].append({"name": "input camera", "camera": 0, "matrix": [float(x) for x in to_world.T.ravel()]})
    children.append(len(doc["nodes"]) - 1)
    h = float(np.sqrt(0.5))
    doc["nodes"].append({"name": "reflab (z up)", "rotation": [-h, 0.0, 0.0, h], "children": children})
    doc["scenes"], doc["scene"] = [{"name": "reflab", "nodes": [len(doc["nodes"]) - 1]}], 0
    for key in ("images", "textures"):
        if not doc[key]:
            del doc[key]
    blob.extend(b"\0" * (-len(blob) % 4))
    doc["buffers"] = [{"byteLength": len(blob)}]
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(blob)
    with atomic_write(path, "wb") as f:
        f.write(struct.pack("<III", 0x46546C67, 2, total))
        f.write(struct.pack("<II", len(text), 0x4E4F534A) + text)
        f.write(struct.pack("<II", len(blob), 0x004E4942) + bytes(blob))
    return [Path(path)], notes


def read_glb(path) -> tuple[dict, bytes]:
    """The JSON document and the binary chunk of a .glb."""
    raw = Path(path).read_bytes()
    magic, version, total = struct.unpack_from("<III", raw, 0)
    if magic != 0x46546C67 or version != 2 or total != len(raw):
        raise ValueError(f"{path}: not a glTF 2.0 binary")
    n, kind = struct.unpack_from("<II", raw, 12)
    doc = json.loads(raw[20:20 + n])
    m, _ = struct.unpack_from("<II", raw, 20 + n)
    return doc, raw[28 + n:28 + n + m]


def read_accessor(doc: dict, blob: bytes, index: int) -> np.ndarray:
    """An accessor's data as a numpy array (float32 or uint32, shaped by its type)."""
    acc = doc["accessors"][index]
    bv = doc["bufferViews"][acc["bufferView"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    dtype = np.float32 if acc["componentType"] == _FLOAT else np.uint32
    data = np.frombuffer(blob, dtype=dtype, count=acc["count"] * width, offset=bv["byteOffset"] + acc.get("byteOffset", 0))
    return data.reshape(-1, width) if width > 1 else data


def read_image(doc: dict, blob: bytes, index: int) -> np.ndarray:
    """An embedded image decoded to linear RGB float64 (sRGB undone)."""
    import cv2

    from reflab.core.images import srgb_to_linear

    bv = doc["bufferViews"][doc["images"][index]["bufferView"]]
    data = np.frombuffer(blob, np.uint8, count=bv["byteLength"], offset=bv["byteOffset"])
    img = cv2.imdecode(data, cv2.IMREAD_COLOR)[:, :, ::-1]
    return srgb_to_linear(img.astype(np.float64) / 255.0)


def write_ply_folder(model, out) -> tuple[list, dict]:
    """``out/<surface>.ply`` (texture_u, texture_v with v up, as MeshLab and Blender read them; a
    ``TextureFile`` comment), ``out/<surface>.png`` (sRGB) and ``.exr`` (linear kd) beside each
    textured one, and ``out/materials.json`` (the materials, as the render takes them from fit.json)."""
    from reflab.core.images import write_image
    from reflab.core.workspace import atomic_write, write_json
    from reflab.inverse.export.ply import write_ply

    out = Path(out)
    written, notes = [], {}
    for s in model.surfaces:
        comments = ["reflab export: recovered diffuse albedo kd in the texture (linear in the .exr)"]
        if s.textured:
            with atomic_write(out / f"{s.name}.png", "wb") as f:
                f.write(_png(s.albedo))
            written += [out / f"{s.name}.png", write_image(out / f"{s.name}.exr", s.albedo)]
            comments.append(f"TextureFile {s.name}.png")
        uv = None if s.uv is None else np.column_stack([s.uv[:, 0], 1.0 - s.uv[:, 1]])
        written.append(write_ply(out / f"{s.name}.ply", s.vertices, s.triangles, normals=s.normals, uv=uv,
                                 uv_names=("texture_u", "texture_v"), comments=comments))
        notes[s.name] = {"vertices": int(len(s.vertices)), "texture": s.textured}
    written.append(write_json(out / "materials.json", {"surfaces": [
        {"name": s.name, "textured": s.textured, "material": s.material.to_json()} for s in model.surfaces]}))
    return written, notes
