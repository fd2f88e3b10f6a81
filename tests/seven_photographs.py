"""A named scene photographed seven times, fitted and textured against the true materials (tests).

Ground truth: the independent reference renderer's images of the true scene and its parameters.
"""
from __future__ import annotations

import numpy as np

SHOTS = "L0,L1,T35,T-35,T70,T-70"  # each lamp alone, the turntable at ±35° and ±70°
RELIT = ((0.25, -0.3, 0.45), (0.10, 0.095, 0.085)), ((-0.2, 0.35, 0.5), (0.09, 0.085, 0.08))


def relit_lights(path):
    """The lamps moved (tests' relit view), saved at ``path``."""
    from reflab.calibration.lights import Lights, PointLight

    lights = Lights([PointLight(p, i) for p, i in RELIT])
    lights.save(path)
    return lights


def true_and_fitted_renders(tmp_path, scene: str, views: dict, width: int = 160, height: int = 120,
                            noise: float = 0.01, seed: int = 0):
    """``scene`` (hardware.sim.scenes) photographed from its input view and :data:`SHOTS` with
    Gaussian noise (``noise`` of each image's peak), written twice under ``tmp_path`` — ``true``
    with the true materials, ``fitted`` fitted — each textured, and each of ``views`` (name →
    (camera.json or None, lights.json or None)) rendered. Returns the lab and
    ``{kind: {view: (image, info)}}``."""
    from reflab.hardware.sim.lab import named_views, write_lab
    from reflab.hardware.sim.reference import render_reference
    from reflab.hardware.sim.scenes import build
    from reflab.inverse.fit.workspace_fit import fit_workspace
    from reflab.inverse.stages import TextureOptions, render_workspace, texture

    lab = build(scene, width, height)
    rng = np.random.default_rng(seed)

    def photograph(cam, lights):
        img = render_reference(lab.scene, cam, lights, albedo=lab.albedo)
        return img + rng.normal(0.0, noise * img.max(), img.shape)

    photo = photograph(lab.camera, lab.lights)
    further = [(n, photograph(c, li), c, li) for n, c, li in named_views(lab.camera, lab.lights, SHOTS)]
    images = {}
    for kind in ("true", "fitted"):
        root = tmp_path / kind
        write_lab(root, lab, materials=kind == "true", photograph=photo, further=further)
        if kind == "fitted":
            fit_workspace(root)
        texture(TextureOptions(root))
        images[kind] = {v: render_workspace(root, cam, lig) for v, (cam, lig) in views.items()}
    return lab, images
