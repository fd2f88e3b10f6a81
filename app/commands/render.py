"""Render the workspace's scene model with the forward model (pixel-intensity trees).

Materials come from fit.json when it exists (the fitted model), else from scene.json; per-point
diffuse albedo comes from textures/ when it exists (the texture stage's ``albedo_nodes``). A
different camera (--camera) gives a novel view, different lights (--lights) a relighting.
Writes a float32 EXR (default WORKSPACE/render.exr, or albedo.exr for --aov albedo) and an
8-bit PNG preview beside it.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from app.commands._args import positive_int

HELP = "render the scene model (scene.json, or fit.json + textures/ when present) to an EXR image"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("workspace", help="workspace folder (camera.json, lights.json, scene.json)")
    parser.add_argument("-o", "--output", help="output image (.exr, .png or .tif); default WORKSPACE/render.exr")
    parser.add_argument("--camera", help="camera.json to render from (novel view); default the workspace's")
    parser.add_argument("--lights", help="lights.json to light with (relighting); default the workspace's")
    parser.add_argument("--aov", choices=["albedo"], help="write the kd of the surface seen at each pixel instead")
    parser.add_argument("--depth", type=positive_int, default=3, help="maximum internal nodes per path (default 3)")


def render_workspace(workspace, camera=None, lights=None, *, aov: str | None = None, depth: int = 3, log=None) -> tuple:
    """Render the model of ``workspace`` (see the module's description).

    Parameters
    ----------
    workspace : path-like
    camera, lights : path-like, optional
        Other camera.json / lights.json files (novel view, relighting).
    aov : {None, "albedo"}
        None: linear radiance; "albedo": kd of the surface seen at each pixel, NaN where unknown.
    depth : int
        Maximum internal nodes per path.
    log : callable, optional
        Told whether the trees were built or reused from the workspace's cache.

    Returns
    -------
    image : (H, W, 3) float64 ndarray
    info : dict
        ``materials`` (source file), ``texture_nodes`` (nodes with recovered albedo, or None),
        ``unknown_albedo`` (nodes whose albedo was unknown), ``unknown_pixels`` ((H, W) bool: a
        node of the pixel's tree had unknown albedo, so the homogeneous kd stood in), ``trees_s``,
        ``render_s``, ``trees``.
    """
    import numpy as np

    from calibration.camera import Camera
    from calibration.lights import Lights
    from hardware.workspace import Workspace
    from inverse.rendering import render, render_albedo
    from inverse.texture import albedo_nodes, load_materials
    from inverse.trees import trees_for_workspace
    from reconstruction.scene import Scene

    ws = Workspace(workspace)
    cam = Camera.load(camera or ws.require(ws.camera, "reflab calibrate camera"))
    lig = Lights.load(lights or ws.require(ws.lights, "reflab calibrate lights"))
    scene = Scene.load(ws.require(ws.scene, "reflab reconstruct"))
    materials, source = load_materials(ws, scene)

    t0 = time.perf_counter()
    trees = trees_for_workspace(ws, scene, cam, lig, depth=depth, log=log)
    t1 = time.perf_counter()
    kd_nodes = albedo_nodes(ws, scene, trees) if ws.textures.is_dir() else None
    info = {"materials": source, "texture_nodes": None, "unknown_albedo": 0,
            "unknown_pixels": np.zeros((cam.height, cam.width), dtype=bool)}
    if kd_nodes is not None:
        unknown = ~np.all(np.isfinite(kd_nodes), axis=1)
        info["texture_nodes"] = int(np.count_nonzero(~unknown))
        info["unknown_albedo"] = int(np.count_nonzero(unknown))
        info["unknown_pixels"] = (np.bincount(trees.pixel[unknown], minlength=cam.width * cam.height) > 0).reshape(cam.height, cam.width)
    if aov == "albedo":
        image = render_albedo(trees, materials, kd_nodes)
    else:
        if kd_nodes is not None:
            # Points the texture stage never saw keep the surface's homogeneous kd.
            homogeneous = np.array([m["kd"] for m in materials])[trees.surface]
            kd_nodes = np.where(np.isfinite(kd_nodes), kd_nodes, homogeneous)
        image = render(trees, materials, lig.intensities, kd_nodes=kd_nodes)
    info.update(trees_s=t1 - t0, render_s=time.perf_counter() - t1, trees=trees)
    return image, info


def run(args) -> int:
    from hardware.images import write_image, write_preview

    start = time.perf_counter()
    image, info = render_workspace(args.workspace, args.camera, args.lights, aov=args.aov, depth=args.depth, log=print)
    default = "albedo.exr" if args.aov == "albedo" else "render.exr"
    out = Path(args.output) if args.output else Path(args.workspace) / default
    write_image(out, image, allow_nan=args.aov == "albedo")
    preview = write_preview(out.with_suffix(".png") if out.suffix.lower() != ".png" else out.with_name(out.stem + "_preview.png"),
                            image, exposure=1.0 if args.aov == "albedo" else None)
    h, w = image.shape[:2]
    texture = ("homogeneous kd" if info["texture_nodes"] is None else
               f"texture on {info['texture_nodes']} nodes ({info['unknown_albedo']} unknown)")
    print(f"materials from {info['materials']}, {texture}")
    print(f"trees {info['trees_s']:.2f} s ({len(info['trees'])} nodes, depth {args.depth}), render {info['render_s']:.2f} s")
    print(f"wrote {out} ({w}x{h}{', albedo' if args.aov else ''}) and {preview} in {time.perf_counter() - start:.1f} s")
    return 0
