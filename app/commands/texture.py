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

from reflab.app.commands._args import nonneg_float, positive_float, positive_int

HELP = "recover per-texel diffuse albedo of every surface seen directly or indirectly (textures/)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("workspace", type=Path, help="workspace folder (camera.json, lights.json, scene.json, input image)")
    parser.add_argument("--depth", type=positive_int, default=None, help="maximum internal nodes per path (default: fit.json's, else 3)")
    parser.add_argument("--texel-scale", type=positive_float, default=1.0,
                        help="texel size as a multiple of the pixel footprint on each surface (default 1)")
    parser.add_argument("--texel-size", type=positive_float, default=None, help="texel size in metres for every surface (overrides --texel-scale)")
    parser.add_argument("--prior", type=nonneg_float, default=1e-3,
                        help="relative weight of the pull toward each surface's homogeneous kd (default 1e-3)")
    parser.add_argument("--smoothness", type=nonneg_float, default=0.01, help="relative weight of neighbouring-texel smoothness (default 0.01)")
    parser.add_argument("--saturation", type=positive_float, default=None,
                        help="pixel value at which the camera clips (default: detect a clipped plateau)")
    parser.add_argument("--max-albedo", type=positive_float, default=1.0, help="upper bound of kd (default 1)")
    parser.add_argument("--single-photograph", action="store_true",
                        help="use the reference photograph alone, ignoring inputs/")


def run(args) -> int:
    import numpy as np

    from reflab.inverse.stages import TextureOptions, texture

    r = texture(TextureOptions(args.workspace, args.depth, args.texel_scale, args.texel_size, args.prior,
                               args.smoothness, args.saturation, args.max_albedo, single=args.single_photograph),
                log=lambda line: print(f"reflab texture: {line}"))
    result, st = r.result, r.result.stats
    trees_note = "from the cache" if r.trees["cache"] == "reused" else f"{r.trees['build_s']:.2f} s"
    rms = ", ".join(f"{v:.3g}" for v in st["residual_rms"])
    print(f"reflab texture: materials from {r.materials_source}; {st['rows']} equations, {st['unknowns']} unknowns, "
          f"{st['components']} components")
    print(f"reflab texture: {st['iterations']} CG iterations, solve {st['solve_s']:.2f} s, total {st['total_s']:.2f} s "
          f"(+ trees {trees_note}); residual RMS per band [{rms}]")
    for s, m in result.maps.items():
        print(f"  {m.name}: {m.kind} {m.width}x{m.height} texels of {m.texel_size * 1000:.2f} mm, "
              f"{int(result.mask[s].sum())} known, {int(np.count_nonzero(result.flags[s] & 1))} amplified > "
              f"{r.solver.amplification_limit:g}x, {int(np.count_nonzero(result.flags[s] & 8))} guessed (their pixels' "
              f"light rests on undetermined parameters)")
    print(f"reflab texture: wrote {len(r.written)} files in {r.folder}")
    return 0
