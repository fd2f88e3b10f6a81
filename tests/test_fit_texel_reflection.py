"""A textured surface's own reflection judged from its texels seen twice (issue #30, docs/fit.md
"Undetermined parameters and uncertainties"). Ground truth: the independent reference renderer's
photographs of a scene of our own design, with the materials that made them."""
import numpy as np

W, H = 160, 120


def _workspace(root, name, shots, seed, noise=0.01):
    from reflab.hardware.sim.lab import photographed
    from reflab.hardware.sim.scenes import build

    return photographed(root, build(name, W, H), shots, noise=noise, seed=seed)


def test_a_textured_floor_reflection_is_determined_by_its_texels_seen_twice(tmp_path):
    """floor_mirror's textured floor reflects the mirror and the room with r = 0. No pixel shows
    that reflection without the floor's texture, which a texel seen once takes up whatever r is;
    but the turntable turned by −35° sees the same texels at another angle, under another
    reflection, and one albedo per texel over the two photographs pins r (80×60 leaves too few
    texels for a steady σ). Determined, within 3σ of the
    value that made the photographs, and its σ tight (on main, which judged r only from
    texture-free pixels, it was held at 0 and reported undetermined)."""
    from reflab.inverse.stages import FitOptions, fit

    root = tmp_path / "ws"
    lab = _workspace(root, "floor_mirror", "T-35", 0)
    true = next(s.material.params for s in lab.scene if s.name == "floor")
    floor = next(s for s in fit(FitOptions(root)).report["surfaces"] if s["name"] == "floor")
    assert "r" not in floor["undetermined"] and not any(n.startswith("r[") for n in floor["undetermined"]), \
        floor["undetermined"]
    r, sd = np.asarray(floor["material"]["r"], dtype=float), np.asarray(floor["sigma"]["r"], dtype=float)
    assert np.all(np.abs(r - np.asarray(true.get("r", 0.0))) <= 3 * sd + 1e-9), (r, sd)
    assert np.all(sd < 0.1), sd  # determined, not merely within a wide σ
