"""`reflab demo --from-truth`: the inverse-only demo (true camera, lamps, geometry; fit, texture, render).

1. writes the simulated lab (hardware/sim/lab.py) as a workspace: camera.json, lights.json,
   meshes, and a scene.json with only what a user knows before fitting (``brdf``, ``ior``, and
   ``r = 0`` for the matte paper ground); the true materials go to truth.json and the true
   albedo seen at each pixel to truth/albedo.exr (the report's texture comparison);
2. renders input.exr with the independent reference renderer (hardware/sim/reference.py) and the
   true textures, optionally with Gaussian noise;
3. runs the later steps of the guided acquisition (app/steps.py: fit, texture, results), the
   functions the GUI runs;
4. prints the recovered model's RMS error against input.exr (the results step rendered it).
"""
from __future__ import annotations

import time

from reflab.app.console import LOG, running
from reflab.core.workspace import Workspace

#: Later steps of the guided acquisition (app/steps.py), in order.
STEPS = ("fit", "texture", "results")


def _log(line: str) -> None:
    LOG.info(f"[demo] {line}")


def _fmt(value) -> str:
    return "[" + ", ".join(f"{x:.3f}" for x in value) + "]" if isinstance(value, list) else f"{value:.3g}"


def _compare_materials(ws: Workspace) -> None:
    """Print fitted against true values for each surface (truth.json vs fit.json)."""
    from reflab.core.workspace import read_json

    truth = {s["name"]: s["material"] for s in read_json(ws.truth_materials)["surfaces"]}
    fit = read_json(ws.fit)
    for item in fit.get("surfaces", []):
        true = truth.get(item.get("name"), {})
        parts = []
        for key in ("kd", "ks", "ns", "r", "t"):
            if key in item.get("material", {}) and true.get(key) is not None:
                parts.append(f"{key} {_fmt(item['material'][key])} (true {_fmt(true[key])})")
        LOG.info(f"[demo]   {item.get('name')}: " + "; ".join(parts))


def run_from_truth(args) -> int:
    import numpy as np

    from reflab.app import steps
    from reflab.app.demo_score import true_albedo
    from reflab.core.images import write_image, write_preview
    from reflab.hardware.sim.lab import build_lab, write_lab
    from reflab.hardware.sim.reference import render_reference

    start = time.perf_counter()
    ws = Workspace(args.workspace)
    width, height = args.size or (320, 240)
    lab = build_lab(width, height)
    write_lab(ws.root, lab, materials=False)
    write_image(ws.truth_albedo, true_albedo(lab), allow_nan=True)  # the report's texture truth
    LOG.info(f"[demo] 1/4 wrote the simulated lab ({width}x{height}, {len(lab.scene)} surfaces, {len(lab.lights)} lamps) "
             f"to {ws.root}/ (true materials in {ws.truth_materials.name})")

    t0 = time.perf_counter()
    stats = {}
    photo = render_reference(lab.scene, lab.camera, lab.lights, depth=args.depth, albedo=lab.albedo, stats=stats)
    if args.noise > 0:
        # Not clipped at 0: noise around black is data (docs/formats.md, Images); clipping lifts the
        # dark pixels and biased dark parameters (glass kd, faint r) beyond 3σ on the zoo.
        photo = photo + np.random.default_rng(args.seed).normal(0.0, args.noise, photo.shape)
    write_image(ws.input_file(), photo)
    write_preview(ws.input_file(".png"), photo)
    LOG.info(f"[demo] 2/4 rendered {ws.input_file().name} with the reference renderer in {time.perf_counter() - t0:.1f} s "
             f"({stats['refractions']} refractions, {stats['tir']} total internal reflections, noise {args.noise:g})")

    LOG.info("[demo] 3/4 recovering the model")
    options = {"results": {"depth": args.depth}}
    for name in STEPS:  # a WorkspaceError stops the demo as it stops the CLI (exit 2)
        t0 = time.perf_counter()
        with running(f"demo {name}") as task:  # a progress bar; Ctrl-C cancels the step
            result = steps.step(name).run(ws.root, task, log=_log, **options.get(name, {}))
        LOG.info(f"[demo] step {name}: {result.summary} ({time.perf_counter() - t0:.1f} s)")
    image, info = result.value.image, result.value.info
    rms = np.sqrt(np.mean((image - photo) ** 2, axis=(0, 1)))
    rel = float(np.sqrt(np.mean((image - photo) ** 2)) / max(np.sqrt(np.mean(photo**2)), 1e-300))
    texture = "homogeneous kd" if info["texture_nodes"] is None else "recovered texture"
    LOG.info(f"[demo] 4/4 rendered the model (materials from {info['materials']}, {texture}) to {result.value.path}")
    LOG.info(f"[demo] RMS model vs input per band: {rms[0]:.4f} {rms[1]:.4f} {rms[2]:.4f} "
             f"(relative {100 * rel:.2f}%, input peak {photo.max():.3f})")
    _compare_materials(ws)
    LOG.info(f"[demo] done in {time.perf_counter() - start:.1f} s")
    return 0
