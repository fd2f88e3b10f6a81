"""The novel and relit views section: the recovered model rendered elsewhere, with PSNR against the
truth."""
from __future__ import annotations

import math

import numpy as np

from reflab.app.report import figures as F
from reflab.app.report.data import Sources
from reflab.app.report.sections.section import Section, num


def psnr(image: np.ndarray, truth: np.ndarray, known: np.ndarray | None = None) -> float:
    """PSNR (dB) over the pixels ``known``: :func:`reflab.app.demo_score.psnr`, the one the console uses."""
    from reflab.app.demo_score import psnr as _psnr

    return _psnr(image, truth, known)


def scores(v: dict) -> dict | None:
    """The view's PSNR against its truth by :func:`reflab.app.demo_score.view_scores` (the demo's
    console line computes the same numbers); None without a truth of the same shape."""
    from reflab.app.demo_score import view_scores

    img, truth = v.get("image"), v.get("truth")
    if img is None or truth is None or truth.shape != img.shape or v.get("albedo") is None:
        return None
    unknown = v.get("unknown")
    unknown = np.zeros(img.shape[:2], bool) if unknown is None else unknown
    guess = v.get("undetermined")
    guess = np.zeros(img.shape[:2], bool) if guess is None else guess
    return view_scores(img, truth, v["albedo"], unknown, guess)


def views_section(src: Sources, views: dict) -> Section | None:
    if not views:
        return None
    sec = Section("views", "Novel and relit views", "The recovered model rendered where the input photograph "
                                                    "did not look, and under other lamps.")
    for key, label in (("novel", "novel view"), ("relit", "relit view")):
        v = views.get(key)
        if not v:
            continue
        if v.get("error"):
            sec.note(f"{label}: {v['error']}", "bad")
            continue
        img, truth = v["image"], v.get("truth")
        exposure = 1.0 / max(float(np.percentile(truth if truth is not None else img, 99.5)), 1e-12)
        items = [(F.thumb(F.display(img, exposure), 480, 360), f"{label}: recovered model ({v['how']})")]
        guess = v.get("undetermined")
        if guess is not None and guess.any():
            items.append((F.thumb(np.where(guess, 235, 40).astype(np.uint8), 480, 360),
                          f"{label}: undetermined pixels (light: the value rests on parameters fit.json calls "
                          f"undetermined, {100 * float(np.mean(guess)):.0f} %)"))
        if truth is not None and truth.shape == img.shape:
            items.append((F.thumb(F.display(truth, exposure), 480, 360), f"{label}: truth ({v['truth_file']})"))
            items.append((F.heat_with_bar(np.abs(img - truth).max(axis=2), "|model − truth|", "linear radiance"), "difference", True))
            sec.images(items)
            e = scores(v) or {}
            sure_text = (f", {num(e['psnr_determined_db'], 4)} dB over the {e['determined_pct']:.0f} % of pixels that "
                         "are determined" if guess is not None and guess.any() and e else "")
            sec.kv([(f"{label} PSNR against truth", f"{num(e.get('psnr_db'), 4)} dB over the {e.get('known_pct', 100):.0f} % of "
                                                     f"pixels of known albedo{sure_text}, {num(e.get('psnr_all_db'), 4)} dB over all"
                                                     if e else None),
                    (f"{label} RMS per band", num(np.sqrt(np.mean((img - truth) ** 2, axis=(0, 1))).tolist()))])
        else:
            sec.images(items)
    return sec
