"""The export stage: the recovered model written for outside tools (docs/export.md).

:func:`export` reads what ``reflab render`` reads (scene.json's meshes, fit.json's materials,
textures/, camera.json, lights.json) and writes one of

- ``mitsuba``: ``OUT/scene.xml`` + ``meshes/*.ply`` (with UVs) + ``textures/*.exr``
  (:mod:`reflab.inverse.export.mitsuba`);
- ``gltf``: one ``.glb`` (``OUT`` itself when it ends in .glb, else ``OUT/scene.glb``;
  :mod:`reflab.inverse.export.gltf`);
- ``ply``: ``OUT/<surface>.ply`` with texture coordinates and ``OUT/<surface>.png`` beside them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from reflab.core.options import opt, positive_int
from reflab.core.task import Task, ensure

FORMATS = ("mitsuba", "gltf", "ply")


@dataclass
class ExportOptions:
    """Options of :func:`export` (``reflab export``'s flags; docs/export.md)."""

    workspace: Path
    format: str = opt("mitsuba", "what to write: a Mitsuba 3 scene, a glTF 2.0 binary or PLY meshes with their "
                                 "textures", choices=list(FORMATS))
    output: Path | None = opt(None, "output folder (a .glb file for gltf); default WORKSPACE/export-FORMAT",
                              flag=("-o", "--output"), type=str)
    depth: int = opt(3, "maximum internal nodes per path, as in reflab render (Mitsuba's max_depth is one more)",
                     type=positive_int)
    spp: int = opt(64, "samples per pixel of the Mitsuba scene's sensor (a scene parameter: mitsuba -Dspp=N)",
                   type=positive_int)


@dataclass
class ExportResult:
    """What :func:`export` wrote: its main file (scene.xml, the .glb, or the folder of PLYs),
    every file, and per surface how the materials were converted (``notes``)."""

    path: Path
    format: str
    written: list
    notes: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)


def export(options: ExportOptions, task: Task | None = None) -> ExportResult:
    """Write the workspace's recovered model in ``options.format`` (see the module's description)."""
    import numpy as np

    from reflab.core.workspace import OptionError, Workspace, check_folder
    from reflab.inverse.export.model import load_model

    task = ensure(task)
    o = options
    if o.format not in FORMATS:
        raise OptionError("format", f"must be one of {', '.join(FORMATS)}, got {o.format!r}")
    ws = Workspace(check_folder(o.workspace))
    out = Path(o.output) if o.output else ws.export(o.format)
    glb = o.format == "gltf" and out.suffix.lower() == ".glb"
    check_folder(out.parent if glb else out, write=True, create=True, what="folder to export into")
    model = load_model(ws)
    warnings = []
    if np.any(model.camera.dist):
        warnings.append("camera.json's lens distortion is not exported (the formats' cameras are pinholes)")
    if not any(s.textured for s in model.surfaces):
        warnings.append("no recovered texture (textures/ missing): surfaces carry their homogeneous kd")
    task.check()
    if o.format == "mitsuba":
        from reflab.inverse.export.mitsuba import write_mitsuba

        written, notes = write_mitsuba(model, out, depth=o.depth, spp=o.spp, task=task)
        path = out / "scene.xml"
    elif o.format == "gltf":
        from reflab.inverse.export.gltf import write_glb

        path = out if glb else out / "scene.glb"
        written, notes = write_glb(model, path)
    else:
        from reflab.inverse.export.gltf import write_ply_folder

        written, notes = write_ply_folder(model, out)
        path = out
    task.step(1, 1, f"wrote {path}")
    return ExportResult(path, o.format, written, notes, warnings)
