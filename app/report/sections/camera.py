"""The camera section: camera.json's intrinsics with σ, per-view reprojection, residuals, and the
input pose against the truth."""
from __future__ import annotations

import numpy as np

from reflab.app.report import figures as F
from reflab.app.report.data import Sources, as_dict, as_list
from reflab.app.report.sections.section import Section, floats, mm, num, pm


CAMERA_KEYS = ("fx", "fy", "cx", "cy", "k1", "k2")


def _camera_values(cam: dict) -> dict:
    K, d = floats(cam.get("K")), floats(cam.get("dist"))
    out = {}
    if K is not None and K.shape == (3, 3):
        out.update(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
    if d is not None and d.size >= 2:
        out.update(k1=d[0], k2=d[1])
    return out


def pose_centre(obj) -> np.ndarray | None:
    """Camera centre −Rᵀt of a {"R", "t"} object, None when malformed."""
    R, t = floats(obj.get("R")), floats(obj.get("t"))
    if R is None or t is None or R.shape != (3, 3) or t.shape != (3,):
        return None
    return -R.T @ t


def _rotation_deg(Ra, Rb) -> float:
    c = (np.trace(np.asarray(Ra) @ np.asarray(Rb).T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def camera_section(src: Sources) -> Section | None:
    cam = src.camera
    if cam is None:
        return None
    cal = as_dict(cam.get("calibration"))
    sec = Section("camera", "Camera", "camera.json: intrinsics with one-sigma uncertainties, per-view reprojection "
                                      "error, and the pose of the input view.")
    truth = src.truth("camera")
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
        C, Ct = pose_centre(cam), pose_centre(truth)
        if C is not None and Ct is not None:
            sec.kv([("input view centre error", f"{mm(1e3 * float(np.linalg.norm(C - Ct)))} mm"),
                    ("input view rotation error", f"{num(_rotation_deg(cam['R'], truth['R']), 3)}°")], "against truth/camera.json")
    return sec


def _residual_field(residuals, cam, views) -> str | None:
    """Quiver plot of per-circle residuals over the image frame (rows [u, v, du, dv] per view)."""
    fig, (ax,) = F.new_figure(6.0, 6.0 * (cam.get("height") or 3) / max(cam.get("width") or 4, 1))
    lengths = []
    for i, rows in enumerate(residuals):
        a = floats(rows)
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
        a = floats(rows)
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
