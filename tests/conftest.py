"""Shared fixtures: the simulated lab written as a workspace with its photograph, and target views.

``lab_photo_workspace(root, width, height, ...)`` writes what several tests start from: the
simulated lab's camera.json, lights.json, scene.json + meshes (with the true materials, or with
only what a user knows before fitting) and input.exr rendered by the forward model with the
lab's true textures. It returns the lab and the image.
"""
from __future__ import annotations

import json

import pytest


def lab_photo_workspace(root, width: int = 64, height: int = 48, *, textured: bool = True, known_only: bool = False,
                        depth: int = 3):
    """Write the lab and its photograph into ``root``; returns (lab, image).

    ``known_only``: scene.json keeps only brdf and ior (and r = 0 for the Lambertian paper ground),
    what a user knows before fitting; untextured, it also says no surface is textured (a textured
    surface's lobe seen once is undetermined, docs/fit.md).
    """
    from reflab.core.images import write_image
    from reflab.hardware.sim.lab import build_lab, write_lab
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees

    lab = build_lab(width, height, textured=textured)
    write_lab(root, lab)
    truth = [s.material for s in lab.scene]
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=depth)
    kd = lab.albedo_at(trees.surface, trees.point) if textured else None
    image = render(trees, truth, lab.lights.intensities, kd_nodes=kd)
    if known_only:
        scene = json.loads((root / "scene.json").read_text())
        for item, m in zip(scene["surfaces"], truth):
            item["material"] = {"brdf": m.brdf, "ior": m.ior, **({"r": 0.0} if m.brdf == "lambert" else {})}
            item["textured"] = item["textured"] and textured
        (root / "scene.json").write_text(json.dumps(scene))
    write_image(root / "input.exr", image)
    return lab, image


@pytest.fixture(scope="module")
def homogeneous_workspace(tmp_path_factory):
    """The untextured 64x48 lab whose scene.json holds only what a user knows before fitting:
    (root, image, true materials). Module-scoped: a test that changes input.exr writes it again."""
    root = tmp_path_factory.mktemp("fitws")
    lab, image = lab_photo_workspace(root, textured=False, known_only=True)
    return root, image, [s.material for s in lab.scene]


@pytest.fixture()
def lab_workspace(tmp_path):
    """A 64x48 textured lab workspace with its photograph and the true materials: (root, lab, image)."""
    root = tmp_path / "ws"
    lab, image = lab_photo_workspace(root)
    return root, lab, image


@pytest.fixture(scope="session")
def target_views():
    """Six 640x480 views of the 11x8 circle target (15 mm spacing, 4.5 mm radius) rendered by the
    simulated lab, with their true cameras: (images, cameras)."""
    import numpy as np

    from reflab.calibration.camera import Camera
    from reflab.hardware.sim import props

    K = np.array([[620.0, 0, 325.0], [0, 620.0, 236.0], [0, 0, 1]])
    poses = props.random_target_poses(6, 11, 8, 0.015, seed=4, distance=0.28)
    cams = [Camera(640, 480, K, np.array([-0.25, 0.08, 0, 0, 0]), R, t) for R, t in poses]
    return props.render_targets(cams, 11, 8, 0.015, 0.0045, spp=1, noise=0.005), cams


@pytest.fixture()
def target_workspace(tmp_path, target_views):
    """A workspace holding only :func:`target_views` in captures/calibration/ (00.exr ... 05.exr)."""
    from reflab.core.images import write_image
    from reflab.core.workspace import Workspace

    ws = Workspace(tmp_path / "ws")
    for i, image in enumerate(target_views[0]):
        write_image(ws.captures_of("calibration") / f"{i:02d}.exr", image)
    return ws.root
