"""`reflab fit` and `reflab texture` on linear images as a real lab makes them (issue 18).

A dark- or ambient-frame subtraction leaves small negative values where noise meets black: that
is data (and fit.json's σ stays a number or null, never NaN). Refused, with one line naming the
file and nothing written: NaN, mostly negative, all zero, an 8-bit image (not linear), a cut-off
file. Truth: the parameters that rendered the image.
"""
import json

import cv2
import numpy as np
import pytest

from reflab.app.cli import main
from reflab.core.images import write_image


@pytest.fixture(scope="module")
def workspace(homogeneous_workspace):
    return homogeneous_workspace  # the 64x48 lab of test_fit_cli (tests/conftest.py)


def _noisy(img, seed=0):
    """The image after a dark-frame subtraction: sensor noise of 0.3 % of the peak, black goes negative."""
    rng = np.random.default_rng(seed)
    return img + rng.normal(0, 0.003 * img.max(), img.shape)


def test_noise_level_negatives_are_data(workspace, capsys):
    root, img, truth = workspace
    noisy = _noisy(img)
    assert noisy.min() < 0 and np.mean(noisy < 0) < 0.5
    write_image(root / "input.exr", noisy)
    assert main(["fit", str(root), "--texture-rounds", "0"]) in (0, 3)
    text = (root / "fit.json").read_text()
    fit = json.loads(text)
    kd = {s["name"]: s["material"]["kd"] for s in fit["surfaces"]}
    np.testing.assert_allclose(kd["ground"], truth[0]["kd"], rtol=0.03)
    # σ is a number or null (undetermined), never NaN: a pane's ks on this homogeneous scene was NaN.
    assert "NaN" not in text and "Infinity" not in text
    sigmas = [v for s in fit["surfaces"] for v in s["sigma"].values()]
    values = [x for v in sigmas for x in (v if isinstance(v, list) else [v])]
    assert values and all(x is None or (isinstance(x, float) and np.isfinite(x) and x >= 0) for x in values), values
    assert main(["texture", str(root)]) == 0
    assert (root / "textures").is_dir()
    capsys.readouterr()


@pytest.mark.parametrize("case", ["nan", "negative", "zero", "8-bit", "cut-off"])
def test_what_cannot_be_a_photograph_is_refused(workspace, case, tmp_path, capsys):
    root, img, _ = workspace
    for name in ("input.exr", "input.png"):
        (root / name).unlink(missing_ok=True)
    before = {p: p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}
    if case == "8-bit":
        path = root / "input.png"
        cv2.imwrite(str(path), (np.clip(img / img.max(), 0, 1) * 255).astype(np.uint8))
        before[path] = path.stat().st_mtime_ns
    else:
        bad = {"nan": np.where(np.arange(img.size).reshape(img.shape) % 7 == 0, np.nan, img),
               "negative": img - np.percentile(img, 80), "zero": np.zeros_like(img)}.get(case)
        path = write_image(root / "input.exr", img if case == "cut-off" else bad, allow_nan=True)
        if case == "cut-off":  # the copy from the camera's card was interrupted
            path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
        before[path] = path.stat().st_mtime_ns
    for command in ("fit", "texture"):
        assert main([command, str(root)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and path.name in err[0], err
        assert {"nan": "NaN", "negative": "negative", "zero": "black", "8-bit": "8-bit", "cut-off": "cut-off"}[case] in err[0]
        assert {p: p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()} == before
    path.unlink()
