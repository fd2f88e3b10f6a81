"""Time and peak memory of `reflab fit`, `reflab texture` and `reflab render` on full-resolution
photographs (docs/texture.md, "Large photographs"; issue #32).

The scene is the zoo's seed 9 (:mod:`reflab.hardware.sim.zoo`): a textured ground and a textured
box, a glass cylinder and a mirror box under two lamps; the workspace holds what a user knows
(scene.json with brdf and ior only) and the photograph made by the reference renderer at the size
(1 % noise), a band of rows at a time so that writing it stays small. Each stage is
``python -m reflab.app.cli STAGE WORKSPACE`` in a fresh process with the trees cache emptied;
its wall time and peak resident memory come from ``os.wait4`` (the child's own rusage).

A texture above ``--texture-max-mp`` (default 12.5: the 12 MP texture peaks at 7.1 GB, the 24 MP
one extrapolates to about 13 GB, more than a run may take on the shared machine) is not run: the
render then uses the largest texture made before, its texel maps being independent of the
photograph's size. ``--reuse`` keeps a size's workspace (photograph, fit.json) from an earlier run
under the same ``--root``, ``--stages`` picks the stages after the fit (``--stages texture,albedo``:
the texture and its coverage).
A fit at a size above ``--fit-max-mp`` is not run; the texture and render then use fit.json of the
same scene's 640x480 fit, said in the table. (The fit reads a sample of the pixels and above 2 MP
builds trees only for those: docs/fit.md, "Large photographs".)

Coverage: the share of the photograph's pixels that see a surface (a primary ray hits) whose
albedo the written texture knows (``reflab render --aov albedo`` finite there; untextured surfaces
count as known), and the same over the pixels that see a textured surface only.

    PYTHONPATH=.. .venv/bin/python docs/figures/megapixels.py [--sizes 1,3] [--root /tmp/reflab-megapixels] [--json out.json]

``--sizes`` in megapixels among 0.3 (640x480), 1, 3, 12, 24 (4:3 frames); the default runs the
small ones. Mind the memory: measure a small size first and extrapolate (docs/texture.md's table).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

#: Megapixels -> (width, height), 4:3 like the zoo's 640x480 camera (its field of view at any size).
SIZES = {0.3: (640, 480), 1: (1152, 864), 3: (2000, 1500), 12: (4000, 3000), 24: (5664, 4248)}
SEED = 9
NOISE = 0.01


def band_camera(camera, r0: int, r1: int):
    """The camera's rows ``r0 .. r1 - 1`` as a camera of their own (principal point moved up)."""
    from reflab.calibration.camera import Camera

    K = camera.K.copy()
    K[1, 2] -= r0
    return Camera(camera.width, r1 - r0, K, camera.dist.copy(), camera.R.copy(), camera.t.copy())


def render_band(width: int, height: int, r0: int, r1: int, out: Path) -> None:
    """Rows ``r0 .. r1 - 1`` of the zoo scene's photograph (noise-free) by the reference renderer, to ``out`` (.npy)."""
    from reflab.hardware.sim.reference import render_reference
    from reflab.hardware.sim.zoo import random_scene

    zoo = random_scene(SEED, width, height, noise=NOISE)
    if np.any(zoo.camera.dist):
        raise SystemExit("a band camera needs an undistorted camera")
    np.save(out, render_reference(zoo.scene, band_camera(zoo.camera, r0, r1), zoo.lights, depth=3, albedo=zoo.albedo))


def write_workspace(root: Path, width: int, height: int, band_pixels: int = 1 << 21) -> Path:
    """The zoo scene's workspace at this size; its photograph rendered a band of rows at a time,
    each in a fresh process (Dr.Jit aborted on the 20th band of one process, "unknown variable")."""
    from reflab.core.images import write_image
    from reflab.hardware.sim.lab import write_lab
    from reflab.hardware.sim.zoo import random_scene
    from reflab.inverse.forward.trees import tile_rows

    shutil.rmtree(root, ignore_errors=True)
    zoo = random_scene(SEED, width, height, noise=NOISE)
    write_lab(root, zoo, materials=False)
    image = np.empty((height, width, 3))
    band = root / "band.npy"
    for r0, r1 in tile_rows(height, width, band_pixels):
        subprocess.run([sys.executable, __file__, "--render-band", str(width), str(height), str(r0), str(r1), str(band)],
                       check=True, env=dict(os.environ))
        image[r0:r1] = np.load(band)
    band.unlink()
    image += np.random.default_rng([35, SEED, 1]).normal(0.0, NOISE * image.max(), image.shape)
    write_image(root / "input.exr", image)
    return root


def run_stage(args: list, log: Path) -> dict:
    """``python -m reflab.app.cli ARGS`` in a fresh process: exit status, wall seconds, peak RSS."""
    t0 = time.perf_counter()
    with open(log, "a") as out:
        proc = subprocess.Popen([sys.executable, "-m", "reflab.app.cli", *args], stdout=out, stderr=subprocess.STDOUT,
                                env=dict(os.environ))
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {"rc": proc.returncode, "wall_s": round(time.perf_counter() - t0, 2),
            "peak_gb": round(usage.ru_maxrss / 2**20, 2),  # ru_maxrss is in KB on Linux
            "load_after": round(os.getloadavg()[0], 1)}  # 1-minute load average when it ended (a shared machine)


def coverage(ws: Path, albedo: Path) -> dict:
    """Shares of the pixels seeing a surface (and a textured one) whose albedo the texture knows."""
    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights
    from reflab.core.images import read_exr
    from reflab.core.workspace import Workspace
    from reflab.inverse.forward.trees import build_trees, tile_rows
    from reflab.reconstruction.scene import Scene

    w = Workspace(ws)
    camera, lights, scene = Camera.load(w.camera), Lights.load(w.lights), Scene.load(w.scene)
    known = np.all(np.isfinite(read_exr(albedo)[:, :, :3]), axis=2).ravel()  # NaN: unknown albedo
    surface = np.full(camera.width * camera.height, -1)
    for r0, r1 in tile_rows(camera.height, camera.width, 1 << 20):
        t = build_trees(scene, camera, lights, 1, rows=(r0, r1))  # primary hits only
        surface[t.pixel + r0 * camera.width] = t.surface
    seen = surface >= 0
    textured = np.isin(surface, [i for i, s in enumerate(scene) if s.textured])
    return {"coverage": round(float(known[seen].mean()), 4),
            "coverage_textured": round(float(known[textured].mean()), 4) if textured.any() else None}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--render-band"]:  # a child of write_workspace
        w, h, r0, r1 = (int(v) for v in argv[1:5])
        return render_band(w, h, r0, r1, Path(argv[5]))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1,3", help="megapixels, comma-separated, among " + ", ".join(map(str, SIZES)))
    ap.add_argument("--root", default="/tmp/reflab-megapixels")
    ap.add_argument("--fit-max-mp", type=float, default=30.0,
                    help="largest size (MP) whose fit is run; above it fit.json comes from the 640x480 fit")
    ap.add_argument("--texture-max-mp", type=float, default=12.5,
                    help="largest size (MP) whose texture is run; above it textures/ come from the largest texture "
                         "run before (texel maps do not depend on the photograph's size): render only")
    ap.add_argument("--reuse", action="store_true",
                    help="keep a size's workspace (photograph and fit.json) from an earlier run under --root: "
                         "time only the stages after it (fit too when there is no fit.json)")
    ap.add_argument("--stages", default="texture,render,albedo",
                    help="which of texture, render, albedo to run after the fit (comma-separated)")
    ap.add_argument("--json")
    ap.add_argument("--tile-pixels", type=int, help="the texture's and render's --tile-pixels (default theirs)")
    args = ap.parse_args(argv)
    root = Path(args.root)
    root.mkdir(parents=True, exist_ok=True)
    sizes = [float(s) if "." in s else int(s) for s in args.sizes.split(",")]
    bad = [s for s in sizes if s not in SIZES]
    if bad:
        raise SystemExit(f"--sizes: {bad} not among {list(SIZES)}")
    small = None
    rows = []
    for mp in sizes:
        width, height = SIZES[mp]
        ws = root / f"ws-{width}x{height}"
        log = root / f"{width}x{height}.log"
        log.unlink(missing_ok=True)
        t0 = time.perf_counter()
        reuse = args.reuse and (ws / "input.exr").is_file()
        if not reuse:
            write_workspace(ws, width, height)
        row = {"size": f"{width}x{height}", "megapixels": round(width * height / 1e6, 2),
               "write_s": "reused" if reuse else round(time.perf_counter() - t0, 1)}
        if reuse and (ws / "fit.json").is_file():
            row["fit"] = "not run: fit.json of an earlier run (--reuse)"
        elif width * height / 1e6 <= args.fit_max_mp:
            row["fit"] = run_stage(["fit", str(ws)], log)
        else:
            if small is None:
                small = root / "ws-640x480"
                if not (small / "fit.json").is_file():
                    write_workspace(small, 640, 480)
                    run_stage(["fit", str(small)], root / "640x480.log")
            shutil.copy(small / "fit.json", ws / "fit.json")
            row["fit"] = "not run: fit.json of the 640x480 fit"
        tile = [] if args.tile_pixels is None else ["--tile-pixels", str(args.tile_pixels)]
        wanted = args.stages.split(",")
        stages = [("texture", tile), ("render", tile), ("albedo", ["--aov", "albedo", "-o", str(ws / "albedo.exr"), *tile])]
        stages = [st for st in stages if st[0] in wanted]
        if width * height / 1e6 > args.texture_max_mp and "texture" in wanted:
            done = sorted((p for p in root.glob("ws-*x*") if (p / "textures" / "index.json").is_file() and p != ws
                           and not (p / "textures-from.txt").is_file()), key=lambda p: int(p.name[3:].split("x")[0]))
            if not done:
                raise SystemExit(f"{row['size']}: no texture of a smaller size to render with (run one first)")
            shutil.copytree(done[-1] / "textures", ws / "textures")
            (ws / "textures-from.txt").write_text(f"{done[-1]}\n")  # a copy: not a texture made at this size
            row["texture"] = f"not run: textures/ of the {done[-1].name[3:]} run"
            stages = [st for st in stages if st[0] != "texture"]
        for stage, extra in stages:
            shutil.rmtree(ws / "cache", ignore_errors=True)
            row[stage] = run_stage(["render" if stage == "albedo" else stage, str(ws), *extra], log)
        fit = json.loads((ws / "fit.json").read_text())
        index = json.loads((ws / "textures" / "index.json").read_text())
        if "albedo" in wanted:  # else albedo.exr may be an earlier texture's
            row.update(coverage(ws, ws / "albedo.exr"))
        row.update(fit_status=fit.get("status"),
                   texels_known=index["stats"]["texels_known"], texture_tiles=index.get("tiles", {}).get("count", 1),
                   texture_unknowns=index["stats"]["unknowns"], texture_nonzeros=index["stats"]["nonzeros"],
                   load_average=round(os.getloadavg()[0], 1))
        rows.append(row)
        print(json.dumps(row), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
