"""The geometry section: registered shots (sfm.json), sparse points and the fitted surfaces, their
distances to the points and to the truth, and the top view."""
from __future__ import annotations

import numpy as np

from reflab.app.report import figures as F
from reflab.app.report.data import Sources, as_dict, as_list
from reflab.app.report.sections.camera import pose_centre
from reflab.app.report.sections.section import Section, floats, mm, num


def _meshes(src: Sources, scene_obj: dict, base) -> dict:
    """name -> Mesh for each surface of a scene.json object whose mesh loads (base: folder of the file)."""
    from reflab.reconstruction.scene import Mesh

    out = {}
    for s in as_list(scene_obj.get("surfaces")):
        if not isinstance(s, dict) or not s.get("mesh"):
            continue
        path = base / s["mesh"]
        try:
            out[str(s.get("name"))] = Mesh.load(path)
        except Exception as err:  # noqa: BLE001 - a broken mesh is named, the rest still reported
            src.unreadable[str(path)] = f"{type(err).__name__}: {err}"
    return out


def _sparse_points(src: Sources) -> np.ndarray | None:
    path = src.ws.sparse
    if not path.is_file():
        return None
    try:
        from reflab.core.open3d_env import open3d
        o3d = open3d()

        return np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float64)
    except Exception as err:  # noqa: BLE001
        src.unreadable[str(path)] = f"{type(err).__name__}: {err}"
        return None


def geometry_section(src: Sources) -> Section | None:
    sfm, scene = src.sfm, src.scene
    if sfm is None and scene is None:
        return None
    sec = Section("geometry", "Geometry", "Registered turntable shots (sfm.json), the sparse points (sparse.ply) "
                                          "and the surfaces fitted to them (scene.json, meshes/).")
    if sfm:
        s = as_dict(sfm.get("sfm"))
        tt = as_dict(sfm.get("turntable"))
        rt = as_dict(sfm.get("rigid_turntable"))
        reg = as_dict(sfm.get("registration"))
        ref = as_dict(sfm.get("reference"))
        times = as_dict(s.get("time_s"))
        sec.kv([("shots registered", f"{s.get('registered')} of {s.get('images')}" if "registered" in s else None),
                ("shots not registered", ", ".join(str(n) for n in sfm["images"] if n not in sfm["poses"]) or None
                 if isinstance(sfm.get("images"), list) and isinstance(sfm.get("poses"), dict) else None),
                ("structure from motion reprojection", f"{num(s.get('reprojection_px'))} px" if "reprojection_px" in s else None),
                ("sparse points", s.get("points")),
                ("one turntable axis", (f"{num(rt.get('rms_px'))} px RMS against {num(rt.get('rms_px_free'))} px with free poses"
                                        + ("" if rt.get("used", True) else " (not used: " + str(rt.get("warning", "")) + ")"))
                 if "rms_px" in rt else None),
                ("turntable axis tilt from +z", f"{num(tt.get('axis_tilt_deg'), 3)}°" if "axis_tilt_deg" in tt else None),
                ("shot angle error vs commanded", f"max {num(tt.get('max_angle_error_deg'), 3)}°, RMS {num(tt.get('rms_angle_error_deg'), 3)}°"
                 if "max_angle_error_deg" in tt else None),
                ("registration", f"{reg.get('method')}, scale {num(reg.get('scale'), 5)} m per structure-from-motion unit" if reg else None),
                ("input shot vs camera.json", f"{mm(ref.get('centre_mm'))} mm, {num(ref.get('rotation_deg'), 3)}°" if ref else None),
                ("time", f"{num(sfm.get('time_s'), 3)} s" + (f" (structure from motion {num(times.get('total_s'), 3)} s)" if "total_s" in times else "")
                 if sfm.get("time_s") is not None else None)])
        errs = tt.get("angle_error_deg")
        if isinstance(errs, list) and errs and isinstance(tt.get("angles_deg"), list):
            fig, (ax,) = F.new_figure(6.0, 2.4)
            ang = np.array([a if isinstance(a, (int, float)) else np.nan for a in tt["angles_deg"]], dtype=float)
            err = np.array([e if isinstance(e, (int, float)) else np.nan for e in errs], dtype=float)[: len(ang)]
            ax.plot(ang[: len(err)], err, "o-", ms=3)  # NaN: a gap (shot not registered)
            ax.axhline(0, color="k", lw=0.5)
            ax.set_xlabel("commanded angle (°)", fontsize=8)
            ax.set_ylabel("recovered − commanded (°)", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
            sec.figure(F.figure_uri(fig), "Each shot's turntable angle recovered by structure from motion, against "
                                          "the commanded one (gaps: shots not registered).")
    points = _sparse_points(src) if sfm else None
    meshes = _meshes(src, scene, src.root) if scene else {}
    truth_scene = src.truth("scene")
    true_meshes = _meshes(src, truth_scene, src.truth_dir) if truth_scene else {}
    rows, surf_res = [], _surface_residuals(meshes, points)
    for s in as_list((scene or {}).get("surfaces")):
        if not isinstance(s, dict):
            continue
        name = str(s.get("name"))
        mat = as_dict(s.get("material"))
        r = surf_res.get(name, {})
        row = [name, s.get("source", "–"),  # reconstruct writes how it made the surface (fitted, marked, imported)
               mat.get("brdf", "–"), num(mat.get("ior")) if mat.get("ior") is not None else "opaque",
               "yes" if s.get("textured", True) else "no"]
        if points is not None:
            row += [r.get("n", 0), mm(r.get("rms_mm")), mm(r.get("p90_mm"))]
        if true_meshes:
            d = _placement_error(meshes.get(name), true_meshes.get(name))
            row += [mm(d[0]), mm(d[1])] if d else ["–", "–"]
        rows.append(row)
    head = ["surface", "source", "BRDF", "ior", "textured"]
    head += ["sparse points within 10 mm (nearest surface)", "point → surface RMS (mm)", "90th percentile (mm)"] if points is not None else []
    head += ["distance to the true surface, mean (mm)", "max (mm)"] if true_meshes else []
    sec.table(head, rows, "Points of sparse.ply are assigned to the nearest final surface within 10 mm; the source column's count "
              "is the points the surface was fitted to (the plane fit's inliers), fewer than those near it." if points is not None else "")
    if meshes or points is not None:
        sec.figure(_top_view(src, meshes, true_meshes, points, sfm), "Top view (world x, y in metres): surfaces "
                   "(outlines), sparse points (grey), the registered shots' camera centres (triangles), the input "
                   "camera (star) and the lamps (circles)" + ("; truth dashed." if true_meshes else "."))
    return sec


def _surface_residuals(meshes: dict, points) -> dict:
    if points is None or not len(points) or not meshes:
        return {}
    from reflab.reconstruction.surfaces import distance_to_mesh

    names = list(meshes)
    dist = np.stack([distance_to_mesh(meshes[n], points) for n in names])
    nearest = np.argmin(dist, axis=0)
    d = dist[nearest, np.arange(len(points))]
    out = {}
    for i, n in enumerate(names):
        mine = d[(nearest == i) & (d < 0.01)] * 1e3
        out[n] = {"n": int(len(mine))}
        if len(mine):
            out[n].update(rms_mm=float(np.sqrt(np.mean(mine**2))), p90_mm=float(np.percentile(mine, 90)))
    return out


def _placement_error(mesh, true_mesh):
    """Mean and max distance (mm) from the recovered surface to the true one, and back for a closed
    (bounded) true mesh; an open one (the ground plane) is larger than what any view covers, so only
    the recovered surface's distance to it counts. Measured on vertices and face centres."""
    if mesh is None or true_mesh is None:
        return None
    from reflab.reconstruction.surfaces import distance_to_mesh

    def samples(m):
        return np.concatenate([m.vertices, m.vertices[m.triangles].mean(axis=1)])

    d = distance_to_mesh(true_mesh, samples(mesh))
    if true_mesh.is_closed():
        d = np.concatenate([d, distance_to_mesh(mesh, samples(true_mesh))])
    return float(np.mean(d)) * 1e3, float(np.max(d)) * 1e3


def _footprint(mesh) -> np.ndarray:
    """The convex outline of a mesh seen from above, (N, 2) metres."""
    from scipy.spatial import ConvexHull

    xy = mesh.vertices[:, :2]
    try:
        return xy[ConvexHull(xy).vertices]
    except Exception:  # noqa: BLE001 - degenerate (a vertical sheet seen edge on): its extent as a segment
        i, j = np.argmin(xy[:, 0] + xy[:, 1]), np.argmax(xy[:, 0] + xy[:, 1])
        return xy[[i, j]]


def _top_view(src: Sources, meshes, true_meshes, points, sfm) -> str:
    """Surfaces, sparse points, shots and lamps from above, zoomed on what is smaller than the table."""
    from matplotlib.patches import Polygon

    fig, (ax,) = F.new_figure(7.8, 5.2)  # the legend beside the map
    focus = []  # what the view is zoomed on: everything but surfaces larger than BIG
    big = 0.6
    for i, (name, m) in enumerate(meshes.items()):
        c = F.COLOURS[i % len(F.COLOURS)]
        hull = _footprint(m)
        ax.add_patch(Polygon(hull, closed=True, facecolor=c, alpha=0.3, edgecolor=c, lw=1))
        ax.add_patch(Polygon(hull, closed=True, facecolor="none", edgecolor=c, lw=1))
        if np.ptp(hull, axis=0).max() < big:
            focus.append(hull)
            ax.annotate(name, hull.mean(axis=0), fontsize=8, color="k", ha="center", va="center")
        else:
            ax.plot([], [], "s", color=c, alpha=0.3, label=f"{name} (extends beyond the view)")
        if name in true_meshes:
            ax.add_patch(Polygon(_footprint(true_meshes[name]), closed=True, facecolor="none", edgecolor=c, lw=1, ls="--"))
    if points is not None and len(points):
        ax.plot(points[:, 0], points[:, 1], ".", color="0.35", ms=1.5, label="sparse points")
        focus.append(np.percentile(points[:, :2], [1, 99], axis=0))
    if sfm and isinstance(sfm.get("poses"), dict):
        cs = [c for c in (pose_centre(p) for p in sfm["poses"].values() if isinstance(p, dict)) if c is not None]
        if cs:
            cs = np.array(cs)
            ax.plot(cs[:, 0], cs[:, 1], "^", color="k", ms=4, label="registered shots")
            focus.append(cs[:, :2])
    cam = src.camera
    C = pose_centre(cam) if cam else None
    if C is not None:
        ax.plot(C[0], C[1], "*", color="crimson", ms=12, label="input camera")
        focus.append(C[None, :2])
    for k, l in enumerate(as_list((src.lights or {}).get("lights"))):
        p = floats(l.get("position")) if isinstance(l, dict) else None
        if p is not None and p.shape == (3,):
            ax.plot(p[0], p[1], "o", color="gold", mec="k", ms=9, label="lamps" if k == 0 else None)
            ax.annotate(f"lamp {k}", p[:2], fontsize=8, xytext=(5, 5), textcoords="offset points")
            focus.append(p[None, :2])
    if focus:
        xy = np.concatenate(focus)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        pad = 0.08 * max(float(np.max(hi - lo)), 0.05)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (m)", fontsize=8)
    ax.set_ylabel("y (m)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1), frameon=False)  # beside the map, hiding nothing
    return F.figure_uri(fig)
