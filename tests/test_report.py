"""`reflab report` writes a self-contained report.html whose numbers come from the stages' files and truth/.

The workspace is the simulated lab at 80×60 with every stage's output made by the product's own
code where it is quick (camera calibration on projected target centres, lamp location from
projected rod marks, the texture stage, the reference renderer for input and truth images) and
written by hand where the real stage takes minutes (sfm.json, sparse.ply: points sampled on the
true surfaces and moved off them by a known distance; fit.json: the true materials, one
perturbed). The truth is perturbed by known amounts, and the report must show those amounts.
"""
import base64
import json
import re
from html.parser import HTMLParser

import numpy as np
import pytest

from reflab.app.cli import main
from reflab.app.demo_score import true_albedo
from reflab.calibration.camera import Camera
from reflab.calibration.lamps import Mark, locate_lamps, write_marks
from reflab.calibration.lights import Lights, PointLight
from reflab.calibration.tsai import calibrate
from reflab.core.images import write_image
from reflab.hardware.sim import props as st
from reflab.hardware.sim.lab import build_lab, write_lab
from reflab.hardware.sim.reference import render_reference
from reflab.core.workspace import write_json

SIZE = (80, 60)
LAMP_SHIFT_MM = 2.0  # lamp 0 of lights.json is this far from the truth, along x
SURFACE_OFFSET_MM = 1.0  # the sparse points sit this far off the true surfaces
FX_SHIFT = 0.5  # camera.json's fx minus the truth's


class Page(HTMLParser):
    """Ids, images and every URL-carrying attribute of an HTML page."""

    def __init__(self):
        super().__init__()
        self.ids, self.images, self.urls, self.tags, self.text = {}, [], [], [], []
        self._stack = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append(tag)
        if "id" in a:
            self.ids[a["id"]] = tag
        if tag == "img":
            self.images.append(a.get("src", ""))
        self.urls += [v for k, v in attrs if k in ("src", "href", "data", "action", "poster") and v]
        self._stack.append(tag)

    def handle_data(self, data):
        self.text.append(data)


def parse(path) -> Page:
    page = Page()
    page.feed(path.read_text())
    page.all_text = " ".join(page.text)
    return page


def _calibration_block(lab):
    """camera.json's calibration block from calibrate() on projected target centres (4 views)."""
    cam = lab.camera
    points = st.target_points(7, 5, 0.02)
    rng = np.random.default_rng(0)
    obs = [Camera(cam.width, cam.height, cam.K, cam.dist, R, t).project(points) + rng.normal(0, 0.05, (len(points), 2))
           for R, t in st.random_target_poses(4, 7, 5, 0.02, seed=3, distance=0.3, max_tilt_deg=35)]
    res = calibrate(obs, points, (cam.width, cam.height), bias_correction=False)
    return dict(res.report([f"captures/calibration/{i:04d}.exr" for i in range(4)]), grid=[7, 5], spacing=0.02)


def _lamps(root, lab):
    """marks.json from projected rod feet and shadow tips, and the lamps located from them."""
    rng = np.random.default_rng(1)
    marks = []
    for k, light in enumerate(lab.lights):
        feet = np.column_stack([rng.uniform(-0.1, 0.1, 6), rng.uniform(-0.05, 0.1, 6), np.zeros(6)])
        tips = np.array([st.RodScene(f, 0.05, 0.0015, light.position).tip for f in feet])
        for b, t in zip(lab.camera.project(feet) + rng.normal(0, 0.1, (6, 2)), lab.camera.project(tips)):
            marks.append(Mark(f"captures/lights/{k:04d}.exr", k, b, t))
    write_marks(root / "marks.json", 0.05, marks)
    fits = locate_lamps(lab.camera, marks, 0.05)
    lights = [PointLight(f.position, l.intensity, f.covariance, {"calibration": dict(f.report(), time_s=0.01)})
              for f, l in zip(fits, lab.lights)]
    # lights.json as written holds the truth shifted: the report must show the shift as the error.
    lights[0] = PointLight(lab.lights[0].position + [LAMP_SHIFT_MM / 1e3, 0, 0], lights[0].intensity,
                           lights[0].sigma_position, lights[0].extra)
    Lights(lights).save(root / "lights.json")


def _sparse(root, lab):
    """sfm.json and sparse.ply: points on the true ground and tile, moved off them along +z."""
    import open3d as o3d

    rng = np.random.default_rng(2)
    ground = np.column_stack([rng.uniform(-0.2, 0.2, 300), rng.uniform(-0.1, 0.3, 300), np.zeros(300)])
    tile = lab.scene[lab.scene.index("tile")].mesh
    top = tile.vertices[tile.vertices[:, 2] > 0.007]
    w = rng.dirichlet(np.ones(len(top)), 100)
    points = np.concatenate([ground, w @ top]) + [0, 0, SURFACE_OFFSET_MM / 1e3]
    o3d.io.write_point_cloud(str(root / "sparse.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
    angles = np.arange(0, 360, 45.0)
    err = [0.01 * np.sin(np.radians(a)) for a in angles]
    write_json(root / "sfm.json", {
        "sfm": {"images": 8, "registered": 7, "reprojection_px": 0.31, "points": 400, "time_s": {"total_s": 4.2}},
        "rigid_turntable": {"used": True, "rms_px": 0.35, "rms_px_free": 0.31, "time_s": 1.1},
        "turntable": {"axis_tilt_deg": 0.05, "angle_error_deg": err, "max_angle_error_deg": 0.01,
                      "rms_angle_error_deg": 0.007, "angles_deg": angles.tolist()},
        "registration": {"method": "axis", "scale": 1.0}, "reference": {"centre_mm": 0.2, "rotation_deg": 0.01},
        "time_s": 6.0, "images": [f"captures/turntable/{i:04d}.exr" for i in range(8)],
        "poses": {f"captures/turntable/{i:04d}.exr": _turned_pose(lab.camera, a) for i, a in enumerate(angles[:7])}})


def _turned_pose(camera, degrees):
    """The camera's pose turned about the world's vertical axis (a turntable shot, seen from the object)."""
    a = np.radians(degrees)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    R = camera.R @ Rz.T
    return {"R": R, "t": -R @ (Rz @ camera.center)}


def _captures(root, photo):
    for folder, kind in (("turntable", "sweep"), ("lights", "lights"), ("input", "input")):
        shots = []
        for i in range(1 if kind == "input" else 2):
            name = "input.exr" if kind == "input" else f"{i:04d}.exr"
            write_image(root / "captures" / folder / name, photo)
            shots.append({"file": name, "role": kind, "angle": 180.0 * i, "lamps": [True, True],
                          "time": f"2026-11-23T10:0{i}:00+00:00", "exposure": 0.5, "size": list(SIZE)})
        write_json(root / "captures" / folder / "manifest.json", {
            "kind": kind, "status": "complete", "error": None, "plan": shots, "shots": shots,
            "camera": {"type": "simulated"}, "started": "2026-11-23T10:00:00+00:00", "updated": "2026-11-23T10:01:00+00:00"})


@pytest.fixture(scope="module")
def lab_workspace(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    lab = build_lab(*SIZE)
    write_lab(root, lab, materials=False)
    write_lab(root / "truth", lab)  # truth/camera.json, lights.json, scene.json + meshes
    (root / "truth" / "truth.json").unlink(missing_ok=True)
    write_image(root / "truth" / "albedo.exr", true_albedo(lab), allow_nan=True)  # as write_truth writes it
    photo = render_reference(lab.scene, lab.camera, lab.lights, depth=2, albedo=lab.albedo)
    write_image(root / "input.exr", photo)
    novel = Camera.look_at(*SIZE, 50.0, eye=(0.35, -0.25, 0.4), target=(0.0, 0.03, 0.0))
    novel.save(root / "truth" / "novel_camera.json")
    write_image(root / "truth" / "novel.exr", render_reference(lab.scene, novel, lab.lights, depth=2, albedo=lab.albedo))
    relit = Lights([PointLight([-0.3, 0.3, 0.5], lab.lights[0].intensity)])
    relit.save(root / "truth" / "relit_lights.json")
    write_image(root / "truth" / "relit.exr", render_reference(lab.scene, lab.camera, relit, depth=2, albedo=lab.albedo))

    cam = json.loads((root / "camera.json").read_text())
    cam["K"][0][0] += FX_SHIFT
    cam["calibration"] = dict(_calibration_block(lab), warnings=["focal length poorly determined (test)"])
    write_json(root / "camera.json", cam)
    _lamps(root, lab)
    _sparse(root, lab)
    _captures(root, photo)
    surfaces = []
    for s in lab.scene:
        material = s.material.to_json()
        if s.name == "tile":
            material["ns"] = 50.0  # truth 60
        surfaces.append({"name": s.name, "material": material, "sigma": {"ns": 2.0}, "undetermined": [],
                         "at_bound": {"ks[0]": "upper"} if s.name == "box" else {}})
        if s.name == "box":
            surfaces[-1].update(albedo_model="texture", albedo_evidence={
                "pixels": 812, "chi2_uniform": 9000.0, "chi2_texture": 2000.0, "block_px": 2, "blocks": 210,
                "delta_bic": 3141.5, "colour": [0.4, 0.3, 0.2], "noise": [0.002, 0.002, 0.003]})
    write_json(root / "fit.json", {"method": "ftbo", "depth": 2, "time_s": 1.5, "rms": [0.01, 0.02, 0.03],
                                   "status": "ok", "noise": [0.001, 0.001, 0.001],
                                   "phases_s": {"trees": 0.1, "structure": 0.05, "scan": 0.4, "refinement": 0.8},
                                   "rejected": {"count": 2, "pixels": [[1, 1], [2, 1]], "threshold_sigmas": 8.0},
                                   "trace": [[0.1, [0.1, 0.1, 0.1]], [0.8, [0.02, 0.03, 0.03]], [1.5, [0.01, 0.02, 0.03]]],
                                   "colour_lobes": {"tile": {"ks": 0.341, "sigma_ks": 0.005, "ns": 62.8, "sigma_ns": 1.9,
                                                             "colour_set": "line", "pixels": 1231, "rejected": 3, "misfit": 1.02}},
                                   "surfaces": surfaces})
    assert main(["texture", str(root)]) == 0
    return root, lab


def test_full_report_is_self_contained_with_every_section_and_the_truth(lab_workspace, capsys):
    root, lab = lab_workspace
    assert main(["report", str(root)]) == 0
    page = parse(root / "report.html")
    for section in ("captures", "camera", "lights", "geometry", "fit", "texture", "views"):
        assert page.ids.get(section) == "section", section
    assert page.ids.get("error-vs-time") == "figure"
    # The texture solve's CG recorded its residual at every iteration, falling to its stopping level.
    cg = json.loads((root / "textures" / "index.json").read_text())["stats"]["trace"]
    assert len(cg) >= 5 and cg[-1][1] < 0.1 * cg[0][1] and all(b[0] >= a[0] for a, b in zip(cg, cg[1:]))
    assert "conjugate gradient" in page.all_text
    # Every image embedded as a PNG that decodes; nothing fetched from anywhere.
    assert len(page.images) >= 15
    for src in page.images:
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    assert all(u.startswith(("data:", "#")) for u in page.urls), [u[:40] for u in page.urls if not u.startswith(("data:", "#"))]
    assert not {"script", "link", "iframe", "object"} & set(page.tags)
    assert "@import" not in (root / "report.html").read_text() and "url(" not in (root / "report.html").read_text()
    text = page.all_text
    # Camera against truth/camera.json: the fx shift, to the report's 3 significant digits.
    cal = json.loads((root / "camera.json").read_text())["calibration"]
    assert "focal length poorly determined (test)" in text
    assert len(cal["residuals_px"]) == 4 and len(cal["residuals_px"][0][0]) == 4
    assert re.search(r"fx\s+\d+\.\d+ ± [\d.e-]+\s+[\d.]+\s+" + re.escape(f"{lab.camera.K[0, 0]:.6g}") + r"\s+0\.5\b", text)
    # Lamp 0 is LAMP_SHIFT_MM from the truth; lamp 1 is where the marks put it.
    row = re.search(r"\b0\s+\[[^\]]+\]\s+\[[^\]]+\]\s+\[[^\]]+\].*?\[[^\]]+\]\s+([\d.]+)\s", text)
    assert row and float(row.group(1)) == pytest.approx(LAMP_SHIFT_MM, rel=1e-3)
    assert re.search(r"intensity error \(%, worst band\)\s+0\s.*?\s0\.0\s+1\s", text)  # lights.json's intensities are the truth's
    assert re.search(r"shots registered\s+7 of 8\s+shots not registered\s+captures/turntable/0007\.exr\s", text)
    # The sparse points sit SURFACE_OFFSET_MM off the ground: its point-to-surface RMS says so.
    ground = re.search(r"ground\s+\S+\s+lambert\s+opaque\s+yes\s+(\d+)\s+([\d.]+)", text)
    assert ground and int(ground.group(1)) >= 250 and float(ground.group(2)) == pytest.approx(SURFACE_OFFSET_MM, rel=0.01)
    # Surfaces are the truth's own meshes: placement error 0.
    assert re.search(r"tile\s+\S+\s+phong\s+opaque\s+yes\s+\d+\s+[\d.]+\s+[\d.]+\s+0\.000\s+0\.000\s", text)
    # The fit's tile ns is 10 below the truth, with its sigma.
    # A shape searched in log2 also reads as its one-σ factor: e^(σ / value).
    assert re.search(r"\b50 ± 2 \(×/÷ 1\.04\)\s+truth 60, error -10\s", text)
    assert re.search(r"\[0\.25, 0\.25, 0\.25\]\s+at its bound: ks\[0\] upper", text)
    assert "Where the fit's time went" in text and re.search(r"\bmethod\s+F-TBO\s", text)
    # The tile's lobe came from its texture's colours: the report says so, with its numbers.
    assert re.search(r"tile\s+0\.341 ± 0\.005\s+ns 62\.8 ± 1\.9 \(×/÷ 1\.03\)\s+line\s+1231 \(3 outliers\)\s+1\.02\s", text)
    # What the photograph said of the box's albedo (fit.json albedo_model).
    assert re.search(r"box\s+texture\s+812\s+3142\s+2 px \(210 blocks\)\s+\[0\.002, 0\.002, 0\.003\]\s", text)
    assert "whose re-render includes this texture" in text  # the texture's residual: the fit's maps
    assert re.search(r"outlier pixels left out of the fit\s+2 \(residual above 8 σ", text)
    # Novel and relit views against truth/ (true materials and a recovered texture): PSNR shown and sane.
    psnrs = re.findall(r"view PSNR against truth\s+([\d.]+) dB over the (\d+) % of pixels of known albedo, ([\d.]+) dB over all", text)
    assert len(psnrs) == 2 and all(float(k) > 20 and float(a) > 20 and float(k) >= float(a) - 1 and 50 < float(s) <= 100
                                   for k, s, a in psnrs), psnrs
    # The texture against truth/albedo.exr, pixel for pixel: every surface's row and the whole. With the
    # truth's geometry, lamps and materials the error is the 80x60 texels' (8-9 mm) resampling of the
    # procedural texture: RMSE [0.043, 0.034, 0.029], 83 % of pixels within 0.05 (measured).
    table = re.findall(r"(ground|box|tile|sheet|mirror|all)\s+(?:recovered texture\s+|homogeneous kd\s+)?(\d+)\s+(\d+)\s+"
                       r"\[([^\]]+)\]\s+\[[^\]]+\]\s+[\d.e-]+\s+([\d.]+)\s", text[text.index("surface seen (recovered model)"):])
    got = {name: (int(n), int(pct), [float(x) for x in rmse.split(",")], float(within)) for name, n, pct, rmse, within in table}
    assert {"ground", "box", "tile", "all"} <= set(got), table
    n, pct, rmse, within = got["all"]
    assert n > 0.9 * SIZE[0] * SIZE[1] and pct >= 95 and all(np.isfinite(rmse)) and max(rmse) < 0.06 and within > 70, got["all"]
    assert max(got["tile"][2]) < 0.045 and got["tile"][3] > 85, got["tile"]
    section = (root / "report.html").read_text()
    section = section[section.index('id="texture"'):section.index('id="views"')]
    error_map = re.search(r'<img src="data:image/png;base64,([^"]+)" alt="albedo error \(top colour', section)
    assert error_map and base64.b64decode(error_map.group(1))[:8] == b"\x89PNG\r\n\x1a\n"
    assert "holds no albedo.exr" not in text
    out = capsys.readouterr().out
    assert "[texture]" in out and "wrote " + str(root / "report.html") in out


def test_texture_section_scores_the_albedo_against_the_truth(lab_workspace):
    """The comparison's numbers follow the albedo given: the truth itself scores 0, the truth plus
    0.1 in the red band scores RMSE [0.1, 0, 0] and none within 0.05; unknown pixels are left out."""
    from reflab.app.report.data import Sources
    from reflab.app.report.sections.texture import texture_section

    root, lab = lab_workspace
    src = Sources(root)
    true = src.albedo_image("truth/albedo.exr")
    surface = np.zeros(true.shape[:2], dtype=np.int64)  # every pixel counted as the ground's
    for offset, rmse, within in ((0.0, [0, 0, 0], 100.0), (0.1, [0.1, 0, 0], 0.0)):
        rec = true + [offset, 0, 0]
        rec[:10] = np.nan  # ten rows the model does not know
        sec = texture_section(src, None, {"albedo": rec, "surface": surface})
        table = next(b for b in sec.blocks if b["kind"] == "table" and "pixels compared" in b["head"])
        all_row = table["rows"][-1]
        assert all_row[0] == "all" and all_row[2] == (SIZE[1] - 10) * SIZE[0]
        np.testing.assert_allclose(json.loads(all_row[4]), rmse, atol=2e-3)
        assert float(all_row[7]) == within and float(all_row[6]) == pytest.approx(offset, abs=2e-3)
        assert any(b["kind"] == "kv" and ("left out: the truth sees a surface, the model's albedo is unknown there",
                                          f"{10 * SIZE[0]} pixels (in a capture lamp's shadow, out of the texture's "
                                          "view, or no surface in the model)") in b["rows"] for b in sec.blocks)


def test_truth_albedo_is_the_labs_albedo_where_each_pixel_ray_lands(lab_workspace):
    """truth/albedo.exr (true_albedo) against the lab's albedo at the hits of pixel rays cast by the
    reference renderer's own ray caster (Mitsuba, not the trees' Open3D), for 40 pixels; NaN where a
    ray meets nothing (a camera looking over the horizon)."""
    from reflab.app.report.data import Sources
    from reflab.hardware.sim.lab import SimLab
    from reflab.hardware.sim.reference import _Caster

    root, lab = lab_workspace
    caster = _Caster(lab.scene)
    true = Sources(root).albedo_image("truth/albedo.exr")  # the file, as the report reads it
    rng = np.random.default_rng(4)
    pix = rng.choice(SIZE[0] * SIZE[1], 40, replace=False)
    o, d = lab.camera.rays(np.column_stack([pix % SIZE[0], pix // SIZE[0]]).astype(float))
    hit, t, surface, _, _ = caster.intersect(o, d)
    assert hit.all() and len(set(surface)) >= 3
    want = lab.albedo_at(surface, o + t[:, None] * d)
    np.testing.assert_allclose(true.reshape(-1, 3)[pix], want, atol=1e-4)  # float32 in the file
    # Over the horizon: NaN exactly where the ray meets nothing.
    sky = SimLab(Camera.look_at(*SIZE, 60.0, eye=(0.0, -0.4, 0.05), target=(0.0, 0.5, 0.1)), lab.lights, lab.scene, lab.textures)
    albedo = true_albedo(sky).reshape(-1, 3)
    o, d = sky.camera.pixel_rays()
    hit, t, surface, _, _ = caster.intersect(o, d)
    assert 0.1 < hit.mean() < 0.9
    assert np.array_equal(np.isfinite(albedo).all(axis=1), hit)
    np.testing.assert_allclose(albedo[hit], lab.albedo_at(surface[hit], o[hit] + t[hit, None] * d[hit]), atol=1e-6)


def test_partial_workspace_reports_what_ran_and_names_the_unreadable(tmp_path, capsys):
    lab = build_lab(*SIZE)
    write_lab(tmp_path, lab)
    (tmp_path / "fit.json").write_text('{"method": "ftbo", "rms": [0.1,')  # cut off mid-write
    long_warning = "word " * 80
    (tmp_path / "textures").mkdir()
    write_json(tmp_path / "textures" / "index.json", {"surfaces": [], "stats": {"note": long_warning.strip()}})
    assert main(["report", str(tmp_path), "--no-render"]) == 0
    page = parse(tmp_path / "report.html")
    assert {"camera", "lights", "geometry", "texture", "unreadable"} <= set(page.ids)
    assert "fit" not in page.ids and "views" not in page.ids and "captures" not in page.ids
    assert "error-vs-time" not in page.ids  # no fit or solve recorded its error against time
    assert str(tmp_path / "fit.json") in page.all_text and "JSONDecodeError" in page.all_text
    captured = capsys.readouterr()
    assert "fit.json is unreadable" in captured.err
    assert long_warning.strip() in captured.out  # whole values, never cut
    report = json.loads((tmp_path / "report.json").read_text())
    assert "fit" not in report and list(report["unreadable"]) == [str(tmp_path / "fit.json")]


def test_empty_workspace_says_so(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 0
    assert "no stage output" in parse(tmp_path / "report.html").all_text.lower()
    assert "no stage output" in capsys.readouterr().out


def test_report_json_holds_the_files_numbers(tmp_path):
    lab = build_lab(*SIZE)
    write_lab(tmp_path, lab)
    write_json(tmp_path / "fit.json", {"method": "ftbo", "depth": 3, "time_s": 1.5, "rms": [0.01, 0.02, 0.03],
                                       "trace": [[0.1, [0.1, 0.1, 0.1]], [1.5, [0.01, 0.02, 0.03]]],
                                       "surfaces": [{"name": lab.scene[0].name, "undetermined": ["ns"]}]})
    assert main(["report", str(tmp_path), "--no-render"]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert [s["name"] for s in report["scene"]] == lab.scene.names
    np.testing.assert_allclose([l["position"] for l in report["lights"]], lab.lights.positions)
    assert report["fit"]["undetermined"] == {lab.scene[0].name: ["ns"]} and report["fit"]["trace_points"] == 2
    assert parse(tmp_path / "report.html").ids.get("error-vs-time") == "figure"


def test_report_names_a_missing_workspace(tmp_path, capsys):
    assert main(["report", str(tmp_path / "nope")]) == 2
    assert "nope" in capsys.readouterr().err


def test_fields_of_unexpected_shape_spoil_only_their_section(tmp_path, capsys):
    """Files from another version (or edited by hand) with fields of other shapes: every section
    still appears, the ones that cannot be drawn say why, and the command succeeds."""
    (tmp_path / "captures" / "input").mkdir(parents=True)
    (tmp_path / "textures").mkdir()
    files = {"camera.json": {"width": "x", "K": "nope", "calibration": {"views": [1, {"image": 3}], "sigma": [1],
                                                                        "residuals_px": [[1, 2]], "grid": [1]}},
             "lights.json": {"lights": [{"position": "a"}, 5, {"position": [1, 2, 3], "sigma_position": [[1]]}]},
             "marks.json": {"marks": [{"base": 1}, 7], "rod_height": "x"},
             "sfm.json": {"sfm": [], "turntable": {"angle_error_deg": [None, "a"], "angles_deg": [1]}, "poses": {"a": 5}},
             "scene.json": {"surfaces": [5, {"name": "x", "mesh": "nope.ply", "material": 3}]},
             "fit.json": {"method": 5, "trace": [[1], "x", [None, 2], [1, "a"]], "surfaces": {"a": 1},
                          "rejected": {"count": 3, "pixels": "x"}, "texture_rounds": {"rounds": [5, {"rms": "x"}]}},
             "textures/index.json": {"surfaces": [5, {"surface": "x", "files": {"kd": "missing.exr"}}],
                                     "stats": {"trace": [[1, 2]], "residual_rms": "a"}},
             "captures/input/manifest.json": {"shots": [5, {"file": "nope.exr", "size": "x"}], "plan": 3}}
    for name, obj in files.items():
        write_json(tmp_path / name, obj)
    assert main(["report", str(tmp_path)]) == 0
    page = parse(tmp_path / "report.html")
    assert {"captures", "camera", "lights", "geometry", "fit", "texture"} <= set(page.ids)
    assert str(tmp_path / "nope.ply") in page.all_text  # named, as scene.json names it
    assert "[fit]" in capsys.readouterr().out


def test_export_section_gives_the_commands_and_names_the_exports_written(tmp_path):
    """The export section: one exact command per format, and the default exports already in the workspace."""
    import shlex
    import subprocess
    import sys

    from reflab.inverse.export.stage import FORMATS, ExportOptions, export

    lab = build_lab(*SIZE)
    write_lab(tmp_path, lab)
    export(ExportOptions(tmp_path, format="gltf"))  # into reflab export's default folder, export-gltf/
    assert main(["report", str(tmp_path), "--no-render"]) == 0
    page = parse(tmp_path / "report.html")
    assert page.ids.get("export") == "section"
    html = (tmp_path / "report.html").read_text()
    section = html[html.index('id="export"'):]
    section = section[:section.index("</section>")]
    commands = re.findall(r"reflab export (\S+) --format (\w+)", section)
    assert [f for _, f in commands] == list(FORMATS)
    assert all(shlex.split(w) == [str(tmp_path.resolve())] for w, _ in commands)
    text = " ".join(parse_text(section).split())
    assert re.search(r"gltf .*? export-gltf/scene\.glb written \d{4}-\d\d-\d\d", text)
    assert len(re.findall(r"not yet", text)) == 2 and "scene.json (not fitted yet" in text
    # The command as the report spells it runs and writes the export it names.
    workspace, fmt = commands[2]
    run = subprocess.run([sys.executable, "-m", "reflab.app.cli", "export", *shlex.split(workspace), "--format", fmt],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert main(["report", str(tmp_path), "--no-render"]) == 0
    text = parse(tmp_path / "report.html").all_text
    assert "export-ply/" in text and len(re.findall(r"not yet", text)) == 1
    # Without scene.json there is nothing to export: no section.
    (tmp_path / "scene.json").unlink()
    assert main(["report", str(tmp_path), "--no-render"]) == 0
    assert "export" not in parse(tmp_path / "report.html").ids


def parse_text(html: str) -> str:
    page = Page()
    page.feed(html)
    return " ".join(page.text)
