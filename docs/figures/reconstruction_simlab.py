"""`reflab reconstruct` on the simulated lab's own 36-shot turntable sweep, measured against the lab's truth.

    .venv/bin/python docs/figures/reconstruction_simlab.py WORKDIR [--size 480x360] [--grain 0.2]
                                                           [--ground turning|fixed] [--free-poses]

1. Renders the sweep as `reflab capture sweep --camera sim` does (``reflab.hardware.sim.lab.build_lab`` +
   ``reflab.hardware.cameras.lab_renderer``, depth 3, turntable axis through (0, 0)), with the lab's
   textures carrying a fine print grain (``build_lab(grain=0.2)``; ``--grain 0`` is the plain lab), into
   ``WORKDIR/captures/turntable`` with its manifest (skipped when the manifest is there).
   ``--ground turning`` puts the lab's ground (the A4 sheet and the table around it) on the
   turntable; ``fixed`` leaves it still, as `reflab capture` does.
2. Writes a marks file for the mirror and the sheet: the corners of their front faces projected
   into the 13 shots from -60 to 60 degrees with 1 px Gaussian noise, their thickness given.
3. Runs `reflab reconstruct WORKDIR --turntable-centre 0,0 --marks marks.json --force`, timed.
4. Prints (and writes ``WORKDIR/measured.json``) what the issue's proof lists: shots registered,
   turntable angle errors, camera centres against the truth, every fitted surface's RMS distance to
   the nearest true surface, the marked surfaces' corner errors, and the stage's run time.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from reflab.app.cli import main  # noqa: E402
from reflab.hardware.sim.camera import lab_renderer, rotate_about_z  # noqa: E402
from reflab.core.images import write_image  # noqa: E402
from reflab.hardware.sim.lab import build_lab  # noqa: E402
from reflab.hardware.sim.user import surface_marks  # noqa: E402
from reflab.core.workspace import read_json, write_json  # noqa: E402
from reflab.reconstruction import surfaces as surf  # noqa: E402
from reflab.reconstruction.scene import Scene  # noqa: E402

N_SHOTS = 36
MARKED = ("mirror", "sheet")  # surfaces from marked corners (hardware/sim/user.py)


def render_sweep(root: Path, lab, ground: str, depth: int = 3) -> float:
    """Render the 36 shots and the manifest `reflab capture sweep` writes; seconds taken."""
    folder = root / "captures" / "turntable"
    if (folder / "manifest.json").exists():
        return float("nan")
    render = lab_renderer(lab, depth=depth, centre=(0.0, 0.0), fixed=() if ground == "turning" else ("ground",))
    t0 = time.perf_counter()
    shots = []
    for i in range(N_SHOTS):
        angle = 360.0 * i / N_SHOTS
        write_image(folder / f"{i:04d}.exr", render(angle, [True] * len(lab.lights)).astype(np.float32))
        shots.append({"file": f"{i:04d}.exr", "role": "sweep", "angle": angle, "angle_reported": angle,
                      "lamps": [True] * len(lab.lights)})
        print(f"rendered {i + 1}/{N_SHOTS}", flush=True)
    write_json(folder / "manifest.json", {"kind": "sweep", "shots": shots, "status": "complete",
                                          "camera": {"type": "simulated"}})
    return time.perf_counter() - t0


def write_marks(path: Path, lab, rng) -> None:
    """The simulated user's marks (hardware/sim/user.py): mirror and sheet corners with 1 px noise, named surfaces."""
    shots = [(f"captures/turntable/{i:04d}.exr", 360.0 * i / N_SHOTS) for i in range(N_SHOTS)]
    write_json(path, {"surfaces": surface_marks(lab, shots, seed=int(rng.integers(1 << 30)))})


def true_centres(lab) -> np.ndarray:
    """Camera centres in the turntable's frame: the object turned by +a = the camera turned by -a."""
    return np.stack([rotate_about_z(lab.camera.center[None], -360.0 * i / N_SHOTS, (0.0, 0.0))[0]
                     for i in range(N_SHOTS)])


def measure(root: Path, lab, seconds: float, ground: str, grain: float) -> dict:
    rep = read_json(root / "sfm.json")
    out = {"ground": ground, "grain": grain, "size": [lab.camera.width, lab.camera.height], "load_average": os.getloadavg(),
           "reconstruct_s": seconds, "registered": rep["sfm"]["registered"], "images": rep["sfm"]["images"],
           "reprojection_px": rep["sfm"]["reprojection_px"], "sfm_time_s": rep["sfm"]["time_s"],
           "points": rep["sfm"]["points"], "turntable": {k: rep["turntable"][k] for k in
                                                         ("axis_tilt_deg", "max_angle_error_deg", "rms_angle_error_deg")},
           "reference": rep["reference"], "rigid_turntable": rep.get("rigid_turntable")}
    names = rep["images"]
    C = np.array([-np.array(rep["poses"][n]["R"]).T @ rep["poses"][n]["t"] if n in rep["poses"] else [np.nan] * 3
                  for n in names])
    err = np.linalg.norm(C - true_centres(lab), axis=1)
    out["centres_mm"] = {"max": float(1e3 * np.nanmax(err)), "rms": float(1e3 * np.sqrt(np.nanmean(err**2)))}
    scene = Scene.load(root / "scene.json")
    truth = {s.name: s.mesh for s in lab.scene}
    fitted = {}
    for s in scene:
        pts = s.mesh.sample_points(5000)
        if s.name == "ground":
            d = np.abs(pts[:, 2])
            match = "ground"
        else:
            dists = {n: surf.distance_to_mesh(m, pts) for n, m in truth.items() if n != "ground"}
            match = min(dists, key=lambda n: np.sqrt(np.mean(dists[n] ** 2)))
            d = dists[match]
        fitted[s.name] = {"truth": match, "source": s.extra.get("source", ""),
                          "rms_mm": float(1e3 * np.sqrt(np.mean(d**2))), "max_mm": float(1e3 * d.max())}
        if s.name in MARKED:
            true_v = truth[s.name].vertices
            fitted[s.name]["corner_max_mm"] = float(1e3 * np.linalg.norm(s.mesh.vertices - true_v, axis=1).max())
    out["surfaces"] = fitted
    return out


def run(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--size", default="480x360")
    ap.add_argument("--grain", type=float, default=0.2, help="print grain of the lab's textures (0 = none)")
    ap.add_argument("--ground", choices=["turning", "fixed"], default="turning")
    ap.add_argument("--free-poses", action="store_true", help="pass --free-poses to reflab reconstruct")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    root = args.workdir
    lab = build_lab(w, h, grain=args.grain)
    lab.camera.save(root / "camera.json")
    lab.lights.save(root / "lights.json")
    render_s = render_sweep(root, lab, args.ground)
    if np.isfinite(render_s):
        print(f"rendered the sweep in {render_s:.1f} s (load average {os.getloadavg()[0]:.2f})")
    write_marks(root / "marks.json", lab, np.random.default_rng(0))
    t0 = time.perf_counter()
    code = main(["reconstruct", str(root), "--turntable-centre", "0,0", "--marks", str(root / "marks.json"), "--force"]
                + ["--free-poses"] * args.free_poses)
    seconds = time.perf_counter() - t0
    if code:
        raise SystemExit(f"reflab reconstruct exited {code}")
    out = measure(root, lab, seconds, args.ground, args.grain)
    write_json(root / "measured.json", out)
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    run()
