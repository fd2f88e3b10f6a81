"""The novel and relit views section: the recovered model rendered elsewhere, with PSNR against the
truth."""
from __future__ import annotations

import math

import numpy as np

from reflab.app.report import figures as F
from reflab.app.report.data import Sources
from reflab.app.report.sections.section import Section, num


def psnr(image: np.ndarray, truth: np.ndarray, known: np.ndarray | None = None) -> float:
    """PSNR (dB) of ``image`` against ``truth`` over the pixels ``known`` (all by default), the peak
    being the truth's maximum (as the demo scores it)."""
    err = np.asarray(image, dtype=np.float64) - truth
    err = err if known is None else err[known]
    mse = float(np.mean(err ** 2)) if err.size else float("nan")
    return float("inf") if mse == 0 else 10 * math.log10(max(float(np.max(truth)), 1e-300) ** 2 / mse)


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
            known = v.get("known")
            share = f"{100 * float(np.mean(known)):.0f}" if known is not None else "100"
            sure = known if guess is None or known is None else known & ~guess
            sure_text = (f", {num(psnr(img, truth, sure), 4)} dB over the {100 * float(np.mean(sure)):.0f} % of those "
                         f"that are determined" if guess is not None and guess.any() and known is not None else "")
            sec.kv([(f"{label} PSNR against truth", f"{num(psnr(img, truth, known), 4)} dB over the {share} % of pixels of "
                                                     f"known albedo{sure_text}, {num(psnr(img, truth), 4)} dB over all"),
                    (f"{label} RMS per band", num(np.sqrt(np.mean((img - truth) ** 2, axis=(0, 1))).tolist()))])
        else:
            sec.images(items)
    return sec
