"""The reconstructed geometry's uncertainty in the fit's σ (inverse/fit/geometry_sigma.py, issue 30).

The photographs are the simulated lab's forward model with 1 % noise; the workspace's mirror mesh
is then turned by a known small angle and shifted, as a mesh from marked corners is off, and
scene.json's pose_sigma says how far it may be off. Ground truth: the lab's materials.
"""
import json

import numpy as np
import pytest

from reflab.core.workspace import WorkspaceError

W, H = 160, 120
#: The mirror's mesh is off by this tilt about its horizontal in-plane axis and this offset.
TILT, OFFSET = 0.005, 0.0002
SHOTS = (-150.0, -165.0, 45.0, -105.0, -75.0)


def _misfit(report, truth):
    """Determined values further than 3σ + 2 % from the truth: (surface, name, band, value, true, σ)."""
    bad = []
    for surf in report["surfaces"]:
        und = set(surf["undetermined"])
        for key, sigma in surf["sigma"].items():
            if key in und or sigma is None:
                continue
            value, true = np.atleast_1d(surf["material"][key]), np.atleast_1d(truth[surf["name"]][key])
            for c, sd in enumerate(np.atleast_1d(sigma)):
                if sd is None or f"{key}[{c}]" in und:
                    continue
                v, t = value[min(c, len(value) - 1)], true[min(c, len(true) - 1)]
                if abs(v - t) > 3 * sd + 0.02 * abs(t):
                    bad.append((surf["name"], key, c, v, t, sd))
    return bad


@pytest.fixture(scope="module")
def tilted(tmp_path_factory):
    """A lab workspace (160x120, six photographs) whose mirror mesh is tilted 5 mrad and shifted
    0.2 mm; returns (root, truth, scene.json without pose_sigma, the mirror's pose_sigma)."""
    from reflab.calibration.rotations import rodrigues
    from reflab.hardware.sim.lab import user_workspace
    from reflab.inverse.forward.photographs import turned_view, write_input
    from reflab.reconstruction.scene import Mesh
    from reflab.reconstruction.surfaces import box_frame

    root = tmp_path_factory.mktemp("geometry") / "ws"
    lab, photo = user_workspace(root, W, H, textured=False, noise=0.01, seed=0)
    for a in SHOTS:
        cam, lights = turned_view(lab.camera, lab.lights, a, (0.0, 0.0))
        write_input(root, f"a{'m' if a < 0 else ''}{abs(a):g}", photo(cam, lights), cam, lights,
                    {"angle_deg": a, "lamps": [0, 1]})
    truth = {s.name: s.material.to_json() for s in lab.scene}
    scene = json.loads((root / "scene.json").read_text())
    item = next(s for s in scene["surfaces"] if s["name"] == "mirror")
    mesh = Mesh.load(root / item["mesh"])
    c, R, size = box_frame(mesh)
    face = int(np.argmin(size))
    inplane = [a for a in range(3) if a != face]
    across = R[:, inplane[int(np.argmin(np.abs(R[2, inplane])))]]  # the horizontal in-plane axis
    turn = rodrigues(TILT * across)
    Mesh((mesh.vertices - c) @ turn.T + c + OFFSET * R[:, face], mesh.triangles, mesh.normals).save(root / item["mesh"])
    pose = {"centre": c.tolist(), "normal": R[:, face].tolist(), "axes": [R[:, a].tolist() for a in inplane],
            "tilt_rad": [TILT, TILT], "offset_m": OFFSET}
    return root, truth, scene, pose


def _fit(root, scene):
    from reflab.inverse.stages import FitOptions, fit

    (root / "scene.json").write_text(json.dumps(scene))
    return fit(FitOptions(root)).report


def test_a_tilted_mirror_is_confidently_wrong_without_its_pose_sigma(tilted):
    """The defect: the fit's σ knows nothing of the mesh's error, and the mirror's ks comes out
    many σ low (0.285 ± 0.002 for 0.30 when measured)."""
    root, truth, scene, _ = tilted
    bad = _misfit(_fit(root, scene), truth)
    assert any(b[:2] == ("mirror", "ks") for b in bad), bad


def test_the_pose_sigma_makes_every_determined_value_hold(tilted):
    """With the mirror's pose_sigma in scene.json every determined value is within 3σ + 2 % of the
    truth, the mirror's lobe still determined; fit.json says what the geometry added."""
    root, truth, scene, pose = tilted
    scene = json.loads(json.dumps(scene))
    next(s for s in scene["surfaces"] if s["name"] == "mirror")["pose_sigma"] = pose
    report = _fit(root, scene)
    assert not _misfit(report, truth)
    mirror = next(s for s in report["surfaces"] if s["name"] == "mirror")
    assert not {"ks", "ns"} & set(mirror["undetermined"])
    geo = report["geometry_sigma"]["surfaces"]
    assert list(geo) == ["mirror"] and geo["mirror"]["pixels"] > 0


def test_trees_of_some_pixels_are_those_of_the_whole_image():
    """build_trees(pixels=): the few pixels' trees render as the whole image's do there."""
    from reflab.hardware.sim.lab import build_lab
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees

    lab = build_lab(48, 36)
    truth = [s.material for s in lab.scene]
    whole = render(build_trees(lab.scene, lab.camera, lab.lights), truth, lab.lights.intensities).reshape(-1, 3)
    pick = np.arange(3 * 48, 20 * 48, 7)
    some = build_trees(lab.scene, lab.camera, lab.lights, rows=(3, 20), pixels=pick - 3 * 48)
    part = render(some, truth, lab.lights.intensities).reshape(-1, 3)
    assert np.abs(whole[pick]).max() > 0.05
    np.testing.assert_allclose(part[pick - 3 * 48], whole[pick], rtol=0, atol=1e-12)
    assert not np.any(np.delete(part, pick - 3 * 48, axis=0))


def test_a_bad_pose_sigma_is_named(tmp_path):
    from reflab.inverse.fit.geometry_sigma import PoseSigma

    good = {"centre": [0, 0, 0], "normal": [0, 0, 1], "axes": [[1, 0, 0], [0, 1, 0]], "tilt_rad": [1e-3, 1e-3],
            "offset_m": 1e-4}
    assert PoseSigma.from_json(good).moves()[0][1] == 1e-3
    with pytest.raises(WorkspaceError, match="mirror.pose_sigma.tilt_rad"):
        PoseSigma.from_json({**good, "tilt_rad": [1e-3]}, tmp_path / "scene.json", "mirror.pose_sigma")
    with pytest.raises(WorkspaceError, match="pose_sigma"):
        PoseSigma.from_json({**good, "offset_m": -1.0}, tmp_path / "scene.json", "mirror.pose_sigma")
