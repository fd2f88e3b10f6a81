"""The fit on the zoo: random scenes it was never tuned on (docs/fit.md, "The zoo").

For each seed, :func:`reflab.hardware.sim.zoo.write_zoo_workspace` writes a random scene as a
workspace (one photograph by the independent reference renderer, what a user knows in
scene.json, the truth beside it); the workspace is fitted as ``reflab fit`` then ``reflab texture``
do (:func:`reflab.inverse.stages.fit`, :func:`reflab.inverse.stages.texture`), and fit.json is
compared with truth.json. Reported over the seeds:

- fit time (``reflab fit``'s wall clock, trees included): median, 90th percentile, max;
- σ calibration over the determined values (fitted, not reported undetermined, finite σ; a
  textured surface's kd, its texture's mean, is left out as in docs/figures/fit_calibration.py):
  the share within 3σ, the worst |error|/σ;
- confident wrong values: determined values beyond 3σ + 2 % of the true value;
- recall: the share of the visible parameters (every parameter the fit was free to fit on a
  surface the photograph sees) that are determined and within 10 % of the truth (or 0.01 for
  r and t, attenuations whose truth may be 0);
- PSNR of the fitted model's novel and relit views (fit.json + textures/, the project's renderer)
  against the reference renderer's truth, and its gap to the oracle's: the true materials with
  the texture recovered from the same photograph (:func:`oracle_workspace`); over the pixels
  whose albedo both know (the oracle's counted at most :data:`PSNR_CAP`, the gap at least 0).

    python docs/figures/zoo.py --seeds 0-11 --size 160x120 [--noise 0.0] [--json out.json] [--keep DIR]
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

#: A determined value is confidently wrong beyond this many σ plus :data:`SLACK` of its true value.
SIGMAS, SLACK = 3.0, 0.02
#: Recall: within this share of the true value (or :data:`ATTENUATION_FLOOR` for r and t).
RECALL, ATTENUATION_FLOOR = 0.10, 0.01
#: The oracle's PSNR counts at most this much in the gap (beyond it both renders are exact).
PSNR_CAP = 60.0


def _seeds(text: str) -> list:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def seen_surfaces(report: dict) -> set:
    """Indices of the surfaces with a column in the fit (seen by the camera and lit)."""
    return {int(m) for name in report["columns"]["names"] for m in re.findall(r"[a-z]+(\d+)", name)}


def compare(report: dict, truth: dict, textured: list) -> list:
    """One row per visible parameter value: (surface, name, fitted, true, σ or None, determined).

    ``report``: fit.json, ``truth``: truth.json, ``textured``: per surface. Values the user gave
    (held: a lambert surface's r) and t of opaque surfaces are not fitted and not listed.
    """
    rows = []
    seen = seen_surfaces(report)
    for i, (item, true) in enumerate(zip(report["surfaces"], truth["surfaces"])):
        if i not in seen:
            continue
        fitted, sig, und = item["material"], item["sigma"], set(item["undetermined"])
        tm = true["material"]
        for name, value in fitted.items():
            if name in ("brdf", "ior") or (name == "kd" and textured[i]):
                continue
            if name == "t" and tm.get("ior") is None or (name == "r" and tm["brdf"] == "lambert"):
                continue
            vals, tvals = np.atleast_1d(value), np.atleast_1d(tm[name])
            sigs = np.atleast_1d(sig.get(name, [None] * len(vals)))
            for c, (v, t, s) in enumerate(zip(vals, tvals, sigs)):
                label = f"{name}[{c}]" if len(vals) > 1 else name
                det = name not in und and label not in und and s is not None and np.isfinite(s) and s > 0
                rows.append((item["name"], label, float(v), float(t), None if s is None else float(s), bool(det)))
    return rows


def score(rows: list) -> dict:
    det = [r for r in rows if r[5]]
    z = np.array([abs(v - t) / s for _, _, v, t, s, _ in det])
    wrong = [f"{a} {b} fit {v:.4g} true {t:.4g} σ {s:.3g}" for a, b, v, t, s, _ in det
             if abs(v - t) > SIGMAS * s + SLACK * abs(t)]

    def close(r):
        floor = ATTENUATION_FLOOR if r[1][0] in "rt" else 0.0
        return r[5] and abs(r[2] - r[3]) <= max(RECALL * abs(r[3]), floor)

    return {"visible": len(rows), "determined": len(det), "recovered": int(sum(close(r) for r in rows)),
            "within_3sigma": int(np.sum(z <= SIGMAS)), "worst": float(z.max()) if len(z) else 0.0, "wrong": wrong}


def oracle_workspace(root: Path) -> Path:
    """A copy of the workspace whose scene.json holds the true materials (truth/scene.json), its
    texture recovered from the same photograph: what one photograph gives with the materials known."""
    import shutil

    from reflab.inverse.stages import TextureOptions, texture

    oracle = root / "oracle"
    shutil.rmtree(oracle, ignore_errors=True)
    oracle.mkdir()
    for name in ("camera.json", "lights.json", "input.exr"):
        shutil.copy(root / name, oracle / name)
    shutil.copytree(root / "meshes", oracle / "meshes")
    shutil.copy(root / "truth" / "scene.json", oracle / "scene.json")
    if any(s["textured"] for s in json.loads((oracle / "scene.json").read_text())["surfaces"]):
        texture(TextureOptions(oracle))
    return oracle


def view_scores(root: Path, depth: int) -> dict:
    """PSNR (dB) of the model's novel and relit views against the reference renderer's, over the
    pixels whose albedo both the model and the oracle (:func:`oracle_workspace`) know, and the
    oracle's over the same pixels."""
    from reflab.app.demo_score import psnr
    from reflab.core.images import read_image
    from reflab.core.workspace import Workspace
    from reflab.inverse.stages import render_workspace

    truth = Workspace(Workspace(root).truth)
    oracle = oracle_workspace(root)
    out = {}
    for which in ("novel", "relit"):
        pose, image_path = truth.view(which)
        view = {"camera": pose} if which == "novel" else {"lights": pose}
        true_image = read_image(image_path).astype(np.float64)
        images, known = [], np.ones(true_image.shape[:2], dtype=bool)
        for ws in (root, oracle):
            albedo, _ = render_workspace(ws, aov="albedo", depth=depth, **view)
            image, info = render_workspace(ws, depth=depth, **view)
            known &= np.all(np.isfinite(albedo), axis=2) & ~info["unknown_pixels"]
            images.append(image)
        out[which] = {"psnr": psnr(images[0], true_image, known), "true_materials": psnr(images[1], true_image, known),
                      "known_pct": float(100 * known.mean())}
    return out


def run_seed(seed: int, width: int, height: int, noise: float, root: Path, depth: int = 3, with_views: bool = True) -> dict:
    from reflab.core.workspace import read_json
    from reflab.hardware.sim.zoo import write_zoo_workspace
    from reflab.inverse.stages import FitOptions, TextureOptions, fit, texture

    zoo = write_zoo_workspace(root, seed, width, height, noise=noise, depth=depth, truth_views=with_views)
    t0 = time.perf_counter()
    result = fit(FitOptions(root, depth=depth))
    fit_s = time.perf_counter() - t0
    if any(s.textured for s in zoo.scene):
        texture(TextureOptions(root, depth=depth))
    rows = compare(result.report, read_json(root / "truth.json"), [s.textured for s in zoo.scene])
    out = {"seed": seed, "surfaces": len(zoo.scene), "lamps": len(zoo.lights), "fit_s": fit_s,
           "status": result.status, **score(rows), "rows": rows}
    if with_views:
        out["views"] = view_scores(root, depth)
    return out


def summary(results: list) -> dict:
    t = np.array([r["fit_s"] for r in results])
    det = sum(r["determined"] for r in results)
    gaps = [max(0.0, min(r["views"][w]["true_materials"], PSNR_CAP) - r["views"][w]["psnr"]) for r in results
            if "views" in r for w in r["views"] if np.isfinite(r["views"][w]["psnr"])]
    return {"scenes": len(results), "fit_median_s": float(np.median(t)), "fit_p90_s": float(np.percentile(t, 90)),
            "fit_max_s": float(t.max()), "determined": det,
            "within_3sigma": sum(r["within_3sigma"] for r in results) / max(det, 1),
            "worst": max(r["worst"] for r in results), "confident_wrong": sum(len(r["wrong"]) for r in results),
            "visible": sum(r["visible"] for r in results), "recovered": sum(r["recovered"] for r in results),
            "psnr_gap_median_db": float(np.median(gaps)) if gaps else None,
            "psnr_gap_max_db": float(np.max(gaps)) if gaps else None}


def table(results: list, s: dict) -> str:
    lines = ["| seed | surfaces | lamps | fit s | determined | within 3σ | worst \\|err\\|/σ | confident wrong | "
             "recovered / visible | novel dB (true) | relit dB (true) |", "|" + "---|" * 11]
    for r in results:
        v = r.get("views", {})
        dbs = [f"{v[w]['psnr']:.1f} ({v[w]['true_materials']:.1f})" if w in v else "–" for w in ("novel", "relit")]
        lines.append(f"| {r['seed']} | {r['surfaces']} | {r['lamps']} | {r['fit_s']:.1f} | {r['determined']} | "
                     f"{r['within_3sigma']} | {r['worst']:.2f} | {len(r['wrong'])} | {r['recovered']} / {r['visible']} | "
                     f"{dbs[0]} | {dbs[1]} |")
    gap = "–" if s["psnr_gap_median_db"] is None else f"{s['psnr_gap_median_db']:.1f} dB median, {s['psnr_gap_max_db']:.1f} max"
    lines += ["", f"{s['scenes']} scenes: fit {s['fit_median_s']:.1f} s median, {s['fit_p90_s']:.1f} s 90th percentile, "
              f"{s['fit_max_s']:.1f} s max; {s['determined']} determined values, {100 * s['within_3sigma']:.0f} % within 3σ, "
              f"worst |err|/σ {s['worst']:.2f}; {s['confident_wrong']} confident wrong (beyond 3σ + 2 %); "
              f"recall {s['recovered']} / {s['visible']} ({100 * s['recovered'] / max(s['visible'], 1):.0f} %) "
              f"within 10 %; PSNR gap to the true materials {gap}"]
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-11", help="e.g. 0-11 or 3,5,8")
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--noise", type=float, default=0.0, help="Gaussian noise of the photograph, share of its peak")
    ap.add_argument("--no-views", action="store_true", help="skip the novel and relit views")
    ap.add_argument("--json")
    ap.add_argument("--keep", help="folder to keep the workspaces in (default: a temporary one)")
    args = ap.parse_args(argv)
    W, H = (int(v) for v in args.size.split("x"))
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(args.keep or tmp)
        for seed in _seeds(args.seeds):
            r = run_seed(seed, W, H, args.noise, base / f"zoo-{seed}-{W}x{H}", with_views=not args.no_views)
            results.append(r)
            print(f"seed {seed}: fit {r['fit_s']:.1f} s, {r['determined']} determined, worst {r['worst']:.2f}, "
                  f"wrong {r['wrong']}, recovered {r['recovered']}/{r['visible']}, views {r.get('views')}", flush=True)
    s = summary(results)
    print(table(results, s))
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "summary": s, "results": results}, indent=1))


if __name__ == "__main__":
    main()
