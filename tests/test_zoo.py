"""The zoo (hardware/sim/zoo.py, docs/fit.md "The zoo"): random scenes the fit was never tuned on.

The generator is deterministic per seed and writes workspaces the stages read; a few seeds at a
small size go through ``reflab fit`` and no determined value may be confidently wrong (beyond
3σ + 2 % of the truth), the bar of docs/figures/zoo.py's table.
"""
import json

import numpy as np
import pytest

from reflab.hardware.sim.zoo import compare, deviation, random_scene, score, sphere_mesh, write_zoo_workspace

#: (seed, noise): varied and quick at 80x60: glass and a textured cylinder (4); glass, a mirror and
#: noise (9); seven surfaces with spheres, a wall and inks (6); a glass box under 1 % noise (2:
#: with the noise clipped at 0 its glass kd came out 3–5σ + 2 % off).
CASES = ((4, 0.0), (9, 0.0), (6, 0.0), (2, 0.01))


def _signature(zoo):
    mats = [(s.name, s.material.brdf, s.material.ior, s.textured, {k: np.asarray(v).tolist() for k, v in s.material.params.items()})
            for s in zoo.scene]
    pts = np.random.default_rng(0).uniform(-0.1, 0.1, (50, 3))
    return (mats, [s.mesh.vertices.tolist() for s in zoo.scene], zoo.lights.positions.tolist(),
            zoo.lights.intensities.tolist(), zoo.camera.R.tolist(), zoo.camera.t.tolist(),
            [zoo.albedo(i, pts).tolist() for i in range(len(zoo.scene))])


def test_generator_is_deterministic_and_varied():
    assert _signature(random_scene(7, 80, 60)) == _signature(random_scene(7, 80, 60))
    scenes = [random_scene(s, 80, 60) for s in range(12)]
    assert len({json.dumps(_signature(z)[0]) for z in scenes}) == 12
    for z in scenes:
        assert 3 <= len(z.scene) <= 8 and 1 <= len(z.lights) <= 3
        assert z.scene[0].name == "ground"
        for s in list(z.scene)[1:]:
            assert s.mesh.is_closed(), (z.seed, s.name)
            assert s.mesh.vertices[:, 2].min() >= 0.001 - 1e-12  # lifted off the ground: no shared face
        for i, s in enumerate(z.scene):
            m = s.material
            assert np.all((m["kd"] >= 0) & (m["kd"] <= 1)), (z.seed, s.name)
            if m.ior is not None:
                assert 1.4 <= m.ior <= 1.6 and np.all(m["r"] == 1) and np.all(m["t"] >= 0.8)
            if s.textured:  # kd is the texture's mean over the surface
                np.testing.assert_allclose(m["kd"], z.albedo(i, s.mesh.sample_points(20000)).mean(axis=0), atol=1e-12)
    kinds = " ".join(d for z in scenes for d in z.description)
    for word in ("glass", "mirror", "ward", "lambert", "ink", "noise", "sphere", "cylinder", "box", "wall"):
        assert word in kinds, word


def test_sphere_mesh_is_closed_and_round():
    m = sphere_mesh(0.03, (0.1, 0.0, 0.031))
    assert m.is_closed()
    np.testing.assert_allclose(np.linalg.norm(m.vertices - [0.1, 0.0, 0.031], axis=1), 0.03, atol=1e-12)
    centroid = m.vertices[m.triangles].mean(axis=1) - [0.1, 0.0, 0.031]
    assert np.all(np.einsum("ij,ij->i", m.face_normals(), centroid) > 0)  # outward


def test_workspace_holds_only_what_a_user_knows(tmp_path):
    from reflab.core.images import read_image
    from reflab.core.workspace import Workspace, read_json
    from reflab.reconstruction.scene import Scene

    zoo = write_zoo_workspace(tmp_path, 9, 40, 30, noise=0.01)
    scene = Scene.load(tmp_path / "scene.json")
    assert scene.names == zoo.scene.names
    for s, true in zip(scene, zoo.scene):
        assert s.material.brdf == true.material.brdf and s.material.ior == true.material.ior
        assert s.material.given == ({"r"} if true.material.brdf == "lambert" else set())
    truth = read_json(tmp_path / "truth.json")["surfaces"]
    np.testing.assert_allclose(truth[1]["material"]["kd"], zoo.scene[1].material["kd"])
    img = read_image(tmp_path / "input.exr")
    assert img.shape == (30, 40, 3) and np.all(np.isfinite(img)) and img.max() > 0
    for which in ("novel", "relit"):
        pose, image = Workspace(tmp_path / "truth").view(which)
        assert pose.exists() and read_image(image).shape == (30, 40, 3)
    # Same seed, same noise: the same photograph.
    write_zoo_workspace(tmp_path / "again", 9, 40, 30, noise=0.01, truth_views=False)
    np.testing.assert_array_equal(read_image(tmp_path / "again" / "input.exr"), img)


def test_score_flags_a_confident_wrong_value():
    report = {"columns": {"names": ["kd0", "ks1"]},
              "surfaces": [{"name": "ground", "material": {"brdf": "lambert", "kd": [0.5, 0.5, 0.5], "r": [0, 0, 0]},
                            "sigma": {"kd": [0.01, 0.01, 0.01]}, "undetermined": ["r"]},
                           {"name": "box", "material": {"brdf": "phong", "kd": [0.3] * 3, "ks": [0.2] * 3, "ns": 40.0,
                                                        "r": [0.0] * 3},
                            "sigma": {"kd": [0.001] * 3, "ks": [0.01] * 3, "ns": None, "r": [0.001] * 3},
                            "undetermined": ["ns"]}]}
    truth = {"surfaces": [{"material": {"brdf": "lambert", "kd": [0.5, 0.53, 0.58], "r": [0] * 3, "ior": None}},
                          {"material": {"brdf": "phong", "kd": [0.3] * 3, "ks": [0.2] * 3, "ns": 80.0, "r": [0.0] * 3,
                                        "ior": None}}]}
    s = score(compare(report, truth, [False, False]))
    # ground kd[2] is 8σ off (beyond 3σ + 2 %), kd[1] 3σ off but within 3σ + 2 %; ns is undetermined.
    assert s["wrong"] == ["ground kd[2] fit 0.5 true 0.58 σ 0.01"]
    assert s["visible"] == 3 + (3 + 3 + 1 + 3) and s["determined"] == 12  # a lambert r is the user's, not fitted
    assert s["recovered"] == 11  # ground kd[2] is 14 % off; box r (true 0) within 0.01


@pytest.mark.parametrize("seed,noise", CASES)
def test_no_confident_wrong_value(tmp_path, seed, noise):
    from reflab.core.workspace import read_json
    from reflab.inverse.stages import FitOptions, fit

    zoo = write_zoo_workspace(tmp_path, seed, 80, 60, noise=noise, truth_views=False)
    result = fit(FitOptions(tmp_path))
    s = score(compare(result.report, read_json(tmp_path / "truth.json"), [x.textured for x in zoo.scene]))
    assert s["determined"] >= 10, s  # the photograph determines something: the check below has teeth
    assert s["wrong"] == [], "; ".join(zoo.description)
    assert s["recovered"] >= 0.5 * s["determined"], s
    assert _lobe_on_bound(result.report) == []  # undetermined means plausible, not a range bound


def _lobe_on_bound(report) -> list:
    """Undetermined lobe values (ks bands, ns, alpha) that fit.json reports on a range bound."""
    from reflab.inverse.fit.ranges import FIT_RANGE, phong_lobe_albedo

    out = []
    for item in report["surfaces"]:
        m, und = item["material"], item["undetermined"]
        upper = 1.0 / float(phong_lobe_albedo(m["ns"])) if m["brdf"] == "phong" else 1.0
        for c, v in enumerate(m.get("ks", [])):
            if ("ks" in und or f"ks[{c}]" in und) and not 1e-6 * upper < v < (1 - 1e-6) * upper:
                out.append((item["name"], f"ks[{c}]", v))
        if "ns" in und and not FIT_RANGE["ns"][0] < m["ns"] < FIT_RANGE["ns"][1]:
            out.append((item["name"], "ns", m["ns"]))
        if "alpha" in und and not 1e-4 < m["alpha"] < 1.0:
            out.append((item["name"], "alpha", m["alpha"]))
    return out


def test_undetermined_lobe_is_held_at_a_plausible_value(tmp_path):
    """Seed 4's textured wall hides its highlight (true ks 6.2 at ns 180): its lobe is undetermined.
    Left where the fit put it, ks was 0, the range's lower bound; then the fit's start (ks 0.1 at
    ns 90.5, a lobe of albedo 0.008). No pixel shows a lobe of that shape, so it is reported (and
    so rendered) at the prior's mean albedo over the field's lobes (determined.plausible_lobes),
    with its σ still saying undetermined."""
    from reflab.core.workspace import read_json
    from reflab.inverse.fit.ranges import ABSENT, LOBE_ALBEDO, phong_lobe_albedo
    from reflab.inverse.stages import FitOptions, fit

    zoo = write_zoo_workspace(tmp_path, 4, 80, 60, truth_views=False)
    report = fit(FitOptions(tmp_path)).report
    assert _lobe_on_bound(report) == []
    wall = report["surfaces"][zoo.scene.names.index("wall")]
    assert {"ks", "ns"} <= set(wall["undetermined"])
    albedo = np.asarray(wall["material"]["ks"]) * float(phong_lobe_albedo(wall["material"]["ns"]))
    np.testing.assert_allclose(albedo, (1 - ABSENT) * LOBE_ALBEDO / 2, rtol=1e-3)  # one grey lobe, unseen
    assert all(s is None or s > wall["material"]["ks"][0] for s in wall["sigma"]["ks"])  # σ spans its scale: honest
    assert not any(k.startswith("ks") for k in wall["at_bound"])
    s = score(compare(report, read_json(tmp_path / "truth.json"), [x.textured for x in zoo.scene]))
    assert s["wrong"] == []


def test_plausible_moves_only_undetermined_values_on_a_bound():
    """ranges.plausible on a zoo scene's parameters: an undetermined ks at its upper bound (a lobe
    reflecting all the light: the issue's 4x too bright novel view) and an undetermined ns on its
    bound go to INITIAL; an undetermined ks inside its range and a determined ks on a bound stay."""
    from reflab.inverse.fit.problem import Free, params_of
    from reflab.inverse.fit.ranges import linear_upper, plausible
    from reflab.inverse.forward.factorization import Factorization
    from reflab.inverse.forward.models import get_model
    from reflab.inverse.forward.trees import build_trees
    from reflab.reconstruction.scene import INITIAL

    zoo = random_scene(8, 40, 30)  # five phong surfaces
    trees = build_trees(zoo.scene, zoo.camera, zoo.lights, depth=2)
    fac = Factorization(trees, [get_model(s.material.brdf) for s in zoo.scene], zoo.lights.intensities)
    p = params_of(fac, [s.material for s in zoo.scene])
    lay = fac.layout
    ks = [k for k, (_, n) in enumerate(lay.x_names) if n == "ks"]
    ns = [q for q, (_, n) in enumerate(lay.theta_names) if n == "ns"]
    assert len(ks) >= 4 and len(ns) >= 4
    ub = linear_upper(fac, p.theta)
    p.x[ks[0]] = [ub[ks[0]], 0.3, ub[ks[0]]]  # loose, two bands on the upper bound
    p.x[ks[1]] = 0.3  # loose, inside
    p.x[ks[2]] = ub[ks[2]]  # determined, on its bound
    th = ns[[lay.theta_names[q][0] for q in ns].index(lay.x_names[ks[3]][0])]  # a fourth surface's ns
    p.theta[th] = 2.0  # loose, on ns's lower bound
    loose = Free(np.zeros_like(p.x, dtype=bool), np.zeros_like(p.s, dtype=bool), np.zeros_like(p.theta, dtype=bool))
    loose.x[ks[0]] = loose.x[ks[1]] = True
    loose.theta[th] = True
    before = p.copy()
    moved = plausible(fac, p, loose)
    s0 = lay.x_names[ks[0]][0]
    assert (s0, "ks[1]") in moved and (lay.theta_names[th][0], "ns") in moved and len(moved) == 4
    assert p.theta[th] == INITIAL["ns"]
    np.testing.assert_array_equal(p.x[ks[0]], INITIAL["ks"])  # a grey lobe at the prior's centre
    np.testing.assert_array_equal(p.x[ks[1]], before.x[ks[1]])
    np.testing.assert_array_equal(p.x[ks[2]], before.x[ks[2]])
    np.testing.assert_array_equal(p.x[ks[3]], before.x[ks[3]])  # its bound rose with ns: still inside


def test_a_lobe_height_known_only_to_a_factor_is_undetermined(tmp_path):
    """Zoo seed 28 at 160x120, seven photographs, 1 % noise: only the 70° turn shows the wall's
    lobe, at most 0.006 a pixel (noise 0.007). Along the ridge of so faint a lobe its height's
    linearised σ shrinks with its estimate: this noise realisation reported ks 0.35 ± 0.15 for
    1.09 (5σ), four others 0.64-1.21 ± 0.42-0.62, and the noise-free photographs leave it
    undetermined. A lobe height beside a free shape is judged in log2 units as its shape is
    (determined.RESOLVE_LOBE): undetermined, and every value reported is within 3σ + 2 %."""
    from reflab.hardware.sim.zoo import write_further_photographs
    from reflab.inverse.stages import FitOptions, fit

    zoo = write_zoo_workspace(tmp_path, 28, 160, 120, noise=0.01, truth_views=False)
    write_further_photographs(tmp_path, zoo, "L0,L1,T35,T-35,T70,T-70", 3)
    report = fit(FitOptions(tmp_path)).report
    wall = next(s for s in report["surfaces"] if s["name"] == "wall")
    assert {"ks", "ns"} <= set(wall["undetermined"]), wall["undetermined"]
    rows = compare(report, json.loads((tmp_path / "truth.json").read_text()), [s.textured for s in zoo.scene])
    assert score(rows)["wrong"] == [], score(rows)["wrong"]


def test_a_broad_lobe_does_not_starve_the_rounds_texture(tmp_path):
    """Zoo seed 49 at 320x240, seven photographs, 1 % noise: the ground's lobe is broad (ns 5,
    albedo 0.09 beside a green kd of 0.28), so it carries over a tenth of nearly every ground
    pixel's light. Read only where texture carries 90 %, every other round's texture knew 1 500
    of 20 000 texels; that round fitted the ground as one colour (green kd 0.43), and a sphere
    mirroring the ground reported r[1] 0.030 ± 0.0035 for 0.046 (4.5σ). The threshold falls per
    surface to its best half of pixels (texture_aware.feeds_texture): every round's texture knows
    the ground, and every reported value is within 3σ + 2 %, the sphere's r within 3σ."""
    from reflab.hardware.sim.zoo import write_further_photographs
    from reflab.inverse.stages import FitOptions, fit

    zoo = write_zoo_workspace(tmp_path, 49, 320, 240, noise=0.01, truth_views=False)
    write_further_photographs(tmp_path, zoo, "L0,L1,T35,T-35,T70,T-70", 3)
    report = fit(FitOptions(tmp_path)).report
    rounds = report["texture_rounds"]["rounds"]
    left_out = np.array([r["pixels_left_out"] for r in rounds])
    # Before: 354 000-442 000 of 460 800 left out, swinging from round to round; now 326 000-329 000.
    assert np.ptp(left_out) < 0.05 * report["sampling"]["of"], left_out
    truth = json.loads((tmp_path / "truth.json").read_text())
    sphere = next(s for s in report["surfaces"] if s["name"] == "sphere0")
    true_r = next(s for s in truth["surfaces"] if s["name"] == "sphere0")["material"]["r"]
    z = (np.asarray(sphere["material"]["r"]) - true_r) / np.asarray(sphere["sigma"]["r"])
    assert np.all(np.abs(z) < 3.0), (sphere["material"]["r"], sphere["sigma"]["r"], true_r)
    rows = compare(report, truth, [s.textured for s in zoo.scene])
    assert score(rows)["wrong"] == [], score(rows)["wrong"]


def test_a_shape_searched_in_log2_is_judged_in_log2():
    """The fit searches ns (and Ward's α) in log2, where its σ is symmetric: ns ± σ is the linear
    step of a log2 σ of σ / (ns ln 2). Held-out seed 61 with one photograph (320x240, 1 % noise)
    fitted a box's ns 5.20 ± 1.65 for 11.03: 3.5σ linearly, 2.4σ in log2. Judged in log2 it is
    not confidently wrong, where a linear parameter with the same numbers is; and a shape fitted
    above its truth is judged tighter than linearly (20 ± 5.5 for 7: 2.4σ linearly, 3.8σ in log2)."""
    up = ("box2", "ns", 5.2039, 11.0345, 1.6528, True)
    z, margin = deviation("ns", *up[2:5])
    assert z == pytest.approx(np.log2(11.0345 / 5.2039) / (1.6528 / (5.2039 * np.log(2))), rel=1e-12)
    assert 2.3 < z < 2.4 and margin < 0
    assert score([up])["wrong"] == [] and score([up])["within_3sigma"] == 1
    assert len(score([("box2", "ks", 5.2039, 11.0345, 1.6528, True)])["wrong"]) == 1
    down = ("box2", "ns", 20.0, 7.0, 5.5, True)
    assert abs(20.0 - 7.0) / 5.5 < 3 and len(score([down])["wrong"]) == 1
    assert deviation("ns", 20.0, 7.0, 5.5)[0] == pytest.approx(np.log2(20 / 7) / (5.5 / (20 * np.log(2))))
