"""Albedo error of the texture stage when the non-Lambertian parameters come from `reflab fit`
(the demo workspace) instead of the truth: input view, textured pixels."""
import numpy as np, subprocess, sys
from pathlib import Path
from reflab.app.cli import main
from reflab.hardware.sim.lab import build_lab
from reflab.inverse.forward.trees import build_trees
from reflab.core.images import read_exr
ws = Path(sys.argv[1] if len(sys.argv) > 1 else 'demo-workspace')  # made by `make demo` (320x240)
assert main(["render", str(ws), "--aov", "albedo", "-o", "/tmp/alb.exr"]) == 0
alb = read_exr('/tmp/alb.exr')[:, :, :3].reshape(-1, 3)
lab = build_lab(320, 240)
tr = build_trees(lab.scene, lab.camera, lab.lights, depth=1)
true = np.full((320*240, 3), np.nan); true[tr.pixel] = lab.albedo_at(tr.surface, tr.point)
textured = np.zeros(320*240, bool); tex_ids=[i for i,s in enumerate(lab.scene) if s.textured]
textured[tr.pixel[np.isin(tr.surface, tex_ids)]] = True
known = textured & np.isfinite(alb).all(1)
print("textured pixels", textured.sum(), "known", known.sum())
print("albedo RMSE with fitted parameters (input view, textured pixels):", np.sqrt(np.mean((alb[known]-true[known])**2)))
err = np.abs(alb[known]-true[known]).max(1)
print("median abs", np.median(err), "p95", np.percentile(err,95))
