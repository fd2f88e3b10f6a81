"""Timings of the forward model: tree building and re-rendering at three image sizes.

Run ``python -m reflab.inverse.forward.benchmarks WORKSPACE``: it times that workspace's scene (camera.json,
lights.json, scene.json) and prints a Markdown table and the machine it ran on. The table of
docs/forward-model.md times the simulated lab: ``python docs/figures/forward_benchmark.py``
(product code does not import the simulated twin; that script hands its scene to :func:`run`).
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

SIZES = ((160, 120), (320, 240), (640, 480))


def machine() -> str:
    """One line naming the CPU, core count and library versions."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    from reflab.core.open3d_env import open3d

    return (f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"numpy {np.__version__}, open3d {open3d().__version__}")


def load_scene(workspace):
    """(scene, camera, lights) of a workspace."""
    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights
    from reflab.core.workspace import Workspace
    from reflab.reconstruction.scene import Scene

    ws = Workspace(workspace)
    return Scene.load(ws.scene), Camera.load(ws.camera), Lights.load(ws.lights)


def _time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def run(scene, camera, lights, sizes=SIZES, depth: int = 3, repeats: int = 3) -> list[dict]:
    """Median seconds of each step at each size.

    Returns
    -------
    list of dict
        Per size: ``size``, ``nodes``, ``rays`` (all kinds), ``build_s`` (:func:`build_trees`),
        ``basis_grad_s`` (:func:`linear_basis_and_grad`), ``render_s`` (:func:`render` from
        scratch), ``rerender_s`` (:func:`render` with a precomputed basis: new linear parameters).
    """
    from reflab.inverse.forward.rendering import linear_basis, linear_basis_and_grad, render
    from reflab.inverse.forward.trees import build_trees

    materials = [s.material for s in scene.surfaces]
    intens = lights.intensities
    rows = []
    for w, h in sizes:
        cam = camera.scaled(w, h)
        build_trees(scene, cam, lights, depth)  # warm-up: Embree's BVH build, caches
        build_s, trees = _time(lambda: build_trees(scene, cam, lights, depth), repeats)
        basis = linear_basis(trees, materials, intens)
        rows.append(dict(
            size=f"{w}x{h}", nodes=len(trees), rays=int(sum(trees.stats["rays"].values())), build_s=build_s,
            basis_grad_s=_time(lambda: linear_basis_and_grad(trees, materials, intens), repeats)[0],
            render_s=_time(lambda: render(trees, materials, intens), repeats)[0],
            rerender_s=_time(lambda: render(trees, materials, intens, basis=basis), repeats)[0],
        ))
    return rows


def table(rows: list[dict]) -> str:
    """The rows of :func:`run` as a Markdown table."""
    out = ["| size | nodes | rays cast | build trees (s) | basis + gradient (s) | render (s) | re-render, basis kept (s) |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['size']} | {r['nodes']} | {r['rays']} | {r['build_s']:.3f} | {r['basis_grad_s']:.3f} "
                   f"| {r['render_s']:.3f} | {r['rerender_s']:.3f} |")
    return "\n".join(out)


def compare_ray_casters(scene, camera, repeats: int = 3) -> dict:
    """Seconds per million primary rays: Open3D RaycastingScene against Mitsuba's ray_intersect.

    The rays are the camera's pixel rays; both casters get the same triangles.
    """
    from reflab.core.open3d_env import open3d
    o3d = open3d()

    from reflab.core.mitsuba_env import mitsuba

    origin, direction = camera.pixel_rays()
    rays = np.concatenate([origin, direction], axis=1).astype(np.float32)
    rc = o3d.t.geometry.RaycastingScene()
    for s in scene.surfaces:
        rc.add_triangles(o3d.core.Tensor(s.mesh.vertices.astype(np.float32)), o3d.core.Tensor(s.mesh.triangles.astype(np.uint32)))
    o3d_s, _ = _time(lambda: rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy(), repeats)

    mi = mitsuba()
    import drjit as dr

    shapes = {}
    for i, s in enumerate(scene.surfaces):
        mesh = mi.Mesh(f"s{i}", len(s.mesh.vertices), len(s.mesh.triangles))
        params = mi.traverse(mesh)
        params["vertex_positions"] = dr.ravel(mi.Point3f(*s.mesh.vertices.T.astype(np.float32)))
        params["faces"] = dr.ravel(mi.Vector3u(*s.mesh.triangles.T.astype(np.uint32)))
        params.update()
        shapes[f"s{i}"] = mesh
    mscene = mi.load_dict({"type": "scene", **shapes})
    ray = mi.Ray3f(mi.Point3f(*origin.T.astype(np.float32)), mi.Vector3f(*direction.T.astype(np.float32)))

    def cast():
        si = mscene.ray_intersect(ray)
        return np.asarray(si.t)

    cast()  # JIT compilation
    mi_s, _ = _time(cast, repeats)
    per_m = 1e6 / len(rays)
    return {"rays": len(rays), "open3d_s_per_Mray": o3d_s * per_m, "mitsuba_s_per_Mray": mi_s * per_m,
            "mitsuba_variant": mi.variant()}


def main(argv=None, scene=None, name: str = "") -> int:
    """The command line; ``scene`` = (scene, camera, lights) given by a caller replaces WORKSPACE."""
    parser = argparse.ArgumentParser(prog="python -m reflab.inverse.forward.benchmarks", description=__doc__.splitlines()[0])
    parser.add_argument("workspace", nargs="?" if scene is not None else None, help="workspace folder")
    parser.add_argument("--depth", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--casters", action="store_true", help="also compare Open3D and Mitsuba ray casting")
    args = parser.parse_args(argv)
    scene, camera, lights = scene if scene is not None else load_scene(args.workspace)
    print(f"machine: {machine()}")
    print(f"scene: {name or args.workspace}, {len(scene.surfaces)} surfaces, {len(lights)} lights, depth {args.depth}\n")
    print(table(run(scene, camera, lights, depth=args.depth, repeats=args.repeats)))
    if args.casters:
        print("\n", compare_ray_casters(scene, camera.scaled(640, 480)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
