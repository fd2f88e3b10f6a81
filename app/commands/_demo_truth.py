"""`reflab demo --from-truth`: the inverse-only demo (true camera, lamps, geometry; fit, texture, render).

1. writes the simulated lab (hardware/sim/lab.py) as a workspace: camera.json, lights.json,
   meshes, and a scene.json with only what a user knows before fitting (``brdf``, ``ior``, and
   ``r = 0`` for the matte paper ground); the true materials go to truth.json;
2. renders input.exr with the independent reference renderer (hardware/sim/reference.py) and the
   true textures, optionally with Gaussian noise;
3. runs the later stages (`reflab fit`, `reflab texture`);
4. renders the recovered model (`reflab render`) and prints its RMS error against input.exr.
"""
from __future__ import annotations

import argparse
import importlib
import time
from pathlib import Path


#: Later stages, in order, run through their own subcommand modules.
STAGES = ("fit", "texture")


def _run_stage(name: str, workspace: Path) -> bool:
    """Run a later stage's subcommand on the workspace; False when it failed."""
    module = importlib.import_module(f"app.commands.{name}")
    parser = argparse.ArgumentParser(prog=f"reflab {name}")
    module.add_arguments(parser)
    args = parser.parse_args([str(workspace)])
    start = time.perf_counter()
    code = module.run(args)
    print(f"[demo] stage {name}: exit {code or 0} in {time.perf_counter() - start:.1f} s")
    return not code


def _fmt(value) -> str:
    return "[" + ", ".join(f"{x:.3f}" for x in value) + "]" if isinstance(value, list) else f"{value:.3g}"


def _compare_materials(workspace: Path) -> None:
    """Print fitted against true values for each surface (truth.json vs fit.json)."""
    from hardware.workspace import read_json

    truth = {s["name"]: s["material"] for s in read_json(workspace / "truth.json")["surfaces"]}
    fit = read_json(workspace / "fit.json")
    for item in fit.get("surfaces", []):
        true = truth.get(item.get("name"), {})
        parts = []
        for key in ("kd", "ks", "ns", "r", "t"):
            if key in item.get("material", {}) and true.get(key) is not None:
                parts.append(f"{key} {_fmt(item['material'][key])} (true {_fmt(true[key])})")
        print(f"[demo]   {item.get('name')}: " + "; ".join(parts))


def run_from_truth(args) -> int:
    import numpy as np

    from inverse.stages import render_workspace
    from hardware.images import write_image, write_preview
    from hardware.sim.reference import render_reference
    from hardware.sim.lab import build_lab, write_lab

    start = time.perf_counter()
    root = Path(args.workspace)
    width, height = args.size or (320, 240)
    lab = build_lab(width, height)
    write_lab(root, lab, materials=False)
    print(f"[demo] 1/4 wrote the simulated lab ({width}x{height}, {len(lab.scene)} surfaces, {len(lab.lights)} lamps) "
          f"to {root}/ (true materials in truth.json)")

    t0 = time.perf_counter()
    stats = {}
    photo = render_reference(lab.scene, lab.camera, lab.lights, depth=args.depth, albedo=lab.albedo, stats=stats)
    if args.noise > 0:
        photo = np.maximum(photo + np.random.default_rng(args.seed).normal(0.0, args.noise, photo.shape), 0.0)
    write_image(root / "input.exr", photo)
    write_preview(root / "input.png", photo)
    print(f"[demo] 2/4 rendered input.exr with the reference renderer in {time.perf_counter() - t0:.1f} s "
          f"({stats['refractions']} refractions, {stats['tir']} total internal reflections, noise {args.noise:g})")

    print("[demo] 3/4 recovering the model")
    for name in STAGES:
        if not _run_stage(name, root):
            print(f"[demo] stage {name} failed: later stages skipped")
            break

    image, info = render_workspace(root, depth=args.depth, log=lambda line: print(f"[demo] {line}"))
    write_image(root / "render.exr", image)
    write_preview(root / "render.png", image)
    rms = np.sqrt(np.mean((image - photo) ** 2, axis=(0, 1)))
    rel = float(np.sqrt(np.mean((image - photo) ** 2)) / max(np.sqrt(np.mean(photo**2)), 1e-300))
    texture = "homogeneous kd" if info["texture_nodes"] is None else "recovered texture"
    print(f"[demo] 4/4 rendered the model (materials from {info['materials']}, {texture}) to {root / 'render.exr'}")
    print(f"[demo] RMS model vs input per band: {rms[0]:.4f} {rms[1]:.4f} {rms[2]:.4f} "
          f"(relative {100 * rel:.2f}%, input peak {photo.max():.3f})")
    if (root / "fit.json").exists():
        _compare_materials(root)
    print(f"[demo] done in {time.perf_counter() - start:.1f} s")
    return 0
