"""A texel is one point of a surface whatever photograph sees it (issue #30, docs/fit.md
"Undetermined parameters and uncertainties"). Ground truth: the independent reference renderer's
photographs of a scene of our own design with known per-point albedo and lobe."""
import numpy as np
import pytest

W, H = 80, 60


def _workspace(root, name, shots, seed, noise=0.01):
    from reflab.hardware.sim.lab import named_views, write_lab
    from reflab.hardware.sim.reference import render_reference
    from reflab.hardware.sim.scenes import build

    lab = build(name, W, H)
    rng = np.random.default_rng(seed)

    def photo(cam, lights):
        img = render_reference(lab.scene, cam, lights, albedo=lab.albedo)
        return img + rng.normal(0.0, noise * img.max(), img.shape)

    further = [(n, photo(cam, li), cam, li) for n, cam, li in named_views(lab.camera, lab.lights, shots)]
    write_lab(root, lab, materials=False, photograph=photo(lab.camera, lab.lights), further=further)
    return lab


@pytest.mark.parametrize("seed", [0, 1])
def test_a_full_colour_lobe_is_determined_by_highlights_that_move_over_its_texture(tmp_path, seed):
    """print_can (a cylinder printed in full colour, phong ks 0.2, ns 20) from the reference and
    each lamp alone: one photograph leaves its lobe open (nothing separates a highlight from a
    full-colour texture), but each lamp alone puts the highlight on other texels, which the
    reference shows at another light: one albedo per texel over the three photographs pins the
    lobe. Determined, and within 3σ of the values that made the images (on main, which counted
    each photograph's view of a point as a texel of its own, it was undetermined)."""
    from reflab.inverse.stages import FitOptions, fit

    root = tmp_path / "ws"
    lab = _workspace(root, "print_can", "L0,L1", seed)
    true = next(s.material.params for s in lab.scene if s.name == "can")
    can = next(s for s in fit(FitOptions(root)).report["surfaces"] if s["name"] == "can")
    assert not {"ks", "ns"} & set(can["undetermined"]), can["undetermined"]
    ks, sd = np.asarray(can["material"]["ks"]), np.asarray(can["sigma"]["ks"])
    assert np.all(np.abs(ks - true["ks"]) <= 3 * sd), (ks, sd)
    assert abs(can["material"]["ns"] - float(true["ns"])) <= 3 * can["sigma"]["ns"], (can["material"]["ns"], can["sigma"]["ns"])
    assert np.all(sd < 0.25 * true["ks"])  # determined, not merely within a wide σ
