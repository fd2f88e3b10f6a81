"""Fit the non-Lambertian parameters of every surface from the one input photograph.

Builds the pixel-intensity trees, factorizes the image into A(θ) y = b keeping only the monomial
columns that occur in this scene, and minimises the squared error with F-TBO (exact linear
sub-problems, shininess on top; default) or NF-TBO (all parameters by conjugate gradient).
Saturated pixels are left out. Writes WORKSPACE/fit.json: fitted materials, one-sigma
uncertainties, the parameters the image leaves undetermined, the error-against-time trace, and a
``status`` with ``warnings`` in words.

Exit status: 3 when fit.json's status is "poor fit" (homogeneous surfaces only, and the model
leaves pixels unexplained far above the image's noise: a wrong basin, model or geometry; fit.json is
written all the same); 2 for bad input; else 0 ("ok"; "not converged" at --max-iterations or
--max-seconds with the image explained; "texture pending" when pixels are unexplained but textured
surfaces may account for them — the warnings are printed either way).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from reflab.app.commands._args import nonneg_int, positive_float, positive_int

HELP = "fit kd, ks, shininess, r and t of every surface from the input image (F-TBO or NF-TBO)"

#: Exit status when the fitted model does not explain the image (fit.json status "poor fit").
EXIT_POOR_FIT = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("workspace", type=Path, help="workspace folder (camera.json, lights.json, scene.json, input image)")
    parser.add_argument("--method", choices=["ftbo", "nftbo"], default="ftbo",
                        help="ftbo: factorized (default, faster); nftbo: all parameters by conjugate gradient")
    parser.add_argument("--depth", type=positive_int, default=3, help="maximum internal nodes per path (default 3)")
    parser.add_argument("--saturation", type=positive_float, default=None,
                        help="pixel value at which the camera clips (default: detect a clipped plateau)")
    parser.add_argument("--max-iterations", type=positive_int, default=None,
                        help="cap on outer iterations (default: 100 for ftbo, 5000 for nftbo)")
    parser.add_argument("--texture-rounds", type=nonneg_int, default=2,
                        help="when a surface is textured: rounds of refitting against the texture recovered from "
                             "the pixels that directly seen texture lights (default 2; 0 = the homogeneous fit "
                             "alone, as in the dissertation)")
    parser.add_argument("--max-seconds", type=positive_float, default=None,
                        help="wall-clock budget of the fit (trees excluded); it stops at the next iteration "
                             "and fit.json's message says so (default: none)")
    parser.add_argument("--single-photograph", action="store_true",
                        help="fit the reference photograph alone, ignoring inputs/ (the dissertation's method)")


def run(args) -> int:
    from reflab.inverse.stages import FitOptions, fit

    def on_round(rec):
        rms = ", ".join(f"{v:.3g}" for v in rec["rms"])
        print(f"reflab fit: texture round {rec['round']}: texture from all but {rec['pixels_left_out']} pixels "
              f"({rec['texture_s']:.1f} s), refit RMS per band [{rms}] ({rec['fit_s']:.1f} s)", flush=True)

    r = fit(FitOptions(args.workspace, args.method, args.depth, args.saturation, args.max_iterations,
                       args.max_seconds, args.texture_rounds, single=args.single_photograph), on_round=on_round)
    report, result = r.report, r.fit
    img, cols = report["image"], report["columns"]
    seconds = report["setup_s"]["trees"]
    print(f"reflab fit: trees: {'reused cache' if report['trees']['cache'] == 'reused' else 'built'} in {seconds:.2f} s")
    print(f"reflab fit: {img['width']}x{img['height']} image, {img['saturated_pixels']} saturated pixels masked, "
          f"{report['trees']['nodes']} tree nodes")
    if len(report.get("photographs", [])) > 1:
        print(f"reflab fit: {len(report['photographs'])} photographs: " + ", ".join(
            f"{p['name']} ({p['pixels_used']} px, RMS {max(p['rms']):.3g})" for p in report["photographs"]))
    print(f"reflab fit: {cols['used']} monomial columns used (the dense factorization has {cols['dense_dissertation']})")
    rms = ", ".join(f"{v:.3g}" for v in report["rms"])
    print(f"reflab fit: {args.method} {result.iterations} iterations in {report['time_s']:.2f} s, RMS per band [{rms}]"
          f" ({result.message})")
    for item in report["surfaces"]:
        und = ", ".join(item["undetermined"]) or "none"
        bound = ", ".join(f"{k} {v}" for k, v in item.get("at_bound", {}).items() if v == "upper")
        print(f"  {item['name']}: {_material_text(item['material'])}; undetermined: {und}"
              + (f"; at the upper bound of its range: {bound}" if bound else ""))
    print(f"reflab fit: wrote {r.path}")
    status = report["status"]
    for text in report["warnings"]:
        print(f"reflab fit: warning: {text}", file=sys.stderr)
    if status == "poor fit":
        print(f"reflab fit: status {status}: the fitted parameters do not explain the image (exit {EXIT_POOR_FIT})",
              file=sys.stderr)
        return EXIT_POOR_FIT
    print(f"reflab fit: status {status}")
    return 0


def _material_text(material: dict) -> str:
    parts = []
    for key, value in material.items():
        if key in ("brdf", "ior") or value is None:
            continue
        parts.append(f"{key}=" + ("[" + ", ".join(f"{v:.3g}" for v in value) + "]" if isinstance(value, list) else f"{value:.4g}"))
    return f"{material['brdf']} " + " ".join(parts)
