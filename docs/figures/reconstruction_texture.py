"""The texture stage on the reconstructed geometry instead of the true one: albedo error, edge texels measured.

    .venv/bin/python docs/figures/reconstruction_texture.py WORKDIR [--grain 0]

WORKDIR is a workspace made by docs/figures/reconstruction_simlab.py (its measured.json says the
lab's size). The geometry is the same whatever the textures; the input photograph is rendered
here by the reference renderer (depth 3) from the lab with ``--grain`` (default 0: the plain
lab, whose textures the texture stage resolves at this size; the 2-8 mm grain that SfM needed
is finer than a texel and would dominate the error with any geometry). Each reconstructed surface gets the true material and ``textured`` flag of
the lab surface it lies nearest to (RMS distance of its area samples); then the trees of the input
view are built (``reflab.inverse.forward.trees.build_trees``, depth 3) and ``reflab.inverse.texture.solve.recover_texture``
runs with the default options. The same is done on the lab's true geometry for comparison.

Every texel centre on a textured surface is compared with the lab's true albedo at the nearest
point of the true surfaces. Texels within 2 texels of an edge of their surface (a boundary or a
crease of its mesh: a box's edges) are reported apart: the dissertation dropped them. "Seen"
texels are those whose bilinear footprint some tree node touches; "unknown" ones are seen but
left out of the solution (coverage below the stage's threshold: the mask). Interior texels are
also split by whether the model's geometry gives the texel the same lamp and camera visibility
as the truth gives the nearest true point ("other shadows": a shadow or outline moved by the
geometric error crosses it).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from reflab.hardware.sim.reference import render_reference  # noqa: E402
from reflab.hardware.sim.lab import build_lab  # noqa: E402
from reflab.core.workspace import read_json, write_json  # noqa: E402
from reflab.inverse.texture.solve import recover_texture  # noqa: E402
from reflab.inverse.forward.trees import build_trees  # noqa: E402
from reflab.reconstruction import surfaces as surf  # noqa: E402
from reflab.reconstruction.scene import Scene, Surface  # noqa: E402

EDGE_TEXELS = 2.0


def feature_edges(mesh, crease_deg: float = 30.0) -> np.ndarray:
    """(E, 2, 3) segments: boundary edges and creases sharper than ``crease_deg``."""
    tri = mesh.triangles
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    owner = np.tile(np.arange(len(tri)), 3)
    uniq, inv, count = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    normals = mesh.face_normals()
    keep = count == 1
    two = np.flatnonzero(count == 2)
    first = np.full(len(uniq), -1)
    second = np.full(len(uniq), -1)
    order = np.argsort(inv, kind="stable")
    starts = np.searchsorted(inv[order], np.arange(len(uniq)))
    first[:] = owner[order[starts]]
    second[two] = owner[order[starts[two] + 1]]
    cos = np.einsum("ij,ij->i", normals[first[two]], normals[second[two]])
    keep[two] = cos < np.cos(np.radians(crease_deg))
    return mesh.vertices[uniq[keep]]


def distance_to_segments(points: np.ndarray, seg: np.ndarray) -> np.ndarray:
    """(N,) distance of each point to the nearest of the segments (E, 2, 3)."""
    a, b = seg[:, 0], seg[:, 1]
    ab = b - a
    t = np.clip(np.einsum("nej,ej->ne", points[:, None] - a[None], ab) / np.maximum((ab**2).sum(1), 1e-300), 0, 1)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None] - closest, axis=2).min(axis=1)


def _raycaster(scene: Scene):
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    ids = {}
    for i, s in enumerate(scene):
        gid = rc.add_triangles(o3d.core.Tensor(s.mesh.vertices.astype(np.float32)),
                               o3d.core.Tensor(s.mesh.triangles.astype(np.uint32)))
        ids[int(gid)] = i
    return rc, ids


def true_albedo(lab, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lab's albedo at the nearest point of its true surfaces, and those points."""
    import open3d as o3d

    rc, ids = _raycaster(lab.scene)
    ans = rc.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    sid = np.array([ids[int(g)] for g in ans["geometry_ids"].numpy()])
    nearest = ans["points"].numpy().astype(np.float64)
    return lab.albedo_at(sid, nearest), nearest


def visibility(scene: Scene, points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(N, T) bool: the segment from each point to each target (lamps, the camera) is unoccluded."""
    import open3d as o3d

    rc, _ = _raycaster(scene)
    out = np.zeros((len(points), len(targets)), dtype=bool)
    for k, target in enumerate(targets):
        d = target - points
        dist = np.linalg.norm(d, axis=1)
        u = d / dist[:, None]
        # Start 0.1 mm off the surface: no self-hit.
        rays = np.concatenate([points + 1e-4 * u, u], axis=1).astype(np.float32)
        out[:, k] = rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy() >= dist - 2e-4
    return out


def with_true_materials(scene: Scene, lab) -> tuple[Scene, dict]:
    """Each reconstructed surface with the material of the lab surface it lies nearest to."""
    out, match = [], {}
    for s in scene:
        pts = s.mesh.sample_points(3000)
        rms = {i: np.sqrt(np.mean(surf.distance_to_mesh(t.mesh, pts) ** 2)) for i, t in enumerate(lab.scene)}
        i = min(rms, key=rms.get)
        match[s.name] = lab.scene[i].name
        out.append(Surface(s.name, s.mesh_path, lab.scene[i].material.copy(), lab.scene[i].textured, s.mesh))
    return Scene(out), match


def evaluate(scene: Scene, lab, image: np.ndarray) -> dict:
    """Run trees + texture on ``scene`` and measure the recovered albedo per texel."""
    t0 = time.perf_counter()
    trees = build_trees(scene, lab.camera, lab.lights, depth=3)
    t1 = time.perf_counter()
    res = recover_texture(scene, trees, [s.material for s in scene], lab.lights.intensities, image)
    t2 = time.perf_counter()
    rows = []
    for s, m in res.maps.items():
        idx, pts = m.texel_centers()
        mesh = scene[s].mesh
        on = surf.distance_to_mesh(mesh, pts) < 0.25 * m.texel_size
        idx, pts = idx[on], pts[on]
        nodes = np.flatnonzero(trees.surface == s)
        tidx, tw = m.bilinear(trees.triangle[nodes], trees.barycentric[nodes])
        touched = np.zeros(m.n_texels, dtype=bool)
        touched[tidx[tw > 0]] = True
        seen = touched[idx]
        known = res.mask[s].ravel()[idx]
        edge = distance_to_segments(pts, feature_edges(mesh)) < EDGE_TEXELS * m.texel_size
        truth, nearest = true_albedo(lab, pts)
        err = res.kd[s].reshape(-1, 3)[idx] - truth
        # Shadows and occlusions of the model against the truth's, seen from the texel.
        targets = np.concatenate([lab.lights.positions, lab.camera.center[None]])
        agree = np.all(visibility(scene, pts, targets) == visibility(lab.scene, nearest, targets), axis=1)
        rows.append(dict(surface=scene[s].name, texel_mm=1e3 * m.texel_size, seen=seen, known=known, edge=edge,
                         err=err, agree=agree))

    def summary(sel_rows):
        seen = np.concatenate([r["seen"] for r in sel_rows])
        known = np.concatenate([r["known"] for r in sel_rows])
        edge = np.concatenate([r["edge"] for r in sel_rows])
        err = np.concatenate([r["err"] for r in sel_rows])
        agree = np.concatenate([r["agree"] for r in sel_rows])
        out = {}
        for part, sel in (("interior", ~edge), ("edge", edge), ("interior, same shadows", ~edge & agree),
                          ("interior, other shadows", ~edge & ~agree)):
            k = sel & known
            out[part] = {"seen": int((sel & seen).sum()), "known": int(k.sum()),
                         "unknown_fraction_of_seen": float(1 - k.sum() / max((sel & seen).sum(), 1)),
                         "rmse": float(np.sqrt(np.mean(err[k] ** 2))) if k.any() else None,
                         "median_abs": float(np.median(np.abs(err[k]).max(axis=1))) if k.any() else None,
                         "within_0.02": float(np.mean(np.abs(err[k]).max(axis=1) < 0.02)) if k.any() else None,
                         "p95_abs": float(np.percentile(np.abs(err[k]).max(axis=1), 95)) if k.any() else None}
        return out

    report = {"all": summary(rows), "surfaces": {r["surface"]: dict(summary([r]), texel_mm=r["texel_mm"]) for r in rows},
              "trees_s": t1 - t0, "texture_s": t2 - t1, "nodes": int(len(trees))}
    return report


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir", type=Path)
    ap.add_argument("--grain", type=float, default=0.0, help="print grain of the photographed lab (0 = none)")
    args = ap.parse_args(argv)
    root = args.workdir
    w, h = read_json(root / "measured.json")["size"]
    lab = build_lab(w, h, grain=args.grain)
    image = render_reference(lab.scene, lab.camera, lab.lights, depth=3, albedo=lab.albedo)
    recon, match = with_true_materials(Scene.load(root / "scene.json"), lab)
    out = {"grain": args.grain, "size": [w, h], "match": match, "true_geometry": evaluate(lab.scene, lab, image),
           "reconstructed_geometry": evaluate(recon, lab, image)}
    write_json(root / f"texture_measured_grain{args.grain:g}.json", out)
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
