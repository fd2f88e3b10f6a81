"""Renders that say where they guess (issue 12, docs/fit.md "Renders that say where they guess").

A shiny textured box seen once (hardware/sim/scenes.py), photographed by the independent reference
renderer with 1 % noise: its lobe is undetermined, so the recovered model cannot predict the box in
a relit or novel view. The model recovered with fitted materials must say so (texels guessed,
pixels undetermined) and agree with the model recovered with the TRUE materials, both against the
reference renderer's images of the true scene, over the pixels it calls determined.
"""
import importlib.util
from pathlib import Path

import numpy as np

from reflab.app.cli import main
from reflab.core.workspace import read_json

ROOT = Path(__file__).resolve().parents[1]


def _fit_psnr():
    spec = importlib.util.spec_from_file_location("fit_psnr", ROOT / "docs" / "figures" / "fit_psnr.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_shiny_textured_box_renders_say_where_they_guess(tmp_path):
    rows = {r["view"].split(" (")[0].split(",")[-1].strip(): r for r in _fit_psnr().measure(160, 120, tmp_path, "print_can", 0.01)}
    relit, novel = rows["relit"], rows["novel view"]
    for r in (relit, novel):
        # Over the pixels it calls determined, the fitted model is within the 1 dB goal ...
        assert r["fitted_determined"] - r["true_determined"] > -1.0, r
        # ... and those leave out the can (a full-colour print: its lobe is guessed), not the ground.
        assert 0.5 < r["determined_fraction"] < r["known_fraction"] - 0.05, r
        # Over every pixel of known albedo, the can included, the guess (a grey lobe, fitted ns)
        # costs what one photograph cannot avoid (measured -3.0 dB relit; two-ink textures, whose
        # lobe the colours determine, -0.0 dB: docs/fit.md).
        assert r["fitted"] - r["true"] > -4.0, r
    fitted = read_json(tmp_path / "fitted" / "textures" / "index.json")
    assert fitted["stats"]["texels_guessed"] > 0 and fitted["undetermined_pixels"] > 0
    assert read_json(tmp_path / "true" / "textures" / "index.json")["stats"]["texels_guessed"] == 0
    # The command line writes the mask beside the render; with the true materials given there is none.
    for kind, expected in (("fitted", True), ("true", False)):
        out = tmp_path / f"{kind}.exr"
        assert main(["render", str(tmp_path / kind), "-o", str(out)]) == 0
        assert (tmp_path / f"{kind}_undetermined.png").is_file() == expected
    from reflab.core.images import read_image

    mask = read_image(tmp_path / "fitted_undetermined.png", linear=False)[:, :, 0] > 0.5
    assert 0.02 < mask.mean() < 0.5
    assert np.isfinite(read_image(tmp_path / "fitted.exr")).all()
    # The guided window's novel view says it too (app/gui/pages/results.py).
    from reflab.app.gui.pages.results import novel_view

    for kind, expected in (("fitted", True), ("true", False)):
        text = novel_view(tmp_path / kind, 15.0, 0.0, [1.0, 1.0])[1]
        assert ("rest on values the photograph did not determine" in text) == expected, text


def test_uncertain_radiance_is_the_renderers_derivative_times_sigma():
    """Each determined parameter's one-sigma part of a node's radiance is its derivative times σ:
    checked against the forward renderer's own finite differences, one parameter at a time (the
    lab's mirror r, the sheet's t — squared on paths through both its faces —, box kd, tile ks and
    ns), and a pixel
    whose light a ±60 % reflection carries is flagged, while exact values flag nothing."""
    from reflab.hardware.sim.lab import build_lab
    from reflab.inverse.forward.rendering import node_radiance, uncertain_radiance, undetermined_pixels
    from reflab.inverse.forward.trees import build_trees

    lab = build_lab(80, 60, textured=False)
    mats = [s.material for s in lab.scene]
    names = lab.scene.names
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    base = node_radiance(trees, mats, lab.lights.intensities)
    for surface, name, band in (("mirror", "r", 0), ("sheet", "t", 2), ("box", "kd", 1), ("tile", "ks", 0), ("tile", "ns", None)):
        s = names.index(surface)
        step = 1e-6 * (mats[s][name] if band is None else 1.0)
        moved = [m.copy() for m in mats]
        if band is None:
            moved[s].params[name] = np.float64(mats[s][name] + step)
            sigma = [{} for _ in mats]
            sigma[s] = {name: 2.0}
        else:
            moved[s].params[name] = np.asarray(mats[s][name], dtype=np.float64).copy()
            moved[s].params[name][band] += step
            sigma = [{} for _ in mats]
            sigma[s] = {name: [0.02 if c == band else None for c in range(3)]}
        expected = np.abs(node_radiance(trees, moved, lab.lights.intensities) - base) / step * (2.0 if band is None else 0.02)
        got = uncertain_radiance(trees, mats, lab.lights.intensities, sigma)
        assert expected.max() > 0, (surface, name)
        np.testing.assert_allclose(got, expected, rtol=1e-3, atol=1e-9 * expected.max())
    mirror = names.index("mirror")
    sigma = [{} for _ in mats]
    none = undetermined_pixels(trees, mats, lab.lights.intensities, [set()] * len(mats), sigma=sigma)
    sigma[mirror] = {"r": [0.5, 0.5, 0.5]}  # r 0.85 ± 0.5
    flagged = undetermined_pixels(trees, mats, lab.lights.intensities, [set()] * len(mats), sigma=sigma)
    first = np.full(80 * 60, -1)
    primary = trees.level == 1
    first[trees.pixel[primary]] = trees.surface[primary]
    seen_in_mirror = (first == mirror).reshape(60, 80)
    assert not none.any()
    assert flagged[seen_in_mirror].mean() > 0.5 and not flagged[first.reshape(60, 80) == names.index("ground")].all()


def test_noise_free_photograph_marks_every_trace_of_a_guessed_lobe(tmp_path):
    """Noise-free, a pixel is determined only if the guessed lobe moves it by less than twice the
    photograph's noise (rendering.UNDETERMINED_NOISE): the full-colour can's lobe (guessed: no
    colour set determines it) reaches nearly every can pixel, and texels made from them carry its error into new
    views. With the 5 % share alone the relit view over the determined pixels was 23 dB worse
    than the true-material model (docs/fit.md); with 1 % noise the cap hardly changes the mask."""
    fit_psnr = _fit_psnr()
    rows = {r["view"].split(" (")[0].split(",")[-1].strip(): r for r in fit_psnr.measure(160, 120, tmp_path / "clean", "print_can", 0.0)}
    for r in (rows["relit"], rows["novel view"]):
        assert r["determined_fraction"] > 0.0, r
        assert r["fitted_determined"] - r["true_determined"] > -3.0, r
    stats = read_json(tmp_path / "clean" / "fitted" / "textures" / "index.json")["stats"]
    assert stats["texels_guessed"] > 0.9 * stats["texels_known"]  # the can is the only textured surface
    noisy = {r["view"].split(" (")[0].split(",")[-1].strip(): r for r in fit_psnr.measure(160, 120, tmp_path / "noisy", "print_can", 0.01)}
    assert noisy["relit"]["determined_fraction"] > 0.8, noisy["relit"]
