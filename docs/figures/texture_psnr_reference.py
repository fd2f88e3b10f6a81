"""Recover-then-render against the independent reference renderer (hardware/sim/reference.py).

The simulated lab's photograph is rendered by the reference renderer with the lab's true albedo
function; `reflab texture` recovers the textures from it (true non-Lambertian parameters in
scene.json); `reflab render`'s code renders the recovered model for three views, each compared
with the reference renderer's image of the true scene:

- the input view re-rendered;
- the input view relit by two new lamps;
- a novel view showing the purple box's back face, which the input saw only in the mirror.

PSNR = 10 log10(peak² / MSE), peak = the truth image's maximum, over all pixels and over the
pixels whose every tree node has a recovered (or homogeneous, untextured) albedo. Two
references frame the numbers: the forward model with the TRUE albedo function (what the two
renderers' differences alone cost: edges, ray offsets) and the homogeneous kd (no texture stage).

Usage: ``.venv/bin/python docs/figures/texture_psnr_reference.py [WIDTH HEIGHT]`` (default 320 240).
"""
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from reflab.app.cli import main  # noqa: E402
from reflab.inverse.stages import render_workspace  # noqa: E402
from reflab.calibration.camera import Camera  # noqa: E402
from reflab.calibration.lights import Lights, PointLight  # noqa: E402
from reflab.core.images import write_image  # noqa: E402
from reflab.hardware.sim.reference import render_reference  # noqa: E402
from reflab.hardware.sim.lab import build_lab, write_lab  # noqa: E402
from reflab.inverse.forward.rendering import render  # noqa: E402

#: Two lamps unlike the capture's: one above the camera, one bluish behind the mirror's right.
RELIGHT = Lights([PointLight([0.0, -0.1, 0.5], [0.5, 0.5, 0.5]), PointLight([0.3, 0.4, 0.3], [0.1, 0.15, 0.3])])


def novel_camera(width: int, height: int) -> Camera:
    """Above and behind the box, looking at its back face (seen by the input only in the mirror)."""
    return Camera.look_at(width, height, 40.0, eye=(-0.09, 0.33, 0.5), target=(-0.075, 0.06, 0.03))


def psnr(image: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB) of ``image`` against ``truth`` (peak = truth's maximum), optionally over a pixel mask."""
    err = (image - truth) ** 2 if mask is None else (image - truth)[mask] ** 2
    if err.size == 0:
        return float("nan")  # no pixel to compare: the tables print n/a
    return float(10 * np.log10(truth.max() ** 2 / max(err.mean(), 1e-30)))


def measure(width: int, height: int, root: Path) -> list[dict]:
    """Build the workspace, recover the texture, render three views; one dict per view."""
    lab = build_lab(width, height)
    write_lab(root, lab)
    write_image(root / "input.exr", render_reference(lab.scene, lab.camera, lab.lights, albedo=lab.albedo))
    assert main(["texture", str(root)]) == 0
    RELIGHT.save(root / "relight.json")
    novel_camera(width, height).save(root / "novel.json")
    views = [("input view, re-rendered", None, None), ("input view, relit (two new lamps)", None, root / "relight.json"),
             ("novel view (box back face seen only in the mirror)", root / "novel.json", None)]
    rows = []
    for name, cam, lig in views:
        image, info = render_workspace(root, cam, lig)
        camera = Camera.load(cam) if cam else lab.camera
        lights = Lights.load(lig) if lig else lab.lights
        truth = render_reference(lab.scene, camera, lights, albedo=lab.albedo)
        known = ~info["unknown_pixels"]
        trees, materials = info["trees"], [s.material for s in lab.scene]
        exact = render(trees, materials, lights.intensities, kd_nodes=lab.albedo_at(trees.surface, trees.point))
        flat = render(trees, materials, lights.intensities)
        rows.append({"view": name, "all": psnr(image, truth), "known": psnr(image, truth, known),
                     "known_fraction": float(known.mean()), "true_albedo": psnr(exact, truth),
                     "homogeneous": psnr(flat, truth)})
    return rows


if __name__ == "__main__":
    w, h = (int(sys.argv[1]), int(sys.argv[2])) if len(sys.argv) > 2 else (320, 240)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        rows = measure(w, h, Path(tmp) / "ws")
    print(f"\n{w}x{h} (total {time.perf_counter() - start:.1f} s)")
    print("| view | recovered model, all pixels | recovered, pixels with known albedo (fraction) "
          "| forward model with the true albedo | homogeneous kd |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['view']} | {r['all']:.1f} dB | {r['known']:.1f} dB ({100 * r['known_fraction']:.1f} %) "
              f"| {r['true_albedo']:.1f} dB | {r['homogeneous']:.1f} dB |")
