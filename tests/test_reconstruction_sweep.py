"""`reflab reconstruct` end to end on a rendered 36-shot turntable sweep, against the truth that made it.

The sweep is rendered here with Mitsuba (self-emitting textures: fast and noise-free): a textured
square plate turning about a vertical axis, the circle target printed on it, a textured box and
a thin tile standing on it, a static textured table around it (which the automatic mask must
hide), seen by a camera with radial distortion. One SfM run serves every test of this module.
"""
import json

import numpy as np
import pytest

from reflab.app.cli import main
from reflab.calibration.camera import Camera
from reflab.core.images import write_image
from reflab.hardware.sim.lab import box_mesh
from reflab.core.workspace import WorkspaceError, read_json
from reflab.reconstruction import registration as reg
from reflab.reconstruction import surfaces as surf
from reflab.reconstruction.scene import Scene
from reflab.reconstruction.sfm import moving_masks, run_sfm, static_mask, turntable_poses

AXIS = np.array([0.045, -0.03, 0.0])
GRID, SPACING, RADIUS = (7, 5), 0.015, 0.004
PLATE = 0.18
BOXES = {"box": ((0.07, 0.05, 0.06), (-0.055, 0.075, 0.03), 20.0),
         "tile": ((0.08, 0.08, 0.01), (0.15, 0.05, 0.005), -15.0)}


def rot_z(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])


def noise_texture(rng, size, scales=(4, 16, 64)):
    import cv2
    img = np.zeros((size, size, 3))
    for s in scales:
        small = rng.random((s, s, 3))
        img += cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC) / len(scales)
    return 0.05 + 0.55 * (img - img.min()) / (img.max() - img.min())


def plate_texture(rng, size=1024):
    """Plate texture with the circle target printed at its known place (row 0 = top = +y)."""
    tex = noise_texture(rng, size)
    x = AXIS[0] - PLATE + (np.arange(size) + 0.5) * 2 * PLATE / size
    y = AXIS[1] + PLATE - (np.arange(size) + 0.5) * 2 * PLATE / size
    X, Y = np.meshgrid(x, y)
    cols, rows = GRID
    paper = (X > -SPACING) & (X < (cols - 1) * SPACING + SPACING) & (Y < SPACING) & (Y > -(rows - 1) * SPACING - SPACING)
    dx = X - np.clip(np.round(X / SPACING), 0, cols - 1) * SPACING
    dy = Y + np.clip(np.round(-Y / SPACING), 0, rows - 1) * SPACING
    d = np.hypot(dx, dy)
    texel = 2 * PLATE / size
    ink = np.clip(0.5 - (d - RADIUS) / texel, 0, 1)
    target = (1 - 0.95 * ink)[..., None] * np.ones(3)
    tex = np.where(paper[..., None], target * 0.9, tex)
    return tex


def box_ply(path, size, rng):
    """A box with per-face texture atlas (3x2 cells) as an ASCII PLY with u, v."""
    m = box_mesh(size, (0, 0, 0))
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    verts, uvs, faces = [], [], []
    for k, q in enumerate(quads):
        cu, cv = (k % 3) / 3, (k // 3) / 2
        corner_uv = [(0.02, 0.02), (0.98, 0.02), (0.98, 0.98), (0.02, 0.98)]
        base = len(verts)
        for vi, (a, b) in zip(q, corner_uv):
            verts.append(m.vertices[vi])
            uvs.append((cu + a / 3, cv + b / 2))
        faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    lines = ["ply", "format ascii 1.0", f"element vertex {len(verts)}", "property float x", "property float y",
             "property float z", "property float u", "property float v", f"element face {len(faces)}",
             "property list uchar int vertex_indices", "end_header"]
    lines += [f"{p[0]} {p[1]} {p[2]} {u} {v}" for p, (u, v) in zip(verts, uvs)]
    lines += [f"3 {a} {b} {c}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def camera(width=480, height=360):
    cam = Camera.look_at(640, 480, 50.0, eye=(0.03, -0.40, 0.36), target=(0.04, 0.0, 0.02),
                         dist=np.array([-0.05, 0, 0, 0, 0.0]))
    return cam.scaled(width, height)


def true_box(name):
    size, centre, yaw = BOXES[name]
    return box_mesh(size, centre, rot_z(yaw))


def render_sweep(tmpdir, angles, width=480, height=360, spp=4):
    from reflab.core.mitsuba_env import mitsuba
    from reflab.hardware.sim.props import render_view
    mi = mitsuba()
    rng = np.random.default_rng(7)
    cam = camera(width, height)
    plate = mi.Bitmap(np.ascontiguousarray(plate_texture(rng)[::-1]).astype(np.float32))
    table = mi.Bitmap(np.ascontiguousarray(noise_texture(rng, 1024) * 0.6).astype(np.float32))
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0] * 3}}
    def emit(bmp):
        return {"type": "area", "radiance": {"type": "bitmap", "bitmap": bmp, "raw": True, "filter_type": "bilinear"}}
    plies = {}
    for name, (size, centre, yaw) in BOXES.items():
        p = tmpdir / f"{name}_uv.ply"
        box_ply(p, size, rng)
        plies[name] = (p, mi.Bitmap(np.ascontiguousarray(noise_texture(rng, 768)).astype(np.float32)))
    images = []
    for a in angles:
        T = mi.ScalarTransform4f().translate(AXIS.tolist()).rotate([0, 0, 1], float(a)).translate((-AXIS).tolist())
        objs = {"integrator": {"type": "direct"},
                "plate": {"type": "rectangle", "bsdf": black, "emitter": emit(plate),
                          "to_world": T @ mi.ScalarTransform4f().translate(AXIS.tolist()).scale([PLATE, PLATE, 1])},
                "table": {"type": "rectangle", "bsdf": black, "emitter": emit(table),
                          "to_world": mi.ScalarTransform4f().translate([0, 0, -0.003]).scale([0.6, 0.6, 1])}}
        for name, (size, centre, yaw) in BOXES.items():
            p, bmp = plies[name]
            objs[name] = {"type": "ply", "filename": str(p), "face_normals": True, "bsdf": black, "emitter": emit(bmp),
                          "to_world": T @ mi.ScalarTransform4f().translate(list(centre)).rotate([0, 0, 1], yaw)}
        images.append(render_view(cam, objs, spp=spp)[:, :, :3].astype(np.float32))
    return cam, images


N_SHOTS, SIZE = 36, (480, 360)  # smaller images lose the 4 mm circles of the target


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("ws")
    angles = np.arange(N_SHOTS) * 360.0 / N_SHOTS
    cam, images = render_sweep(tmp_path_factory.mktemp("render"), angles, *SIZE)
    cam.save(root / "camera.json")
    folder = root / "captures" / "turntable"
    shots = []
    for i, (a, img) in enumerate(zip(angles, images)):
        write_image(folder / f"{i:04d}.exr", img)
        shots.append({"file": f"{i:04d}.exr", "angle": float(a), "role": "sweep"})
    (folder / "manifest.json").write_text(json.dumps({"kind": "sweep", "shots": shots}))
    assert main(["reconstruct", str(root), "--target", f"{GRID[0]}x{GRID[1]}", "--spacing", str(SPACING)]) == 0
    return root, cam, angles, images


def true_centres(cam, angles):
    # Object turned by +a about the axis = camera turned by -a about it, in the object's frame.
    return np.stack([AXIS + rot_z(-a) @ (cam.center - AXIS) for a in angles])


@pytest.mark.slow  # shares one render + SfM run of the sweep
def test_sweep_registered_turntable_and_centres(sweep):
    root, cam, angles, _ = sweep
    rep = read_json(root / "sfm.json")
    assert rep["sfm"]["registered"] == N_SHOTS and rep["sfm"]["reprojection_px"] < 0.5
    assert rep["rigid_turntable"]["used"]  # one turntable axis explains the shots
    assert rep["turntable"]["max_angle_error_deg"] < 0.1  # the bar is 0.2; measured 0.028
    assert rep["turntable"]["axis_tilt_deg"] < 0.2 and rep["turntable"]["direction"] == 1
    C = np.array([-np.array(rep["poses"][n]["R"]).T @ rep["poses"][n]["t"] for n in rep["images"]])
    assert np.linalg.norm(C - true_centres(cam, angles), axis=1).max() < 1e-3  # bar 2 mm; measured 0.18 mm
    assert rep["reference"]["centre_mm"] < 1.0


@pytest.mark.slow  # shares one render + SfM run of the sweep
def test_colmap_model_kept_in_the_world_frame(sweep):
    """sparse/0/ is COLMAP's own model (what COLMAP's GUI opens), its images named by their capture
    files and moved into the workspace's metric frame: its cameras sit where sfm.json puts them."""
    import pycolmap

    from reflab.core.workspace import Workspace

    root, cam, angles, _ = sweep
    ws = Workspace(root)
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= {p.name for p in ws.colmap_model.iterdir()}
    model = pycolmap.Reconstruction(str(ws.colmap_model))
    rep = read_json(ws.sfm)
    assert model.num_reg_images() == N_SHOTS and model.num_points3D() >= rep["sfm"]["points"] > 100
    centres = {}
    for image in model.images.values():
        pose = image.cam_from_world()
        centres[image.name] = -pose.rotation.matrix().T @ pose.translation
    assert sorted(centres) == sorted(rep["images"]) and all(n.startswith("captures/turntable/") for n in centres)
    # sfm.json's poses are COLMAP's refined by one rigid turntable axis, and the frame is fitted to
    # those: COLMAP's own cameras lie within 2 mm of them and of the truth.
    ours = np.array([-np.array(rep["poses"][n]["R"]).T @ rep["poses"][n]["t"] for n in rep["images"]])
    colmap = np.array([centres[n] for n in rep["images"]])
    off_json = np.linalg.norm(colmap - ours, axis=1).max()
    off_true = np.linalg.norm(colmap - true_centres(cam, angles), axis=1).max()
    assert off_json < 2e-3 and off_true < 2e-3  # measured 1.08 mm and 1.16 mm
    assert not any(p.name.startswith(".") for p in ws.colmap_model.parent.iterdir())  # no temporary left


@pytest.mark.slow  # shares one render + SfM run of the sweep
def test_ground_and_boxes_within_1mm(sweep):
    root, *_ = sweep
    scene = Scene.load(root / "scene.json")
    assert scene.names[0] == "ground"
    g = scene[0].mesh.sample_points(5000)
    assert np.sqrt(np.mean(g[:, 2] ** 2)) < 1e-3
    found = {}
    for s in scene.surfaces[1:]:
        name = min(BOXES, key=lambda n: np.linalg.norm(true_box(n).vertices.mean(0) - s.mesh.vertices.mean(0)))
        d = surf.distance_to_mesh(true_box(name), s.mesh.sample_points(5000))
        found[name] = float(np.sqrt(np.mean(d**2)))
        assert s.mesh.is_closed()
    assert set(found) == set(BOXES), found
    # The 1 cm tile's sides carry few points: its footprint comes from its top face and the ground.
    assert found["box"] < 1e-3 and found["tile"] < 1e-3, found


@pytest.mark.slow  # shares one render + SfM run of the sweep
def test_marks_on_registered_shots(sweep, tmp_path):
    """A box marked in eight registered shots (true corners + 1 px noise) comes within 2 mm."""
    root, cam, angles, _ = sweep
    rng = np.random.default_rng(0)
    truth = true_box("box")
    shots = [f"captures/turntable/{i:04d}.exr" for i in range(0, 8)]
    corners = []
    for k in range(8):
        marks = {}
        for name in shots:
            a = angles[int(name[-8:-4])]
            X = AXIS + rot_z(a) @ (truth.vertices[k] - AXIS)  # where the corner is at that angle
            marks[name] = (cam.project(X[None])[0] + rng.normal(0, 1.0, 2)).tolist()
        corners.append({"corner": surf.CORNERS[k].tolist(), "marks": marks})
    path = tmp_path / "marks.json"
    path.write_text(json.dumps({"surfaces": [{"name": "marked", "shape": "box", "corners": corners}]}))
    assert main(["reconstruct", str(root), "--marks", str(path)]) == 0
    scene = Scene.load(root / "scene.json")
    marked = scene[scene.index("marked")].mesh
    assert np.linalg.norm(marked.vertices - truth.vertices, axis=1).max() < 2e-3
    assert "ground" in scene.names  # the fitted surfaces are kept


@pytest.mark.slow  # shares one render + SfM run of the sweep
def test_target_not_found(sweep):
    root, cam, _, images = sweep
    rep = read_json(root / "sfm.json")
    R = np.array([rep["poses"][n]["R"] for n in rep["images"]])
    t = np.array([rep["poses"][n]["t"] for n in rep["images"]])
    blank = [np.full_like(images[0], 0.3)] * len(images)
    with pytest.raises(WorkspaceError, match=r"circle target found in at least 2"):
        reg.register_target(blank, R, t, cam, GRID, SPACING, 0)


def test_too_few_images_registered(tmp_path):
    cam = camera(160, 120)
    rng = np.random.default_rng(0)
    noise = [rng.random((120, 160, 3)).astype(np.float32) for _ in range(4)]
    with pytest.raises(WorkspaceError, match=r"at least 4 of 4 turntable shots registered"):
        run_sfm(noise, [f"captures/turntable/{i:04d}.exr" for i in range(4)], cam, workdir=tmp_path)


def test_existing_scene_skips_and_open_transparent_mesh_refused(tmp_path, capsys):
    Camera.look_at(64, 48, 50.0, (0, -0.4, 0.4), (0, 0, 0)).save(tmp_path / "camera.json")
    surf.quad_mesh([0, 0, 0.05], np.eye(3), [0.1, 0.1, 0]).save(tmp_path / "pane.ply")
    box_mesh((0.1, 0.1, 0.003), (0, 0, 0.05)).save(tmp_path / "slab.ply")
    assert main(["reconstruct", str(tmp_path), "--mesh", f"pane={tmp_path / 'pane.ply'}", "--ior", "pane=1.5"]) == 2
    assert "closed mesh" in capsys.readouterr().err
    # A given mesh needs no sweep: no captures here, and it works.
    assert main(["reconstruct", str(tmp_path), "--mesh", f"slab={tmp_path / 'slab.ply'}", "--ior", "slab=1.5"]) == 0
    scene = Scene.load(tmp_path / "scene.json")
    assert scene.names == ["slab"] and scene[0].material.ior == 1.5
    assert main(["reconstruct", str(tmp_path)]) == 0
    assert "nothing to reconstruct" in capsys.readouterr().out


def test_moving_masks_drop_a_still_ground_crossed_by_shadows():
    """A still textured ground that a shadow sweeps across, around a turning disk: only the disk is kept."""
    rng = np.random.default_rng(1)
    n, size = 12, 64
    v, u = np.mgrid[0:size, 0:size]
    disk = np.hypot(u - 32, v - 32) < 14
    ground = 0.2 + 0.6 * rng.random((size, size))
    shots = []
    for i in range(n):
        img = ground * np.where(np.abs(u - 6 * i) < 8, 0.3, 1.0)  # the shadow moves 6 px a shot
        shots.append(np.where(disk, 0.2 + 0.6 * rng.random((size, size)), img))  # the disk's texture turns
    masks = moving_masks(shots, closed=True)  # grown by 2 px: disk pixels equal by chance come back
    away = np.hypot(u - 32, v - 32) > 14 + 3
    assert static_mask(shots)[~disk].mean() < 0.1  # over the sweep nearly every ground pixel changes
    assert masks[:, disk].mean() > 0.99 and masks[:, away].mean() < 0.02


def test_turntable_poses_see_what_the_turned_objects_show():
    """The commanded poses project an unturned point where the camera sees it after the turn."""
    from reflab.hardware.sim.camera import rotate_about_z

    cam = camera(160, 120)
    X = np.array([[0.05, 0.02, 0.03], [-0.04, 0.06, 0.0]])
    angles = np.array([0.0, 30.0, -70.0, 200.0])
    R, t = turntable_poses(cam, angles, AXIS[:2])
    for k, a in enumerate(angles):
        seen = cam.R @ rotate_about_z(X, a, AXIS[:2]).T + cam.t[:, None]
        np.testing.assert_allclose(R[k] @ X.T + t[k][:, None], seen, atol=1e-12)
    R2, _ = turntable_poses(cam, angles, AXIS[:2], direction=-1.0)
    np.testing.assert_allclose(R2[1], cam.R @ rot_z(-30.0), atol=1e-12)


def test_bad_options_name_their_flag_on_the_command_line_and_their_field_in_the_library(tmp_path, capsys):
    from reflab.core.workspace import OptionError
    from reflab.reconstruction.stages import ReconstructOptions, reconstruct

    # --target is the old spelling of --grid (hidden alias): the message names the flag by its one name.
    assert main(["reconstruct", str(tmp_path), "--target", "1x8"]) == 2
    assert "--grid: need at least 2 circles" in capsys.readouterr().err
    with pytest.raises(OptionError, match="^ior: no imported mesh named 'pane'"):
        reconstruct(ReconstructOptions(tmp_path, iors={"pane": 1.5}))


@pytest.mark.slow  # one more structure-from-motion run of the shared sweep
def test_reconstruct_cancelled_while_matching_then_rerun(sweep, tmp_path):
    """Cancelled inside structure from motion, reconstruct writes nothing; run again on the same
    workspace it registers every shot, as the uninterrupted run did."""
    import shutil

    from reflab.core.task import Cancelled, Task
    from reflab.core.workspace import Workspace
    from reflab.reconstruction.stages import ReconstructOptions, reconstruct

    root, *_ = sweep
    ws = Workspace(tmp_path / "ws")
    shutil.copytree(Workspace(root).captures, ws.captures)
    shutil.copy(Workspace(root).camera, ws.camera)
    options = ReconstructOptions(ws.root, target=GRID, spacing=SPACING)
    seen = []

    def progress(done, total, message):
        seen.append(message)
        if message.endswith("matching"):
            task.cancel()

    task = Task(progress)
    with pytest.raises(Cancelled):
        reconstruct(options, task)
    assert seen[-1].endswith("matching") and not any("mapping" in m for m in seen)
    assert not ws.sfm.exists() and not ws.scene.exists() and not ws.sparse.exists() and not ws.colmap_model.exists()
    reconstruct(options)
    again, first = read_json(ws.sfm), read_json(Workspace(root).sfm)
    assert again["sfm"]["registered"] == N_SHOTS == first["sfm"]["registered"]
    # Repeatable: the same shots give the same poses, to the bit (COLMAP on one thread).
    assert again["poses"] == first["poses"] and again["rigid_turntable"]["rms_px"] == first["rigid_turntable"]["rms_px"]
    assert Scene.load(ws.scene).names[0] == "ground"
