"""`reflab fit` on a simulated workspace: fit.json contents, bad input, saturated pixels."""
import json

import numpy as np
import pytest

from reflab.app.cli import main
from reflab.core.images import write_image
from reflab.core.workspace import write_json


@pytest.fixture(scope="module")
def workspace(homogeneous_workspace):
    return homogeneous_workspace


def test_fit_writes_materials_sigmas_trace_and_columns(workspace):
    root, img, truth = workspace
    write_image(root / "input.exr", img)
    assert main(["fit", str(root)]) == 0
    fit = json.loads((root / "fit.json").read_text())
    assert fit["method"] == "ftbo" and fit["depth"] == 3 and fit["image"]["saturated_pixels"] == 0
    assert 0 < fit["columns"]["used"] < fit["columns"]["dense_dissertation"]
    assert len(fit["trace"]) >= 2 and all(len(t) == 2 and len(t[1]) == 3 for t in fit["trace"])
    by_name = {s["name"]: s for s in fit["surfaces"]}
    tile = by_name["tile"]["material"]
    # float32 EXR input: parameters to float32 precision, far from the initial 0.1 / 2^6.5.
    np.testing.assert_allclose(tile["kd"], truth[4]["kd"], rtol=1e-4)
    np.testing.assert_allclose(tile["ns"], truth[4]["ns"], rtol=1e-3)
    assert by_name["tile"]["sigma"]["ns"] > 0
    # `reflab render` reads these materials back.
    from reflab.reconstruction.scene import Material

    for i, s in enumerate(fit["surfaces"]):
        Material.from_json(s["material"], root / "fit.json", f"surfaces[{i}].material")


def test_saturated_pixels_are_masked_and_counted(workspace):
    root, img, truth = workspace
    level = np.percentile(img, 99.5)
    clipped = np.minimum(img, level)
    write_image(root / "input.exr", clipped)
    assert main(["fit", str(root)]) == 0
    fit = json.loads((root / "fit.json").read_text())
    stored = clipped.astype(np.float32)
    n_sat = int(np.any(stored == stored.max(), axis=2).sum())
    assert fit["image"]["saturated_pixels"] == n_sat > 0
    kd = {s["name"]: s["material"]["kd"] for s in fit["surfaces"]}
    np.testing.assert_allclose(kd["ground"], truth[0]["kd"], rtol=1e-4)


@pytest.mark.parametrize("case", ["size", "black"])
def test_bad_input_is_a_clear_error(workspace, case, capsys):
    root, img, _ = workspace
    bad = np.zeros((30, 40, 3)) + 0.1 if case == "size" else np.zeros_like(img)
    write_image(root / "input.exr", bad)
    assert main(["fit", str(root)]) == 2
    err = capsys.readouterr().err
    assert "input.exr" in err
    assert ("64x48" in err and "40x30" in err) if case == "size" else "black" in err


def test_poor_fit_is_reported_and_exits_3(workspace, capsys):
    """A bright patch no surface model can make, on surfaces all declared homogeneous: too many
    pixels (64, over 1% of those used) to be outliers; a 3x3 speck is rejected and mapped instead."""
    root, img, truth = workspace
    scene = json.loads((root / "scene.json").read_text())
    original = json.dumps(scene)
    for item in scene["surfaces"]:
        item["textured"] = False
    write_json(root / "scene.json", scene)
    try:
        speck = img.copy()
        speck[30:33, 10:13] += 0.3 * img.max()
        write_image(root / "input.exr", speck)
        assert main(["fit", str(root), "--max-seconds", "60"]) == 0
        fit = json.loads((root / "fit.json").read_text())
        assert fit["rejected"]["count"] == 9 and sorted(map(tuple, fit["rejected"]["pixels"])) == [
            (u, v) for u in range(10, 13) for v in range(30, 33)]
        tile = {s["name"]: s for s in fit["surfaces"]}["tile"]["material"]
        np.testing.assert_allclose(tile["kd"], truth[4]["kd"], rtol=1e-4)
        patch = img.copy()
        patch[28:36, 8:16] += 0.3 * img.max()
        write_image(root / "input.exr", patch)
        capsys.readouterr()
        assert main(["fit", str(root), "--max-seconds", "60"]) == 3
    finally:
        write_json(root / "scene.json", json.loads(original))
    err = capsys.readouterr().err
    assert "poor fit" in err and "does not explain" in err
    fit = json.loads((root / "fit.json").read_text())
    assert fit["status"] == "poor fit" and fit["warnings"] and len(fit["noise"]) == 3


def test_fit_workspace_task_progress_and_cancel(workspace):
    """fit_workspace steps the task per iteration; a cancel raises Cancelled and writes no fit.json."""
    from reflab.core.task import Cancelled, Task
    from reflab.inverse.fit.workspace_fit import fit_workspace

    root, img, truth = workspace
    write_image(root / "input.exr", img)
    (root / "fit.json").unlink(missing_ok=True)
    steps = []
    report, _ = fit_workspace(root, task=Task(progress=lambda d, t, m: steps.append((d, t, m))))
    assert steps and (root / "fit.json").exists() and report["status"] == "ok"
    (root / "fit.json").unlink()
    task = Task(progress=lambda d, t, m: task.cancel())
    with pytest.raises(Cancelled):
        fit_workspace(root, task=task)
    assert not (root / "fit.json").exists()
