"""The export section: what the workspace can be exported to, the exact commands, and the exports
already written in the workspace (``reflab export``'s default folders, export-FORMAT/)."""
from __future__ import annotations

import datetime
import shlex

from reflab.app.report.data import Sources
from reflab.app.report.sections.section import Section

#: Per format: what it is for, and its main file in its output folder ("" for the folder itself).
FORMATS = (("mitsuba", "Mitsuba 3 scene (scene.xml, meshes with UVs, EXR textures): plain Mitsuba renders the "
                       "input view", "scene.xml"),
           ("gltf", "glTF 2.0 binary for viewers and Blender (one mesh per surface, KHR materials, lamps, camera)",
            "scene.glb"),
           ("ply", "PLY meshes with UVs and their textures as PNG, for MeshLab", ""))


def _written(src: Sources, fmt: str, main: str) -> str:
    """The default export of ``fmt`` in the workspace, relative to it, with when it was written; "" when none."""
    folder = src.ws.export(fmt)
    path = folder / main if main else folder
    if main and not path.is_file():
        return ""
    if not main and not (folder.is_dir() and any(folder.glob("*.ply"))):
        return ""
    when = datetime.datetime.fromtimestamp(path.stat().st_mtime, datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    rel = src.rel(path).as_posix() + ("/" if not main else "")
    return f"{rel}\nwritten {when}"


def export_section(src: Sources) -> Section | None:
    """None without scene.json (no model to export)."""
    if src.scene is None:
        return None
    sec = Section("export", "Export", "The recovered model for outside tools: reflab export writes it (docs/export.md); "
                                      "the window's results page does the same under Export.")
    missing = [(name, made_by) for name, made_by, obj in (("camera.json", "reflab calibrate camera", src.camera),
                                                          ("lights.json", "reflab calibrate lights", src.lights))
               if obj is None]
    for name, made_by in missing:
        sec.note(f"{name} is missing (made by {made_by}): export needs it for the camera and the lamps", "warn")
    fitted = ("fit.json (fitted)" if src.fit is not None else "scene.json (fit.json is unreadable)"
              if src.ws.fit.exists() else "scene.json (not fitted yet: reflab fit)")
    sec.kv([("materials", fitted),
            ("texture", "textures/ (recovered)" if src.textures is not None else
             "none: surfaces carry their homogeneous kd (reflab texture)")], "what an export carries now")
    workspace = shlex.quote(str(src.root.resolve()))
    rows = []
    for fmt, what, main in FORMATS:
        rows.append([fmt, what, f"reflab export {workspace} --format {fmt}", _written(src, fmt, main) or "not yet"])
    sec.table(["format", "for", "command", "in this workspace"], rows,
              "Each command writes WORKSPACE/export-FORMAT/ (-o OUT writes elsewhere). The files already written "
              "are named relative to the workspace, beside this report; they are not embedded (the report stays one "
              "self-contained file), so they do not travel with it.")
    return sec
