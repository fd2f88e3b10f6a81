"""Fit the non-Lambertian parameters of every surface from the one input photograph.

Builds the pixel-intensity trees, factorizes the image into A(θ) y = b keeping only the monomial
columns that occur in this scene, and minimises the squared error with F-TBO (exact linear
sub-problems, shininess on top; default) or NF-TBO (all parameters by conjugate gradient).
Saturated pixels are left out. Writes WORKSPACE/fit.json: fitted materials, one-sigma
uncertainties, the parameters the image leaves undetermined, and the error-against-time trace.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from app.commands._args import positive_float, positive_int

HELP = "fit kd, ks, shininess, r and t of every surface from the input image (F-TBO or NF-TBO)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("workspace", type=Path, help="workspace folder (camera.json, lights.json, scene.json, input image)")
    parser.add_argument("--method", choices=["ftbo", "nftbo"], default="ftbo",
                        help="ftbo: factorized (default, faster); nftbo: all parameters by conjugate gradient")
    parser.add_argument("--depth", type=positive_int, default=3, help="maximum internal nodes per path (default 3)")
    parser.add_argument("--saturation", type=positive_float, default=None,
                        help="pixel value at which the camera clips (default: detect a clipped plateau)")
    parser.add_argument("--max-iterations", type=positive_int, default=None,
                        help="cap on outer iterations (default: 100 for ftbo, 5000 for nftbo)")


def run(args) -> int:
    from inverse.fitting import fit_workspace

    report, result = fit_workspace(args.workspace, args.method, args.depth, saturation=args.saturation,
                                   maxiter=args.max_iterations)
    img, cols = report["image"], report["columns"]
    print(f"reflab fit: {img['width']}x{img['height']} image, {img['saturated_pixels']} saturated pixels masked, "
          f"{report['trees']['nodes']} tree nodes")
    print(f"reflab fit: {cols['used']} monomial columns used (the dense factorization has {cols['dense_dissertation']})")
    rms = ", ".join(f"{v:.3g}" for v in report["rms"])
    print(f"reflab fit: {args.method} {result.iterations} iterations in {report['time_s']:.2f} s, RMS per band [{rms}]"
          f" ({result.message})")
    for item in report["surfaces"]:
        und = ", ".join(item["undetermined"]) or "none"
        print(f"  {item['name']}: {_material_text(item['material'])}; undetermined: {und}")
    print(f"reflab fit: wrote {Path(args.workspace) / 'fit.json'}")
    return 0


def _material_text(material: dict) -> str:
    parts = []
    for key, value in material.items():
        if key in ("brdf", "ior") or value is None:
            continue
        parts.append(f"{key}=" + ("[" + ", ".join(f"{v:.3g}" for v in value) + "]" if isinstance(value, list) else f"{value:.4g}"))
    return f"{material['brdf']} " + " ".join(parts)
