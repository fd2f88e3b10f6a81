"""One function per report section: what a stage wrote, its errors, and (simulated lab) the truth.

Each ``*_section(src, ...)`` returns a :class:`Section` (None when its stage left nothing). Fields
are read defensively: a value that is present is shown, a missing one is skipped, so files from
older or newer versions of a stage still report. Where ``truth/`` exists (INTERFACES.md, "The
simulated lab's truth") each section adds the error against it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from app.report import figures as F
from app.report.data import Sources, as_dict, as_list

#: fit.json's method, as the docs name it.
METHOD_NAMES = {"ftbo": "F-TBO", "nftbo": "NF-TBO"}
#: The photometric parameters shown per surface, in this order.
MATERIAL_KEYS = ("kd", "ks", "ns", "alpha", "sigma", "r", "t", "ior")


@dataclass
class Section:
    """A report section: an id (an anchor), a title, a one-line lead and its blocks in order."""

    id: str
    title: str
    lead: str = ""
    blocks: list = field(default_factory=list)

    def kv(self, rows, caption: str = "") -> None:
        rows = [(k, v) for k, v in rows if v not in (None, "", [])]
        if rows:
            self.blocks.append({"kind": "kv", "rows": rows, "caption": caption})

    def table(self, head, rows, caption: str = "") -> None:
        if rows:
            self.blocks.append({"kind": "table", "head": list(head), "rows": rows, "caption": caption})

    def figure(self, src: str | None, caption: str, id: str | None = None) -> None:
        if src:
            self.blocks.append({"kind": "figure", "src": src, "caption": caption, "id": id})

    def images(self, items, caption: str = "") -> None:
        """A row of pictures: (src, caption) for images shown pixel for pixel, (src, caption, True) for plots."""
        items = [{"src": it[0], "caption": it[1], "plot": len(it) > 2 and it[2]} for it in items if it[0]]
        if items:
            self.blocks.append({"kind": "images", "items": items, "caption": caption})

    def note(self, text: str, level: str = "info") -> None:
        self.blocks.append({"kind": "note", "text": text, "level": level})


# ---------------------------------------------------------------------- formatting
def num(x, digits: int = 4) -> str:
    """A number or a list of numbers, ``digits`` significant; '–' for None/NaN."""
    if isinstance(x, (list, tuple)):
        return "[" + ", ".join(num(v, digits) for v in x) + "]"
    if isinstance(x, bool) or x is None:
        return "–" if x is None else str(x)
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    if isinstance(x, (float, np.floating)):
        return "–" if not math.isfinite(x) else f"{x:.{digits}g}"
    return str(x)


def mm(x) -> str:
    """A length in millimetres, to the micrometre."""
    return f"{x:.3f}" if isinstance(x, (int, float)) and math.isfinite(x) else "–"


def pm(value, sigma, digits: int = 4) -> str:
    """'value ± sigma' (per band for lists); the value alone where σ is unknown."""
    if sigma is None or (isinstance(sigma, list) and all(s is None for s in sigma)):
        return num(value, digits)
    if isinstance(value, list) and isinstance(sigma, list):
        return "[" + ", ".join(pm(v, s, digits) for v, s in zip(value, sigma)) + "]"
    if isinstance(value, (int, float)) and isinstance(sigma, (int, float)):
        return f"{num(value, digits)} ± {num(sigma, 2)}"
    return num(value, digits)


def _floats(x) -> np.ndarray | None:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return a if a.size and np.all(np.isfinite(a)) else None


def _pose_centre(obj) -> np.ndarray | None:
    """Camera centre −Rᵀt of a {"R", "t"} object, None when malformed."""
    R, t = _floats(obj.get("R")), _floats(obj.get("t"))
    if R is None or t is None or R.shape != (3, 3) or t.shape != (3,):
        return None
    return -R.T @ t


def _rotation_deg(Ra, Rb) -> float:
    c = (np.trace(np.asarray(Ra) @ np.asarray(Rb).T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def psnr(image: np.ndarray, truth: np.ndarray, known: np.ndarray | None = None) -> float:
    """PSNR (dB) of ``image`` against ``truth`` over the pixels ``known`` (all by default), the peak
    being the truth's maximum (as the demo scores it)."""
    err = np.asarray(image, dtype=np.float64) - truth
    err = err if known is None else err[known]
    mse = float(np.mean(err ** 2)) if err.size else float("nan")
    return float("inf") if mse == 0 else 10 * math.log10(max(float(np.max(truth)), 1e-300) ** 2 / mse)


def _when(stamp) -> str:
    """An ISO 8601 UTC time as 'YYYY-MM-DD HH:MM:SS' (as written when it does not parse)."""
    import datetime

    if not isinstance(stamp, str):
        return "–"
    try:
        t = datetime.datetime.fromisoformat(stamp)
    except ValueError:
        return stamp
    if t.tzinfo is not None:
        t = t.astimezone(datetime.timezone.utc)
    return t.strftime("%Y-%m-%d %H:%M:%S")


# ---------------------------------------------------------------------- captures
def captures_section(src: Sources, thumbs: int = 6) -> Section | None:
    manifests = src.manifests()
    if not manifests:
        return None
    sec = Section("captures", "Captures", "What was photographed, when, and with which exposure (captures/*/manifest.json).")
    rows = []
    for folder, m in manifests.items():
        shots = [s for s in as_list(m.get("shots")) if isinstance(s, dict)]
        exposures = sorted({s.get("exposure") for s in shots if s.get("exposure") is not None})
        sizes = sorted({"x".join(map(str, s.get("size"))) for s in shots if isinstance(s.get("size"), list)})
        cam = as_dict(m.get("camera"))
        rows.append([folder, m.get("kind", folder), m.get("status", "–"), f"{len(shots)} of {len(m['plan']) if isinstance(m.get('plan'), list) else '?'}",
                     _when(m.get("started")), _when(m.get("updated")),
                     ", ".join(num(e) for e in exposures) or "camera's own", ", ".join(sizes) or "–",
                     cam.get("type", "–")])
        if m.get("error"):
            sec.note(f"captures/{folder}: {m['error']}", "bad" if m.get("status") == "stopped" else "warn")
    sec.table(["folder", "kind", "status", "shots", "started (UTC)", "last written", "exposure (s)", "size", "camera"],
              rows)
    for folder, m in manifests.items():
        shots = [s for s in as_list(m.get("shots")) if isinstance(s, dict) and s.get("file")]
        if not shots:
            continue
        pick = [shots[i] for i in sorted(set(np.linspace(0, len(shots) - 1, min(thumbs, len(shots))).round().astype(int)))]
        items = []
        for s in pick:
            img = src.image(f"captures/{folder}/{s['file']}")
            if img is None:
                continue
            lamps = s.get("lamps")
            on = "" if not isinstance(lamps, list) else " lamps " + (",".join(str(k) for k, v in enumerate(lamps) if v) or "off")
            angle = f" {num(s.get('angle'), 4)}°" if isinstance(s.get("angle"), (int, float)) else ""
            items.append((F.thumb(F.display(img), 200, 150), f"{s['file']}{angle}{on}"))
        sec.images(items, f"captures/{folder}: {len(pick)} of {len(shots)} shots")
    return sec


# ---------------------------------------------------------------------- camera
CAMERA_KEYS = ("fx", "fy", "cx", "cy", "k1", "k2")


def _camera_values(cam: dict) -> dict:
    K, d = _floats(cam.get("K")), _floats(cam.get("dist"))
    out = {}
    if K is not None and K.shape == (3, 3):
        out.update(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
    if d is not None and d.size >= 2:
        out.update(k1=d[0], k2=d[1])
    return out


def camera_section(src: Sources) -> Section | None:
    cam = src.camera
    if cam is None:
        return None
    cal = as_dict(cam.get("calibration"))
    sec = Section("camera", "Camera", "camera.json: intrinsics with one-sigma uncertainties, per-view reprojection "
                                      "error, and the pose of the input view.")
    truth = src.truth("camera.json")
    ours, sig = _camera_values(cam), as_dict(cal.get("sigma"))
    tv = _camera_values(truth) if truth else {}
    cc = as_dict(cal.get("opencv_crosscheck"))
    head = ["parameter", "value ± σ"] + (["OpenCV calibrateCamera"] if cc else []) + (["truth", "error", "error / σ"] if tv else [])
    rows = []
    for k in CAMERA_KEYS:
        if k not in ours:
            continue
        s = sig.get(k)
        row = [k, pm(float(ours[k]), s, 6)]
        if cc:
            row.append(num(cc.get(k), 6))
        if tv:
            err = ours[k] - tv[k] if k in tv else None
            row += [num(tv.get(k), 6), num(err, 3),
                    num(err / s, 2) if err is not None and isinstance(s, (int, float)) and s > 0 else "–"]
        rows.append(row)
    sec.table(head, rows, "fx, fy, cx, cy in pixels (pixel (0, 0) is the centre of the top-left pixel); "
                          "k1, k2 OpenCV radial distortion")
    sec.kv([("image size", f"{cam.get('width')} × {cam.get('height')} px"),
            ("reprojection RMS", f"{num(cal.get('rms_px'))} px" if cal.get("rms_px") is not None else None),
            ("views used", len(as_list(cal.get("views"))) or None),
            ("views skipped (no grid found)", ", ".join(as_list(cal.get("skipped"))) or None),
            ("target", f"{cal['grid'][0]}×{cal['grid'][1]} circles, spacing {num(cal.get('spacing'))} m"
             if isinstance(cal.get("grid"), list) and len(cal["grid"]) == 2 else None),
            ("estimated circle radius", f"{num(1e3 * cal['circle_radius_m'])} mm"
             if isinstance(cal.get("circle_radius_m"), (int, float)) else None),
            ("ellipse-centre bias correction", cal.get("bias_correction")),
            ("OpenCV cross-check RMS", f"{num(cc.get('rms_px'))} px (uncorrected centres)" if cc.get("rms_px") is not None else None),
            ("Tsai (f in mm, kappa1 in 1/mm²)", ", ".join(f"{k} {pm(v, as_dict(sig.get('tsai')).get(k), 6)}"
                                                      for k, v in as_dict(cam.get("tsai")).items()) or None),
            ("reference view (input pose)", cal.get("reference_image")),
            ("calibration time", f"{num(cal.get('time_s'), 3)} s" if cal.get("time_s") is not None else None)])
    for w in as_list(cal.get("warnings")) if isinstance(cal.get("warnings"), list) else []:
        sec.note(str(w), "warn")
    if not cal:
        sec.note("camera.json has no calibration block (written by hand or by another tool): no uncertainties, "
                 "per-view errors or residuals to show.")
    rejected = [v for v in as_list(cal.get("rejected")) if isinstance(v, dict)]
    if rejected:
        sec.note("views left out (reprojecting far worse than the others): "
                 + ", ".join(f"{v.get('image')} ({num(v.get('rms_px'), 3)} px)" for v in rejected), "warn")
    views = [v for v in as_list(cal.get("views")) if isinstance(v, dict)]
    if views:
        labels = [str(v.get("image", i)).rsplit("/", 1)[-1] for i, v in enumerate(views)]
        sec.figure(F.bars(labels, {"RMS": [v.get("rms_px") for v in views], "worst": [v.get("worst_px") for v in views]},
                          "reprojection error (px)", "per view"),
                   "Reprojection error of each calibration view: RMS and worst circle centre.")
    residuals = cal.get("residuals_px")
    if isinstance(residuals, list) and residuals:
        sec.figure(_residual_field(residuals, cam, views), "Residual vectors (measured centre → model), magnified; "
                   "one colour per view. A pattern (a swirl, a radial trend) means a model error; noise looks random.")
    elif cal:
        sec.note("camera.json holds no per-circle residuals (calibrated by an older version): the residual vector "
                 "field is not shown; rerun `reflab calibrate camera` to get it.")
    if truth:
        C, Ct = _pose_centre(cam), _pose_centre(truth)
        if C is not None and Ct is not None:
            sec.kv([("input view centre error", f"{mm(1e3 * float(np.linalg.norm(C - Ct)))} mm"),
                    ("input view rotation error", f"{num(_rotation_deg(cam['R'], truth['R']), 3)}°")], "against truth/camera.json")
    return sec


def _residual_field(residuals, cam, views) -> str | None:
    """Quiver plot of per-circle residuals over the image frame (rows [u, v, du, dv] per view)."""
    fig, (ax,) = F.new_figure(6.0, 6.0 * (cam.get("height") or 3) / max(cam.get("width") or 4, 1))
    lengths = []
    for i, rows in enumerate(residuals):
        a = _floats(rows)
        if a is None or a.ndim != 2 or a.shape[1] != 4:
            continue
        lengths.append(np.hypot(a[:, 2], a[:, 3]))
    if not lengths or not np.concatenate(lengths).max() > 0:
        return None
    biggest = float(np.concatenate(lengths).max())
    typical = float(np.percentile(np.concatenate(lengths), 95)) or biggest
    scale = 0.04 * (cam.get("width") or 640) / typical  # the 95th percentile drawn 4 % of the width long
    # residuals_px holds one list per view of calibration.views, in the same order.
    names = [str(v.get("image", i)).rsplit("/", 1)[-1] for i, v in enumerate(views)] if len(views) == len(residuals) else None
    for i, rows in enumerate(residuals):
        a = _floats(rows)
        if a is None or a.ndim != 2 or a.shape[1] != 4:
            continue
        ax.quiver(a[:, 0], a[:, 1], a[:, 2] * scale, a[:, 3] * scale, angles="xy", scale_units="xy", scale=1,
                  color=F.COLOURS[i % len(F.COLOURS)], width=0.003, label=names[i] if names else f"view {i}")
    ax.set_xlim(0, cam.get("width") or 1)
    ax.set_ylim(cam.get("height") or 1, 0)
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)", fontsize=8)
    ax.set_ylabel("v (px)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_title(f"residuals × {num(scale, 3)} (95 % under {num(typical, 3)} px, longest {num(biggest, 3)} px)", fontsize=9)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1), frameon=False, title="view", title_fontsize=7)
    return F.figure_uri(fig)


# ---------------------------------------------------------------------- lights
def lights_section(src: Sources) -> Section | None:
    lights = src.lights
    if lights is None:
        return None
    items = [l for l in as_list(lights.get("lights")) if isinstance(l, dict)]
    sec = Section("lights", "Lights", "lights.json: point lamps located from rod shadows (marks.json), with "
                                      "one-sigma uncertainties.")
    truth = src.truth("lights.json")
    true_items = [l for l in as_list((truth or {}).get("lights")) if isinstance(l, dict)]
    rows = []
    for k, l in enumerate(items):
        pos = _floats(l.get("position"))
        cov = _floats(l.get("sigma_position"))
        sd = np.sqrt(np.clip(np.diag(cov), 0, None)) * 1e3 if cov is not None and cov.shape == (3, 3) else None
        cal = as_dict(l.get("calibration"))
        row = [k, num(pos.tolist() if pos is not None else None, 5), num(sd.tolist(), 2) if sd is not None else "–",
               num(l.get("intensity"), 4), num(cal.get("mark_sigma_px"), 3), num(cal.get("outliers") or "none")]
        if true_items:
            tp = _floats(true_items[k].get("position")) if k < len(true_items) else None
            err = float(np.linalg.norm(pos - tp)) * 1e3 if pos is not None and tp is not None else None
            ti = _floats(true_items[k].get("intensity")) if k < len(true_items) else None
            li = _floats(l.get("intensity"))
            ierr = (100 * float(np.max(np.abs(li / ti - 1))) if li is not None and ti is not None and li.shape == ti.shape
                    and np.all(ti > 0) else None)
            row += [num(tp.tolist() if tp is not None else None, 5), mm(err),
                    num(err / float(np.linalg.norm(sd)), 2) if err is not None and sd is not None and np.linalg.norm(sd) > 0 else "–",
                    f"{ierr:.1f}" if ierr is not None else "–"]
        rows.append(row)
    head = ["lamp", "position (m)", "σ x, y, z (mm)", "intensity", "mark σ (px)", "outlier marks"]
    sec.table(head + (["truth (m)", "error (mm)", "error / |σ|", "intensity error (%, worst band)"] if true_items else []), rows)
    if not any(isinstance(l.get("calibration"), dict) for l in items):
        sec.note("lights.json has no calibration blocks (written by hand or by another tool): no mark residuals.")
    marks = src.marks
    if marks and isinstance(marks.get("marks"), list):
        fig = _marks_figure(src, marks, items)
        sec.figure(fig, "Rod marks: the rod's foot (dot) and its shadow's tip (cross) in the camera image (behind: the "
                        "first marked image), one colour per lamp (left); each mark's reprojection error after the lamp "
                        "fit (right).")
        sec.kv([("rod height", f"{num(marks.get('rod_height'))} m"), ("marks", len(marks["marks"]))])
    return sec


def _marks_figure(src: Sources, marks: dict, items: list) -> str | None:
    cam = src.camera or {}
    fig, (ax, bx) = F.new_figure(10.0, 3.8, ncols=2)
    ms = [m for m in marks["marks"] if isinstance(m, dict)]
    backdrop = next((img for img in (src.image(m["image"]) for m in ms[:1] if isinstance(m.get("image"), str))
                     if img is not None), None)
    if backdrop is not None:
        h, w = backdrop.shape[:2]
        ax.imshow(F.display(backdrop), extent=(-0.5, w - 0.5, h - 0.5, -0.5), alpha=0.6)
    for m in ms:
        b, t = _floats(m.get("base")), _floats(m.get("tip"))
        if b is None or t is None:
            continue
        c = F.COLOURS[int(m.get("light", 0)) % len(F.COLOURS)]
        ax.plot([b[0], t[0]], [b[1], t[1]], "-", color=c, lw=1)
        ax.plot(b[0], b[1], "o", color=c, ms=3)
        ax.plot(t[0], t[1], "x", color=c, ms=4)
    if cam.get("width") and cam.get("height"):
        ax.set_xlim(0, cam["width"])
        ax.set_ylim(cam["height"], 0)
    else:
        ax.invert_yaxis()
    ax.set_aspect("equal")
    ax.set_title("marks in the image (px)", fontsize=9)
    ax.tick_params(labelsize=7)
    x0, ticks, names = 0, [], []
    for k, l in enumerate(items):
        errs = _floats((l.get("calibration") or {}).get("mark_errors_px"))
        if errs is None:
            continue
        errs = errs.reshape(len(errs), -1)  # one row per mark of this lamp: foot, tip
        x = np.arange(len(errs)) + x0
        for j, name in enumerate(["foot", "tip"][: errs.shape[1]]):
            bx.bar(x + (j - 0.5) * 0.4, errs[:, j], 0.4, color=F.COLOURS[k % len(F.COLOURS)],
                   alpha=1.0 if j else 0.5, label=f"lamp {k} {name}")
        # Each mark named by its image (marks.json lists a lamp's marks in the order of its errors).
        images = [str(m.get("image", "")).rsplit("/", 1)[-1].rsplit(".", 1)[0] for m in ms if m.get("light") == k]
        ticks += x.tolist()
        names += images if len(images) == len(errs) else [str(i) for i in range(len(errs))]
        x0 += len(errs) + 1
    if x0:
        bx.set_xticks(ticks, names, rotation=90 if len(ticks) > 12 else 0, fontsize=7)
        bx.set_ylabel("reprojection error (px)", fontsize=8)
        bx.set_xlabel("mark (its image)", fontsize=8)
        bx.legend(fontsize=7)
        bx.tick_params(labelsize=7)
        bx.grid(axis="y", alpha=0.3)
    else:
        bx.set_visible(False)
    return F.figure_uri(fig)


# ---------------------------------------------------------------------- geometry
def _meshes(src: Sources, scene_obj: dict, base) -> dict:
    """name -> Mesh for each surface of a scene.json object whose mesh loads (base: folder of the file)."""
    from reconstruction.scene import Mesh

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
    path = src.path("sparse.ply")
    if not path.is_file():
        return None
    try:
        import open3d as o3d

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
                ("registration", f"{reg.get('method')}, scale {num(reg.get('scale'), 5)}" if reg else None),
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
    truth_scene = src.truth("scene.json")
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
    head += ["sparse points on it", "point → surface RMS (mm)", "90th percentile (mm)"] if points is not None else []
    head += ["distance to the true surface, mean (mm)", "max (mm)"] if true_meshes else []
    sec.table(head, rows, "Points are assigned to the nearest surface within 10 mm." if points is not None else "")
    if meshes or points is not None:
        sec.figure(_top_view(src, meshes, true_meshes, points, sfm), "Top view (world x, y in metres): surfaces "
                   "(outlines), sparse points (grey), the registered shots' camera centres (triangles), the input "
                   "camera (star) and the lamps (circles)" + ("; truth dashed." if true_meshes else "."))
    return sec


def _surface_residuals(meshes: dict, points) -> dict:
    if points is None or not len(points) or not meshes:
        return {}
    from reconstruction.surfaces import distance_to_mesh

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
    from reconstruction.surfaces import distance_to_mesh

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
        cs = [c for c in (_pose_centre(p) for p in sfm["poses"].values() if isinstance(p, dict)) if c is not None]
        if cs:
            cs = np.array(cs)
            ax.plot(cs[:, 0], cs[:, 1], "^", color="k", ms=4, label="registered shots")
            focus.append(cs[:, :2])
    cam = src.camera
    C = _pose_centre(cam) if cam else None
    if C is not None:
        ax.plot(C[0], C[1], "*", color="crimson", ms=12, label="input camera")
        focus.append(C[None, :2])
    for k, l in enumerate(as_list((src.lights or {}).get("lights"))):
        p = _floats(l.get("position")) if isinstance(l, dict) else None
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


# ---------------------------------------------------------------------- fit
def fit_section(src: Sources, model: dict | None) -> Section | None:
    fit = src.fit
    if fit is None:
        return None
    sec = Section("fit", "Fit", "fit.json: the non-Lambertian parameters fitted to the input photograph, their "
                                "uncertainties, and how well the model explains the image.")
    status = fit.get("status")
    if status:
        sec.note(f"status: {status}" + (f" — {fit['message']}" if fit.get("message") else ""),
                 "good" if status == "ok" else "bad" if status == "poor fit" else "warn")
    for w in as_list(fit.get("warnings")):
        sec.note(str(w), "warn")
    image = as_dict(fit.get("image"))
    sec.kv([("method", _method(fit)), ("depth", fit.get("depth")),
            ("image", f"{image.get('file')} {image.get('width')} × {image.get('height')}, {image.get('saturated_pixels')} saturated pixels masked"
             if image else None),
            ("RMS residual per band", num(fit.get("rms"))), ("image noise σ per band", num(fit.get("noise"))),
            ("outlier pixels left out of the fit", _rejected_text(fit.get("rejected"))),
            ("iterations / evaluations", f"{fit.get('iterations')} / {fit.get('evaluations')}" if "iterations" in fit else None),
            ("fit time", f"{num(fit.get('time_s'), 3)} s" if fit.get("time_s") is not None else None),
            ("set-up", ", ".join(f"{k} {num(v, 3)} s" for k, v in fit["setup_s"].items()) if isinstance(fit.get("setup_s"), dict) else None)])
    phases = {k: v for k, v in (fit.get("phases_s") or {}).items() if isinstance(v, (int, float)) and v > 0} \
        if isinstance(fit.get("phases_s"), dict) else {}
    if phases:
        sec.figure(_phases_figure(phases), "Where the fit's time went (fit.json phases_s), in the order they run; "
                   "the error-vs-time plot below shows the error over the same seconds.")
    truth, truth_file = src.truth_materials()
    items = [s for s in as_list(fit.get("surfaces")) if isinstance(s, dict)]
    keys = [k for k in MATERIAL_KEYS if any(isinstance(s.get("material"), dict) and s["material"].get(k) is not None
                                             for s in items)]
    rows = []
    for s in items:
        name, mat = str(s.get("name")), as_dict(s.get("material"))
        sig = as_dict(s.get("sigma"))
        und = [str(u) for u in as_list(s.get("undetermined"))]
        bounds = as_dict(s.get("at_bound"))  # {"ks[0]": "upper"}
        true = truth.get(name, {})
        row = [name, mat.get("brdf", "–")]
        for key in keys:
            if mat.get(key) is None:
                row.append("")
                continue
            lines = [pm(mat[key], sig.get(key), 4)]
            held = [u for u in und if u == key or u.startswith(key + "[")]
            if held:
                lines.append("undetermined" + ("" if held == [key] else " " + ", ".join(held)))
            on = [f"{k} {side}" for k, side in bounds.items() if k == key or str(k).startswith(key + "[")]
            if on:
                lines.append("at its bound: " + ", ".join(on))
            if true.get(key) is not None and key != "ior":
                a, b = _floats(mat[key]), _floats(true[key])
                err = (a - b).tolist() if a is not None and b is not None and a.shape == b.shape else None
                lines.append(f"truth {num(true[key])}, error {num(err, 3)}")
            row.append("\n".join(lines))
        rows.append(row)
    sec.table(["surface", "BRDF"] + list(keys), rows,
              "value ± σ (one standard deviation, per band R, G, B where there are three); undetermined: the image "
              "does not fix it: either held at its initial or user-given value (no σ), or fitted with a σ that spans "
              "its plausible range (value and σ shown, docs/fit.md)" + (f"; truth: {truth_file}." if truth else "."))
    if model and model.get("image") is not None:
        _model_images(sec, src, fit, model)
    elif model and model.get("error"):
        sec.note(f"re-render of the model failed: {model['error']}", "bad")
    return sec


def _method(fit: dict):
    """fit.json's method as the docs name it (F-TBO, NF-TBO); another value as written."""
    m = fit.get("method")
    return METHOD_NAMES.get(m, m) if isinstance(m, str) else m


def _phases_figure(phases: dict) -> str:
    fig, (ax,) = F.new_figure(6.0, 0.5 + 0.16 * len(phases))
    left = 0.0
    for i, (name, secs) in enumerate(phases.items()):
        ax.barh(0, secs, left=left, color=F.COLOURS[i % len(F.COLOURS)], label=f"{name} {secs:.2g} s")
        left += secs
    ax.set_yticks([])
    ax.set_xlabel("seconds", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    return F.figure_uri(fig)


def _rejected_text(rejected) -> str | None:
    if not isinstance(rejected, dict) or not rejected.get("count"):
        return None
    return (f"{rejected['count']} (residual above {num(rejected.get('threshold_sigmas'))} σ; cyan in the map below)"
            if rejected.get("threshold_sigmas") is not None else str(rejected["count"]))


def _model_images(sec: Section, src: Sources, fit: dict, model: dict) -> None:
    photo, img = model["photo"], model["image"]
    if photo is None or photo.shape != img.shape:
        sec.images([(F.thumb(F.display(img), 480, 360), "re-rendered model")])
        return
    from inverse.fitting import DIAG_FLOOR, DIAG_SIGMAS

    exposure = 1.0 / max(float(np.percentile(photo, 99.5)), 1e-12)
    diff = np.abs(img - photo).max(axis=2)
    noise = _floats(fit.get("noise"))
    peak = float(photo.max())
    tol = DIAG_SIGMAS * (noise if noise is not None and noise.shape == (3,) else np.zeros(3)) + DIAG_FLOOR * peak
    bad = np.any(np.abs(img - photo) > tol, axis=2)
    overlay = F.display(photo, exposure).copy()
    overlay[bad] = [255, 0, 255]
    rejected = _floats(as_dict(fit.get("rejected")).get("pixels"))
    if rejected is not None and rejected.ndim == 2 and rejected.shape[1] == 2:
        x, y = rejected[:, 0].astype(int), rejected[:, 1].astype(int)
        inside = (x >= 0) & (x < overlay.shape[1]) & (y >= 0) & (y < overlay.shape[0])
        overlay[y[inside], x[inside]] = [0, 255, 255]
    what = "fitted materials with the recovered texture" if model.get("textured") else "fitted materials, homogeneous kd"
    sec.images([(F.thumb(F.display(photo, exposure), 480, 360), "input photograph"),
                (F.thumb(F.display(img, exposure), 480, 360), f"re-rendered model ({what}), same exposure")])
    sec.images([(F.heat_with_bar(diff, "|model − input|, largest band", "linear radiance"), "difference", True),
                (F.thumb(overlay, 480, 360), f"unexplained pixels (magenta): {int(bad.sum())} of {bad.size}, residual "
                                             f"above {DIAG_SIGMAS:g} σ + {DIAG_FLOOR:g} × peak in some band"
                                             + ("; outliers the fit left out in cyan" if rejected is not None else ""))])
    share = float(np.sum((img - photo)[bad] ** 2) / max(np.sum((img - photo) ** 2), 1e-300))
    sec.note(f"Unexplained pixels: the fit's test (docs/fit.md) on this re-render, with σ = fit.json's image noise "
             f"{num(noise.tolist() if noise is not None else None, 3)}; they hold {100 * share:.0f}% of the squared "
             "residual. Unlike the fit's own diagnosis, no allowance is made for texture: the re-render "
             + ("includes the recovered texture." if model.get("textured") else "uses homogeneous albedo, so texture shows."))
    rms = np.sqrt(np.mean((img - photo) ** 2, axis=(0, 1)))
    sec.kv([("model vs input RMS per band", num(rms.tolist())),
            ("relative RMS", f"{num(100 * float(np.sqrt(np.mean((img - photo) ** 2)) / max(np.sqrt(np.mean(photo ** 2)), 1e-300)), 3)} %"),
            ("render time", f"trees {num(model.get('trees_s'), 2)} s, render {num(model.get('render_s'), 2)} s")])


# ---------------------------------------------------------------------- texture
def texture_section(src: Sources, model: dict | None = None, albedo: dict | None = None) -> Section | None:
    idx = src.textures
    if idx is None:
        return None
    sec = Section("texture", "Texture", "textures/: the recovered diffuse albedo of each textured surface, which "
                                        "texels the image determines, and which were amplified.")
    st = as_dict(idx.get("stats"))
    sec.kv([("materials from", idx.get("materials")),
            ("residual RMS per band", num(st.get("residual_rms"))),
            ("equations / unknowns / non-zeros", f"{st.get('rows')} / {st.get('unknowns')} / {st.get('nonzeros')}" if "rows" in st else None),
            ("CG iterations, active-set rounds", f"{st.get('iterations')}, {st.get('active_set_rounds')}" if "iterations" in st else None),
            ("texels known / amplified > 10× / clipped", f"{st.get('texels_known')} / {st.get('texels_amplified')} / {st.get('texels_clipped')}"
             if "texels_known" in st else None),
            ("time", f"{num(st.get('total_s'), 3)} s (maps {num(st.get('maps_s'), 2)}, system {num(st.get('system_s'), 2)}, "
                     f"solve {num(st.get('solve_s'), 2)}; trees {num(idx.get('trees_s'), 2)})" if "total_s" in st else None)])
    rounds = as_dict(as_dict(src.fit).get("texture_rounds")).get("rounds")
    if isinstance(rounds, list) and rounds:
        sec.table(["round", "pixels left out", "RMS per band", "texture (s)", "refit (s)"],
                  [[i + 1, r.get("pixels_left_out"), num(r.get("rms")), num(r.get("texture_s"), 3), num(r.get("fit_s"), 3)]
                   for i, r in enumerate(rounds) if isinstance(r, dict)],
                  "fit.json texture_rounds: the fit refitted against the texture (docs/fit.md).")
    if model and model.get("textured") and model.get("image") is not None:
        sec.note("The texture's residual in the image: the fit section's difference and unexplained-pixel maps, "
                 "whose re-render includes this texture.")
    if src.ws.truth_albedo.is_file():
        _albedo_against_truth(sec, src, albedo)
    elif src.truth_dir.is_dir():
        sec.note(f"{src.rel(src.truth_dir).as_posix()}/ holds no albedo.exr (written before the truth had one): the texture is "
                 "scored through the novel and relit views below (PSNR over the pixels of known albedo).")
    for e in as_list(idx.get("surfaces")):
        if not isinstance(e, dict):
            continue
        name, files = e.get("surface"), as_dict(e.get("files"))
        kd = src.image(f"textures/{files['kd']}") if files.get("kd") else None
        mask = src.image(f"textures/{files['mask']}") if files.get("mask") else None
        diag = src.image(f"textures/{files['diag']}") if files.get("diag") else None
        items = []
        flip = e.get("kind") == "planar"  # rows run along +v: flipped, +v points up as seen from above
        orient = (lambda a: a[::-1]) if flip else (lambda a: a)
        if kd is not None:
            items.append((F.thumb(orient(F.display(kd, 1.0)), 320, 240), "albedo kd (sRGB, 1 = white)"))
        if mask is not None:
            known = mask[:, :, 0] > 0.5
            items.append((F.thumb(orient(np.where(known, 230, 40).astype(np.uint8)), 320, 240), "determined texels (light)"))
        if diag is not None:
            flags = np.nan_to_num(diag[:, :, 2]).astype(np.uint8)
            rgb = np.full(flags.shape + (3,), 235, np.uint8)
            if mask is not None and mask.shape[:2] == flags.shape:
                rgb[mask[:, :, 0] <= 0.5] = 90
            rgb[(flags & 1) > 0] = [220, 30, 30]
            rgb[(flags & 2) > 0] = [30, 90, 220]
            rgb[(flags & 4) > 0] = [230, 180, 0]
            items.append((F.thumb(orient(rgb), 320, 240), "red: amplified > 10×, blue: saturated, yellow: clipped, grey: unknown"))
        size = f"{e.get('width')}×{e.get('height')} texels of {num(1e3 * e['texel_size'], 3)} mm" if isinstance(e.get("texel_size"), (int, float)) else ""
        sec.images(items, f"{name}: {e.get('kind', '')} {size}, {e.get('texels_known')} known, {e.get('texels_amplified')} amplified")
    return sec


#: An albedo error (largest band) at most this counts as right in the texture's comparison with the truth.
ALBEDO_TOLERANCE = 0.05


def _albedo_against_truth(sec: Section, src: Sources, albedo: dict | None) -> None:
    """The recovered albedo at the input view against truth/albedo.exr, pixel for pixel: per surface
    and overall, RMSE per band, mean error and share within :data:`ALBEDO_TOLERANCE`, and the error map."""
    rel = src.rel(src.ws.truth_albedo).as_posix()
    true = src.albedo_image(rel)
    if true is None:
        return  # unreadable: named at the top of the report
    if albedo is None:
        sec.note(f"{rel} holds the true albedo at the input view; the recovered albedo was not rendered "
                 "(--no-render), so it is not compared.")
        return
    if albedo.get("error"):
        sec.note(f"against {rel}: {albedo['error']}", "bad")
        return
    rec, surface = np.asarray(albedo["albedo"], dtype=np.float64), albedo["surface"]
    if rec.shape != true.shape:
        sec.note(f"{rel} is {true.shape[1]}×{true.shape[0]} px, the input view {rec.shape[1]}×{rec.shape[0]}: "
                 "not compared.", "bad")
        return
    seen, known = np.all(np.isfinite(true), axis=2), np.all(np.isfinite(rec), axis=2)
    both = seen & known
    diff = np.where(both[:, :, None], rec - true, np.nan)
    worst = np.max(np.abs(diff), axis=2)  # NaN outside ``both``
    surfaces = as_list(as_dict(src.scene).get("surfaces"))
    textured = {as_dict(e).get("surface") for e in as_list(src.textures.get("surfaces"))}

    def row(label, what, sel, of):
        n = int(np.count_nonzero(sel))
        if n == 0:
            return [label, what, 0, "–", "–", "–", "–", "–"]
        d = diff[sel]
        return [label, what, n, f"{100 * n / max(int(np.count_nonzero(of)), 1):.0f}",
                num(np.sqrt(np.mean(d ** 2, axis=0)).tolist(), 3), num(np.mean(d, axis=0).tolist(), 2),
                num(round(float(np.median(worst[sel])), 4), 2), f"{100 * float(np.mean(worst[sel] <= ALBEDO_TOLERANCE)):.1f}"]

    rows = []
    for k in np.unique(surface[both]):
        entry = as_dict(surfaces[k]) if 0 <= k < len(surfaces) else {}
        name = str(entry.get("name", f"surface {k}"))
        what = "recovered texture" if name in textured else (
            "homogeneous kd" if entry.get("textured") is False else "homogeneous kd (no texture recovered)")
        on = seen & (surface == k)
        rows.append(row(name, what, both & (surface == k), on))
    rows.append(row("all", "", both, seen))
    sec.table(["surface seen (recovered model)", "albedo from", "pixels compared", "% of its pixels",
               "RMSE per band", "mean error per band", "median |error|", f"% within {ALBEDO_TOLERANCE:g}"], rows,
              f"The recovered albedo at the input view (`reflab render --aov albedo`) against {rel}, pixel for pixel, "
              "over the pixels where both know it: the truth sees a surface and the model knows the albedo of the "
              "surface it sees (a determined texel, or an untextured surface's kd). "
              "% of its pixels: of those where the model sees that surface and the truth sees one; "
              f"within {ALBEDO_TOLERANCE:g}: the largest band's |recovered − true| at most {ALBEDO_TOLERANCE:g}; "
              "mean error: recovered − true (a bias, e.g. from a lamp's intensity); median |error|: of the largest "
              "band (an RMSE far above it comes from few pixels: outlines where the recovered geometry sees "
              "another surface than the truth, amplified texels).")
    unknown, missing = int(np.count_nonzero(seen & ~known)), int(np.count_nonzero(known & ~seen))
    share = 100 * float(np.mean(both))
    sec.kv([("compared over", f"{int(np.count_nonzero(both))} pixels ({share:.0f} % of the image)"),
            ("left out: the truth sees a surface, the model's albedo is unknown there", f"{unknown} pixels"
             + (" (in a capture lamp's shadow, out of the texture's view, or no surface in the model)" if unknown else "")),
            ("left out: the model sees a surface the truth does not", f"{missing} pixels" if missing else None)],
           f"against {rel}")
    sec.images([(F.thumb(F.display(true, 1.0), 320, 240), f"true albedo ({rel}, sRGB, 1 = white)"),
                (F.thumb(F.display(rec, 1.0), 320, 240), "recovered albedo at the input view (black: unknown)"),
                (F.heat_with_bar(worst, "|recovered − true| kd, largest band", "albedo error (white: not compared)",
                                 vmax=4 * ALBEDO_TOLERANCE),
                 f"albedo error (top colour: {4 * ALBEDO_TOLERANCE:g} or more)", True)])


# ---------------------------------------------------------------------- views
def views_section(src: Sources, views: dict) -> Section | None:
    if not views:
        return None
    sec = Section("views", "Novel and relit views", "The recovered model rendered where the input photograph "
                                                    "did not look, and under other lamps.")
    for key, label in (("novel", "novel view"), ("relit", "relit view")):
        v = views.get(key)
        if not v:
            continue
        if v.get("error"):
            sec.note(f"{label}: {v['error']}", "bad")
            continue
        img, truth = v["image"], v.get("truth")
        exposure = 1.0 / max(float(np.percentile(truth if truth is not None else img, 99.5)), 1e-12)
        items = [(F.thumb(F.display(img, exposure), 480, 360), f"{label}: recovered model ({v['how']})")]
        if truth is not None and truth.shape == img.shape:
            items.append((F.thumb(F.display(truth, exposure), 480, 360), f"{label}: truth ({v['truth_file']})"))
            items.append((F.heat_with_bar(np.abs(img - truth).max(axis=2), "|model − truth|", "linear radiance"), "difference", True))
            sec.images(items)
            known = v.get("known")
            share = f"{100 * float(np.mean(known)):.0f}" if known is not None else "100"
            sec.kv([(f"{label} PSNR against truth", f"{num(psnr(img, truth, known), 4)} dB over the {share} % of pixels of "
                                                     f"known albedo, {num(psnr(img, truth), 4)} dB over all"),
                    (f"{label} RMS per band", num(np.sqrt(np.mean((img - truth) ** 2, axis=(0, 1))).tolist()))])
        else:
            sec.images(items)
    return sec


# ---------------------------------------------------------------------- error against run time
def error_section(src: Sources) -> Section | None:
    fit, idx, cam, sfm = src.fit, src.textures, src.camera, src.sfm
    photometric, convergence, geometric = [], [], []

    def band_mean(v):
        a = _floats(v)
        return None if a is None else float(np.mean(a))

    if fit and isinstance(fit.get("trace"), list):
        # [seconds, rms per band] or [seconds, rms, phase name]: one series per phase where named.
        raw = [(p[0], band_mean(p[1]), p[2] if len(p) > 2 and isinstance(p[2], str) else None)
               for p in fit["trace"] if isinstance(p, (list, tuple)) and len(p) >= 2]
        raw = [r for r in raw if isinstance(r[0], (int, float)) and r[1] is not None]
        pts = [(t, e) for t, e, _ in raw]
        method = _method(fit)
        for phase in dict.fromkeys(ph for _, _, ph in raw):
            sel = [(t, e) for t, e, ph in raw if ph == phase]
            what = ", ".join(str(w) for w in (method, phase) if w)
            photometric.append({"label": f"fit ({what})" if what else "fit", "points": sel})
        rounds = as_dict(fit.get("texture_rounds")).get("rounds")
        if isinstance(rounds, list) and rounds and pts:
            t_end = pts[-1][0]
            t = t_end - sum((r.get("texture_s") or 0) + (r.get("fit_s") or 0) for r in rounds if isinstance(r, dict))
            marks = []
            for r in rounds:
                if isinstance(r, dict):
                    t += (r.get("texture_s") or 0) + (r.get("fit_s") or 0)
                    if band_mean(r.get("rms")) is not None:
                        marks.append((t, band_mean(r.get("rms"))))
            if marks:
                photometric.append({"label": "fit, end of each texture round", "points": marks, "style": "s",
                                    "phase": (t_end - sum((r.get("texture_s") or 0) + (r.get("fit_s") or 0)
                                                          for r in rounds if isinstance(r, dict)), "texture rounds start")})
    if idx and isinstance(idx.get("stats"), dict):
        st = idx["stats"]
        trace = st.get("trace")
        if isinstance(trace, list) and trace:
            pts = [(p[0], band_mean(p[1])) for p in trace if isinstance(p, (list, tuple)) and len(p) >= 2]
            convergence.append({"label": f"texture CG ({st.get('trace_quantity', 'residual')}, "
                                         f"{st.get('active_set_rounds', '?')} active-set rounds)",
                                "points": [(t, e) for t, e in pts if isinstance(t, (int, float)) and e is not None]})
        if st.get("total_s") is not None and band_mean(st.get("residual_rms")) is not None:
            photometric.append({"label": f"texture solve, end ({st.get('iterations', '?')} CG iterations)",
                                "points": [(st["total_s"], band_mean(st["residual_rms"]))], "style": "D"})
    cal = as_dict(as_dict(cam).get("calibration"))
    if cal.get("time_s") is not None and cal.get("rms_px") is not None:
        geometric.append({"label": "camera calibration", "points": [(cal["time_s"], cal["rms_px"])], "style": "o"})
    for k, l in enumerate(as_list((src.lights or {}).get("lights"))):
        c = (l or {}).get("calibration") if isinstance(l, dict) else None
        if isinstance(c, dict) and c.get("time_s") is not None and _floats(c.get("mark_errors_px")) is not None:
            e = _floats(c["mark_errors_px"])
            geometric.append({"label": f"lamp {k}", "points": [(c["time_s"], float(np.sqrt(np.mean(e ** 2))))], "style": "v"})
    if sfm:
        s = as_dict(sfm.get("sfm"))
        ts = as_dict(s.get("time_s"))
        if ts.get("total_s") is not None and s.get("reprojection_px") is not None:
            geometric.append({"label": "structure from motion", "points": [(ts["total_s"], s["reprojection_px"])], "style": "^"})
        rt = as_dict(sfm.get("rigid_turntable"))
        if rt.get("time_s") is not None and rt.get("rms_px") is not None:
            geometric.append({"label": "one turntable axis", "points": [(rt["time_s"], rt["rms_px"])], "style": "s"})
    if not photometric and not convergence and not geometric:
        return None
    sec = Section("error", "Error against run time", "Every fit and solve: its error against the seconds it ran "
                                                      "(each from its own start).")
    homogeneous = ("; until the texture rounds start the fit's model has homogeneous albedo, so texture counts as "
                   "its error there" if any(s.get("phase") for s in photometric) else "")
    panels = [(series, ylabel, what) for series, ylabel, what in (
        (photometric, "RMS residual (linear radiance)", "photometric fits: RMS residual in linear radiance (mean of "
                                                        "the bands; fit: over pixels, texture: over its equations"
                                                        + homogeneous + ")"),
        (convergence, "relative residual", "the texture solver's conjugate gradient: its normal-equation residual "
                                           "relative to that of the homogeneous kd (the stopping test's scale); each "
                                           "jump starts an active-set round (texels outside [0, 1] fixed at the bound, "
                                           "the rest solved again)"),
        (geometric, "RMS reprojection (px)", "geometric solves: RMS reprojection error in pixels")) if series]
    where = ["Left", "middle", "right"] if len(panels) == 3 else ["Left", "right"] if len(panels) == 2 else [""]
    caption = "; ".join(f"{w}: {what}" if w else what for w, (_, _, what) in zip(where, panels))
    sec.figure(_error_plot([(series, ylabel) for series, ylabel, _ in panels]), caption[0].upper() + caption[1:] + ".",
               id="error-vs-time")
    return sec


def _error_plot(panels) -> str:
    """One figure, one log-log panel per (series, y label): error against seconds."""
    fig, axes = F.new_figure(4.6 * len(panels), 3.6, ncols=len(panels))
    for ax, (series, ylabel) in zip(axes, panels):
        for i, s in enumerate(series):
            t = np.maximum([p[0] for p in s["points"]], 1e-3)
            e = [p[1] for p in s["points"]]
            style = s.get("style")
            ax.plot(t, e, (style or ".") + ("" if style else "-"), color=F.COLOURS[i % len(F.COLOURS)],
                    ms=6 if style else 3, lw=1, label=s["label"])
            if s.get("phase"):
                ax.axvline(max(s["phase"][0], 1e-3), color="0.4", ls=":", lw=1)
                ax.annotate(s["phase"][1], (max(s["phase"][0], 1e-3), 0.5), xycoords=("data", "axes fraction"),
                            rotation=90, fontsize=7, color="0.3", ha="right", va="center")
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):
            _plain_log_labels(axis)
        ax.set_xlabel("run time (s)", fontsize=8)
        ax.set_ylabel(ylabel, fontsize=8)
        ax.tick_params(which="both", labelsize=7)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    return F.figure_uri(fig)


def _plain_log_labels(axis) -> None:
    """Label a log axis (already holding its data) in plain numbers at 1, 2, 5 × 10^k, and at 3 × 10^k
    too where it spans less than a decade. Matplotlib's default labels every minor tick as
    'a × 10^b' on an axis spanning under two decades, where they overlap."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    lo, hi = sorted(axis.get_view_interval())
    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    threes = FuncFormatter(lambda v, _: f"{v:g}" if v > 0 and round(v / 10 ** math.floor(math.log10(v)), 6) == 3 else "")
    axis.set_minor_formatter(threes if lo > 0 and hi / lo < 10 else NullFormatter())
