"""The recovered model in a form outside renderers take: meshes with UVs, albedo images, materials.

What ``reflab render`` reads (scene.json's meshes, fit.json's materials, textures/) becomes one
:class:`ExportSurface` per surface: its mesh with per-vertex UVs into its texture atlas (vertices
split where two triangles give one vertex different texel coordinates, at chart seams), and its
diffuse albedo as an image or a constant.

Albedo convention: reflab's ``kd`` multiplies ``n·l`` with no 1/π (docs/formats.md), while
Mitsuba's ``diffuse``, glTF's ``baseColor`` and every physically based renderer divide their
reflectance by π. The exported albedo is ``kd`` itself (in [0, 1], as the texture stage bounds
it; ``π kd`` would pass 1 on the lab's ground) and the lamps carry the π instead:
:data:`LAMP_SCALE` times lights.json's intensity (docs/export.md).

UV convention here: ``u`` along texel columns and ``v`` down the rows, both in [0, 1] over the
atlas, texel centres at ``(i + 0.5) / size`` (glTF's and Mitsuba's bitmap lookup); writers of a
``v``-up format flip it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The exported lamps' intensity over lights.json's: reflab's ``kd`` has no 1/π (module docstring).
LAMP_SCALE = np.pi


@dataclass
class ExportSurface:
    """One surface ready to write.

    Attributes
    ----------
    name : str
    vertices : (V, 3) float64
    triangles : (T, 3) int64
    normals : (V, 3) float64 or None
        The mesh's shading normals (None: flat, the renderer takes face normals).
    uv : (V, 2) float64
        Texture coordinates (u right, v down, [0, 1]): into the recovered atlas, or for an
        untextured surface into a blank one of its own charts.
    albedo : (H, W, 3) float64 or None
        ``kd`` per texel (unknown texels filled, :func:`fill_unknown`); None without a texture.
    albedo_constant : (3,) float64
        ``kd`` of the homogeneous material (what a texel the input never saw keeps).
    material : reflab.reconstruction.scene.Material
        The fitted (or given) material.
    facing : float
        Mean ``n·v`` over the triangles facing the camera (area-weighted; 1 when none face it):
        the view cosine a lobe's conversion assumes.
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray | None
    uv: np.ndarray | None
    albedo: np.ndarray | None
    albedo_constant: np.ndarray
    material: object
    facing: float = 1.0

    @property
    def textured(self) -> bool:
        return self.albedo is not None


@dataclass
class ExportModel:
    """Camera, lamps and surfaces of a workspace's recovered model."""

    camera: object  # reflab.calibration.camera.Camera
    lights: object  # reflab.calibration.lights.Lights
    surfaces: list
    materials_source: str  # "fit.json" or "scene.json"


def split_vertices(triangles: np.ndarray, tri_uv: np.ndarray, normals: np.ndarray | None = None) -> tuple:
    """Per-vertex UVs from per-corner ones: one vertex per distinct (vertex, uv) pair.

    Returns
    -------
    source : (V',) int64
        The original vertex of each new vertex.
    uv : (V', 2) float64
        Its texture coordinates (as given per corner).
    triangles : (T, 3) int64
        The triangles over the new vertices.
    """
    corners = np.asarray(triangles, np.int64).reshape(-1)
    uv = np.asarray(tri_uv, np.float64).reshape(-1, 2)
    # Texel coordinates equal to 1e-6 texel are one vertex (chart seams differ by whole charts).
    key = np.column_stack([corners, np.round(uv * 1e6).astype(np.int64)])
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return corners[first], uv[first], inverse.reshape(-1, 3).astype(np.int64)


def fill_unknown(kd: np.ndarray, mask: np.ndarray, constant: np.ndarray) -> np.ndarray:
    """The albedo image a plain bilinear lookup should see.

    ``reflab render`` blends only the known texels around a point (weights renormalised) and
    takes the homogeneous kd where they carry under half the weight. A bitmap has no mask, so an
    unknown texel next to known ones takes their mean (the renormalised blend, near enough), and
    the others the homogeneous value.
    """
    kd = np.asarray(kd, np.float64)
    known = np.asarray(mask, bool)
    out = np.where(known[..., None], kd, 0.0)
    pad = np.pad(out, ((1, 1), (1, 1), (0, 0)))
    cnt = np.pad(known.astype(np.float64), 1)
    h, w = known.shape
    total = sum(pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1))
    count = sum(cnt[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1))
    ring = ~known & (count > 0)
    out[ring] = total[ring] / count[ring][:, None]
    out[~known & ~ring] = np.asarray(constant, np.float64)
    return out


def _facing(vertices, triangles, centre) -> float:
    v = vertices[triangles]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area = np.linalg.norm(n, axis=1)
    n = n / np.maximum(area, 1e-300)[:, None]
    view = centre - v.mean(axis=1)
    view /= np.maximum(np.linalg.norm(view, axis=1), 1e-300)[:, None]
    cos = np.einsum("ij,ij->i", n, view)
    # Either side may face the camera (reflab shades both sides); count the side it sees.
    cos = np.abs(cos)
    ok = area > 0
    return float(np.average(cos[ok], weights=area[ok])) if ok.any() else 1.0


def load_model(workspace) -> ExportModel:
    """Read a workspace's recovered model (camera.json, lights.json, scene.json, fit.json, textures/)."""
    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights
    from reflab.core.workspace import Workspace
    from reflab.inverse.texture.solve import load_materials, load_texture_maps
    from reflab.inverse.texture.texels import build_texel_map
    from reflab.reconstruction.scene import Scene

    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    camera = Camera.load(ws.require(ws.camera, "reflab calibrate camera"))
    lights = Lights.load(ws.require(ws.lights, "reflab calibrate lights"))
    scene = Scene.load(ws.require(ws.scene, "reflab reconstruct"))
    materials, source = load_materials(ws, scene)
    textures = load_texture_maps(ws, scene) if ws.texture_index.exists() else {}
    out = []
    for s, surf in enumerate(scene):
        mesh, mat = surf.mesh, materials[s]
        constant = np.asarray(mat["kd"], np.float64) if "kd" in mat.params else np.zeros(3)
        facing = _facing(mesh.vertices, mesh.triangles, camera.center)
        if surf.textured and s in textures:
            tmap, kd, mask = textures[s]
            uv = (tmap.tri_uv + 0.5) / np.array([tmap.width, tmap.height], np.float64)
            source_v, vuv, tris = split_vertices(mesh.triangles, uv)
            normals = None if mesh.normals is None else mesh.normals[source_v]
            albedo = fill_unknown(kd, mask, np.asarray(mat["kd"], np.float64))
            out.append(ExportSurface(surf.name, mesh.vertices[source_v], tris, normals, vuv, albedo, constant,
                                     mat, facing))
        else:
            # UVs all the same (every surface of an export has them), into an atlas left blank.
            extent = float(np.ptp(mesh.vertices, axis=0).max())
            tmap = build_texel_map(s, surf.name, mesh, max(extent, 1e-6) / 256)
            uv = (tmap.tri_uv + 0.5) / np.array([tmap.width, tmap.height], np.float64)
            source_v, vuv, tris = split_vertices(mesh.triangles, uv)
            normals = None if mesh.normals is None else mesh.normals[source_v]
            out.append(ExportSurface(surf.name, mesh.vertices[source_v], tris, normals, vuv, None, constant,
                                     mat, facing))
    return ExportModel(camera, lights, out, source)
