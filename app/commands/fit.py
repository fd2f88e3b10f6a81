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
from pathlib import Path

from reflab.app.console import LOG

HELP = "fit kd, ks, shininess, r and t of every surface from the input image (F-TBO or NF-TBO)"

#: Exit status when the fitted model does not explain the image (fit.json status "poor fit").
EXIT_POOR_FIT = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from reflab.core.options import add_arguments as table_arguments
    from reflab.inverse.stages import FitOptions

    parser.add_argument("workspace", type=Path, help="workspace folder (camera.json, lights.json, scene.json, input image)")
    table_arguments(parser, FitOptions)


def run(args) -> int:
    from reflab.app.console import running
    from reflab.core.options import options_from_args
    from reflab.inverse.stages import FitOptions, fit

    def on_round(rec):
        rms = ", ".join(f"{v:.3g}" for v in rec["rms"])
        loose = rec.get("loosely_textured")
        loose = f", {loose} pixels on loosely known texels left out" if loose else ""
        LOG.info(f"reflab fit: texture round {rec['round']}: texture from all but {rec['pixels_left_out']} pixels "
                 f"({rec['texture_s']:.1f} s), refit RMS per band [{rms}] ({rec['fit_s']:.1f} s){loose}")

    with running("fit") as task:
        r = fit(options_from_args(FitOptions, args, workspace=args.workspace), task, on_round=on_round)
    report, result = r.report, r.fit
    img, cols = report["image"], report["columns"]
    seconds = report["setup_s"]["trees"]
    LOG.info(f"reflab fit: trees: {'reused cache' if report['trees']['cache'] == 'reused' else 'built'} in {seconds:.2f} s")
    LOG.info(f"reflab fit: {img['width']}x{img['height']} image, {img['saturated_pixels']} saturated pixels masked, "
             f"{report['trees']['nodes']} tree nodes")
    if len(report.get("photographs", [])) > 1:
        LOG.info(f"reflab fit: {len(report['photographs'])} photographs: " + ", ".join(
            f"{p['name']} ({p['pixels_used']} px, RMS {max(p['rms']):.3g}"
            + (f", {100 * p['unexplained']:.1f} % unexplained)" if "unexplained" in p else ")")
            for p in report["photographs"]))
    LOG.info(f"reflab fit: {cols['used']} monomial columns used (the dense factorization has {cols['dense_dissertation']})")
    rms = ", ".join(f"{v:.3g}" for v in report["rms"])
    LOG.info(f"reflab fit: {args.method} {result.iterations} iterations in {report['time_s']:.2f} s, RMS per band [{rms}]"
             f" ({result.message})")
    for item in report["surfaces"]:
        und = ", ".join(item["undetermined"]) or "none"
        bound = ", ".join(f"{k} {v}" for k, v in item.get("at_bound", {}).items() if v == "upper")
        LOG.info(f"  {item['name']}: {_material_text(item['material'])}; undetermined: {und}"
                 + (f"; at the upper bound of its range: {bound}" if bound else ""))
    LOG.info(f"reflab fit: wrote {r.path}")
    status = report["status"]
    for text in report["warnings"]:
        LOG.warning(f"reflab fit: warning: {text}")
    if status == "poor fit":
        LOG.error(f"reflab fit: status {status}: the fitted parameters do not explain the image (exit {EXIT_POOR_FIT})")
        return EXIT_POOR_FIT
    LOG.info(f"reflab fit: status {status}")
    return 0


def _material_text(material: dict) -> str:
    parts = []
    for key, value in material.items():
        if key in ("brdf", "ior") or value is None:
            continue
        parts.append(f"{key}=" + ("[" + ", ".join(f"{v:.3g}" for v in value) + "]" if isinstance(value, list) else f"{value:.4g}"))
    return f"{material['brdf']} " + " ".join(parts)
