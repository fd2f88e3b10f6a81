"""`reflab demo`: the simulated lab end to end at a small size, through the real stages."""
import re
import numpy as np
import pytest

from app.cli import main
from hardware.images import read_image
from hardware.simlab import build_lab
from hardware.workspace import read_json
from inverse.rendering import render
from inverse.trees import build_trees
from reconstruction.scene import Scene


def _summary(out):
    return float(re.search(r"relative ([0-9.]+)%", out).group(1))


def test_demo_end_to_end(tmp_path, capsys):
    ws = tmp_path / "demo"
    assert main(["demo", str(ws), "--size", "64x48"]) == 0
    out = capsys.readouterr().out
    assert "stage fit: exit 0" in out and "stage texture: exit 0" in out
    assert "materials from fit.json" in out and "recovered texture" in out
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


def test_demo_fit_with_a_matte_ground_gets_the_sheet_right(tmp_path, capsys):
    """160x120: with the paper ground declared matte (r = 0), the homogeneous fit on the textured
    photograph finds the sheet's transmission (it made the paper a mirror, and t [0, 0.3, 0.75],
    when the ground's r was free) and the recovered model re-renders the input within 5 %."""
    ws = tmp_path / "demo"
    assert main(["demo", str(ws), "--size", "160x120"]) == 0
    assert _summary(capsys.readouterr().out) < 5  # 4.0 % measured (6.9 % at 320x240 with r free)
    fitted = {s["name"]: s["material"] for s in read_json(ws / "fit.json")["surfaces"]}
    truth = {s["name"]: s["material"] for s in read_json(ws / "truth.json")["surfaces"]}
    np.testing.assert_allclose(fitted["sheet"]["t"], truth["sheet"]["t"], atol=0.05)  # 0.032 measured
    assert fitted["ground"]["r"] == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("bad", [["--size", "0x5"], ["--size", "big"], ["--noise", "-1"], ["--depth", "0"]])
def test_demo_rejects_bad_options(tmp_path, bad):
    with pytest.raises(SystemExit) as exc:
        main(["demo", str(tmp_path / "d"), *bad])
    assert exc.value.code == 2
