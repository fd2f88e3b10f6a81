"""Novel-view and relit PSNR of the recovered model: fitted materials against true ones (issue 12).

The simulated lab's photograph by the independent reference renderer (true albedo function). Two
workspaces recover the model from it: one whose scene.json holds the TRUE materials (`reflab
texture` only), one where `reflab fit` finds them (scene.json: brdf, ior, the matte ground's
r = 0), then `reflab texture`. Each renders the input view, the input view relit by two new
lamps, and a novel view (:mod:`texture_psnr_reference`'s), compared with the reference renderer's
image of the true scene over the pixels whose albedo is known in both. The issue asks the fitted
model within 3 dB of the true-material one (goal 1 dB).

The textured scenes of our own (:mod:`reflab.hardware.sim.scenes`) are measured the same way
(``--scene``): their novel view turns the input camera 40° about its target and rises 8 cm.

Usage: ``python docs/figures/fit_psnr.py [WIDTH HEIGHT] [--scene lab|shiny_box|floor_mirror|curved|glass_block|all]
[--noise 0.01] [--texture-seed K] [--photographs L0,L1,T35,T-35,T70,T-70]``; ``--scene more`` measures
:data:`reflab.hardware.sim.scenes.MORE`. ``--photographs``: further photographs in inputs/ of both
workspaces (``Lk`` lamp k alone, ``TA`` the turntable turned by A degrees about the vertical axis
through the origin), by the reference renderer with the same noise; fit and texture use them all.
(default 320 240, the lab).
"""
import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from texture_psnr_reference import RELIGHT, novel_camera, psnr  # noqa: E402

from reflab.app.cli import main  # noqa: E402
from reflab.calibration.camera import Camera  # noqa: E402
from reflab.calibration.lights import Lights  # noqa: E402
from reflab.hardware.sim.lab import build_lab, named_views, write_lab  # noqa: E402
from reflab.hardware.sim.reference import render_reference  # noqa: E402
from reflab.hardware.sim.scenes import MORE, NAMES, build  # noqa: E402
from reflab.hardware.sim.zoo import score  # noqa: E402
from reflab.inverse.stages import render_workspace  # noqa: E402


def turned(camera: Camera, target, degrees: float = 40.0, rise: float = 0.08) -> Camera:
    """``camera`` moved round ``target`` by ``degrees`` about the vertical and raised by ``rise``."""
    from reflab.calibration.rotations import axis_rotation

    eye = axis_rotation((0.0, 0.0, 1.0), degrees) @ (camera.center - target) + target + [0.0, 0.0, rise]
    fov = np.degrees(2 * np.arctan(camera.width / 2 / camera.K[0, 0]))
    return Camera.look_at(camera.width, camera.height, fov, eye=tuple(eye), target=tuple(target))


def views(root: Path, width: int, height: int, lab, scene: str):
    RELIGHT.save(root / "relight.json")
    novel = novel_camera(width, height) if scene == "lab" else turned(lab.camera, np.array([0.0, 0.02, 0.02]))
    novel.save(root / "novel.json")
    return [("input view, re-rendered", None, None), ("input view, relit (two new lamps)", None, root / "relight.json"),
            ("novel view" + (" (box back face)" if scene == "lab" else ""), root / "novel.json", None)]


def parameters(fitted: Path, true: Path) -> dict:
    """The fitted workspace's fit.json against the true one's scene.json, as the zoo scores it
    (:func:`reflab.hardware.sim.zoo.compare`): the visible parameters, those determined, within 3σ,
    confidently wrong (beyond 3σ + 2 %) and recovered (determined and within 10 %)."""
    import json

    from reflab.hardware.sim.zoo import compare, score

    report = json.loads((fitted / "fit.json").read_text())
    truth = json.loads((true / "scene.json").read_text())
    rows = compare(report, truth, [bool(s.get("textured")) for s in truth["surfaces"]])
    return {**score(rows), "rows": rows}


def shown(lab, rows: list, views: list, noise: float) -> list:
    """How much each scored parameter shows in each photograph: the χ² (in units of the noise,
    ``noise`` × each photograph's peak) by which moving its true value by the recall tolerance
    (10 %, or 0.01 for r and t) changes that photograph, by the reference renderer, noise-free.

    ``views``: ``(name, camera, lights)``, the reference first. Returns per row a list of χ², one
    per view. A parameter "the reference view shows" is one whose χ² there is at least 9 (a 3σ
    change); one that no photograph shows cannot be determined by any method from these shots.
    """
    from reflab.hardware.sim.zoo import ATTENUATION_FLOOR, RECALL

    surfaces = {s.name: s for s in lab.scene.surfaces}
    base = [render_reference(lab.scene, cam, li, albedo=lab.albedo) for _, cam, li in views]
    out = []
    for name, label, _, true, _, _ in rows:
        param, band = (label.split("[")[0], int(label[-2])) if "[" in label else (label, None)
        material = surfaces[name].material
        old = material.params[param]
        step = max(RECALL * abs(true), ATTENUATION_FLOOR if param in "rt" else 0.0)
        moved = np.array(old, dtype=np.float64, copy=True)
        if band is None:
            moved = moved + step
        else:
            moved[band] += step
        material.params[param] = moved
        try:
            chi = []
            for (_, cam, li), b in zip(views, base):
                d = (render_reference(lab.scene, cam, li, albedo=lab.albedo) - b) / (noise * b.max())
                chi.append(float(np.sum(d[..., band] ** 2 if band is not None else d ** 2)))
        finally:
            material.params[param] = old
        out.append(chi)
    return out


def measure(width: int, height: int, tmp: Path, scene: str = "lab", noise: float = 0.0, seed: int = 0,
            texture_seed: int | None = None, photographs: str = "", scores: dict | None = None) -> list[dict]:
    lab = build_lab(width, height) if scene == "lab" else build(scene, width, height, texture_seed=texture_seed)
    photo = render_reference(lab.scene, lab.camera, lab.lights, albedo=lab.albedo)
    if noise:  # Gaussian, sigma = noise x the image's peak, the same photograph for both models
        photo = photo + np.random.default_rng(seed).normal(0.0, noise * photo.max(), photo.shape)
    further = []
    for name, cam, li in named_views(lab.camera, lab.lights, photographs):
        img = render_reference(lab.scene, cam, li, albedo=lab.albedo)
        if noise:
            img = img + np.random.default_rng(seed + 1 + len(further)).normal(0.0, noise * img.max(), img.shape)
        further.append((name, img, cam, li))
    out = {}
    for kind in ("true", "fitted"):
        root = tmp / kind
        write_lab(root, lab, materials=kind == "true", photograph=photo, further=further)
        if kind == "fitted":
            assert main(["fit", str(root)]) in (0, 3)
            if scores is not None:
                scores.update(parameters(root, tmp / "true"))
                shots = [("reference", lab.camera, lab.lights)] + [(n, c, li) for n, _, c, li in further]
                scores["shown"] = shown(lab, scores["rows"], shots, noise or 0.01)
        assert main(["texture", str(root)]) == 0
        out[kind] = {}
        for name, cam, lig in views(root, width, height, lab, scene):
            image, info = render_workspace(root, cam, lig)
            out[kind][name] = (image, ~info["unknown_pixels"], ~info["undetermined_pixels"], cam, lig)
    rows = []
    for name in out["true"]:
        img_t, known_t, _, cam, lig = out["true"][name]
        img_f, known_f, determined, _, _ = out["fitted"][name]
        camera = Camera.load(cam) if cam else lab.camera
        lights = Lights.load(lig) if lig else lab.lights
        truth = render_reference(lab.scene, camera, lights, albedo=lab.albedo)
        known = known_t & known_f
        sure = known & determined
        rows.append({"view": name, "true": psnr(img_t, truth, known), "fitted": psnr(img_f, truth, known),
                     "known_fraction": float(known.mean()),
                     "true_determined": psnr(img_t, truth, sure), "fitted_determined": psnr(img_f, truth, sure),
                     "determined_fraction": float(sure.mean())})
    return rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("size", nargs="*", type=int, default=[320, 240])
    ap.add_argument("--scene", default="lab",
                    help="lab, one of " + ", ".join(NAMES + MORE) + ", all (the lab and " + ", ".join(NAMES) + ") or more (" + ", ".join(MORE) + ")")
    ap.add_argument("--noise", type=float, default=0.0, help="Gaussian noise on the photograph, fraction of its peak")
    ap.add_argument("--texture-seed", type=int, help="another realisation of our scenes' textures (reflab.hardware.sim.scenes.build)")
    ap.add_argument("--photographs", default="", help="further photographs: Lk (lamp k alone), TA (turntable A degrees)")
    args = ap.parse_args()
    w, h = args.size
    for scene in {"all": ("lab",) + NAMES, "more": MORE}.get(args.scene, (args.scene,)):
        start = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            recall = {}
            rows = measure(w, h, Path(tmp), scene, args.noise, texture_seed=None if scene == "lab" else args.texture_seed,
                           photographs=args.photographs, scores=recall)
        print(f"\n{scene} {w}x{h}, noise {args.noise:g}, further photographs [{args.photographs}] "
              f"(total {time.perf_counter() - start:.1f} s)")
        print(f"parameters: {recall['visible']} visible, {recall['determined']} determined, "
              f"{recall['within_3sigma']} within 3σ (worst {recall['worst']:.2f}σ), {len(recall['wrong'])} confidently "
              f"wrong {recall['wrong'] or ''}, {recall['recovered']} ({100 * recall['recovered'] / max(recall['visible'], 1):.0f} %) "
              "determined and within 10 %")
        seen = [r for r, chi in zip(recall["rows"], recall["shown"]) if chi[0] >= 9]
        kept = score(seen) if seen else {"recovered": 0}
        print(f"shown by the reference view (10 % of the value moves it by χ² ≥ 9): {len(seen)}, of which "
              f"{kept['recovered']} ({100 * kept['recovered'] / max(len(seen), 1):.0f} %) determined and within 10 %")
        for r, chi in zip(recall["rows"], recall["shown"]):
            ok = "recovered" if r in seen and score([r])["recovered"] else "-"
            print(f"  {r[0]} {r[1]}: fit {r[2]:.4g} true {r[3]:.4g} σ {r[4] if r[4] is None else f'{r[4]:.3g}'} "
                  f"{'determined' if r[5] else 'undetermined'}; χ² per photograph {[round(c) for c in chi]} {ok}")
        print("| view | true materials + texture | fitted materials + texture | difference | pixels compared "
              "| over determined pixels: true | fitted | difference | pixels |")
        print("|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            def db(v, sign=""):
                return f"{v:{sign}.1f} dB" if np.isfinite(v) else "n/a"  # n/a: no pixel determined

            print(f"| {r['view']} | {db(r['true'])} | {db(r['fitted'])} | {db(r['fitted'] - r['true'], '+')} "
                  f"| {100 * r['known_fraction']:.1f} % | {db(r['true_determined'])} | {db(r['fitted_determined'])} "
                  f"| {db(r['fitted_determined'] - r['true_determined'], '+')} | {100 * r['determined_fraction']:.1f} % |")
