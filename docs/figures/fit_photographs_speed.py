"""Time of `reflab fit` (trees included) against the number of photographs (docs/fit.md, "Several
photographs and the plan": the fit should grow at most linearly, about 5 s per 640x480 photograph).

The simulated lab (the demo's textured set, or ``--homogeneous``) with only what a user knows in
scene.json; the reference photograph and the further ones (``L0``, ``L1``: one lamp alone;
``T35`` ...: the turntable turned) made by the forward model from the true materials, 0.5 % noise.
Each fit is `python -m reflab.app.cli fit WORKSPACE` in a fresh process with the trees cache
emptied; ``--repeat`` runs, the fastest kept (the others waited on the rest of the machine).
Each row also gives that run's CPU time (user + system of the fit's process: on a shared machine
a steadier measure than the wall), the machine's load average when it started, the fit's
evaluations and the pixels it read.

    .venv/bin/python docs/figures/fit_photographs_speed.py [--size 640x480] [--counts 1,3,7] [--homogeneous] [--json out.json]
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

SHOTS = ["L0", "L1", "T35", "T-35", "T70", "T-70"]


def workspace(root: Path, width: int, height: int, count: int, textured: bool) -> Path:
    from reflab.hardware.sim.lab import named_views, user_workspace
    from reflab.inverse.forward.photographs import write_input

    ws = root / f"n{count}"
    shutil.rmtree(ws, ignore_errors=True)
    lab, photo = user_workspace(ws, width, height, textured=textured, noise=0.005)
    for name, cam, lights in named_views(lab.camera, lab.lights, SHOTS[:count - 1]):
        write_input(ws, name, photo(cam, lights), cam, lights)
    return ws


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--counts", default="1,3,7")
    ap.add_argument("--homogeneous", action="store_true")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--root", default="/tmp/fit-photographs-speed")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))
    rows = []
    for count in (int(c) for c in args.counts.split(",")):
        ws = workspace(Path(args.root), width, height, count, not args.homogeneous)
        walls, cpus, loads = [], [], []
        for _ in range(args.repeat):
            shutil.rmtree(ws / "cache", ignore_errors=True)
            loads.append(round(os.getloadavg()[0], 2))
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, "-m", "reflab.app.cli", "-q", "fit", str(ws)],
                                 capture_output=True, text=True, env=dict(os.environ))
            walls.append(time.perf_counter() - t0)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpus.append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
            if out.returncode not in (0, 3):
                raise SystemExit(out.stderr)
        fit = json.loads((ws / "fit.json").read_text())
        best = int(np.argmin(walls))
        row = {"photographs": count, "wall_s": round(min(walls), 2), "walls": [round(w, 2) for w in walls],
               "per_photograph_s": round(min(walls) / count, 2), "cpu_s": round(cpus[best], 2),
               "load": loads[best], "trees_s": fit["setup_s"]["trees"],
               "fit_s": fit["time_s"], "evaluations": fit["evaluations"],
               "pixels_read": fit["used_pixels"], "status": fit["status"],
               "undetermined": {s["name"]: s["undetermined"] for s in fit["surfaces"] if s["undetermined"]}}
        rows.append(row)
        print(json.dumps(row), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
