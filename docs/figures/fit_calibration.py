"""Is the fit's σ honest? Errors over noise realisations on the textured scenes of docs/fit.md.

For each scene of :mod:`reflab.hardware.sim.scenes` (photograph by the independent reference renderer,
rendered once), ``--realisations`` noisy copies (Gaussian, ``--noise`` of the peak, seeds 0..N−1;
with ``--vary-texture`` each on its own texture realisation, photographed anew) are fitted as ``reflab fit`` does (F-TBO, then the texture rounds; the user knows brdf, ior and
that a lambert surface does not mirror); every determined parameter's error over its σ is pooled
(a textured surface's kd, its texture's mean, is left to the texture stage). Prints, per scene and
in all: how many determined parameters, the share within 1, 2, 3 σ, within 3σ + 2 % (the issue's
bar), the worst |error|/σ, and how often each parameter was reported undetermined.

    python docs/figures/fit_calibration.py --size 80x60 --realisations 20 --noise 0.01 [--vary-texture] [--json out.json]
    python docs/figures/fit_calibration.py --size 160x120 --realisations 1 --noise 0 --verbose   # one fit per scene
    python docs/figures/fit_calibration.py --scenes more ...   # the further designs (reflab.hardware.sim.scenes.MORE)
    python docs/figures/fit_calibration.py --photographs L0,L1,T35,T-35,T70,T-70 ...   # several photographs
    python docs/figures/fit_calibration.py --pixels 1500 ...   # the fit reading a sample (docs/fit.md "Sampling")

``--photographs``: further photographs fitted together with the reference (docs/fit.md "Several
photographs"): ``Lk`` lamp k alone, ``TA`` the turntable turned by A degrees about the vertical
axis through the origin, every lamp on; each rendered by the reference renderer, noisy like it.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from reflab.hardware.sim.scenes import MORE, NAMES, build, determined, render, user_materials  # noqa: E402
from reflab.inverse.fit.workspace_fit import fit_scene  # noqa: E402
from reflab.inverse.forward.photographs import stack_trees  # noqa: E402
from reflab.inverse.forward.trees import build_trees  # noqa: E402
from reflab.reconstruction.scene import Scene, Surface  # noqa: E402


def rows(res, fac, truth, user):
    """Determined (as :func:`reflab.hardware.sim.scenes.determined`) and the names of the others."""
    det = determined(res, fac, truth, user)
    lay, free = fac.layout, res.free
    fitted = [(user.names[s], f"{n}[{c}]") for k, (s, n) in enumerate(lay.x_names) for c in range(3)
              if free.x[k, c] and not (n == "kd" and user[s].textured)]
    fitted += [(user.names[f // 2], f"{'rt'[f % 2]}[{c}]") for f in range(lay.n_factors) for c in range(3) if free.s[f, c]]
    fitted += [(user.names[s], n) for q, (s, n) in enumerate(lay.theta_names) if free.theta[q]]
    shown = {(user.names[r[0]], r[1]) for r in det}
    return det, [f for f in fitted if f not in shown]


def _views(ts, shots: str) -> list:
    """(camera, lights) of the reference and of each further shot named in ``shots``."""
    from reflab.hardware.sim.lab import named_views

    return [(ts.camera, ts.lights)] + [(c, li) for _, c, li in named_views(ts.camera, ts.lights, shots)]


def _photographs(ts, views) -> np.ndarray:
    """The views photographed by the reference renderer, stacked one below the other."""
    from reflab.hardware.sim.reference import render_reference

    return np.concatenate([render_reference(ts.scene, c, li, depth=3, albedo=ts.albedo) for c, li in views], axis=0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="80x60")
    ap.add_argument("--realisations", type=int, default=20)
    ap.add_argument("--noise", type=float, default=0.01)
    ap.add_argument("--scenes", default=",".join(NAMES), help="comma-separated names, or 'more' for " + ", ".join(MORE))
    ap.add_argument("--json")
    ap.add_argument("--verbose", action="store_true", help="print every determined parameter of every fit")
    ap.add_argument("--pixels", type=int, default=0,
                    help="pixels the fit reads at most (reflab fit --pixels; default 0 here: every pixel)")
    ap.add_argument("--photographs", default="", help="further shots: Lk (lamp k alone), TA (turntable A degrees)")
    ap.add_argument("--vary-texture", action="store_true",
                    help="realisation k also draws another texture (reflab.hardware.sim.scenes.build's texture_seed=k)")
    args = ap.parse_args(argv)
    W, H = (int(v) for v in args.size.split("x"))
    report, pooled = {}, []
    for name in (MORE if args.scenes == "more" else args.scenes.split(",")):
        ts = build(name, W, H)
        views = _views(ts, args.photographs)
        clean = _photographs(ts, views)
        init = user_materials(ts.scene)
        user = Scene([Surface(s.name, s.mesh_path, m, s.textured, s.mesh) for s, m in zip(ts.scene, init)])
        stack = stack_trees([build_trees(user, c, li, depth=3) for c, li in views], [li for _, li in views])
        trees, intensities = stack.trees, stack.intensities
        truth = [s.material for s in ts.scene]
        z, undetermined, t0 = [], Counter(), time.perf_counter()
        for seed in range(args.realisations):
            if args.vary_texture:  # another texture on the same geometry: its own photograph and truth
                ts = build(name, W, H, texture_seed=seed)
                clean, truth = _photographs(ts, views), [s.material for s in ts.scene]
            img = clean + (np.random.default_rng(seed).normal(0.0, args.noise * clean.max(), clean.shape) if args.noise else 0.0)
            done = fit_scene(trees, user, intensities, img, np.ones(trees.width * trees.height, dtype=bool),
                             pixels=args.pixels, sample_above=0)
            res, fac = done.result, done.fac
            det, und = rows(res, fac, truth, user)
            if args.verbose:
                for r in det:
                    print(f"  {user.names[r[0]]:7s} {r[1]:6s} fit {r[2]:.4f} true {r[3]:.4f} σ {r[4]:.3g} "
                          f"|err|/σ {abs(r[2] - r[3]) / r[4]:.2f}")
                print("  undetermined:", {n: u for n, u in zip(user.names, res.undetermined)},
                      "rejected:", res.stats.get("rejected", {}).get("count"))
            undetermined.update(und)
            z += [(user.names[r[0]], r[1], float(r[2] - r[3]), float(r[4]), float(abs(r[3]))) for r in det]
            print(f"{name} seed {seed}: {len(det)} determined, worst |err|/σ "
                  f"{max((abs(e) / s for _, _, e, s, _ in z[-len(det):]), default=0):.2f}", flush=True)
        pooled += z
        report[name] = summary(z) | {"undetermined": {f"{a} {b}": n for (a, b), n in undetermined.items()},
                                     "seconds": round(time.perf_counter() - t0, 1)}
        print(name, json.dumps(report[name]), flush=True)
    report["all"] = summary(pooled)
    print("all", json.dumps(report["all"]))
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "report": report, "errors": pooled}, indent=1))


def summary(z):
    r = np.array([abs(e) / s for _, _, e, s, _ in z]) if z else np.zeros(0)
    bar = np.array([abs(e) <= 3 * s + 0.02 * t for _, _, e, s, t in z], dtype=bool)
    return {"determined": len(z), "within_1sigma": float(np.mean(r <= 1)) if len(r) else None,
            "within_2sigma": float(np.mean(r <= 2)) if len(r) else None,
            "within_3sigma": float(np.mean(r <= 3)) if len(r) else None,
            "within_3sigma_2pct": float(np.mean(bar)) if len(r) else None,
            "worst": float(r.max()) if len(r) else None}


if __name__ == "__main__":
    main()
