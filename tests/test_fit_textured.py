"""The fit on textured scenes of our own design (hardware/sim/scenes.py, not the demo), photographs
by the independent reference renderer with known per-point albedo; outlier pixels; plausible
ranges; values the user gave. docs/fit.md, "Trustworthy on textured scenes", has the figures."""
import numpy as np
import pytest

from reflab.inverse.forward.factorization import Factorization
from reflab.inverse.fit.rounds import Free, fit, params_of
from reflab.inverse.forward.models import get_model
from reflab.inverse.fit.ranges import at_bound, clip, linear_upper, phong_lobe_albedo
from reflab.hardware.sim.scenes import determined, user_materials
from reflab.reconstruction.scene import Scene, Surface

W, H = 80, 60


def _fit_scene(ts, image, rounds=None, uncertainty=True):
    """(fit, factorization, user scene); ``rounds``, a list, gets fit.json's texture round records;
    ``uncertainty=False``: the homogeneous start as fit_workspace fits it when rounds follow (no σ,
    its undetermined lobes not weighed)."""
    from reflab.inverse.fit.texture_aware import fit_with_texture
    from reflab.inverse.forward.trees import build_trees

    init = user_materials(ts.scene)
    user = Scene([Surface(s.name, s.mesh_path, m, s.textured, s.mesh) for s, m in zip(ts.scene, init)])
    trees = build_trees(user, ts.camera, ts.lights, depth=3)
    models = [get_model(m.brdf) for m in init]
    held = [m.given for m in init]
    fac = Factorization(trees, models, ts.lights.intensities)
    start = fit(fac, image, init, "ftbo", textured=[s.textured for s in user], names=user.names, held=held,
                uncertainty=uncertainty)
    res, records = fit_with_texture(trees, user, models, ts.lights.intensities, image, start, rounds=2, held=held)
    if rounds is not None:
        rounds += records
    return res, fac, user


def _check(res, fac, truth, user):
    assert all(np.all(~np.isnan(a)) for a in (res.sigma.x, res.sigma.s, res.sigma.theta))
    assert not clip(fac, res.params.copy())  # inside every plausible range
    rows = determined(res, fac, truth, user)
    bad = [r for r in rows if abs(r[2] - r[3]) > 3 * r[4] + 0.02 * abs(r[3]) + 1e-9]
    assert not bad, [(user.names[r[0]], *r[1:]) for r in bad]
    return rows


@pytest.mark.parametrize("name, noise", [("curved", 0.0), ("curved", 0.01), ("shiny_box", 0.01), ("print_can", 0.01)])
def test_singly_seen_textured_lobe_is_claimed_only_from_its_colours(name, noise):
    """A shiny textured surface seen once. Printed in two inks (curved, shiny_box) its albedo is on
    a line in RGB and its highlight has the lamps' colour, off that line: the lobe is determined
    from colour (reflab.inverse.fit.dichromatic) and within 3σ + 2 % of the truth. Printed in full colour
    (print_can) nothing separates highlight from texture: ks and ns are reported undetermined (the
    homogeneous fit of the same image claimed them to 1e-4). Every determined value is within
    3σ + 2 %."""
    from reflab.hardware.sim.scenes import build, render

    ts = build(name, W, H)
    img = render(ts)
    if noise:
        img = img + np.random.default_rng(1).normal(0.0, noise * img.max(), img.shape)
    records = []
    res, fac, user = _fit_scene(ts, img, records)
    rows = _check(res, fac, [s.material for s in ts.scene], user)
    shiny = [i for i, s in enumerate(user) if s.textured][0]
    lobes = res.stats.get("colour_lobes", {})
    # The colour lobes' time is recorded, inside the last round's texture step.
    assert "colour_s" not in records[0] and 0.0 < records[-1]["colour_s"] <= records[-1]["texture_s"]
    if name == "print_can":
        assert {"ks", "ns"} <= set(res.undetermined[shiny]) and not lobes
        assert len(rows) >= 3  # the ground's kd at least
        return
    assert not {"ks", "ns"} & set(res.undetermined[shiny]), res.undetermined[shiny]
    assert lobes[user.names[shiny]]["colour_set"] == "line"
    claimed = {r[1] for r in rows if r[0] == shiny}
    assert {"ks[0]", "ns"} <= claimed and len(rows) >= 7
    if name == "shiny_box":
        # Its reflection of the matte ground is light its free texture takes up as well: held at
        # 0 and undetermined (fitted, it took up texture instead: 0.1-0.24 per band, true 0).
        assert "r" in res.undetermined[shiny] and np.all(np.asarray(res.materials[shiny]["r"]) == 0.0)


def test_matte_floor_seen_in_a_mirror():
    """The floor is seen directly and in the mirror: its texture is fixed by the direct view, so the
    mirror's r is determined, within 3σ + 2% of the truth (80x60, noise-free)."""
    from reflab.hardware.sim.scenes import build, render

    ts = build("floor_mirror", W, H)
    res, fac, user = _fit_scene(ts, render(ts))
    rows = _check(res, fac, [s.material for s in ts.scene], user)
    got = {(user.names[r[0]], r[1]) for r in rows}
    assert {("mirror", "r[0]"), ("mirror", "r[1]"), ("mirror", "r[2]")} <= got


def test_a_textured_lobe_seen_twice_is_determined_and_a_reflection_is_not_attenuated():
    """Floor in a mirror, 160x120, 1 % noise, four noise realisations. The floor's texels seen
    both directly and in the mirror share one albedo, so its own lobe shows in how the two views
    differ: ks and ns are determined (σ with each texel's albedo profiled out), within 3σ + 2 %
    (they were undetermined: the direct view that pins the texture carries the same lobe). And
    the mirror's r, regressed on texels made from noisy pixels, is no longer pulled toward 0 by
    their noise: r[2] came out 0.83 for 0.85 in every realisation (3–4σ), now 0.85 on average."""
    from reflab.hardware.sim.scenes import build, render

    ts = build("floor_mirror", 160, 120)
    clean = render(ts)
    r2 = []
    for seed in range(4):
        img = clean + np.random.default_rng(seed).normal(0.0, 0.01 * clean.max(), clean.shape)
        res, fac, user = _fit_scene(ts, img)
        rows = _check(res, fac, [s.material for s in ts.scene], user)
        got = {(user.names[r[0]], r[1]) for r in rows}
        assert {("floor", "ks[0]"), ("floor", "ks[1]"), ("floor", "ks[2]"), ("floor", "ns"), ("mirror", "r[2]")} <= got, got
        r2.append(float(res.materials[user.names.index("mirror")]["r"][2]))
    assert abs(np.mean(r2) - 0.85) < 0.008, r2


def test_a_texel_seen_once_says_nothing_and_twice_only_its_difference():
    """reflab.inverse.fit.uncertainty.profiled against the Schur complement formed densely: each texel's
    albedo a free column of its pixels' derivatives e; a texel of one pixel adds nothing."""
    from reflab.inverse.fit.uncertainty import profiled

    rng = np.random.default_rng(3)
    m, n = 9, 4
    J, e = rng.normal(size=(3, m, n)), rng.uniform(0.5, 2.0, size=(3, m))
    group = np.array([0, 0, 1, 1, 1, 2, 3, 3, 4])  # texels 2 and 4 seen once
    weights, res = np.array([1.0, 2.0, 0.5]), rng.normal(size=(3, m))
    tile = np.arange(m) % 2
    H, scores = profiled(J, e, group, weights, res, tile, 2)
    want_H, want_s = np.zeros((n, n)), np.zeros((n, 2))
    for c in range(3):
        E = np.zeros((m, group.max() + 1))
        E[np.arange(m), group] = e[c]
        P = np.eye(m) - E @ np.linalg.pinv(E)  # the residual maker of the texel columns
        want_H += weights[c] * J[c].T @ P @ J[c]
        for t in range(2):
            want_s[:, t] += (P @ J[c])[tile == t].T @ (weights[c] * res[c][tile == t])
    np.testing.assert_allclose(H, want_H, atol=1e-12)
    np.testing.assert_allclose(scores, want_s, atol=1e-12)
    lone = profiled(J[:, [5, 8]], e[:, [5, 8]], np.array([0, 1]), weights, res[:, [5, 8]], tile[[5, 8]], 2)
    assert np.abs(lone[0]).max() < 1e-12 and np.abs(lone[1]).max() < 1e-12


@pytest.mark.parametrize("size", [(W, H), (160, 120)])
def test_glass_block_over_texture(size):
    """A thick glass block on a textured floor: the floor behind it is seen through it (refracted
    twice) and its texture pinned by the direct view, so the block's t is determined, within
    3σ + 2 %. Its highlight is out of view (a faint tail, 1 % of the peak at most): ks and ns
    are both reported undetermined (ns alone was called determined at 160x120, 106 ± 36 for a
    true 250, 4σ off)."""
    from reflab.hardware.sim.scenes import build, render

    ts = build("glass_block", *size)
    res, fac, user = _fit_scene(ts, render(ts))
    rows = _check(res, fac, [s.material for s in ts.scene], user)
    got = {(user.names[r[0]], r[1]) for r in rows}
    assert {("block", "t[0]"), ("block", "t[1]"), ("block", "t[2]")} <= got
    assert {"ks", "ns"} <= set(res.undetermined[user.names.index("block")])


@pytest.mark.parametrize("name", ["ward_tile", "near_lamp", "oren_mirror", "sheet_flat", "high_ns", "two_textured",
                                  "tile_mirror", "glossy_floor_mirror"])
def test_other_designs_are_honest(name):
    """The further designs of reflab.hardware.sim.scenes.MORE (a textured Ward tile, a lamp 3 cm off a
    textured floor, a textured Oren-Nayar box before a mirror, a flat sheet over texture, a tile of
    shininess 3000, two glossy textured surfaces, a glossy textured tile and a glossy textured
    floor each seen directly and in a mirror), 80x60, 1 % noise: σ never NaN, nothing outside its
    range, every determined value within 3σ + 2 % (docs/fit.md, "Other designs"). The two-ink
    Ward tile's lobe is claimed from its colours; the Oren-Nayar roughness from the mirror's view. The glossy floor
    in a mirror at 160x120: at 80x60 its mirror's kd and r trade in one band past 3σ in 1 of 10
    realisations (docs/fit.md)."""
    from reflab.hardware.sim.scenes import build, render

    ts = build(name, *((160, 120) if name == "glossy_floor_mirror" else (W, H)))
    img = render(ts)
    img = img + np.random.default_rng(0).normal(0.0, 0.01 * img.max(), img.shape)
    res, fac, user = _fit_scene(ts, img)
    rows = _check(res, fac, [s.material for s in ts.scene], user)
    for i, model in enumerate(fac.models):
        if not user[i].textured:
            continue
        if name in ("glossy_floor_mirror", "ward_tile"):  # seen twice, or in two inks: its lobe is claimed
            assert not ({"ks"} | set(model.nonlinear)) & set(res.undetermined[i]), res.undetermined[i]
        elif name == "oren_mirror":  # its roughness shows in the texels the mirror shows again
            # Claimed since the first texture round keeps the box's pixels (0.278 ± 0.071 for 0.4;
            # undetermined at 0.104 when its r[2], 0.12 from the homogeneous start, left them out).
            assert not set(model.nonlinear) & set(res.undetermined[i]), (user.names[i], res.undetermined[i])
    assert len(rows) >= (0 if name == "two_textured" else 6)


def test_held_parameters_keep_their_uncertainty_in_the_others_sigma():
    """Floor in a mirror, 80x60, 1 % noise: the mirror's kd[0] has no resolved signal and is held at
    its start; the mirror's r[0], which shares its pixels, was then reported with the σ of a known
    kd[0] (5.4, 4.1, 4.7, 3.9σ off for these noise seeds). Counted free in the σ, every determined
    value is within 3σ (measured at most 2.5σ)."""
    from reflab.hardware.sim.scenes import build, render

    ts = build("floor_mirror", W, H)
    clean = render(ts)
    for seed in (0, 2, 10, 18):
        img = clean + np.random.default_rng(seed).normal(0.0, 0.01 * clean.max(), clean.shape)
        res, fac, user = _fit_scene(ts, img)
        rows = determined(res, fac, [s.material for s in ts.scene], user)
        assert all(abs(r[2] - r[3]) <= 3 * r[4] for r in rows), [(user.names[r[0]], *r[1:]) for r in rows]


def test_a_value_held_by_an_earlier_round_keeps_its_uncertainty():
    """A glossy textured tile before a mirror (tile_mirror, texture 2, 160x120, 1 % noise): the
    first texture round holds the mirror's kd[1] (0.001 for 0.02); the last round, which starts
    with it held, reported r[1] 0.8825 ± 0.0007 (true 0.85, 47σ) by counting it known. Counted
    free, as the holding rounds' own holds are, every determined value is within 3σ + 2 %."""
    from reflab.hardware.sim.scenes import build, render

    ts = build("tile_mirror", 160, 120, texture_seed=2)
    img = render(ts)
    img = img + np.random.default_rng(2).normal(0.0, 0.01 * img.max(), img.shape)
    # The start as `reflab fit` fits it: a completed start's undetermined mirror lobe, weighed
    # (docs/fit.md "Undetermined means plausible"), seeded the rounds at ks 0.0001, ns 8, where
    # a lobe of no height shows no shininess, and kd[1] came out 0.0037 ± 0.0036 (true 0.02).
    res, fac, user = _fit_scene(ts, img, uncertainty=False)
    _check(res, fac, [s.material for s in ts.scene], user)
    mirror = user.names.index("mirror")
    assert res.sigma.s[2 * mirror, 1] > 0.003, res.sigma.s[2 * mirror]


def test_a_value_still_held_is_never_reported_fitted():
    """A value an earlier round held (``still_held``) is a guess even when the same round greys a
    textured lobe (``guessed``, reported like a fitted value once its σ resolves it): the mirror's
    r held at its start value was reported determined beside the floor's grey ks."""
    from reflab.hardware.sim.scenes import build, render
    from reflab.inverse.forward.trees import build_trees

    ts = build("floor_mirror", W, H)
    init = user_materials(ts.scene)
    user = Scene([Surface(s.name, s.mesh_path, m, s.textured, s.mesh) for s, m in zip(ts.scene, init)])
    fac = Factorization(build_trees(user, ts.camera, ts.lights, depth=3), [get_model(m.brdf) for m in init],
                        ts.lights.intensities)
    held, textured, img = [m.given for m in init], [s.textured for s in user], render(ts)
    start = fit(fac, img, init, "ftbo", textured=textured, names=user.names, held=held)
    mirror = user.names.index("mirror")
    still = start.free.copy()
    still.s[2 * mirror] = False  # the mirror's r held, as an earlier round would
    res = fit(fac, img, start.materials, "ftbo", textured=textured, names=user.names, held=held, scan=False,
              structure=start.structure, still_held=still, guessed=[{"ks"}, set()])
    assert "r" in res.undetermined[mirror] and not res.free.s[2 * mirror].any()


def test_a_textured_surface_lobe_is_grey():
    """A textured surface is a dielectric: its highlight has the lamp's colour, so its last texture
    round holds ks at the mean over the bands and refits the shininess. Where its colours do not
    determine it (the full-colour print_can, 160x120, 1 % noise) it is still reported undetermined;
    a ks the user gave is left as given."""
    from reflab.hardware.sim.scenes import build, render
    from reflab.inverse.fit.texture_aware import grey_lobes

    ts = build("print_can", 160, 120)
    img = render(ts)
    img = img + np.random.default_rng(0).normal(0.0, 0.01 * img.max(), img.shape)
    res, fac, user = _fit_scene(ts, img)
    box = user.names.index("can")
    ks = np.asarray(res.materials[box]["ks"])
    assert np.ptp(ks) == 0.0 and 0.0 < ks[0] < 0.5, ks
    assert {"ks", "ns"} <= set(res.undetermined[box])
    given = [set(), {"ks"}]
    mats, guessed = grey_lobes(res.materials, [False, True], given)
    assert guessed == [set(), set()] and mats[box] is res.materials[box]


def test_corrupted_pane_edge_pixels_are_rejected():
    """Homogeneous lab by the reference renderer, 20 pixels at the transparent sheet's edges scaled by
    0.3-2: without rejection the fit is poor and parameters move by up to 0.24; with it, every
    determined parameter is within 1e-3 (θ relative) and the pixels are counted and mapped."""
    from reflab.hardware.sim.lab import build_lab
    from reflab.hardware.sim.reference import render_reference
    from reflab.inverse.forward.trees import build_trees

    lab = build_lab(W, H, textured=False)
    truth = [s.material for s in lab.scene]
    img = render_reference(lab.scene, lab.camera, lab.lights, depth=3)
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    first = np.full(W * H, -1)
    primary = trees.level == 1
    first[trees.pixel[primary]] = trees.surface[primary]
    f = first.reshape(H, W)
    edge = np.zeros((H, W), dtype=bool)
    edge[:-1] |= f[:-1] != f[1:]
    edge[1:] |= f[1:] != f[:-1]
    edge[:, :-1] |= f[:, :-1] != f[:, 1:]
    edge[:, 1:] |= f[:, 1:] != f[:, :-1]
    rng = np.random.default_rng(0)
    pick = rng.choice(np.flatnonzero((edge & (f == 2)).ravel()), 20, replace=False)
    bad = img.reshape(-1, 3).copy()
    bad[pick] *= rng.uniform(0.3, 2.0, (20, 1))
    fac = Factorization(trees, [get_model(m.brdf) for m in truth], lab.lights.intensities)
    res = fit(fac, bad.reshape(img.shape), user_materials(lab.scene), "ftbo")
    t = params_of(fac, truth)
    assert np.abs(res.params.x - t.x)[res.free.x].max() < 1e-3  # measured 1.9e-4
    assert np.abs(res.params.s - t.s)[res.free.s].max() < 1e-3  # measured 3.3e-4
    assert (np.abs(res.params.theta - t.theta) / t.theta)[res.free.theta].max() < 1e-3
    rejected = {y * W + x for x, y in res.stats["rejected"]["pixels"]}
    assert res.stats["rejected"]["count"] == len(rejected) and len(rejected & set(pick.tolist())) >= 15


def test_plausible_ranges_are_kept_and_flagged():
    """Phong ks at most 1 / L(ns) (energy); a fit whose best ks lies beyond stops at the bound,
    flags it, and the reconstructed box of the issue (ks = [16.1, 0, 0]) is clipped."""
    from reflab.hardware.sim.lab import build_lab
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees

    np.testing.assert_allclose(1 / phong_lobe_albedo([2.0, 30.0]), [1.2, 4.53], rtol=2e-3)
    lab = build_lab(W, H, textured=False)
    truth = [s.material.copy() for s in lab.scene]
    truth[1].params.update(ks=np.array([6.0, 0.2, 0.2]), ns=np.float64(4.0))  # box: red ks above 1/L(4) = 1.6
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    fac = Factorization(trees, [get_model(m.brdf) for m in truth], lab.lights.intensities)
    res = fit(fac, render(trees, truth, lab.lights.intensities), user_materials(lab.scene), "ftbo")
    ub = linear_upper(fac, res.params.theta)
    assert np.all(res.params.x <= ub[:, None] + 1e-12) and not clip(fac, res.params.copy())
    assert "upper" in res.stats["at_bound"][1].values()  # the box's red ks or kd, pushed to its bound
    p = params_of(fac, truth)
    p.x[fac.layout.x_offset[1] + 1] = [16.1, 0.0, 0.0]
    p.theta[0] = 2.4
    assert clip(fac, p) and p.x[fac.layout.x_offset[1] + 1, 0] == pytest.approx(1 / phong_lobe_albedo(2.4))
    every = Free(np.ones_like(p.x, dtype=bool), np.ones_like(p.s, dtype=bool), np.ones_like(p.theta, dtype=bool))
    assert at_bound(fac, p, every)[1]["ks[0]"] == "upper"


def test_an_oren_nayar_roughness_at_zero_is_flagged_quietly():
    """Oren-Nayar's σ range starts at 0 (ns and Ward's α are judged in log2): at σ = 0 it is flagged
    at its lower bound, with no log of zero on the way (it warned "divide by zero")."""
    import warnings

    from reflab.hardware.sim.lab import build_lab, _material
    from reflab.inverse.forward.trees import build_trees

    lab = build_lab(W, H, textured=False)
    mats = [s.material for s in lab.scene]
    mats[1] = _material("oren-nayar", kd=0.4, sigma=0.0)
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    fac = Factorization(trees, [get_model(m.brdf) for m in mats], lab.lights.intensities)
    p = params_of(fac, mats)
    every = Free(np.ones_like(p.x, dtype=bool), np.ones_like(p.s, dtype=bool), np.ones_like(p.theta, dtype=bool))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        flags = at_bound(fac, p, every)
    assert flags[1]["sigma"] == "lower"


def test_values_given_in_scene_json_are_held():
    """A shininess the user wrote down is kept, even a wrong one; the rest is fitted around it."""
    from reflab.hardware.sim.lab import build_lab
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees

    lab = build_lab(W, H, textured=False)
    truth = [s.material for s in lab.scene]
    trees = build_trees(lab.scene, lab.camera, lab.lights, depth=3)
    fac = Factorization(trees, [get_model(m.brdf) for m in truth], lab.lights.intensities)
    init = user_materials(lab.scene)
    init[4].params["ns"] = np.float64(45.0)
    held = [set() for _ in init]
    held[4] = {"ns"}
    res = fit(fac, render(trees, truth, lab.lights.intensities), init, "ftbo", held=held)
    assert res.materials[4]["ns"] == 45.0 and "ns" in res.undetermined[4]
    assert np.all(np.isfinite(res.params.x))


def test_sigma_holds_over_noise_and_texture_realisations():
    """σ is honest when both the noise and the texture change (the issue's calibration of σ):
    6 realisations of each scene, each its own texture (reflab.hardware.sim.scenes.build's texture_seed)
    photographed by the reference renderer with 1 % noise: at least 95 % of the determined values
    within 3σ of the truth, every one within 3σ + 2 % (docs/fit.md: 99.7 % of 289 over 20)."""
    from reflab.hardware.sim.scenes import NAMES, build, render

    ratios, bar = [], []
    for name in NAMES:
        for seed in range(6):
            ts = build(name, W, H, texture_seed=seed)
            img = render(ts)
            img = img + np.random.default_rng(seed).normal(0.0, 0.01 * img.max(), img.shape)
            res, fac, user = _fit_scene(ts, img)
            for _, _, fitted, true, sigma in determined(res, fac, [s.material for s in ts.scene], user):
                ratios.append(abs(fitted - true) / sigma)
                bar.append(abs(fitted - true) <= 3 * sigma + 0.02 * abs(true) + 1e-9)
    ratios = np.array(ratios)
    assert len(ratios) > 60 and np.all(np.isfinite(ratios))
    assert np.mean(ratios <= 3) >= 0.95, np.sort(ratios)[-5:]
    assert all(bar), np.sort(ratios)[-5:]


def test_a_reflection_the_user_gave_is_not_zeroed_as_confounded():
    """The shiny box's r is confounded with its texture and held at 0 when unknown; a value the
    user wrote in scene.json is held at that value instead."""
    from reflab.hardware.sim.scenes import build, render
    from reflab.inverse.fit.texture_aware import fit_with_texture
    from reflab.inverse.forward.trees import build_trees
    from reflab.reconstruction.scene import Material

    ts = build("shiny_box", W, H)
    img = render(ts)
    init = user_materials(ts.scene)
    box = [i for i, s in enumerate(ts.scene) if s.textured][0]
    init[box] = Material.from_json({"brdf": "phong", "ior": None, "r": 0.05}, "scene.json", "box")
    user = Scene([Surface(s.name, s.mesh_path, m, s.textured, s.mesh) for s, m in zip(ts.scene, init)])
    trees = build_trees(user, ts.camera, ts.lights, depth=3)
    models = [get_model(m.brdf) for m in init]
    held = [m.given for m in init]
    assert "r" in held[box]
    fac = Factorization(trees, models, ts.lights.intensities)
    start = fit(fac, img, init, "ftbo", textured=[s.textured for s in user], names=user.names, held=held)
    res, _ = fit_with_texture(trees, user, models, ts.lights.intensities, img, start, rounds=2, held=held)
    assert np.allclose(res.materials[box]["r"], 0.05) and np.allclose(start.materials[box]["r"], 0.05)


def test_a_lobe_the_texture_colours_give_is_not_an_earlier_round_hold():
    """A lobe an earlier round held (``still_held``: a texture round that could not resolve it) and
    the last round takes from the texture's colours (``colour``) is that estimate, fresh, with its
    σ: reported determined, as without the hold (the lab's tile, seven photographs at 640x480,
    texture rounds that went on: held at ks [0.70, 0.52, 0.17] in a middle round, reported
    undetermined at the colours' 0.350 / 60.0 for 0.35 / 60). curved, two inks, 1 % noise."""
    import dataclasses

    from reflab.hardware.sim.scenes import build, render
    from reflab.inverse.fit.dichromatic import colour_lobes
    from reflab.inverse.forward.trees import build_trees

    ts = build("curved", W, H)
    img = render(ts)
    img = img + np.random.default_rng(0).normal(0.0, 0.01 * img.max(), img.shape)
    init = user_materials(ts.scene)
    user = Scene([Surface(s.name, s.mesh_path, m, s.textured, s.mesh) for s, m in zip(ts.scene, init)])
    trees = build_trees(user, ts.camera, ts.lights, depth=3)
    fac = Factorization(trees, [get_model(m.brdf) for m in init], ts.lights.intensities)
    held, textured = [m.given for m in init], [s.textured for s in user]
    start = fit(fac, img, init, "ftbo", textured=textured, names=user.names, held=held)
    s = textured.index(True)
    lobes = colour_lobes(trees, start.materials, ts.lights.intensities, img, textured, start.stats["noise"], held=held)
    assert s in lobes and lobes[s].resolved()
    mats = list(start.materials)
    mats[s] = dataclasses.replace(mats[s], params=dict(mats[s].params) | {"ks": np.full(3, lobes[s].ks),
                                                                          "ns": float(lobes[s].theta)})
    guessed = [{"ks", "ns"} if i == s else set() for i in range(len(mats))]
    k, q = fac.layout.x_offset[s] + fac.models[s].linear.index("ks"), fac.layout.theta_offset[s]
    still = start.free.copy()
    still.x[k], still.theta[q] = False, False  # held by an earlier round
    runs = [fit(fac, img, mats, "ftbo", textured=textured, names=user.names, held=held, scan=False,
                structure=start.structure, still_held=h, guessed=guessed, colour={s: lobes[s]}, reject=False)
            for h in (None, still)]
    for res in runs:
        assert not {"ks", "ns"} & {n.split("[")[0] for n in res.undetermined[s]}, res.undetermined[s]
        truth = ts.scene[s].material
        assert abs(float(res.materials[s]["ns"]) - float(truth["ns"])) <= 3 * res.sigma.theta[q]
