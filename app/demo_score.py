"""The simulated lab's truth (WORKSPACE/truth/) and each demo stage's error against it.

The truth (docs/formats.md, "The simulated lab's truth"): camera.json, lights.json, scene.json with
its meshes (true materials), novel_camera.json + novel.exr (a view the input did not see) and
relit_lights.json + relit.exr (the input view under other lamps), both rendered with the true
textures by the independent reference renderer (hardware/sim/reference.py), and albedo.exr (the
true kd seen at each pixel of the input view, :func:`true_albedo`).

PSNR is ``10 log10(peak² / MSE)`` with ``peak`` the true image's maximum, over the pixels whose
albedo the recovered model knows: every node of the pixel's tree (the surface seen, and what it
reflects or transmits) has a determined albedo (:func:`view_psnr`).
"""
from __future__ import annotations

import numpy as np

from reflab.core.workspace import Workspace

#: Turntable angle (degrees) of the novel view's camera about the vertical axis through the origin.
NOVEL_TURN = -25.0
#: The relit view's lamps: positions (m) and intensities (the input's lamps are elsewhere).
RELIT = [((0.30, -0.25, 0.50), (0.20, 0.19, 0.17)), ((-0.25, 0.35, 0.55), (0.30, 0.27, 0.22))]


def _turned(camera, degrees: float):
    from reflab.calibration.camera import Camera
    from reflab.calibration.rotations import axis_rotation

    Rz = axis_rotation((0.0, 0.0, 1.0), degrees)
    C = Rz @ camera.center
    R = camera.R @ Rz.T
    return Camera(camera.width, camera.height, camera.K.copy(), camera.dist.copy(), R, -R @ C)


def write_truth(root, size, *, depth: int = 3, grain: float = 0.2) -> dict:
    """Write ``root/truth/`` for the simulated lab as `reflab capture --camera sim` renders it; return it in memory."""
    from reflab.calibration.lights import Lights, PointLight
    from reflab.core.images import write_image, write_preview
    from reflab.hardware.sim.lab import build_lab, write_lab
    from reflab.hardware.sim.reference import render_reference

    truth = Workspace(Workspace(root).truth)
    lab = build_lab(*size, grain=grain)
    write_lab(truth.root, lab, materials=True)
    novel = _turned(lab.camera, NOVEL_TURN)
    novel.save(truth.view("novel")[0])
    relit = Lights([PointLight(p, i) for p, i in RELIT])
    relit.save(truth.view("relit")[0])
    images = {}
    for name, cam, lights in (("novel", novel, lab.lights), ("relit", lab.camera, relit)):
        images[name] = render_reference(lab.scene, cam, lights, depth, albedo=lab.albedo)
        image_path = truth.view(name)[1]
        write_image(image_path, images[name])
        write_preview(image_path.with_suffix(".png"), images[name])
    write_image(Workspace(root).truth_albedo, true_albedo(lab), allow_nan=True)
    return {"lab": lab, "novel_camera": novel, "relit_lights": relit, "images": images, "depth": depth}


def true_albedo(lab) -> np.ndarray:
    """truth/albedo.exr: the true kd (H, W, 3) of the surface seen directly at each pixel of the lab's
    camera, NaN where none is seen (``reflab render --aov albedo``'s form): the lab's albedo at the
    level-1 nodes of the true scene's trees (pixel centres), independent of any recovered model."""
    from reflab.inverse.forward.trees import build_trees

    cam = lab.camera
    trees = build_trees(lab.scene, cam, lab.lights, depth=1)
    first = trees.level == 1
    out = np.full((cam.height * cam.width, 3), np.nan)
    out[trees.pixel[first]] = lab.albedo_at(trees.surface[first], trees.point[first])
    return out.reshape(cam.height, cam.width, 3)


def camera_error(cam, true) -> dict:
    f = np.array([cam.K[0, 0], cam.K[1, 1]]) / np.array([true.K[0, 0], true.K[1, 1]]) - 1
    dR = cam.R @ true.R.T
    return {"focal_pct": float(100 * np.max(np.abs(f))), "centre_mm": float(1e3 * np.linalg.norm(cam.center - true.center)),
            "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))),
            "principal_px": float(np.hypot(*(cam.K[:2, 2] - true.K[:2, 2])))}


def lights_error(lights, true) -> list[dict]:
    out = []
    for k, (got, want) in enumerate(zip(lights, true)):
        d = np.linalg.norm(got.position - want.position)
        out.append({"lamp": k, "position_mm": float(1e3 * d), "of_distance_pct": float(100 * d / np.linalg.norm(want.position)),
                    "intensity_pct": float(100 * np.max(np.abs(got.intensity / want.intensity - 1)))})
    return out


def geometry_error(scene, true_scene) -> dict:
    """Per true surface: RMS and max distance (mm) between it and the surface of the same name."""
    from reflab.reconstruction.surfaces import distance_to_mesh

    names = {s.name: s for s in scene}
    out = {}
    for t in true_scene:
        s = names.get(t.name)
        if s is None:
            out[t.name] = None
            continue
        d = distance_to_mesh(t.mesh, s.mesh.sample_points(4000))
        if t.name != "ground":  # a bounded object: both ways (a missing part counts too)
            d = np.concatenate([d, distance_to_mesh(s.mesh, t.mesh.sample_points(4000))])
        out[t.name] = {"rms_mm": float(1e3 * np.sqrt(np.mean(d**2))), "max_mm": float(1e3 * d.max())}
    return out


def psnr(image, truth, known=None) -> float:
    """PSNR (dB) of ``image`` against ``truth`` over the pixels ``known`` (all by default), the peak
    being the truth's maximum; NaN over no pixel."""
    err = np.asarray(image, float) - truth
    err = err if known is None else err[known]
    mse = float(np.mean(err**2)) if err.size else float("nan")
    return float(10 * np.log10(float(np.max(truth)) ** 2 / max(mse, 1e-300))) if np.isfinite(mse) else float("nan")


def view_scores(image, true, albedo, unknown, undetermined) -> dict:
    """The one PSNR computation of a novel or relit view against its truth, for the demo's console
    line and the report alike (:func:`view_psnr`'s keys).

    ``albedo``: the model's albedo AOV at that view (NaN where the seen surface's is unknown);
    ``unknown``: the render's ``unknown_pixels``; ``undetermined``: its ``undetermined_pixels``.
    """
    primary = np.all(np.isfinite(albedo), axis=2)
    known = primary & ~np.asarray(unknown, bool)
    determined = known & ~np.asarray(undetermined, bool)
    return {"psnr_db": psnr(image, true, known), "known_pct": float(100 * known.mean()),
            "psnr_primary_db": psnr(image, true, primary), "primary_known_pct": float(100 * primary.mean()),
            "psnr_all_db": psnr(image, true),
            "psnr_determined_db": psnr(image, true, determined), "determined_pct": float(100 * determined.mean())}


def view_psnr(root, truth: dict, which: str) -> dict:
    """PSNR of the recovered model's novel or relit view against the truth, over pixels of known albedo.

    A pixel's albedo is known when every node of its tree has one (docs/texture.md's "known",
    the render's ``unknown_pixels``): a textured point the input saw directly, in a mirror or
    through the sheet, or an untextured surface. A mirror pixel that reflects a point the input
    never determined (in a capture lamp's shadow, or out of its view: its texel is 0 in
    textures/<surface>_mask.png and the render puts the homogeneous kd there) is not known,
    though the mirror itself is. ``psnr_primary_db`` is the PSNR over the pixels whose directly
    seen surface alone has a known albedo (finite albedo AOV), the score used until 2026-11-24;
    ``psnr_determined_db`` over the known pixels whose value rests on no undetermined parameter
    (the render's ``undetermined_pixels``).
    """
    from reflab.inverse.stages import render_workspace
    from reflab.core.images import read_image

    ws = Workspace(root)
    pose = Workspace(ws.truth).view(which)[0]
    view = {"camera": pose} if which == "novel" else {"lights": pose}
    albedo, info = render_workspace(ws.root, aov="albedo", depth=truth["depth"], **view)
    undetermined = render_workspace(ws.root, depth=truth["depth"], **view)[1]["undetermined_pixels"]
    image, true = read_image(ws.view(which)[1]), truth["images"][which]
    return view_scores(image, true, albedo, info["unknown_pixels"], undetermined)


def score_stage(stage: str, root, truth: dict) -> str:
    """One line: the stage's error against the truth ('' for stages with nothing to compare)."""
    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights
    from reflab.core.workspace import read_json
    from reflab.reconstruction.scene import Scene

    ws, lab = Workspace(root), truth["lab"]
    if stage == "calibrate camera":
        e = camera_error(Camera.load(ws.camera), lab.camera)
        return (f"focal {e['focal_pct']:.3f} %, camera centre {e['centre_mm']:.2f} mm, rotation {e['rotation_deg']:.3f} deg, "
                f"principal point {e['principal_px']:.2f} px")
    if stage == "calibrate lights":
        return "; ".join(f"lamp {e['lamp']} {e['position_mm']:.1f} mm ({e['of_distance_pct']:.2f} % of its distance), "
                         f"intensity {e['intensity_pct']:.1f} %" for e in lights_error(Lights.load(ws.lights), lab.lights))
    if stage == "reconstruct":
        errs = geometry_error(Scene.load(ws.scene), lab.scene)
        return ", ".join(f"{n} missing" if e is None else f"{n} {e['rms_mm']:.2f} mm RMS (max {e['max_mm']:.1f})"
                         for n, e in errs.items())
    if stage == "fit":
        fit = read_json(ws.fit)
        want = {s.name: s.material for s in lab.scene}
        parts = [f"re-render RMS {np.round(fit['rms'], 4).tolist()}"]
        for item in fit.get("surfaces", []):
            m, t = item.get("material", {}), want.get(item.get("name"))
            if t is None:
                continue
            keys = [k for k in ("ks", "ns", "r", "t") if k in m and k in t.params and np.any(t.params[k])]
            parts.append(f"{item['name']} " + " ".join(f"{k} {np.round(np.mean(m[k]), 3)} ({np.round(np.mean(t.params[k]), 3)})"
                                                        for k in keys))
        return "; ".join(parts) + " (true in brackets)"
    if stage in ("render novel", "render relit"):
        e = view_psnr(ws.root, truth, stage.split()[1])
        return (f"PSNR {e['psnr_db']:.1f} dB over the {e['known_pct']:.0f} % of pixels of known albedo "
                f"({e['psnr_primary_db']:.1f} dB over the {e['primary_known_pct']:.0f} % whose seen surface's is known, "
                f"{e['psnr_all_db']:.1f} dB over all, "
                + (f"{e['psnr_determined_db']:.1f} dB over the {e['determined_pct']:.0f} % whose value rests on no "
                   "undetermined parameter)" if np.isfinite(e["psnr_determined_db"]) else
                   "no pixel whose value rests on determined parameters only)"))
    return ""
