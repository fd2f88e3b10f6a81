"""F-TBO against NF-TBO: error against run time on the homogeneous simulated lab (docs/fit.md).

The image is the forward model's rendering of the true materials plus Gaussian noise of 1% of the
peak (seed 0), depth 3; both methods start from docs/method.md §3's initial values. Writes the numbers
(every trace point) to a JSON file after each fit, and draws RMS against time with cv2.

    .venv/bin/python docs/figures/fit_benchmark.py [--sizes 160x120,320x240,640x480]
        [--nftbo-seconds 1200] [--json fit-bench.json] [--png docs/img/fit-error-vs-time.png]
    .venv/bin/python docs/figures/fit_benchmark.py --plot-only      (redraw from the JSON)
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))


def run(sizes, nftbo_seconds, path: Path) -> dict:
    """Fit every size with both methods; the JSON is rewritten after each fit."""
    from reflab.hardware.sim.lab import build_lab
    from reflab.core.workspace import write_json
    from reflab.inverse.forward.factorization import Factorization
    from reflab.inverse.fit.rounds import fit
    from reflab.inverse.forward.models import get_model
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees
    from reflab.reconstruction.scene import Material

    out = json.loads(path.read_text()) if path.exists() else {}
    for width, height in sizes:
        lab = build_lab(width, height, textured=False)
        trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
        truth = [s.material for s in lab.scene]
        clean = render(trees, truth, lab.lights.intensities)
        image = clean + np.random.default_rng(0).normal(0.0, 0.01 * clean.max(), clean.shape)
        init = [Material.from_json({"brdf": m.brdf, "ior": m.ior}, "scene.json", "material") for m in truth]
        fac = Factorization(trees, [get_model(m.brdf) for m in truth], lab.lights.intensities)
        for method in ("ftbo", "nftbo"):
            res = fit(fac, image, init, method, max_seconds=nftbo_seconds if method == "nftbo" else None)
            out[f"{width}x{height}/{method}"] = {
                "time_s": res.time_s, "rms": res.rms.tolist(), "noise_rms": float(np.sqrt(np.mean((image - clean) ** 2))),
                "iterations": res.iterations, "evaluations": res.evaluations, "trace": res.trace,
                "columns": fac.n_columns, "dense": fac.dense_columns, "nodes": int(len(trees.pixel)),
                "message": res.message, "status": res.stats["status"], "undetermined": res.undetermined,
                "load_average": os.getloadavg()[0]}
            print(width, height, method, round(res.time_s, 2), res.rms, res.iterations, res.message, flush=True)
            write_json(path, out)
    return out


def plot(data: dict, png: Path) -> None:
    """RMS (mean of bands, log scale) against seconds (log scale), one curve per size and method."""
    import cv2

    from reflab.core.workspace import atomic_path

    W, H, left, right, top, bottom = 900, 560, 80, 220, 30, 60
    img = np.full((H, W, 3), 255, np.uint8)
    curves = {k: np.array([[max(t, 1e-3), float(np.mean(r))] for t, r in v["trace"]]) for k, v in data.items()}
    allp = np.concatenate(list(curves.values()))
    tx = np.log10([allp[:, 0].min(), allp[:, 0].max()])
    ty = np.log10([allp[:, 1].min() * 0.9, allp[:, 1].max() * 1.1])
    tx = [np.floor(tx[0]), np.ceil(tx[1])]

    def xy(t, r):
        x = left + (np.log10(t) - tx[0]) / (tx[1] - tx[0]) * (W - left - right)
        y = H - bottom - (np.log10(r) - ty[0]) / (ty[1] - ty[0]) * (H - top - bottom)
        return np.stack([x, y], axis=-1).astype(np.int32)

    cv2.rectangle(img, (left, top), (W - right, H - bottom), (0, 0, 0), 1)
    for e in range(int(tx[0]), int(tx[1]) + 1):
        x = int(xy(np.array([10.0**e]), np.array([10 ** ty[0]]))[0, 0])
        cv2.line(img, (x, H - bottom), (x, H - bottom + 5), (0, 0, 0), 1)
        cv2.putText(img, f"1e{e}", (x - 15, H - bottom + 22), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    for v in np.logspace(ty[0], ty[1], 5):
        y = int(xy(np.array([10.0 ** tx[0]]), np.array([v]))[0, 1])
        cv2.putText(img, f"{v:.4f}", (5, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    cv2.putText(img, "run time (s, log)", (W // 2 - 100, H - 15), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    cv2.putText(img, "RMS per band, mean (log)", (left + 5, top - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    colours = {"160x120": (200, 80, 0), "320x240": (0, 150, 0), "640x480": (0, 0, 220)}
    row = 0
    for key, pts in sorted(curves.items()):
        size, method = key.split("/")
        colour = colours.get(size, (90, 90, 90))
        poly = xy(pts[:, 0], pts[:, 1])
        if method == "ftbo":
            cv2.polylines(img, [poly.reshape(-1, 1, 2)], False, colour, 2, cv2.LINE_AA)
        else:  # dashed: every other segment
            for a, b in zip(poly[:-1:2], poly[1::2]):
                cv2.line(img, tuple(map(int, a)), tuple(map(int, b)), colour, 1, cv2.LINE_AA)
        y = top + 20 + 22 * row
        cv2.line(img, (W - right + 15, y - 4), (W - right + 45, y - 4), colour, 2 if method == "ftbo" else 1)
        label = f"{size} {'F-TBO' if method == 'ftbo' else 'NF-TBO'}"
        cv2.putText(img, label, (W - right + 50, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
        row += 1
    with atomic_path(png) as tmp:
        ok, buf = cv2.imencode(".png", img)
        Path(tmp).write_bytes(buf.tobytes())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="160x120,320x240,640x480")
    parser.add_argument("--nftbo-seconds", type=float, default=1200.0, help="NF-TBO's wall-clock budget per fit")
    parser.add_argument("--json", type=Path, default=Path("fit-bench.json"))
    parser.add_argument("--png", type=Path, default=Path(__file__).resolve().parents[1] / "img" / "fit-error-vs-time.png")
    parser.add_argument("--plot-only", action="store_true")
    args = parser.parse_args(argv)
    if args.plot_only:
        data = json.loads(args.json.read_text())
    else:
        sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
        data = run(sizes, args.nftbo_seconds, args.json)
    plot(data, args.png)
    print(f"wrote {args.json} and {args.png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
