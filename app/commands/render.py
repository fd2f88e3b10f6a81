"""Render the workspace's scene model with the forward model (pixel-intensity trees).

Materials come from fit.json when it exists (the fitted model), else from scene.json; per-point
diffuse albedo comes from textures/ when it exists (the texture stage's ``albedo_nodes``). A
different camera (--camera) gives a novel view, different lights (--lights) a relighting.
Writes a float32 EXR (default WORKSPACE/render.exr, or albedo.exr for --aov albedo) and an
8-bit PNG preview beside it (without -o, an earlier render.exr there is replaced, and the command says
so in one line: the render is made from the workspace's files and can be made again; -o keeps it); where some pixels' values rest on parameters fit.json calls
undetermined (or on texels made from such pixels), a mask OUT_undetermined.png of them.
"""
from __future__ import annotations

import argparse
import time

from reflab.app.console import LOG

HELP = "render the scene model (scene.json, or fit.json + textures/ when present) to an EXR image"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from reflab.core.options import add_arguments as table_arguments
    from reflab.inverse.stages import RenderOptions

    parser.add_argument("workspace", help="workspace folder (camera.json, lights.json, scene.json)")
    table_arguments(parser, RenderOptions)


def run(args) -> int:
    from reflab.app.console import running
    from reflab.core.options import options_from_args
    from reflab.inverse.stages import RenderOptions, render

    from reflab.core.workspace import Workspace

    start = time.perf_counter()
    default = None if args.output else Workspace(args.workspace).render(args.aov)
    earlier = default.stat().st_mtime if default is not None and default.is_file() else None
    with running("render") as task:
        r = render(options_from_args(RenderOptions, args, workspace=args.workspace), task, log=LOG.info)
    info = r.info
    h, w = r.image.shape[:2]
    texture = ("homogeneous kd" if info["texture_nodes"] is None else
               f"texture on {info['texture_nodes']} nodes ({info['unknown_albedo']} unknown)")
    LOG.info(f"materials from {info['materials']}, {texture}")
    LOG.info(f"trees {info['trees_s']:.2f} s ({info['nodes']} nodes, depth {args.depth}), render {info['render_s']:.2f} s")
    if earlier is not None:
        LOG.warning(f"reflab render: replaced the earlier {r.path} (written "
                    f"{time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(earlier))}); -o FILE writes elsewhere")
    LOG.info(f"wrote {r.path} ({w}x{h}{', albedo' if args.aov else ''}) and {r.preview} in {time.perf_counter() - start:.1f} s")
    if r.undetermined is not None:
        n = int(info["undetermined_pixels"].sum())
        LOG.info(f"{n} pixels ({100 * n / (w * h):.1f} %) rest on parameters fit.json calls undetermined, on values its σ "
                 f"leaves loose (over 5 % of the light) or on texels the texture stage guessed: a guess, not a prediction "
                 f"(white in {r.undetermined})")
    return 0
