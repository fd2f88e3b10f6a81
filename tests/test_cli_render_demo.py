"""`reflab demo`: the simulated lab end to end at a small size, through the real stages."""
import re
import numpy as np
import pytest

from reflab.app.cli import main
from reflab.core.images import read_image
from reflab.hardware.sim.lab import build_lab
from reflab.core.workspace import read_json
from reflab.inverse.forward.rendering import render
from reflab.inverse.forward.trees import build_trees
from reflab.reconstruction.scene import Scene


def _summary(out):
    return float(re.search(r"relative ([0-9.]+)%", out).group(1))


def test_demo_end_to_end(tmp_path, capsys):
    ws = tmp_path / "demo"
    assert main(["demo", str(ws), "--from-truth", "--size", "64x48"]) == 0
    out = capsys.readouterr().out
    # The steps the GUI runs (app/steps.py), not the subcommands.
    assert "step fit: fit.json written" in out and "step texture: textures written" in out
    assert "step results: model re-rendered" in out
    assert "materials from fit.json" in out and "recovered texture" in out
    # One camera, one lamp set: fit builds the trees, texture and render reuse the workspace's cache.
    assert read_json(ws / "fit.json")["trees"]["cache"] == "built" and out.count("trees: reused cache") == 2
    # The photograph is the true lab: the forward model with true materials and texture agrees.
    lab = build_lab(64, 48)
    photo = read_image(ws / "input.exr")
    assert photo.shape == (48, 64, 3)
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    model = render(trees, [s.material for s in lab.scene], lab.lights.intensities,
                   kd_nodes=lab.albedo_at(trees.surface, trees.point))
    assert np.sqrt(np.mean((model - photo) ** 2)) / np.sqrt(np.mean(model**2)) < 0.01
    # scene.json holds only what a user knows; the truth is beside it.
    raw = read_json(ws / "scene.json")
    assert all(set(s["material"]) == ({"brdf", "ior", "r"} if s["material"]["brdf"] == "lambert" else {"brdf", "ior"})
               for s in raw["surfaces"])
    assert raw["surfaces"][0]["material"]["r"] == [0.0, 0.0, 0.0]  # the matte paper ground does not mirror
    truth = read_json(ws / "truth.json")["surfaces"]
    assert [t["material"] for t in truth] == [s.material.to_json() for s in lab.scene]
    # The recovered model (fit + texture) re-renders the photograph far better than the initial
    # values (relative RMS ~80%); 6% measured, the rest from fitting one kd per textured surface.
    initial = render(trees, [s.material for s in Scene.load(ws / "scene.json")], lab.lights.intensities)
    assert np.sqrt(np.mean((initial - photo) ** 2)) / np.sqrt(np.mean(photo**2)) > 0.5
    assert _summary(out) < 10
    assert np.all(np.isfinite(read_json(ws / "fit.json")["rms"]))
    assert (ws / "textures" / "index.json").exists() and (ws / "render.png").exists()


def test_demo_fit_against_the_texture(tmp_path, capsys):
    """160x120, photograph by the independent renderer. With the paper ground declared matte
    (r = 0) the homogeneous fit already finds the sheet's transmission (with r free it made the
    paper a mirror and t [0, 0.3, 0.75]); the texture rounds (`reflab fit --texture-rounds`, 2 by
    default) then bring the mirror's r, the sheet's t and the tile's ks and r to the truth, and
    the recovered model re-renders the input within 3 %."""
    ws = tmp_path / "demo"
    assert main(["demo", str(ws), "--from-truth", "--size", "160x120"]) == 0
    assert _summary(capsys.readouterr().out) < 3  # 1.9 % measured (6.9 % at 320x240 before both changes)
    truth = {s["name"]: s["material"] for s in read_json(ws / "truth.json")["surfaces"]}

    def errors():
        fitted = {s["name"]: s["material"] for s in read_json(ws / "fit.json")["surfaces"]}
        assert fitted["ground"]["r"] == [0.0, 0.0, 0.0]  # the matte paper ground does not mirror
        return {(n, k): np.abs(np.subtract(fitted[n][k], truth[n][k])).max()
                for n, k in (("mirror", "r"), ("sheet", "t"), ("tile", "ks"), ("tile", "r"))}

    textured = errors()
    _determined_within_their_sigma(ws, truth)
    rounds = read_json(ws / "fit.json")["texture_rounds"]["rounds"]
    assert len(rounds) == 2 and all(r["pixels_left_out"] > 0 for r in rounds)
    # Measured: mirror r 0.009, sheet t 0.015, tile ks 0.028, tile r 0.018 off.
    assert textured[("mirror", "r")] < 0.02 and textured[("sheet", "t")] < 0.03
    assert textured[("tile", "ks")] < 0.05 and textured[("tile", "r")] < 0.03
    assert main(["fit", str(ws), "--texture-rounds", "0"]) == 0
    homogeneous = errors()  # measured: mirror r 0.15, sheet t 0.032, tile ks 0.13, tile r 0.11
    assert "texture_rounds" not in read_json(ws / "fit.json")
    for key in (("mirror", "r"), ("tile", "ks"), ("tile", "r")):
        assert homogeneous[key] > 2 * textured[key], (key, homogeneous[key], textured[key])


def _determined_within_their_sigma(ws, truth):
    """Every value fit.json calls determined is within 3σ + 2 % of the truth (a textured surface's
    kd is its texture's mean, the texture stage's to judge); the box's lobe, seen directly and in
    the mirror, is reported undetermined: the view that pins its texture carries the same lobe
    (it was fitted ns 2.5 ± 0.7 against a true 30 and called determined)."""
    textured = {s["name"] for s in read_json(ws / "scene.json")["surfaces"] if s.get("textured", True)}
    bad = []
    for surf in read_json(ws / "fit.json")["surfaces"]:
        name, und = surf["name"], set(surf["undetermined"])
        for key, sigma in surf["sigma"].items():
            if key in und or (key == "kd" and name in textured) or sigma is None:
                continue
            value, true = np.atleast_1d(surf["material"][key]), np.atleast_1d(truth[name][key])
            for c, sd in enumerate(np.atleast_1d(sigma)):
                if sd is None or f"{key}[{c}]" in und:
                    continue
                t = true[min(c, len(true) - 1)]
                if abs(value[min(c, len(value) - 1)] - t) > 3 * sd + 0.02 * abs(t) + 1e-9:
                    bad.append((name, key, c, value[min(c, len(value) - 1)], t, sd))
    assert not bad, bad
    box = next(s for s in read_json(ws / "fit.json")["surfaces"] if s["name"] == "box")
    assert {"ks", "ns"} <= set(box["undetermined"])


@pytest.mark.parametrize("bad", [["--size", "0x5"], ["--size", "big"], ["--noise", "-1"], ["--depth", "0"]])
def test_demo_rejects_bad_options(tmp_path, bad):
    with pytest.raises(SystemExit) as exc:
        main(["demo", str(tmp_path / "d"), *bad])
    assert exc.value.code == 2
