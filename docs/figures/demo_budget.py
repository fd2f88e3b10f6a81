"""Where the demo's novel and relit PSNR goes (docs/fit.md, "Where the demo's error lives").

On a finished `reflab demo WORKSPACE` (its truth/ beside it), each view is rendered as the demo
scores it (:func:`reflab.app.demo_score.view_psnr`'s ``psnr_primary_db``: over the pixels whose
directly seen surface has a known albedo) and its squared error split by the surface seen at each
pixel. Then copies of the workspace (fit.json dropped where the materials are given, inputs/ kept,
`reflab texture` run again on every photograph with the options textures/index.json records, the
demo's texel scale and smoothness):

- ``true materials``: truth/scene.json's materials on the reconstructed meshes (what the fit loses);
- ``true materials and geometry``: truth/scene.json with its meshes (what reconstruct loses);
- ``true mesh: NAME``: the fitted materials, the one surface's true mesh (each surface's geometry);
- ``true albedo``: the workspace's model with the lab's albedo function at every node instead of
  the recovered texture (what a perfect texture stage gives on that camera, lamps and geometry).

    python docs/figures/demo_budget.py WORKSPACE [--keep DIR]
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from reflab.app.demo_score import psnr  # noqa: E402
from reflab.core.images import read_image  # noqa: E402
from reflab.core.workspace import Workspace  # noqa: E402


def _views(root: Path, albedo=None) -> dict:
    """Per view: PSNR over the pixels whose seen surface's albedo is known, and per surface seen
    there its share of the squared error and its RMS."""
    from reflab.inverse.forward.rendering import render as render_trees
    from reflab.inverse.stages import _inputs, render_workspace
    from reflab.inverse.texture.solve import load_materials

    ws = Workspace(root)
    truth = Workspace(ws.truth)
    out = {}
    for which in ("novel", "relit"):
        pose, image_path = truth.view(which)
        view = {"camera": pose} if which == "novel" else {"lights": pose}
        true = read_image(image_path).astype(np.float64)
        aov, _ = render_workspace(root, aov="albedo", depth=3, **view)
        image, info = render_workspace(root, depth=3, **view)
        trees = info["trees"]
        cam, lig, scene = _inputs(ws, view.get("camera"), view.get("lights"))
        if albedo is not None:  # the lab's albedo at every node of a textured surface
            names = [s.name for s in albedo.scene]
            kd = np.full((len(trees.surface), 3), np.nan)
            for s, surf in enumerate(scene):
                sel = trees.surface == s
                if surf.textured and surf.name in names:
                    kd[sel] = albedo.albedo(names.index(surf.name), trees.point[sel])
            materials, _ = load_materials(ws, scene)
            homogeneous = np.array([m["kd"] for m in materials])[trees.surface]
            image = render_trees(trees, materials, lig.intensities, kd_nodes=np.where(np.isfinite(kd), kd, homogeneous))
        primary = np.all(np.isfinite(aov), axis=2)
        first = trees.level == 1
        seen = np.full(cam.width * cam.height, -1)
        seen[trees.pixel[first]] = trees.surface[first]
        seen = seen.reshape(cam.height, cam.width)
        err2 = ((image - true) ** 2).mean(axis=2)
        total = err2[primary].sum()
        parts = {}
        for s, surf in enumerate(scene):
            m = primary & (seen == s)
            if m.any():
                parts[surf.name] = (float(100 * err2[m].sum() / total), float(np.sqrt(err2[m].mean())))
        out[which] = {"psnr": psnr(image, true, primary), "known_pct": float(100 * primary.mean()), "surfaces": parts}
    return out


def _copy(src: Path, dst: Path, *, materials: bool = False, meshes=(), truth_scene: bool = False) -> Path:
    from reflab.inverse.stages import TextureOptions, texture

    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("captures", "textures", "cache"))
    true = json.loads((src / "truth" / "scene.json").read_text())
    if truth_scene:
        shutil.rmtree(dst / "meshes")
        shutil.copytree(src / "truth" / "meshes", dst / "meshes")
        (dst / "scene.json").write_text(json.dumps(true))
    elif materials:
        scene = json.loads((src / "scene.json").read_text())
        given = {s["name"]: s["material"] for s in true["surfaces"]}
        for s in scene["surfaces"]:
            s["material"] = given[s["name"]]
        (dst / "scene.json").write_text(json.dumps(scene))
    for name in meshes:
        shutil.copy(src / "truth" / "meshes" / f"{name}.ply", dst / "meshes" / f"{name}.ply")
    if materials or truth_scene:
        (dst / "fit.json").unlink()
    texture(TextureOptions(dst, **_texture_options(src)))
    return dst


def _texture_options(root: Path) -> dict:
    """The options the workspace's textures were recovered with (textures/index.json), as
    TextureOptions fields."""
    import dataclasses

    from reflab.inverse.stages import TextureOptions

    used = json.loads((root / "textures" / "index.json").read_text()).get("options", {})
    fields = {f.name for f in dataclasses.fields(TextureOptions)} - {"workspace"}
    return {k: (tuple(v) if isinstance(v, list) else v) for k, v in used.items() if k in fields and v is not None}


def _line(label: str, res: dict) -> str:
    cells = []
    for which in ("novel", "relit"):
        r = res[which]
        parts = ", ".join(f"{n} {share:.0f} % ({rms:.4f})" for n, (share, rms) in r["surfaces"].items())
        cells.append(f"{r['psnr']:.2f} dB: {parts}")
    return f"| {label} | " + " | ".join(cells) + " |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace")
    ap.add_argument("--keep", help="folder to keep the copies in (default: a temporary one)")
    args = ap.parse_args()
    from reflab.hardware.sim.lab import build_lab

    src = Path(args.workspace).resolve()
    width, height = (json.loads((src / "camera.json").read_text())[k] for k in ("width", "height"))
    tmp = Path(args.keep or tempfile.mkdtemp())
    tmp.mkdir(parents=True, exist_ok=True)
    print("| model | novel: PSNR, per seen surface share of squared error (RMS) | relit: the same |")
    print("|---|---|---|")
    print(_line("the demo's", _views(src)), flush=True)
    print(_line("… with the true albedo at every node", _views(src, albedo=build_lab(width, height, grain=0.2))), flush=True)
    print(_line("true materials", _views(_copy(src, tmp / "materials", materials=True))), flush=True)
    print(_line("true materials and geometry", _views(_copy(src, tmp / "geometry", truth_scene=True))), flush=True)
    for name in [s["name"] for s in json.loads((src / "scene.json").read_text())["surfaces"]]:
        if name != "ground":
            print(_line(f"true mesh: {name}", _views(_copy(src, tmp / f"mesh_{name}", meshes=[name]))), flush=True)
    if not args.keep:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
