"""The marks file's ``surfaces`` list: corners marked by hand and what the user knows per surface.

One file, ``WORKSPACE/marks.json`` (beside the rod marks of `reflab calibrate lights`), written by
the GUI, by a person, or by the simulated user (hardware/sim/user.py). Each entry is either

- a **marked** surface (it has ``corners``): a box or open rectangle fitted to its corners marked
  in two or more sweep shots (docs/reconstruction.md, "Marks file"); or
- a **pointed** surface (it has ``at``): a pixel ``[u, v]`` of the input view (camera.json) on a
  surface that reconstruction fitted by itself (``ground``, ``box0``, ...), which then takes the
  entry's ``name``.

and says what the user knows, once, in plain words:

- ``"matte": true``: a diffuse surface that does not mirror (brdf lambert, r = 0);
- ``"mirror": true``: a mirror (phong, opaque, untextured);
- ``"ior": 1.46``: transparent, with its refraction index (a closed box, untextured);
- ``"untextured": true`` (or ``"textured": false``): one homogeneous albedo.

`reflab reconstruct` applies them when it writes scene.json, so no later stage needs a hand edit.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from reflab.calibration.camera import Camera
from reflab.core.workspace import Workspace, WorkspaceError, as_array, read_json
from reflab.reconstruction.scene import Material, Scene


def has_surfaces(path) -> bool:
    """Whether a marks file holds a ``surfaces`` list."""
    path = Path(path)
    return path.exists() and isinstance(read_json(path).get("surfaces"), list)


def _known(item: dict, path, where: str) -> dict:
    """brdf, ior, textured (and r = 0 for matte) from an entry's plain-word options."""
    for key in ("matte", "mirror", "untextured"):
        if key in item and not isinstance(item[key], bool):
            raise WorkspaceError(path, f"{where}.{key}", "true or false", got=item[key])
    ior = item.get("ior")
    if item.get("matte") and (item.get("mirror") or ior is not None):
        raise WorkspaceError(path, f"{where}.matte", "a matte surface that is neither a mirror nor transparent", got=True)
    brdf = item.get("brdf", "lambert" if item.get("matte") else "phong")
    textured = item.get("textured", not (item.get("untextured") or item.get("mirror") or ior is not None))
    return {"brdf": brdf, "ior": ior, "textured": bool(textured), "matte": bool(item.get("matte"))}


def read_surfaces(path) -> tuple[dict, list[dict]]:
    """``(marked, pointed)``: the marks file's marked entries as :func:`reflab.reconstruction.surfaces.load_marks`
    specs, and its pointed entries as ``{"name", "at", "where", brdf, ior, textured, matte}``."""
    from reflab.reconstruction import surfaces as surf

    path = Path(path)
    obj = read_json(path)
    items = obj.get("surfaces")
    if not isinstance(items, list):
        raise WorkspaceError(path, "surfaces", "a list of marked or pointed surfaces", got=items)
    marked, pointed = [], []
    for i, item in enumerate(items):
        where = f"surfaces[{i}]"
        if not isinstance(item, dict):
            raise WorkspaceError(path, where, "an object", got=item)
        known = _known(item, path, where)
        if "corners" in item:
            marked.append(dict(item, brdf=known["brdf"], ior=known["ior"], textured=known["textured"]))
        elif "at" in item:
            name = item.get("name")
            if not isinstance(name, str) or not name:
                raise WorkspaceError(path, f"{where}.name", "a non-empty string", got=name)
            pointed.append(dict(known, name=name, where=where, at=as_array(item["at"], (2,), path, f"{where}.at")))
        else:
            raise WorkspaceError(path, where, "'corners' (a marked surface) or 'at' (a pixel on a fitted surface)",
                                 got=sorted(item))
    specs = surf.load_marks(path, {"surfaces": marked}) if marked else []
    matte = {m["name"] for m in marked if m.get("matte")}
    for s in specs:
        s["matte"] = s["name"] in matte
    return specs, pointed


def _first_hit(scene: Scene, camera: Camera, uv: np.ndarray) -> int:
    """Index of the surface the input view's ray through pixel ``uv`` meets first (-1: none)."""
    from reflab.core.open3d_env import open3d
    o3d = open3d()

    rc = o3d.t.geometry.RaycastingScene()
    ids = [rc.add_triangles(o3d.core.Tensor(s.mesh.vertices.astype(np.float32)),
                            o3d.core.Tensor(s.mesh.triangles.astype(np.uint32))) for s in scene]
    o, d = camera.rays(np.asarray(uv, dtype=np.float64).reshape(1, 2))
    ans = rc.cast_rays(o3d.core.Tensor(np.concatenate([o, d], axis=1).astype(np.float32)))
    geom = int(ans["geometry_ids"].numpy()[0])
    return ids.index(geom) if geom in ids else -1


def apply_options(root, scene: Scene, specs: list[dict], pointed: list[dict], camera: Camera, path) -> Scene:
    """Rename the pointed surfaces and set what the user knows (brdf, ior, textured, r = 0 when matte); save scene.json."""
    ws = Workspace(root)
    root = ws.root
    surfaces = list(scene.surfaces)
    renames = {}
    for p in pointed:
        k = _first_hit(scene, camera, p["at"])
        if k < 0:
            raise WorkspaceError(path, f"{p['where']}.at", "a pixel of the input view on a reconstructed surface",
                                 got=p["at"].tolist())
        old = surfaces[k].name
        if old in renames and renames[old] != p["name"]:
            raise WorkspaceError(path, f"{p['where']}.at", f"a pixel on another surface than '{renames[old]}' "
                                                            f"(both point at '{old}')", got=p["at"].tolist())
        renames[old] = p["name"]
        if p["name"] != old and p["name"] in [s.name for s in surfaces]:
            raise WorkspaceError(path, f"{p['where']}.name", f"a name no other surface has", got=p["name"])
        s = surfaces[k]
        mesh_path = ws.mesh(p["name"]).relative_to(root).as_posix()
        if p["name"] != old:
            (root / s.mesh_path).unlink(missing_ok=True)
            s.mesh.save(ws.mesh(p["name"]))
        material = Material.from_json(dict({"brdf": p["brdf"], "ior": p["ior"]}, **({"r": [0.0] * 3} if p["matte"] else {})),
                                      ws.scene, p["name"])
        s.name, s.mesh_path, s.material, s.textured = p["name"], mesh_path, material, p["textured"]
    for spec in specs:
        names = [s.name for s in surfaces]
        if spec.get("matte") and spec["name"] in names:
            s = surfaces[names.index(spec["name"])]
            s.material = Material.from_json({"brdf": spec["brdf"], "ior": spec["ior"], "r": [0.0] * 3},
                                            ws.scene, spec["name"])
    out = Scene(surfaces, root)
    out.save(ws.scene, write_meshes=False)
    return out
