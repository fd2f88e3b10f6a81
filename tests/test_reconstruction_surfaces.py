"""Surfaces from marks, from sparse points and from files, against the simulated lab's true geometry.

Views are the lab camera turned about the turntable axis (the true poses of a sweep); marks are
the true corners projected into them with 1 px Gaussian noise, as the issue asks.
"""
import json

import numpy as np
import pytest

from reflab.hardware.sim.lab import build_lab
from reflab.core.workspace import WorkspaceError
from reflab.reconstruction import surfaces as surf
from reflab.reconstruction.scene import Mesh, Scene


def _rot_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


@pytest.fixture(scope="module")
def lab():
    return build_lab(640, 480)


def _views(camera, angles):
    # The object turned by +a about the vertical axis through the origin = camera pose R Rz(a), t.
    return surf.Views(camera, {f"shot{a:+04d}": (camera.R @ _rot_z(a), camera.t.copy()) for a in angles})


def _marks(name, mesh, corners, views, rng, size, ior=None):
    items = []
    for k in corners:
        label = surf.CORNERS[k]
        marks = {n: (views.project(n, mesh.vertices[k])[0] + rng.normal(0, 1.0, 2)).tolist() for n in views.poses}
        items.append({"corner": label.tolist(), "marks": marks})
    return {"name": name, "shape": "box", "ior": ior, "size": size, "corners": items}


def _write_marks(tmp_path, items):
    path = tmp_path / "marks.json"
    path.write_text(json.dumps({"surfaces": items}))
    return path


def test_mirror_and_sheet_from_marks_within_2mm(lab, tmp_path):
    rng = np.random.default_rng(1)
    views = _views(lab.camera, range(-70, 71, 20))  # eight marked shots, as Façade used ≥ 8
    mirror, sheet = lab.scene[lab.scene.index("mirror")].mesh, lab.scene[lab.scene.index("sheet")].mesh
    front = [k for k in range(8) if surf.CORNERS[k][1] < 0]  # the face toward the camera (-y)
    items = [_marks("mirror", mirror, front, views, rng, [None, 0.006, None]),
             _marks("sheet", sheet, front, views, rng, [None, 0.003, None], ior=1.46)]
    specs = surf.load_marks(_write_marks(tmp_path, items))
    for spec, truth in zip(specs, (mirror, sheet)):
        m = surf.box_from_marks(spec, views)
        err = np.linalg.norm(m.mesh.vertices - truth.vertices, axis=1)
        assert err.max() < 2e-3, (spec["name"], err)
        assert m.mesh.is_closed()
        assert m.info["reprojection_px"] < 2.0
    # The transparent sheet is written closed and read back by the scene loader.
    scene = surf.write_scene(tmp_path, [surf.box_from_marks(s, views) for s in specs])
    back = Scene.load(tmp_path / "scene.json")
    assert back.names == ["mirror", "sheet"] and back[1].material.ior == 1.46 and back[1].mesh.is_closed()
    assert len(scene) == 2


def test_marked_pose_sigma_covers_the_true_plane_error(lab, tmp_path):
    """scene.json's pose_sigma of a face from marked corners (1 px noise): over 12 noise draws the
    true face's tilts about both in-plane axes and its offset along the normal lie within 3σ of
    the fitted face, and the σ is not a blanket (the errors' RMS over σ is 0.3–2); write_scene keeps it."""
    views = _views(lab.camera, range(-70, 71, 20))
    front = [k for k in range(8) if surf.CORNERS[k][1] < 0]
    z = []
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        for name, size, ior in (("mirror", [None, 0.006, None], None), ("sheet", [None, 0.003, None], 1.46)):
            truth = lab.scene[lab.scene.index(name)].mesh
            spec = surf.load_marks(_write_marks(tmp_path, [_marks(name, truth, front, views, rng, size, ior)]))[0]
            m = surf.box_from_marks(spec, views)
            ps = m.info["pose_sigma"]
            centre, n, axes = (np.asarray(ps[k]) for k in ("centre", "normal", "axes"))
            c, R, sz = surf.box_frame(truth)
            n_true = R[:, 1] * np.sign(R[:, 1] @ n)
            face = c + R[:, 1] * sz[1] / 2 * np.sign(R[:, 1] @ (centre - c))  # the true face's centre
            err = [(n_true - n) @ np.cross(axes[k], n) for k in range(2)] + [(face - centre) @ n]
            z.append(np.array(err) / np.array([*ps["tilt_rad"], ps["offset_m"]]))
    z = np.array(z)
    assert np.all(np.abs(z) < 3.0), np.abs(z).max(axis=0)
    assert np.all((0.3 < np.sqrt(np.mean(z ** 2, axis=0))) & (np.sqrt(np.mean(z ** 2, axis=0)) < 2.0)), z
    scene = surf.write_scene(tmp_path, [m])
    assert Scene.load(tmp_path / "scene.json")[0].extra["pose_sigma"]["tilt_rad"] == ps["tilt_rad"]
    assert len(scene) == 1


def test_box_from_three_faces_of_marks(lab, tmp_path):
    rng = np.random.default_rng(2)
    views = _views(lab.camera, [-40, -20, 0, 20, 40])
    box = lab.scene[lab.scene.index("box")].mesh
    visible = [k for k in range(8) if surf.CORNERS[k][2] > 0 or surf.CORNERS[k][1] < 0]  # top and front
    spec = surf.load_marks(_write_marks(tmp_path, [_marks("box", box, visible, views, rng, [None] * 3)]))[0]
    m = surf.box_from_marks(spec, views)
    assert np.linalg.norm(m.mesh.vertices - box.vertices, axis=1).max() < 2e-3


def test_ground_and_boxes_fitted_to_points_within_1mm(lab):
    rng = np.random.default_rng(3)
    ground, box, tile = (lab.scene[lab.scene.index(n)].mesh for n in ("ground", "box", "tile"))
    # Sparse points as SfM leaves them: on the visible faces (not the bottoms), 0.3 mm noise.
    pts = [rng.uniform([-0.2, -0.2, 0], [0.25, 0.25, 0], (3000, 3))]
    for mesh, n in ((box, 800), (tile, 600)):
        p = mesh.sample_points(4 * n, seed=4)
        pts.append(p[p[:, 2] > 1e-4][:n])
    ground_pts = pts[0]
    for mesh in (box, tile):
        # Ground points under a box are hidden: drop those inside its footprint (box frame from its corners).
        v = mesh.vertices
        ex, ey = v[4] - v[0], v[2] - v[0]
        local = (ground_pts - v.mean(axis=0)) @ np.stack([ex / np.linalg.norm(ex), ey / np.linalg.norm(ey)], 1)
        ground_pts = ground_pts[np.any(np.abs(local) > [np.linalg.norm(ex) / 2, np.linalg.norm(ey) / 2], axis=1)]
    pts = np.concatenate([ground_pts] + pts[1:])
    pts += rng.normal(0, 3e-4, pts.shape)
    fitted = surf.fit_scene_points(pts)
    assert fitted[0].name == "ground" and len(fitted) == 3
    g = fitted[0].mesh.sample_points(5000)
    assert np.sqrt(np.mean(g[:, 2] ** 2)) < 1e-3
    for m in fitted[1:]:
        truth = min((box, tile), key=lambda t: np.linalg.norm(t.vertices.mean(0) - m.mesh.vertices.mean(0)))
        d = surf.distance_to_mesh(truth, m.mesh.sample_points(5000))
        assert np.sqrt(np.mean(d**2)) < 1e-3, (m.name, np.sqrt(np.mean(d**2)))
        assert m.mesh.is_closed()


def test_marks_bad_input_named(lab, tmp_path):
    views = _views(lab.camera, [0, 20])
    mirror = lab.scene[lab.scene.index("mirror")].mesh
    rng = np.random.default_rng(5)
    item = _marks("mirror", mirror, [0, 1, 4, 5], views, rng, [None, 0.006, None])
    # An image that is not among the registered shots.
    bad = json.loads(json.dumps(item))
    bad["corners"][0]["marks"]["captures/turntable/9999.exr"] = bad["corners"][0]["marks"].pop("shot+000")
    spec = surf.load_marks(_write_marks(tmp_path, [bad]))[0]
    with pytest.raises(WorkspaceError, match=r"9999\.exr"):
        surf.box_from_marks(spec, views)
    # A corner marked in one image only.
    one = json.loads(json.dumps(item))
    one["corners"][1]["marks"] = {"shot+000": [1.0, 2.0]}
    with pytest.raises(WorkspaceError, match=r"corners\[1\]\.marks.*at least two images"):
        surf.load_marks(_write_marks(tmp_path, [one]))
    # One face marked and its thickness not given.
    thick = json.loads(json.dumps(item))
    thick["size"] = [None, None, None]
    with pytest.raises(WorkspaceError, match=r"size\[1\]"):
        surf.box_from_marks(surf.load_marks(_write_marks(tmp_path, [thick]))[0], views)
    # A transparent open plane.
    plane = {"name": "sheet", "shape": "plane", "ior": 1.46, "corners": [{"corner": [1, 1], "marks": {}}]}
    with pytest.raises(WorkspaceError, match=r"surfaces\[0\]\.shape.*closed"):
        surf.load_marks(_write_marks(tmp_path, [plane]))


def test_imported_mesh_must_be_closed_when_transparent(tmp_path):
    quad = surf.quad_mesh([0, 0, 0.05], np.eye(3), [0.1, 0.1, 0])
    quad.save(tmp_path / "open.ply")
    surf.box_mesh([0, 0, 0.05], np.eye(3), [0.1, 0.1, 0.003]).save(tmp_path / "closed.ply")
    with pytest.raises(WorkspaceError, match=r"open\.ply.*closed mesh.*'pane'"):
        surf.import_mesh("pane", tmp_path / "open.ply", ior=1.5)
    assert surf.import_mesh("pane", tmp_path / "closed.ply", ior=1.5).mesh.is_closed()
    opaque = surf.import_mesh("card", tmp_path / "open.ply")
    assert np.allclose(opaque.mesh.vertices, quad.vertices)
    assert isinstance(opaque.mesh, Mesh)


def _box_points_as_the_lab_sweep_leaves_them(box, rng):
    """The lab sweep's sparse points on its 100x70x60 mm box: a dense top face that thins out
    3 mm short of its edges (features straddling an occluding edge do not match), 6 to 12
    isolated points per side face, and ground points reaching 1 mm under the box's foot."""
    v = box.vertices
    ex, ey = v[4] - v[0], v[2] - v[0]
    size = np.array([np.linalg.norm(ex), np.linalg.norm(ey), v[:, 2].max()])
    R = np.stack([ex / size[0], ey / size[1], [0, 0, 1.0]], axis=1)
    centre = v.mean(axis=0)
    top = rng.uniform(-size[:2] / 2 + 0.003, size[:2] / 2 - 0.003, (450, 2))
    # Denser toward one corner, as shading and the lamps leave it: the top alone biases the yaw.
    top = top[rng.random(len(top)) < 0.3 + 0.7 * (top[:, 0] / size[0] + 0.5)]
    local = [np.c_[top, np.full(len(top), size[2] / 2)]]
    for axis, count in ((0, 6), (0, 12), (1, 8), (1, 10)):
        sign = 1.0 if count > 8 else -1.0
        p = rng.uniform(-size / 2 * 0.9, size / 2 * 0.9, (count, 3))
        p[:, axis] = sign * size[axis] / 2
        local.append(p)
    pts = centre + np.concatenate(local) @ R.T
    ring = rng.uniform(-size[:2] / 2 - 0.03, size[:2] / 2 + 0.03, (4000, 2))
    outside = np.any(np.abs(ring) > size[:2] / 2 - 0.001, axis=1)  # 1 mm under the foot: shadowed edge matches
    ground = np.c_[centre[:2] + ring[outside] @ R[:2, :2].T, np.zeros(outside.sum())]
    return np.concatenate([pts + rng.normal(0, 3e-4, pts.shape), ground + rng.normal(0, 3e-4, ground.shape)])


def test_tall_box_footprint_from_its_sparse_sides(lab):
    """The yaw comes from the few side points, not the top face's uneven spread or the foot's ground points."""
    box = lab.scene[lab.scene.index("box")].mesh
    fitted = surf.fit_scene_points(_box_points_as_the_lab_sweep_leaves_them(box, np.random.default_rng(5)))
    assert [m.name for m in fitted] == ["ground", "box0"]
    m = fitted[1]
    e = m.mesh.vertices[4] - m.mesh.vertices[0]
    yaw = (np.degrees(np.arctan2(e[1], e[0])) - 12.0 + 45.0) % 90.0 - 45.0  # the lab's box is turned 12 deg
    d = surf.distance_to_mesh(box, m.mesh.sample_points(5000))
    assert abs(yaw) < 0.5 and np.sqrt(np.mean(d**2)) < 6e-4, (yaw, np.sqrt(np.mean(d**2)), m.info)


def test_still_ground_is_the_frame_plane_over_the_input_view(lab):
    """No sparse points on a ground that did not turn: the plane z = 0 spanning what the camera sees."""
    rng = np.random.default_rng(6)
    box, tile = (lab.scene[lab.scene.index(n)].mesh for n in ("box", "tile"))
    pts = [m.sample_points(4 * n, seed=4) for m, n in ((box, 800), (tile, 600))]
    pts = np.concatenate([p[p[:, 2] > 1e-4][:n] for p, n in zip(pts, (800, 600))])  # no bottom faces
    pts += rng.normal(0, 3e-4, pts.shape)
    fitted = surf.fit_scene_points(pts, camera=lab.camera)
    assert [m.name for m in fitted] == ["ground", "box0", "box1"]
    ground = fitted[0]
    assert "did not turn" in ground.source and np.all(ground.mesh.vertices[:, 2] == 0.0)
    # Every point of the true ground that the camera sees lies on it; it reaches no more than 10 cm past them.
    g = np.stack(np.meshgrid(np.linspace(-0.7, 0.7, 141), np.linspace(-0.4, 1.2, 161)), -1).reshape(-1, 2)
    uv = lab.camera.project(np.c_[g, np.zeros(len(g))])
    seen = g[(uv[:, 0] >= 0) & (uv[:, 0] <= lab.camera.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= lab.camera.height - 1)]
    lo, hi = ground.mesh.vertices[:, :2].min(axis=0), ground.mesh.vertices[:, :2].max(axis=0)
    assert np.all(seen >= lo) and np.all(seen <= hi)
    assert np.all(lo > seen.min(axis=0) - 0.1) and np.all(hi < seen.max(axis=0) + 0.1)
    for m in fitted[1:]:
        truth = min((box, tile), key=lambda t: np.linalg.norm(t.vertices.mean(0) - m.mesh.vertices.mean(0)))
        d = surf.distance_to_mesh(truth, m.mesh.sample_points(5000))
        assert np.sqrt(np.mean(d**2)) < 1e-3, (m.name, np.sqrt(np.mean(d**2)))
    # Without the camera there is nothing to fall back on: the largest level plane is taken (the tile's top).
    assert "RANSAC" in surf.fit_scene_points(pts)[0].source


def test_low_box_yaw_from_its_top_face_outline(lab):
    """A tile shows points on its top only: inside the footprint they say nothing about the yaw,
    so the few mismatches just beyond an edge (as the lab sweep leaves them, 1-3 mm out) must not
    turn it: the smallest rectangle around the top face's points, each edge at its third
    outermost point, does not (lab sweep: 18.5 deg fitted for 20 before, 20.1 after; here
    -4.4 deg and a corner 6.9 mm off before, over seeds 7-12 within 0.64 deg and 2.5 mm after)."""
    tile = lab.scene[lab.scene.index("tile")].mesh
    v = tile.vertices
    ex, ey = v[4] - v[0], v[2] - v[0]
    size = np.array([np.linalg.norm(ex), np.linalg.norm(ey), v[:, 2].max()])
    R = np.stack([ex / size[0], ey / size[1], [0, 0, 1.0]], axis=1)
    rng = np.random.default_rng(7)
    top = rng.uniform(-size[:2] / 2 + 0.002, size[:2] / 2 - 0.002, (900, 2))
    top = top[rng.random(len(top)) < 0.3 + 0.7 * (top[:, 0] / size[0] + 0.5)]  # denser toward one side
    stray = np.array([[-size[0] / 2 - 0.003, -0.02], [0.03, size[1] / 2 + 0.0025], [size[0] / 2 + 0.001, 0.04]])
    local = np.c_[np.concatenate([top, stray]), np.full(len(top) + len(stray), size[2] / 2)]
    pts = v.mean(axis=0) + local @ R.T + rng.normal(0, 3e-4, local.shape)
    fitted = surf.fit_scene_points(pts, camera=lab.camera)
    assert [m.name for m in fitted] == ["ground", "box0"]
    e = fitted[1].mesh.vertices[4] - fitted[1].mesh.vertices[0]
    yaw = (np.degrees(np.arctan2(e[1], e[0])) - 20.0 + 45.0) % 90.0 - 45.0  # the lab's tile is turned 20 deg
    d = surf.distance_to_mesh(tile, fitted[1].mesh.sample_points(5000))
    assert abs(yaw) < 0.75 and d.max() < 2.6e-3, (yaw, d.max(), fitted[1].info)


def test_box_edges_moved_to_where_the_shots_show_them():
    """Footprint edges fitted short of a tile's true edges (sparse points stop 1-3 mm inside), or
    beyond them, move to where the shots show its top edges: here within 0.1 mm (true poses, six
    turntable angles); in the lab demo at 480x360, with structure from motion's poses, tile 0.57 ->
    0.22 mm RMS (worst corner 2.9 -> 0.9 mm), box 0.55 -> 0.37 mm."""
    from reflab.calibration.rotations import axis_rotation
    from reflab.hardware.sim.camera import lab_renderer
    from reflab.hardware.sim.lab import build_lab

    lab = build_lab(480, 360, grain=0.2)
    render = lab_renderer(lab, depth=1)
    cam = lab.camera
    angles = (0, 60, 120, 180, 240, 300)
    views = surf.Views(cam, {f"shot{a}": (cam.R @ axis_rotation((0.0, 0.0, 1.0), a), cam.t) for a in angles})
    gradients = surf.edge_gradients({f"shot{a}": render(a, [True, True]) for a in angles})
    tile = lab.scene[lab.scene.index("tile")].mesh
    v = tile.vertices
    axes = np.stack([v[4] - v[0], v[2] - v[0], v[1] - v[0]], axis=1)
    size = np.linalg.norm(axes, axis=0)
    R = axes / size
    short = np.array([0.002, -0.001, 0.003, -0.002])  # -x, +x, -y, +y edges moved inward (outward if < 0)
    lo, hi = -size[:2] / 2 + short[[0, 2]], size[:2] / 2 - short[[1, 3]]
    fitted = surf.box_mesh(v.mean(axis=0) + R[:, :2] @ ((lo + hi) / 2), R, [*(hi - lo), size[2]])
    moved, shifts = surf.refine_box_edges(fitted, views, gradients)
    assert all(s is not None for s in shifts) and np.allclose(shifts, short, atol=3e-4), shifts
    d = surf.distance_to_mesh(tile, moved.sample_points(4000))
    assert d.max() < 4e-4, d.max()


def test_marked_face_moved_to_where_the_shots_show_its_edges(tmp_path):
    """A mirror's box from corners marked with 1 px noise (the simulated user's marks, in the shots
    within 60 degrees of facing it) has its plane 0.14-0.44 degrees off, 0.3-0.7 mm RMS; its top
    and side edges found in the shots that see its face (true poses, every 10 degrees; the edge on
    the ground left out) bring it to 0.04-0.20 degrees, 0.10-0.15 mm (measured over 6 seeds of the
    marks' noise; 4 here), the thickness kept as given."""
    from reflab.calibration.rotations import axis_rotation
    from reflab.hardware.sim.camera import lab_renderer
    from reflab.hardware.sim.user import surface_marks

    lab = build_lab(480, 360, grain=0.2)
    render = lab_renderer(lab, depth=1)
    cam = lab.camera
    angles = list(range(-90, 91, 10))
    names = {a: f"shot{a}" for a in angles}
    views = surf.Views(cam, {names[a]: (cam.R @ axis_rotation((0.0, 0.0, 1.0), a), cam.t) for a in angles})
    gradients = surf.edge_gradients({names[a]: render(a, [True, True]) for a in angles})
    truth = lab.scene[lab.scene.index("mirror")].mesh
    tv = truth.vertices
    true_n = np.cross(tv[4] - tv[0], tv[1] - tv[0])
    true_n /= np.linalg.norm(true_n)

    def plane_error(mesh):
        v = mesh.vertices
        nrm = np.cross(v[4] - v[0], v[1] - v[0])
        angle = np.degrees(np.arccos(min(1.0, abs(nrm @ true_n) / np.linalg.norm(nrm))))
        d = surf.distance_to_mesh(truth, mesh.sample_points(4000))
        return angle, 1e3 * np.sqrt(np.mean(d**2)), np.linalg.norm(v[2] - v[0])

    before, after = [], []
    for seed in range(4):
        entries = surface_marks(lab, [(names[a], float(a)) for a in angles], seed=seed)
        spec = surf.load_marks(tmp_path / "marks.json", {"surfaces": [e for e in entries if e["name"] == "mirror"]})[0]
        m = surf.box_from_marks(spec, views)
        assert m.info["face"] == [1, -1.0]
        moved, found = surf.refine_marked_face(m.mesh, views, gradients, *m.info["face"])
        assert found["-z"] is None and all(found[k] is not None for k in ("-x", "+x", "+z")), found
        before.append(plane_error(m.mesh))
        after.append(plane_error(moved))
    before, after = np.array(before), np.array(after)
    assert np.allclose(after[:, 2], 0.006), after  # thickness as given
    assert after[:, 0].max() < 0.25 and after[:, 0].mean() < 0.7 * before[:, 0].mean(), (before, after)
    assert after[:, 1].max() < 0.2 and after[:, 1].max() < before[:, 1].min(), (before, after)
