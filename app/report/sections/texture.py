"""The texture section: textures/'s albedo maps and what the image determines, and the albedo at
the input view against truth/albedo.exr."""
from __future__ import annotations

import numpy as np

from reflab.app.report import figures as F
from reflab.app.report.data import Sources, as_dict, as_list
from reflab.app.report.sections.section import Section, num


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
            ("texels known / amplified > 10× / clipped / guessed", f"{st.get('texels_known')} / {st.get('texels_amplified')} / "
             f"{st.get('texels_clipped')} / {st.get('texels_guessed', 0)}" if "texels_known" in st else None),
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
        kd = src.image(src.rel(src.ws.textures / files["kd"])) if files.get("kd") else None
        mask = src.image(src.rel(src.ws.textures / files["mask"])) if files.get("mask") else None
        diag = src.image(src.rel(src.ws.textures / files["diag"])) if files.get("diag") else None
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
            rgb[(flags & 8) > 0] = [150, 60, 190]
            rgb[(flags & 4) > 0] = [230, 180, 0]
            items.append((F.thumb(orient(rgb), 320, 240), "red: amplified > 10×, blue: saturated, yellow: clipped, "
                                                          "purple: guessed (from light resting on undetermined parameters), grey: unknown"))
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
