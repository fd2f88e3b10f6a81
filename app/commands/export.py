"""Export the recovered model for outside tools: a Mitsuba 3 scene, a glTF 2.0 binary or PLY meshes.

`reflab export WORKSPACE --format mitsuba|gltf|ply [-o OUT]` reads what `reflab render` reads
(scene.json's meshes, fit.json's materials, textures/, camera.json, lights.json) and writes
meshes with texture coordinates into the recovered texture atlases, the textures as images, the
materials mapped to the format's own (docs/export.md: each approximation and its measured error),
the lamps and the input camera. `mitsuba`: OUT/scene.xml (plain Mitsuba 3 loads and renders it);
`gltf`: OUT/scene.glb, or OUT itself when it ends in .glb; `ply`: OUT/<surface>.ply and .png.
"""
from __future__ import annotations

import argparse

from reflab.app.console import LOG

HELP = "export the recovered model: a Mitsuba 3 scene, a glTF 2.0 binary (.glb) or PLY meshes with UVs"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from reflab.core.options import add_arguments as table_arguments
    from reflab.inverse.export.stage import ExportOptions

    parser.add_argument("workspace", help="workspace folder (scene.json; fit.json and textures/ when present)")
    table_arguments(parser, ExportOptions)


def run(args) -> int:
    from reflab.app.console import running
    from reflab.core.options import options_from_args
    from reflab.inverse.export.stage import ExportOptions, export

    with running("export") as task:
        r = export(options_from_args(ExportOptions, args, workspace=args.workspace), task)
    for warning in r.warnings:
        LOG.warning(f"reflab export: {warning}")
    LOG.info(f"reflab export: {len(r.notes)} surfaces, {len(r.written)} files; wrote {r.path}")
    return 0
