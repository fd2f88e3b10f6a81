"""Time and error of `reflab fit` (trees included) on three scenes at three sizes (docs/fit.md, "Speed").

Scenes, each written as a workspace whose scene.json holds only what a user knows (brdf, ior, the
matte ground's r = 0) with the truth in truth.json:

- ``demo``: `reflab demo`'s workspace (the textured simulated lab, photograph by the independent
  reference renderer, noise-free);
- ``six``: a homogeneous scene of our own: the lab's five surfaces with other materials, a sixth
  glossy cube, one lamp moved; reference renderer, Gaussian noise of 0.5% of the peak (seed 0);
- ``six-textured``: the same scene with the lab's textures on ground, box and tile.

Each fit is `python -m reflab.app.cli fit WORKSPACE` in a fresh process with the trees cache emptied, so
the wall time counts imports, trees, factorization and fit; the CPU time (user + system of that
process) is the figure to compare on a shared machine. Errors against truth.json over the
parameters the fit determines: the largest absolute error of kd, r, t and of ks (any band) and
|log2 ns error| per surface; and the fit's RMS residual relative to the image's RMS. ``--nftbo-seconds S`` also runs
NF-TBO (budget S) on ``six`` at the sizes given by ``--nftbo-sizes`` and reads from both traces
the time each method needs to come within 1e-3 (relative) of F-TBO's final RMS. ``--repeat N``
runs each F-TBO fit N times (default 3): ``wall_s`` and ``cpu_s`` are the fastest run's (as
``timeit`` reports: the others waited on the rest of the machine), ``walls`` lists every run.

    .venv/bin/python docs/figures/fit_speed.py [--sizes 160x120,320x240,640x480] [--scenes demo,six,six-textured]
        [--nftbo-seconds 300 --nftbo-sizes 160x120,320x240] [--json fit-speed.json] [--root /tmp/fit-speed] [--repeat 3]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
SCENES = ("demo", "six", "six-textured")


def build_scene(name: str, width: int, height: int):
    """(SimLab, noise σ as a fraction of the peak) of one benchmark scene."""
    from reflab.calibration.lights import Lights, PointLight
    from reflab.hardware.sim.lab import SimLab, _material, _rot_z, box_mesh, build_lab
    from reflab.reconstruction.scene import Scene, Surface

    if name == "demo":
        return build_lab(width, height), 0.0
    lab = build_lab(width, height, textured=name == "six-textured")
    new = {"box": dict(ks=0.4, ns=15.0, r=0.03), "tile": dict(ks=0.25, ns=120.0, r=0.08),
           "mirror": dict(kd=0.03, ks=0.2, ns=400.0, r=0.9)}
    surfaces = []
    for s in lab.scene.surfaces:
        m = s.material.copy()
        for key, value in new.get(s.name, {}).items():
            m.params[key] = np.float64(value) if key == "ns" else np.broadcast_to(np.float64(value), (3,)).copy()
        surfaces.append(Surface(s.name, s.mesh_path, m, textured=s.textured and name == "six-textured", mesh=s.mesh))
    cube = box_mesh((0.06, 0.06, 0.06), (0.17, 0.10, 0.03), _rot_z(30.0))
    surfaces.append(Surface("cube", "meshes/cube.ply", _material("phong", kd=[0.2, 0.45, 0.3], ks=0.3, ns=40.0, r=0.05),
                            textured=False, mesh=cube))
    lamp = list(lab.lights)
    lights = Lights([PointLight(lamp[0].position + [0.05, -0.05, 0.0], lamp[0].intensity),
                     PointLight(lamp[1].position, lamp[1].intensity)])
    return SimLab(lab.camera, lights, Scene(surfaces), lab.textures), 0.005


def write_workspace(root: Path, name: str, width: int, height: int) -> float:
    """Write the scene's workspace with its photograph; returns the image's RMS."""
    from reflab.core.images import write_image
    from reflab.hardware.sim.lab import write_lab
    from reflab.hardware.sim.reference import render_reference

    lab, noise = build_scene(name, width, height)
    write_lab(root, lab, materials=False)
    photo = render_reference(lab.scene, lab.camera, lab.lights, depth=3, albedo=lab.albedo if lab.textures else None)
    if noise:
        photo = np.maximum(photo + np.random.default_rng(0).normal(0.0, noise * photo.max(), photo.shape), 0.0)
    write_image(root / "input.exr", photo)
    return float(np.sqrt(np.mean(photo**2)))


def errors(fit: dict, truth: dict) -> dict:
    """Largest absolute error of the determined kd, r, t and of ks; |log2 ns error| per surface."""
    true = {s["name"]: s["material"] for s in truth["surfaces"]}
    out = {"kd_r_t": 0.0, "ks": 0.0, "log2_ns": {}}
    for item in fit["surfaces"]:
        held = {u for u in item["undetermined"] if "[" not in u}
        t = true[item["name"]]
        for key in ("kd", "ks", "r", "t"):
            if key in item["material"] and key not in held and t.get(key) is not None:
                bands = [c for c in range(3) if f"{key}[{c}]" not in item["undetermined"]]
                d = np.abs(np.subtract(item["material"][key], t[key]))[bands]
                name = "ks" if key == "ks" else "kd_r_t"
                out[name] = max(out[name], float(d.max()) if len(d) else 0.0)
        if "ns" in item["material"] and "ns" not in held:
            out["log2_ns"][item["name"]] = round(abs(float(np.log2(item["material"]["ns"] / t["ns"]))), 4)
    return out


def first_within(trace, target: float, rel: float = 1e-3):
    """Seconds of the first trace point whose mean RMS is within ``rel`` of ``target``."""
    for t, rms in trace:
        if float(np.mean(rms)) <= target * (1.0 + rel):
            return float(t)
    return None


def run_fit(ws: Path, *args) -> tuple[float, float, dict, str]:
    """Wall and CPU (user + system) seconds of one `reflab fit` process, its fit.json and stdout."""
    shutil.rmtree(ws / "cache", ignore_errors=True)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "reflab.app.cli", "fit", str(ws), *args], cwd=REPO, env=env,
                          capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode not in (0, 3):
        raise RuntimeError(f"reflab fit {ws} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return wall, cpu, json.loads((ws / "fit.json").read_text()), proc.stdout


def table(data: dict, before: dict | None = None) -> str:
    """docs/fit.md's markdown table from the JSON (and the same runs of an earlier version)."""
    rows = ["| scene | size | method | CPU s | wall s (median) | load | iterations | evaluations | max error kd r t / ks "
            "| log2 ns error | RMS / image RMS | before: CPU s, iterations, error kd r t / ks |", "|" + "---|" * 12]
    for key, r in data.items():
        e = r["errors"]
        ns = ", ".join(f"{k} {v:.2g}" for k, v in e["log2_ns"].items())
        old = (before or {}).get(key)
        then = (f"{old['cpu_s']:.1f}, {old['iterations']}, {old['errors']['kd_r_t']:.3f} / {old['errors']['ks']:.3f}"
                if old else "")
        wall = f"{r['wall_s']:.1f}" + (f" ({np.median(r['walls']):.1f})" if len(r.get("walls", [])) > 1 else "")
        rows.append(f"| {r['scene']} | {r['size']} | {r['method']} | {r['cpu_s']:.1f} | {wall} | "
                    f"{r['load_before'][0]:.1f} | {r['iterations']} | {r['evaluations']} | "
                    f"{e['kd_r_t']:.3f} / {e['ks']:.3f} | {ns} | {r['relative_rms']:.4f} | {then} |")
    return "\n".join(rows)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="160x120,320x240,640x480")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--nftbo-seconds", type=float, default=0.0)
    ap.add_argument("--nftbo-sizes", default="160x120,320x240")
    ap.add_argument("--root", type=Path, default=Path("/tmp/fit-speed"))
    ap.add_argument("--json", type=Path, default=Path("fit-speed.json"))
    ap.add_argument("--table", action="store_true", help="print docs/fit.md's table from --json and exit")
    ap.add_argument("--before", type=Path, help="with --table: the same runs of an earlier version")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each F-TBO fit; the fastest is reported")
    args = ap.parse_args()
    if args.table:
        print(table(json.loads(args.json.read_text()), json.loads(args.before.read_text()) if args.before else None))
        return 0
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",") if s]
    out = json.loads(args.json.read_text()) if args.json.exists() else {}
    for name in [s for s in args.scenes.split(",") if s]:
        for width, height in sizes:
            ws = args.root / f"{name}-{width}x{height}"
            image_rms = write_workspace(ws, name, width, height)
            truth = json.loads((ws / "truth.json").read_text())
            runs = [("ftbo", [])]
            if args.nftbo_seconds and name == "six" and f"{width}x{height}" in args.nftbo_sizes.split(","):
                runs.append(("nftbo", ["--method", "nftbo", "--max-seconds", str(args.nftbo_seconds)]))
            final = None
            for method, extra in runs:
                load = os.getloadavg()
                timed = [run_fit(ws, *extra) for _ in range(max(args.repeat, 1) if method == "ftbo" else 1)]
                wall, cpu, fit, _ = min(timed, key=lambda r: r[0])
                rms = float(np.mean(fit["rms"]))
                final = rms if method == "ftbo" else final
                rec = {"scene": name, "size": f"{width}x{height}", "method": method, "wall_s": round(wall, 2), "cpu_s": round(cpu, 2),
                       "walls": [round(r[0], 2) for r in timed],
                       "fit_s": fit["time_s"], "setup_s": fit.get("setup_s"), "phases_s": fit.get("phases_s"),
                       "iterations": fit["iterations"], "evaluations": fit["evaluations"],
                       "scan_evaluations": fit.get("scan_evaluations"),
                       "nodes": fit["trees"]["nodes"], "relative_rms": rms / image_rms, "status": fit["status"],
                       "to_ftbo_rms_s": first_within(fit["trace"], final), "message": fit["message"],
                       "load_before": [round(v, 2) for v in load], "load_after": [round(v, 2) for v in os.getloadavg()],
                       "errors": errors(fit, truth), "undetermined": [s["undetermined"] for s in fit["surfaces"]]}
                out[f"{name}/{width}x{height}/{method}"] = rec
                print(json.dumps(rec), flush=True)
                args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
