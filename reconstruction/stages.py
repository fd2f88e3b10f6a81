"""The reconstruct stage as a library function: options in, a typed result out, a Task for progress.

:func:`reconstruct` runs, each part skipped when what it makes is already there: structure from
motion over ``captures/turntable`` and registration into the world frame (:func:`reconstruct_sweep`:
sfm.json, sparse.ply), surfaces fitted to the sparse points, boxes from marked corners, imported
meshes; then writes scene.json and meshes/. docs/reconstruction.md describes the files.

This module is the orchestration: it imports the numerics (sfm, turntable, registration,
surfaces), none of which imports it, so reconstruction/ has no import cycle.
"""
from __future__ import annotations


import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from reflab.calibration.camera import Camera
from reflab.core.options import float_list, name_value, opt
from reflab.core.task import Task, ensure
from reflab.core.workspace import OptionError, Workspace, WorkspaceError, check_folder


@dataclass
class ReconstructOptions:
    """Options of :func:`reconstruct` (and of :func:`reconstruct_sweep`).

    workspace : the workspace folder.
    meshes : surface name -> PLY/OBJ file (metres, world frame) to import.
    iors : surface name (of ``meshes``) -> refraction index (the mesh must then be closed).
    marks : corners marked in the turntable shots (docs/reconstruction.md).
    target : ``(cols, rows)`` (or ``"COLSxROWS"``) of the circle target lying on the turntable.
    spacing : that target's circle spacing, metres.
    turntable_centre : ``(x, y)`` where the turntable axis meets the ground (metres), used
        without a target to fix the scale.
    overlap : each shot is matched with the next ``overlap`` shots.
    rigid_turntable : refine the poses as one axis and one angle per shot (False: free poses).
    fit_surfaces : fit planes and boxes to the sparse points.
    force : redo structure from motion and every surface.
    """

    workspace: Path
    meshes: dict = opt(factory=dict, help="import a mesh (PLY/OBJ, metres, world frame) as surface NAME; repeatable",
                       flag="--mesh", action="append", type=name_value(Path, "PATH"), metavar="NAME=PATH", convert=dict)
    iors: dict = opt(factory=dict, help="refraction index of an imported surface (its mesh must then be closed)",
                     flag="--ior", action="append", type=name_value(float, "INDEX"), metavar="NAME=INDEX", convert=dict)
    marks: Path | None = opt(None, "corners marked in the turntable shots and what the user knows per surface "
                                   "(default: WORKSPACE/marks.json when it has 'surfaces'; docs/reconstruction.md)",
                             type=Path, metavar="FILE")
    target: tuple | str | None = opt(None, "circles per row and column of the circle target lying on the turntable, "
                                           "to fix the frame", flag="--grid", aliases=("--target",), type=str,
                                     metavar="COLSxROWS")
    spacing: float = opt(0.015, "circle spacing of --grid's target", unit="m")
    turntable_centre: tuple | None = opt(None, "where the turntable axis meets the ground, to fix the scale without "
                                               "a target", unit="m", type=float_list, metavar="X,Y")
    overlap: int = opt(5, "each shot is matched with the next N shots")
    rigid_turntable: bool = opt(True, "keep structure from motion's free poses instead of one turntable axis and one "
                                      "angle per shot (for a turntable that wobbles)", flag="--free-poses")
    fit_surfaces: bool = opt(True, "do not fit planes and boxes to the sparse points", flag="--no-fit")
    force: bool = opt(False, "redo structure from motion and every surface")


@dataclass
class ReconstructResult:
    """What :func:`reconstruct` did: ``sfm`` is sfm.json's report when structure from motion ran
    now (else None), ``scene`` the written scene (None when nothing needed doing), ``modelled``
    the surfaces made or imported now (``reflab.reconstruction.surfaces.Modelled``)."""

    scene_path: Path
    scene: object = None
    modelled: list = field(default_factory=list)
    sfm: dict | None = None
    time_s: float = 0.0

    @property
    def skipped(self) -> bool:
        return self.scene is None


def _reference_angle(ws) -> float:
    """Turntable angle of the input photograph (captures/input/manifest.json), else 0."""
    from reflab.core.workspace import read_json

    manifest = ws.manifest("input")
    if manifest.exists():
        for shot in read_json(manifest).get("shots") or []:
            if isinstance(shot, dict) and shot.get("role") == "input" and isinstance(shot.get("angle"), (int, float)):
                return float(shot["angle"])
    return 0.0


def _grid(target) -> tuple[int, int]:
    from reflab.calibration.circles import parse_grid

    return parse_grid(target, "target") if isinstance(target, str) else (int(target[0]), int(target[1]))


def reconstruct_sweep(ws, camera: Camera, options: ReconstructOptions, task: Task | None = None, *,
                      log=None) -> dict:
    """Structure from motion over ``captures/turntable``, registered into the world frame.

    Writes ``sparse.ply`` (the sparse points seen in three or more shots with a reprojection
    error under 1 px, world frame) and then ``sfm.json`` (per-shot world poses and every report).
    Uses ``options.target``, ``spacing``, ``turntable_centre``, ``overlap`` and ``rigid_turntable``.
    ``log`` gets one progress line per step; COLMAP's own log goes to ``WORKSPACE/logs/colmap.log``.

    Returns
    -------
    dict
        ``report`` (as written to sfm.json), ``R``, ``t`` (world-frame poses), ``points``, ``names``.
    """
    from reflab.core.open3d_env import open3d
    o3d = open3d()

    from reflab.core.images import read_image
    from reflab.core.workspace import atomic_path, write_json
    from reflab.reconstruction.registration import reference_check, register_axis, register_target, turntable_check
    from reflab.reconstruction.sfm import load_sweep, run_sfm, turntable_poses, write_colmap_model

    task = ensure(task)
    o = options
    t0 = time.perf_counter()
    ws = Workspace(ws.root if isinstance(ws, Workspace) else ws)
    folder = ws.captures_of("sweep")
    paths, angles = load_sweep(folder)
    if o.target is None and o.turntable_centre is None:
        raise WorkspaceError(folder, expected="a way to fix the reconstruction's scale: the circle target lying on "
                                              "the turntable (target COLSxROWS) or where the turntable axis meets "
                                              "the ground (turntable centre X,Y)", got="neither")
    centre = None
    if o.target is None:
        centre = np.asarray(o.turntable_centre, dtype=float).ravel()
        if centre.size != 2 or not np.all(np.isfinite(centre)):
            raise OptionError("turntable_centre", f"expected X,Y in metres, got {o.turntable_centre!r}")
        centre = centre.tolist()
    ref_angle = _reference_angle(ws)
    reference = 0 if angles is None else int(np.argmin(np.abs((angles - ref_angle + 180.0) % 360.0 - 180.0)))
    images, keep, unreadable = [], [], []
    for i, p in enumerate(paths):
        task.step(i, len(paths) + 3, f"reading {p.name}")
        try:
            images.append(read_image(p, linear=False))  # geometry: any image a camera writes
            keep.append(i)
        except WorkspaceError as exc:  # one shot that cannot be read (cut-off file) is not fatal
            if i == reference:
                raise
            unreadable.append(str(p.relative_to(ws.root)))
            if log is not None:
                log(f"warning: skipping {exc}")
    reference = keep.index(reference)
    paths = [paths[i] for i in keep]
    angles = None if angles is None else angles[keep]
    names = [str(p.relative_to(ws.root)) for p in paths]
    # With the axis known, the commanded angles give every shot's pose to within the rig's error:
    # matches that contradict it (a turning mirror showing the still room) go before mapping.
    commanded = None if centre is None or angles is None else [
        turntable_poses(camera, angles - angles[reference], centre, sign) for sign in (1.0, -1.0)]
    task.step(len(paths), len(paths) + 3, "structure from motion")
    sfm = run_sfm(images, names, camera, overlap=o.overlap, closed=angles is None or np.ptp(angles) + np.min(
        np.abs(np.diff(np.r_[angles, angles[0] + 360.0]))) >= 359.0, commanded=commanded,
                  log_file=ws.logs / "colmap.log", progress=log, task=task)
    if not sfm.registered[reference]:
        raise WorkspaceError(paths[reference], expected="the shot taken from the input view registered by structure "
                                                        "from motion", got="not registered")
    task.step(len(paths) + 1, len(paths) + 3, "turntable axis")
    rigid = None
    if o.rigid_turntable and sfm.observations is not None and len(sfm.points):
        from reflab.reconstruction.turntable import refine_if_rigid

        rigid = refine_if_rigid(sfm.R, sfm.t, sfm.points, sfm.observations, reference, float(camera.K[0, 0]))
        if rigid["report"]["used"]:
            sfm.R, sfm.t, sfm.points, sfm.point_error = rigid["R"], rigid["t"], rigid["points"], rigid["point_error"]
    task.step(len(paths) + 2, len(paths) + 3, "registration")
    if o.target is not None:
        sim, reg = register_target(images, sfm.R, sfm.t, camera, _grid(o.target), o.spacing, reference, str(folder))
    else:
        sim, reg = register_axis(sfm.R, sfm.t, camera, reference, centre)
    reg["scale"] = sim.scale
    Rw, tw = sim.poses(sfm.R, sfm.t)
    # Points seen by few shots or reprojecting poorly sit mostly on occluding edges (mismatches).
    good = (sfm.point_error < 1.0) & (np.array([len(tr) for tr in sfm.tracks], dtype=int) >= 3)
    points = sim.points(sfm.points[good])
    report = {"sfm": dict(sfm.report, unreadable=unreadable), "registration": reg, "reference_shot": names[reference],
              "reference": reference_check(Rw, tw, camera, reference)}
    if rigid is not None:
        report["rigid_turntable"] = rigid["report"]
    if angles is not None:
        report["turntable"] = turntable_check(Rw, angles, reference)
        report["turntable"]["angles_deg"] = angles.tolist()
    report["time_s"] = round(time.perf_counter() - t0, 3)
    poses = {n: {"R": Rw[i], "t": tw[i]} for i, n in enumerate(names) if sfm.registered[i]}
    task.check()
    # COLMAP's model and sparse.ply first: sfm.json is what says structure from motion is done.
    if sfm.model is not None:
        write_colmap_model(sfm.model, ws.colmap_model, sim)
    with atomic_path(ws.sparse) as tmp:
        o3d.io.write_point_cloud(str(tmp), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
    write_json(ws.sfm, dict(report, images=names, poses=poses))
    return {"report": report, "R": Rw, "t": tw, "points": points, "names": names}


def load_views(ws, camera: Camera):
    """Registered shots (:class:`reflab.reconstruction.surfaces.Views`) and sparse points from sfm.json / sparse.ply."""
    from reflab.core.open3d_env import open3d
    o3d = open3d()

    from reflab.core.workspace import as_array, read_json
    from reflab.reconstruction.surfaces import Views

    ws = Workspace(ws.root if isinstance(ws, Workspace) else ws)
    path = ws.sfm
    obj = read_json(path)
    poses = obj.get("poses")
    if not isinstance(poses, dict) or not poses:
        raise WorkspaceError(path, "poses", "registered shots (reconstruct again, forcing it)", got=poses)
    out = {}
    for name, p in poses.items():
        out[name] = (as_array(p.get("R"), (3, 3), path, f"poses[{name!r}].R"),
                     as_array(p.get("t"), (3,), path, f"poses[{name!r}].t"))
    ply = ws.sparse
    points = np.asarray(o3d.io.read_point_cloud(str(ply)).points) if ply.exists() else np.zeros((0, 3))
    return Views(camera, out), points


def _shot_gradients(ws, views) -> dict:
    """:func:`reflab.reconstruction.surfaces.edge_gradients` of the registered shots."""
    from reflab.core.images import read_image
    from reflab.reconstruction import surfaces as surf

    images = {}
    for name in views.poses:
        try:
            images[name] = read_image(ws.root / name, linear=False)
        except WorkspaceError:  # an unreadable shot was already skipped by structure from motion
            continue
    return surf.edge_gradients(images)


def _refine_marked(views, gradients: dict, m, task: Task | None = None):
    """A box from marked corners with its marked face moved to where the shots show its edges
    (:func:`reflab.reconstruction.surfaces.refine_marked_face`); ``info["edges"]`` says which edges were
    found and how far they moved (normal, outward; mm), or that the marks were kept."""
    from reflab.reconstruction import surfaces as surf

    if "face" not in m.info or m.ior is not None:  # a transparent box's edges show what lies behind, refracted
        return m
    mesh, found = surf.refine_marked_face(m.mesh, views, gradients, *m.info["face"], check=ensure(task).check)
    shown = {k: v for k, v in found.items() if v is not None}
    if shown:
        m.mesh = mesh
        m.info["size_m"] = surf.box_frame(m.mesh)[2].tolist()
        m.info["pose_sigma"] = surf.refined_pose_sigma(mesh, *m.info["face"], found, m.info["pose_sigma"])
    m.info["edges"] = ("from the shots: " + ", ".join(f"{k} {1e3 * a:+.1f}/{1e3 * b:+.1f} mm" for k, (a, b) in shown.items())
                       if shown else "as marked (no clear edge in the shots)")
    kept = [k for k, v in found.items() if v is None]
    if shown and kept:
        m.info["edges"] += f"; {', '.join(kept)} as marked"
    return m


def _refine_edges(ws, views, modelled: list, task: Task | None = None, gradients: dict | None = None) -> list:
    """The boxes fitted to sparse points, each footprint edge moved to where the registered shots
    show it (:func:`reflab.reconstruction.surfaces.refine_box_edges`); ``info["edge_shifts_mm"]`` says how far."""
    from reflab.reconstruction import surfaces as surf

    boxes = [m for m in modelled if m.name.startswith("box") and m.source.startswith("box on the ground")]
    if not boxes:
        return modelled
    gradients = _shot_gradients(ws, views) if gradients is None else gradients
    task = ensure(task)
    for i, m in enumerate(boxes):
        task.step(i, len(boxes), f"edges of {m.name} from the shots")
        m.mesh, shifts = surf.refine_box_edges(m.mesh, views, gradients, check=task.check)
        m.info["edge_shifts_mm"] = [None if x is None else round(1e3 * x, 2) for x in shifts]
        m.info["size_m"] = surf.box_frame(m.mesh)[2].tolist()
    return modelled


def reconstruct(options: ReconstructOptions, task: Task | None = None, *, log=None) -> ReconstructResult:
    """Recover the scene's geometry and write scene.json + meshes/ (see the module's description).

    An existing scene.json is left alone (``result.skipped``) unless ``marks`` or ``meshes`` add
    to it, or ``force`` redoes it. ``log`` gets structure from motion's progress lines.
    """
    from reflab.reconstruction import marks as user_marks
    from reflab.reconstruction import surfaces as surf
    from reflab.reconstruction.scene import Scene

    task = ensure(task)
    o = options
    t0 = time.perf_counter()
    ws = Workspace(check_folder(o.workspace, write=True))
    if o.marks is None and user_marks.has_surfaces(ws.marks):  # the GUI's (or simulated user's) marks.json
        o = replace(o, marks=ws.marks)
    unknown = set(o.iors) - set(o.meshes)
    if unknown:
        raise OptionError("ior", f"no imported mesh named {sorted(unknown)[0]!r}")
    existing = Scene.load(ws.scene) if ws.scene.exists() and not o.force else None
    if existing is not None and not o.meshes and not o.marks:
        return ReconstructResult(ws.scene)
    modelled = [surf.import_mesh(name, Path(path), o.iors.get(name)) for name, path in o.meshes.items()]
    sfm_report = None
    need_sfm = bool(o.marks) or (existing is None and not o.meshes)
    if need_sfm:
        camera = Camera.load(ws.require(ws.camera, "reflab calibrate camera"))
        fresh = o.force or not ws.sfm.exists()
        if fresh:
            sfm_report = reconstruct_sweep(ws, camera, o, task, log=log)["report"]
        views, points = load_views(ws, camera)
        task.check()
        specs, pointed = user_marks.read_surfaces(o.marks) if o.marks else ([], [])
        fit = fresh and o.fit_surfaces and not o.meshes
        gradients = _shot_gradients(ws, views) if fit or specs else None
        if fit:
            modelled = _refine_edges(ws, views, surf.fit_scene_points(points, camera=camera), task, gradients) + modelled
        for spec in specs:
            modelled.append(_refine_marked(views, gradients, surf.box_from_marks(spec, views), task))
    if not modelled:
        raise WorkspaceError(ws.scene, expected="at least one surface (fitted, marked or imported)", got="none")
    task.check()
    scene = surf.write_scene(ws.root, modelled, existing)
    if o.marks:  # names and what the user knows, said once in the marks file
        scene = user_marks.apply_options(ws.root, scene, specs, pointed, Camera.load(ws.camera), o.marks)
    return ReconstructResult(ws.scene, scene, modelled, sfm_report, time.perf_counter() - t0)


def turntable_axis(workspace) -> tuple[np.ndarray, float]:
    """Where the turntable axis meets the ground (x, y) and its sense (+1: a positive angle turns
    the objects counter-clockwise seen from +z), from the sweep that reconstruct registered.

    The camera centres of the registered sweep shots, seen from the turning objects, trace a
    circle about the axis: ``C_i = Rz(−d a_i)(C_ref − c) + c``; ``c`` is their least-squares
    solution. Raises WorkspaceError when sfm.json holds no sweep with angles.
    """
    from reflab.calibration.rotations import axis_rotation
    from reflab.core.workspace import read_json

    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    obj = read_json(ws.require(ws.sfm, "reflab reconstruct"))
    turn = obj.get("turntable") or {}
    angles, names, poses = turn.get("angles_deg"), obj.get("images"), obj.get("poses") or {}
    if not isinstance(angles, list) or not isinstance(names, list) or len(angles) != len(names):
        raise WorkspaceError(ws.sfm, "turntable.angles_deg", "the sweep's turntable angles (reconstruct from a sweep)",
                             got=angles)
    d = float(turn.get("direction", 1))
    ref = names.index(obj.get("reference_shot")) if obj.get("reference_shot") in names else 0
    centres, a = [], []
    for name, angle in zip(names, angles):
        if name in poses:
            R, t = np.asarray(poses[name]["R"], float), np.asarray(poses[name]["t"], float)
            centres.append(-R.T @ t)
            a.append(float(angle) - float(angles[ref]))
    if len(centres) < 2:
        raise WorkspaceError(ws.sfm, "poses", "at least two registered sweep shots", got=len(centres))
    C, a = np.array(centres), np.array(a)
    C0 = C[int(np.argmin(np.abs(a)))]
    Rz = axis_rotation((0.0, 0.0, 1.0), -d * a)[:, :2, :2]
    lhs = (np.eye(2)[None] - Rz).reshape(-1, 2)
    rhs = (C[:, :2] - Rz @ C0[:2]).reshape(-1)
    centre = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    return centre, d
