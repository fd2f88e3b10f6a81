"""Recover the diffuse texture of every surface point the input photograph sees, directly, in
mirrors or through transparent sheets (docs/method.md §4, the sparse system E z = b − Q).

Non-Lambertian parameters come from fit.json when it exists, else from scene.json's materials
(a user who knows them need not fit). Surfaces marked ``"textured": false`` keep their one
homogeneous albedo. Writes WORKSPACE/textures/: ``<surface>.exr`` (kd per band per texel),
``<surface>_mask.png`` (texels the image determines), ``<surface>_diag.exr`` (observation
weight, amplification, flags) and ``index.json`` (which texel maps to which surface point,
solver statistics).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from reflab.app.console import LOG

HELP = "recover per-texel diffuse albedo of every surface seen directly or indirectly (textures/)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from reflab.core.options import add_arguments as table_arguments
    from reflab.inverse.stages import TextureOptions

    parser.add_argument("workspace", type=Path, help="workspace folder (camera.json, lights.json, scene.json, input image)")
    table_arguments(parser, TextureOptions)


def run(args) -> int:
    import numpy as np

    from reflab.app.console import running
    from reflab.core.options import options_from_args
    from reflab.inverse.stages import TextureOptions, texture

    with running("texture") as task:
        r = texture(options_from_args(TextureOptions, args, workspace=args.workspace), task,
                    log=lambda line: LOG.info(f"reflab texture: {line}"))
    result, st = r.result, r.result.stats
    trees_note = "from the cache" if r.trees["cache"] == "reused" else f"{r.trees['build_s']:.2f} s"
    rms = ", ".join(f"{v:.3g}" for v in st["residual_rms"])
    LOG.info(f"reflab texture: materials from {r.materials_source}; {st['rows']} equations, {st['unknowns']} unknowns, "
             f"{st['components']} components")
    LOG.info(f"reflab texture: {st['iterations']} CG iterations, solve {st['solve_s']:.2f} s, total {st['total_s']:.2f} s "
             f"(+ trees {trees_note}); residual RMS per band [{rms}]")
    for s, m in result.maps.items():
        LOG.info(f"  {m.name}: {m.kind} {m.width}x{m.height} texels of {m.texel_size * 1000:.2f} mm, "
                 f"{int(result.mask[s].sum())} known, {int(np.count_nonzero(result.flags[s] & 1))} amplified > "
                 f"{r.solver.amplification_limit:g}x, {int(np.count_nonzero(result.flags[s] & 8))} guessed (their pixels' "
                 f"light rests on undetermined parameters)")
    LOG.info(f"reflab texture: wrote {len(r.written)} files in {r.folder}")
    return 0
