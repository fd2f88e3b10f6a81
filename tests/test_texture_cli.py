"""`reflab texture WORKSPACE`: files written, index readable, albedo_nodes, fit.json, bad input."""
import json

import numpy as np
import pytest

from reflab.app.cli import main
from reflab.core.images import read_image, write_image
from reflab.hardware.sim.lab import build_lab, write_lab
from reflab.inverse.forward.rendering import render
from reflab.inverse.texture.solve import albedo_nodes
from reflab.inverse.forward.trees import build_trees
from reflab.reconstruction.scene import Scene


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    root = tmp_path_factory.mktemp("ws")
    lab = build_lab(128, 96)
    write_lab(root, lab)
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    image = render(trees, [s.material for s in lab.scene], lab.lights.intensities,
                   kd_nodes=lab.albedo_at(trees.surface, trees.point))
    write_image(root / "input.exr", image)
    assert main(["texture", str(root)]) == 0
    return root, lab, trees


def test_files_and_index(workspace, capsys):
    root, lab, _ = workspace
    index = json.loads((root / "textures" / "index.json").read_text())
    names = [e["surface"] for e in index["surfaces"]]
    assert names == ["ground", "box", "tile"]  # the textured surfaces only
    for e in index["surfaces"]:
        kd = read_image(root / "textures" / e["files"]["kd"])
        mask = read_image(root / "textures" / e["files"]["mask"])
        assert kd.shape[:2] == mask.shape[:2] == (e["height"], e["width"])
        assert np.all(np.isfinite(kd)) and 0 < e["texels_known"] == int((mask[:, :, 0] > 0.5).sum())
    st = index["stats"]
    assert len(st["residual_rms"]) == 3 and st["solve_s"] >= 0 and st["iterations"] > 0
    assert index["materials"] == "scene.json"
    assert not list((root / "textures").glob(".*tmp"))  # atomic writes leave no temporaries


def test_albedo_nodes_matches_truth_and_is_nan_where_unseen(workspace):
    root, lab, trees = workspace
    scene = Scene.load(root / "scene.json")
    kd = albedo_nodes(root, scene, trees)
    truth = lab.albedo_at(trees.surface, trees.point)
    primary = (trees.level == 1) & np.isin(trees.surface, [0, 1, 4])
    ok = primary & np.isfinite(kd).all(1)
    assert ok.sum() > 0.95 * primary.sum()
    assert np.sqrt(np.mean((kd[ok] - truth[ok]) ** 2)) < 0.03
    mirror = trees.surface == 3  # untextured: its homogeneous kd
    np.testing.assert_allclose(kd[mirror], np.broadcast_to(lab.scene[3].material["kd"], kd[mirror].shape))
    # The table's corner behind and below the input camera was never seen: unknown, not invented.
    from reflab.calibration.camera import Camera

    corner = Camera.look_at(64, 48, 30.0, eye=(-0.55, -0.32, 0.3), target=(-0.55, -0.32, 0.0), up=(0, 1, 0))
    below = build_trees(scene, corner, lab.lights, depth=1)
    seen = below.surface == 0
    assert seen.sum() > 100 and np.all(np.isnan(albedo_nodes(root, scene, below)[seen]))


def test_fit_json_materials_are_used(workspace, tmp_path):
    root, lab, trees = workspace
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(root, ws)
    mirror = lab.scene[3].material.to_json()
    mirror["kd"] = [0.2, 0.3, 0.4]
    (ws / "fit.json").write_text(json.dumps({"depth": 3, "surfaces": [{"name": "mirror", "material": mirror}]}))
    scene = Scene.load(ws / "scene.json")
    kd = albedo_nodes(ws, scene, trees)
    np.testing.assert_allclose(kd[trees.surface == 3], np.broadcast_to([0.2, 0.3, 0.4], kd[trees.surface == 3].shape))
    (ws / "fit.json").write_text(json.dumps({"surfaces": [{"name": "nosuch", "material": mirror}]}))
    assert main(["texture", str(ws)]) == 2


def test_bad_workspace_inputs(workspace, tmp_path, capsys):
    root, _, _ = workspace
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(root, ws)
    write_image(ws / "input.exr", np.zeros((10, 12, 3), np.float32))
    assert main(["texture", str(ws)]) == 2
    assert "input.exr" in capsys.readouterr().err
    (ws / "scene.json").unlink()
    assert main(["texture", str(ws)]) == 2
    assert "scene.json" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["texture", str(ws), "--prior", "-1"])


def test_texels_seen_through_a_loosely_known_sheet_are_guessed(workspace, tmp_path):
    """The ground behind the sheet is seen only through it: with fit.json's sheet t known to
    ± 0.3, the texels made from those pixels are flagged guessed (and renders mark them); known to
    ± 0.001, none are. Nothing else in fit.json differs (the true materials, no undetermined)."""
    root, lab, _ = workspace
    import shutil

    counts = {}
    for sigma_t in (0.3, 0.001):
        ws = tmp_path / f"ws-{sigma_t}"
        write_lab(ws, lab, materials=False)  # scene.json: what a user knows; t is not given
        shutil.copy(root / "input.exr", ws / "input.exr")
        surfaces = [{"name": s.name, "material": s.material.to_json(), "undetermined": [],
                     "sigma": {"t": [sigma_t] * 3} if s.name == "sheet" else {}} for s in lab.scene]
        (ws / "fit.json").write_text(json.dumps({"depth": 3, "surfaces": surfaces}))
        assert main(["texture", str(ws)]) == 0
        counts[sigma_t] = json.loads((ws / "textures" / "index.json").read_text())["stats"]["texels_guessed"]
    assert counts[0.3] > 0 and counts[0.001] == 0, counts
