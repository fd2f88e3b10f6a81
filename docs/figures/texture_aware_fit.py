"""Toward a texture-aware fit: what fitting the non-Lambertian parameters of a textured scene needs.

    .venv/bin/python docs/figures/texture_aware_fit.py WORKSPACE [oracle|alternate|exclude|criterion|scan ...]

WORKSPACE is a demo workspace (`reflab demo WORKSPACE`: the simulated lab, photograph by the
independent reference renderer, fit.json and textures/ from the homogeneous fit). Trees are built
from its scene.json (the homogeneous fit's starting materials), depth 3. Prints, against the
lab's truth:

- ``oracle``: F-TBO with every textured node's diffuse term scaled by the lab's TRUE albedo
  (``Factorization(albedo=...)``: kd becomes a gain);
- ``alternate``: the same with the texture that `reflab texture` recovered from the homogeneous
  fit's parameters (pixels whose nodes have no known albedo left out): one round of alternation;
- ``exclude``: the homogeneous fit, then four of `reflab fit`'s texture rounds
  (:func:`reflab.inverse.fit.texture_aware.fit_with_texture`: the texture from the pixels where directly seen
  texture carries at least 90 % of the model's light, texels left unknown at their surface's mean);
- ``criterion``: the texture stage's residual RMS and per-surface texel-gradient energy with
  every parameter true but one (the ground's r, the box's ns) swept;
- ``scan``: a coordinate scan of r, t, ns and ks (ns and ks one at a time) on the texture-eliminated
  objective J = |model with the recovered texture − image|² from the homogeneous fit's values
  (each candidate is a full texture solve; per-band parameters judged band by band).
"""
from __future__ import annotations

import copy
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from reflab.calibration.camera import Camera  # noqa: E402
from reflab.calibration.lights import Lights  # noqa: E402
from reflab.core.images import read_image  # noqa: E402
from reflab.hardware.sim.lab import build_lab  # noqa: E402
from reflab.core.workspace import Workspace  # noqa: E402
from reflab.inverse.forward.factorization import Factorization  # noqa: E402
from reflab.inverse.fit.rounds import fit, saturated_pixels  # noqa: E402
from reflab.inverse.forward.models import get_model  # noqa: E402
from reflab.inverse.forward.rendering import render  # noqa: E402
from reflab.inverse.texture.solve import SolverOptions, albedo_nodes, load_materials, recover_texture, sample_texture  # noqa: E402
from reflab.inverse.forward.trees import build_trees  # noqa: E402
from reflab.reconstruction.scene import Scene  # noqa: E402

SHOWN = ("ks", "ns", "r", "t")


def show(tag, scene, materials, truth):
    for s, m in enumerate(materials):
        got = {k: np.round(m[k], 3).tolist() for k in SHOWN if k in m.params}
        want = {k: np.round(truth[s][k], 3).tolist() for k in SHOWN if k in truth[s].params}
        print(f"  {tag} {scene[s].name}: {got}  | true {want}")


def fit_with(ctx, albedo, mask):
    scene, trees, lab, image = ctx["scene"], ctx["trees"], ctx["lab"], ctx["image"]
    fac = Factorization(trees, [get_model(s.material.brdf) for s in scene], lab.lights.intensities, mask=mask,
                        albedo=albedo)
    res = fit(fac, image, [s.material for s in scene], "ftbo", textured=[s.textured for s in scene], names=scene.names)
    print(f"  RMS per band {np.round(res.rms, 5).tolist()}, {res.time_s:.1f} s")
    show("fit", scene, res.materials, ctx["truth"])


def oracle(ctx):
    trees, lab = ctx["trees"], ctx["lab"]
    on = ctx["textured"][trees.surface]
    albedo = np.full((len(trees.pixel), 3), np.nan)
    albedo[on] = lab.albedo_at(trees.surface[on], trees.point[on])
    print("oracle: F-TBO with the true texture")
    fit_with(ctx, albedo, ctx["used"])


def alternate(ctx):
    trees = ctx["trees"]
    albedo = albedo_nodes(ctx["ws"].root, ctx["scene"], trees)
    on = ctx["textured"][trees.surface]
    albedo[~on] = np.nan
    unknown = on & ~np.isfinite(albedo).all(axis=1)
    bad = np.zeros(ctx["used"].size, bool)
    bad[trees.pixel[unknown]] = True
    print(f"alternate: F-TBO with the texture recovered from the homogeneous fit ({bad.sum()} pixels left out)")
    fit_with(ctx, albedo, ctx["used"] & ~bad)


def exclude(ctx, rounds=4):
    """The homogeneous fit, then ``rounds`` of :func:`reflab.inverse.fit.texture_aware.fit_with_texture`."""
    from reflab.inverse.fit.texture_aware import fit_with_texture

    scene, trees, lab, image = ctx["scene"], ctx["trees"], ctx["lab"], ctx["image"]
    models = [get_model(x.material.brdf) for x in scene]
    fac = Factorization(trees, models, lab.lights.intensities, mask=ctx["used"])
    start = fit(fac, image, [x.material for x in scene], "ftbo", textured=list(ctx["textured"]), names=scene.names)
    print(f"exclude: homogeneous fit RMS per band {np.round(start.rms, 5).tolist()}, then {rounds} texture rounds")
    out, records = fit_with_texture(trees, scene, models, lab.lights.intensities, image, start, mask=ctx["used"],
                                    rounds=rounds)
    for r in records:
        print(f"  round {r['round']}: {r['pixels_left_out']} pixels left out, RMS per band {np.round(r['rms'], 5).tolist()}")
    show("exclude", scene, out.materials, ctx["truth"])


def criterion(ctx):
    scene, trees, lab, image = ctx["scene"], ctx["trees"], ctx["lab"], ctx["image"]
    print("criterion: texture stage with every parameter true but one")
    for surf, name, values in (("ground", "r", (0.0, 0.2, 0.5, 0.82, 1.0)), ("box", "ns", (4.0, 15.0, 30.0, 60.0))):
        s = scene.index(surf)
        for v in values:
            mats = [copy.deepcopy(m) for m in ctx["truth"]]
            mats[s].params[name] = np.full_like(np.asarray(mats[s][name], dtype=float), v)
            res = recover_texture(scene, trees, mats, lab.lights.intensities, image, SolverOptions())
            energy = {}
            for t, m in res.mask.items():
                kd, g = res.kd[t], 0.0
                for ax in (0, 1):
                    both = np.take(m, range(1, m.shape[ax]), axis=ax) & np.take(m, range(m.shape[ax] - 1), axis=ax)
                    g += float((np.diff(kd, axis=ax)[both] ** 2).sum())
                energy[scene[t].name] = round(g, 1)
            print(f"  {surf} {name} = {v:g}: residual RMS {np.round(res.stats['residual_rms'], 5).tolist()}, "
                  f"texel-gradient energy {energy}")


def scan(ctx):
    scene, trees, lab, image, used = ctx["scene"], ctx["trees"], ctx["lab"], ctx["image"], ctx["used"]
    mats, _ = load_materials(ctx["ws"].root, scene)
    und = {s["name"]: set(s["undetermined"]) for s in json.loads(ctx["ws"].fit.read_text())["surfaces"]}
    count = [0]

    def objective(materials):
        count[0] += 1
        res = recover_texture(scene, trees, materials, lab.lights.intensities, image, SolverOptions())
        kd = np.empty((len(trees.pixel), 3))
        for s in range(len(scene)):
            sel = np.nonzero(trees.surface == s)[0]
            kd[sel] = materials[s]["kd"]
            if s in res.kd:
                a = sample_texture(res.maps[s], res.kd[s], res.mask[s], trees.triangle[sel], trees.barycentric[sel])
                kd[sel] = np.where(np.isfinite(a), a, materials[s]["kd"])
        r = (render(trees, materials, lab.lights.intensities, kd_nodes=kd).reshape(-1, 3) - image.reshape(-1, 3))[used]
        return (r**2).sum(axis=0)

    t0 = time.perf_counter()
    cur = objective(mats)
    print(f"scan: J = {cur.sum():.3f} at the homogeneous fit")
    for sweep in range(2):
        for s, surf in enumerate(scene):
            for name in ("r", "t", "ns", "ks"):
                if name not in mats[s].params or name in und[surf.name]:
                    continue
                base = np.asarray(mats[s][name], dtype=float)
                if name == "ns":
                    grid = np.arange(1, 17, 2.0) if sweep == 0 else np.log2(base) + np.array([-1, -.5, -.25, .25, .5, 1])
                    cands = [np.array(2.0**v) for v in grid]
                elif name == "ks":
                    cands = [base * f for f in (0.5, 0.7, 0.85, 1.2, 1.4, 2.0)]
                elif sweep == 0:
                    cands = [np.full(3, v) for v in (0.0, 0.05, 0.15, 0.3, 0.5, 0.7, 0.85, 1.0)]
                else:
                    cands = [np.clip(base + d, 0, 1) for d in (-0.1, -0.05, -0.02, 0.02, 0.05, 0.1)]
                for c in cands:
                    trial = [copy.deepcopy(m) for m in mats]
                    trial[s].params[name] = c
                    j = objective(trial)
                    if name == "ns":
                        if j.sum() < cur.sum():
                            mats, cur = trial, j
                    elif (j < cur).any():  # bands are independent given θ: judge each band alone
                        mats = [copy.deepcopy(m) for m in mats]
                        mats[s].params[name] = np.where(j < cur, c, np.asarray(mats[s][name], dtype=float))
                        cur = objective(mats)
            print(f"  sweep {sweep} {surf.name}: J = {cur.sum():.3f} ({count[0]} texture solves, "
                  f"{time.perf_counter() - t0:.0f} s)", flush=True)
    show("scan", scene, mats, ctx["truth"])


def main(argv):
    ws = Workspace(argv[0])
    camera, lights = Camera.load(ws.camera), Lights.load(ws.lights)
    scene = Scene.load(ws.scene)
    lab = build_lab(camera.width, camera.height)
    image = read_image(ws.input_image)
    ctx = {"ws": ws, "scene": scene, "lab": lab, "image": image, "truth": [s.material for s in lab.scene],
           "trees": build_trees(scene, camera, lights, depth=3), "used": ~saturated_pixels(image).reshape(-1),
           "textured": np.array([s.textured for s in scene])}
    for what in argv[1:] or ["oracle", "alternate", "exclude", "criterion", "scan"]:
        {"oracle": oracle, "alternate": alternate, "exclude": exclude, "criterion": criterion, "scan": scan}[what](ctx)


if __name__ == "__main__":
    main(sys.argv[1:])
