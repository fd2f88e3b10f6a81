"""The report's summary (issue 31): at the top, undetermined values as their plausible range (never a
σ wider than it), no stale fit status, and the same numbers as the sections and the demo's console."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from reflab.app.cli import main
from reflab.app.report.sections.fit import status_text, value_text
from reflab.app.report.sections.section import pm_range
from reflab.inverse.fit.ranges import phong_lobe_albedo, plausible_range

from test_report import lab_workspace, parse  # noqa: F401 - the module's workspace fixture


def test_a_sigma_wider_than_the_plausible_range_reads_undetermined():
    # ns's range is [2, 2^20]; kd's [0, 1]: a σ of 6.6e3 on kd says nothing.
    assert pm_range(0.3483, 6.6e3, (0.0, 1.0)) == "undetermined (plausible range 0–1)"
    assert pm_range(0.3483, 0.01, (0.0, 1.0)) == "0.3483 ± 0.01"
    assert pm_range([0.2, 0.3, 0.4], [0.01, 5.0, 0.01], (0.0, 1.0)) == \
        "[0.2 ± 0.01, undetermined (plausible range 0–1), 0.4 ± 0.01]"
    assert pm_range([0.2, 0.3], None, (0.0, 1.0), [True, True]) == "undetermined (plausible range 0–1)"
    # Phong ks's bound follows ns: 1 / L(ns), 4.5 at ns = 30 (ranges.py's docstring).
    lo, hi = plausible_range("phong", "ks", {"ns": 30.0})
    assert lo == 0 and hi == pytest.approx(1 / float(phong_lobe_albedo(30.0))) and 4.0 < hi < 5.0
    assert plausible_range("phong", "ns") == (2.0, 2.0**20) and plausible_range("phong", "ior") is None
    # A shape searched in log2 reads with its one-σ factor, e^(σ / value): ns 5.2 ± 1.65 spans
    # 3.8-7.1 at one σ, and its truth 11.03 (zoo seed 61) lies 2.4 of these factors up.
    assert pm_range(5.2, 1.65, (2.0, 2.0**20), log=True) == "5.2 ± 1.6 (×/÷ 1.37)"
    assert pm_range(5.2, 1.65, (2.0, 2.0**20)) == "5.2 ± 1.6"
    text = value_text("phong", "ns", {"brdf": "phong", "ns": 46.52}, 8.2e4, [])
    assert text.startswith("undetermined (plausible range 2–") and "±" not in text


def test_texture_pending_is_not_stale_once_the_texture_ran():
    fit = {"status": "texture pending"}
    assert status_text(fit, False) == "status: texture pending"
    assert "texture stage has run" in status_text(fit, True) and not status_text(fit, True).startswith("status: texture")


def test_summary_on_top_with_undetermined_ranges_plan_and_truth(lab_workspace, tmp_path):  # noqa: F811
    root, lab = lab_workspace
    fit = json.loads((root / "fit.json").read_text())
    work = tmp_path / "ws"
    import shutil

    shutil.copytree(root, work)
    for s in fit["surfaces"]:
        if s["name"] == "tile":
            s["sigma"] = {"ns": 8.2e4}  # wider than ns's range: undetermined
        if s["name"] == "box":
            s["undetermined"] = ["ks[0]"]
    fit["status"] = "texture pending"
    fit["photographs"] = [{"name": "input", "file": "input.exr", "width": 80, "height": 60, "lamps": [0],
                           "pixels_used": 4700, "rms": [0.01, 0.02, 0.03]},
                          {"name": "l1", "file": "inputs/l1.exr", "width": 80, "height": 60, "lamps": [1],
                           "pixels_used": 4500, "rms": [0.02, 0.02, 0.02]}]
    (work / "fit.json").write_text(json.dumps(fit))
    (work / "plan.json").write_text(json.dumps({"shots": [{"name": "am90_l01", "angle_deg": -90.0, "lamps": [0, 1],
                                                           "determines": ["tile.ns"]}], "left_open": ["sheet.ns"]}))
    assert main(["report", str(work)]) == 0
    html = (work / "report.html").read_text()
    page = parse(work / "report.html")
    assert page.ids.get("summary") == "section"
    assert html.index('id="summary"') < min(html.index(f'id="{s}"') for s in ("captures", "camera", "fit"))
    summary = html[html.index('id="summary"'):html.index('id="captures"')]
    text = re.sub(r"<[^>]+>", " ", summary)
    assert re.search(r"tile ns: undetermined \(plausible range 2–1\.05e\+06\)", text), text
    assert "box ks: [undetermined (plausible range 0–" in text
    assert "am90_l01: turntable -90°, lamps [0, 1], determines tile.ns" in text and "left open even then: sheet.ns" in text
    assert "input: RMS per band [0.01, 0.02, 0.03]" in text and "l1: RMS" in text
    assert "texture stage has run" in text and "status: texture pending" not in html
    # The re-render's unexplained pixels: the same count in the summary and the fit section.
    counts = re.findall(r"(\d+) of (?:all )?(\d+) (?:image )?pixels unexplained|unexplained pixels of this re-render \(magenta\): "
                        r"(\d+) of all (\d+)", re.sub(r"<[^>]+>", " ", html))
    got = {(a or c, b or d) for a, b, c, d in counts}
    assert len(got) == 1 and int(next(iter(got))[1]) == 80 * 60, counts
    # Against the truth: the camera's fx shift (0.5 px) as a focal error, the lamp's 2 mm shift.
    fx = float(json.loads((root / "truth" / "camera.json").read_text())["K"][0][0])
    m = re.search(r"focal ([\d.e-]+) %", text)
    assert m and float(m.group(1)) == pytest.approx(100 * 0.5 / fx, rel=0.01)
    assert re.search(r"lamp 0 2(\.0+)? mm", text), text
    # The views' PSNR: the summary's and the views section's are one number.
    views = re.sub(r"<[^>]+>", " ", html[html.index('id="views"'):])
    for label in ("novel view", "relit view"):
        a = re.search(label + r"\s+PSNR ([\d.]+) dB over the (\d+) %", text)
        b = re.search(label + r" PSNR against truth\s+([\d.]+) dB over the (\d+) %", views)
        assert a and b and a.groups() == b.groups(), (a, b)
    # Every σ the fit table shows is inside the range of its value.
    fit_html = re.sub(r"<[^>]+>", " ", html[html.index('id="fit"'):html.index('id="texture"')])
    assert "± 8.2e+04" not in fit_html and "tile" in fit_html
