"""Structure from motion over a turntable sweep with pycolmap, on the CPU.

The camera stands still while the turntable turns the objects, which is the same as the camera
orbiting objects that stand still, provided what does not turn (the table, the room) is masked
out. The intrinsics come from camera.json and stay fixed; images are matched in sweep order
with the sweep closed into a loop (shot N-1 is matched with shot 0), and COLMAP's incremental
mapper recovers one pose per shot in an arbitrary similarity frame (see
:mod:`reflab.reconstruction.registration` for the workspace frame).

COLMAP puts the centre of the top-left pixel at (0.5, 0.5); camera.json (OpenCV) puts it at
(0, 0): the principal point is shifted by half a pixel on the way in and keypoints on the way out.
"""
from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.calibration.camera import Camera
from reflab.calibration.rotations import axis_rotation
from reflab.core.images import linear_to_srgb
from reflab.core.task import Task, ensure
from reflab.core.workspace import WorkspaceError

#: A pixel whose display value varies less than this over the whole sweep does not turn.
STATIC_THRESHOLD = 4.0 / 255.0


@dataclass
class SfMResult:
    """Poses and sparse points of one turntable sweep, in the reconstruction's own frame.

    Attributes
    ----------
    names : list of str
        Image names in sweep order (the input order).
    R : (N, 3, 3) ndarray
        World-to-camera rotations; NaN rows for images that were not registered.
    t : (N, 3) ndarray
        World-to-camera translations; NaN for images that were not registered.
    points : (P, 3) ndarray
        Sparse 3D points.
    point_error : (P,) ndarray
        Mean reprojection error of each point (pixels).
    tracks : list of ndarray
        For each point, the indices (into ``names``) of the images that see it.
    observations : reflab.reconstruction.turntable.Observations or None
        Every measurement of the points (point, image, undistorted normalised coordinates).
    report : dict
        ``registered``, ``images``, ``unregistered`` (names), ``reprojection_px`` (mean),
        ``points``, ``mean_track_length``, ``time_s`` per stage and in all.
    """

    names: list
    R: np.ndarray
    t: np.ndarray
    points: np.ndarray
    point_error: np.ndarray
    tracks: list
    observations: object = None
    report: dict = field(default_factory=dict)
    #: COLMAP's reconstruction (``pycolmap.Reconstruction``) in the SfM frame, its images named as ``names``;
    #: None when nothing registered.
    model: object = None

    @property
    def registered(self) -> np.ndarray:
        """(N,) bool: images with a recovered pose."""
        return np.all(np.isfinite(self.t), axis=1)

    @property
    def centers(self) -> np.ndarray:
        """(N, 3) camera centres (NaN where unregistered)."""
        return -np.einsum("nji,nj->ni", self.R, self.t)


def colmap_camera(camera: Camera) -> tuple[str, str]:
    """COLMAP camera model name and parameter string for ``camera``'s fixed intrinsics.

    Raises
    ------
    ValueError
        For skewed pixels or thin-prism/tilt distortion terms, which COLMAP cannot hold.
    """
    K, d = camera.K, np.zeros(8)
    if abs(K[0, 1]) > 1e-9 * K[0, 0]:
        raise ValueError(f"camera.json: field 'K': COLMAP cannot hold a skew of {K[0, 1]} (expected 0)")
    if len(camera.dist) > 8 and np.any(camera.dist[8:] != 0):
        raise ValueError("camera.json: field 'dist': COLMAP cannot hold thin-prism or tilt terms (expected at most 8)")
    d[: min(8, len(camera.dist))] = camera.dist[:8]
    head = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]
    if np.any(d[4:] != 0):
        return "FULL_OPENCV", ",".join(f"{x:.17g}" for x in head + list(d))
    return "OPENCV", ",".join(f"{x:.17g}" for x in head + list(d[:4]))


def static_mask(images: list) -> np.ndarray:
    """(H, W) bool: pixels that look the same in every shot (the table, the room: they do not turn).

    Parameters
    ----------
    images : list of (H, W) ndarray
        Display-encoded grey images in [0, 1], one per shot.
    """
    stack = np.stack(images).astype(np.float32)
    spread = stack.max(axis=0) - stack.min(axis=0)
    return spread < STATIC_THRESHOLD


def moving_masks(images: list, closed: bool, grow: int = 2) -> np.ndarray:
    """(N, H, W) bool: pixels of each shot that changed since the previous shot and before the next.

    A still ground under turning objects is not static over the whole sweep: shadows,
    reflections and light bounced off the objects sweep across it, so :func:`static_mask` keeps
    most of it, and features there match at the same place in consecutive shots (a still
    scene, which defeats the turntable's geometry). Content that turns differs from both
    neighbours; a still pixel that a shadow crosses once differs from at most one of them.
    The mask is grown by ``grow`` pixels so that features on a turning edge keep their support.

    Parameters
    ----------
    images : list of (H, W) ndarray
        Display-encoded grey images in [0, 1], in sweep order.
    closed : bool
        The sweep is a full turn: the first shot's previous one is the last.
    """
    import cv2

    stack = np.stack(images).astype(np.float32)
    diff = np.abs(np.diff(stack, axis=0)) > STATIC_THRESHOLD  # diff[i]: shot i vs shot i + 1
    wrap = np.abs(stack[0] - stack[-1]) > STATIC_THRESHOLD
    before = np.concatenate([(wrap if closed else diff[0])[None], diff])  # shot i vs i - 1
    after = np.concatenate([diff, (wrap if closed else diff[-1])[None]])
    moving = (before & after).astype(np.uint8)
    kernel = np.ones((2 * grow + 1, 2 * grow + 1), np.uint8)
    return np.stack([cv2.dilate(m, kernel) > 0 for m in moving])


def _display(images: list) -> list:
    """8-bit-ready sRGB grey images sharing one exposure (SIFT wants perceptual contrast)."""
    exposure = 1.0 / max(float(np.percentile(np.stack([im.mean(axis=2) for im in images]), 99.5)), 1e-12)
    out = []
    for im in images:
        out.append(linear_to_srgb(np.clip(np.nan_to_num(im.mean(axis=2)) * exposure, 0.0, 1.0)))
    return out


def loop_pairs(n: int, overlap: int, closed: bool) -> list[tuple[int, int]]:
    """Index pairs ``(i, i + d)`` for d = 1..overlap, wrapping around when the sweep is closed."""
    pairs = set()
    for d in range(1, min(overlap, n - 1) + 1):
        for i in range(n):
            j = i + d
            if j >= n:
                if not closed:
                    continue
                j -= n
            if i != j:
                pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


def turntable_poses(camera: Camera, angles, centre_xy, direction: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera poses (N, 3, 3), (N, 3) of a still camera seeing objects turned by ``angles``.

    The objects turned by ``direction * angle`` degrees (counter-clockwise seen from +z) about the
    vertical axis through ``centre_xy`` are seen as if the camera had turned the other way:
    ``x = R (Rz(a) (X - c) + c) + t``.
    """
    Rz = axis_rotation((0.0, 0.0, 1.0), direction * np.asarray(angles, dtype=np.float64))
    c = np.array([centre_xy[0], centre_xy[1], 0.0])
    R = camera.R @ Rz
    t = camera.t + (camera.R @ (c[None] - Rz @ c).T).T
    return R, t


def filter_matches(database, files: list, camera: Camera, commanded: list, tol_px: float = 3.0) -> dict:
    """Drop verified matches that the commanded turntable motion rules out (epipolar distance > ``tol_px``).

    COLMAP verifies each pair against the motion most of its matches agree on. A turning
    mirror shows the still room moving rigidly too, with another motion; where it fills more of
    the view than the turning objects' texture, a shot is registered tens of degrees off. The
    commanded angles and the turntable axis give each pair's motion to a few pixels: matches
    off its epipolar lines go, and COLMAP still recovers every pose from those that stay.

    Parameters
    ----------
    database : path-like
        COLMAP database after matching.
    files : list of str
        Image names in the database, in the order of ``R`` and ``t``.
    camera : Camera
    commanded : list of ((N, 3, 3), (N, 3)) ndarray pairs
        Candidate commanded world-to-camera poses (:func:`turntable_poses`), e.g. for both
        turning directions; the one that keeps the most matches is used.
    tol_px : float
        Largest Sampson distance from the commanded motion's epipolar geometry, in pixels.

    Returns
    -------
    dict
        ``pairs``, ``kept`` and ``dropped`` inlier matches, ``candidate`` (index used).
    """
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        index = {img.name: files.index(img.name) for img in db.read_all_images()}
        ids = {img.name: img.image_id for img in db.read_all_images()}
        by_id = {ids[n]: index[n] for n in ids}
        xy = {}
        for name, i in index.items():
            kp = db.read_keypoints(ids[name])[:, :2].astype(np.float64) - 0.5  # COLMAP's pixel centres: +0.5
            xy[ids[name]] = camera.undistort(kp)
        tol = tol_px / camera.K[0, 0]
        pair_ids, geometries = db.read_two_view_geometries()
        pairs = [(pycolmap.pair_id_to_image_pair(p), g, np.asarray(g.inlier_matches)) for p, g in zip(pair_ids, geometries)]
        pairs = [(ids_, g, m) for ids_, g, m in pairs if len(m)]

        def consistent(R, t, id1, id2, m):
            i, j = by_id[id1], by_id[id2]
            Rij = R[j] @ R[i].T
            E = np.cross(np.eye(3), t[j] - Rij @ t[i]) @ Rij  # [t]x R
            x1 = np.c_[xy[id1][m[:, 0]], np.ones(len(m))]
            x2 = np.c_[xy[id2][m[:, 1]], np.ones(len(m))]
            Ex1, Etx2 = x1 @ E.T, x2 @ E
            sampson = np.abs(np.einsum("ij,ij->i", x2, Ex1)) / np.sqrt(
                Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2 + 1e-300)
            return sampson < tol

        keep = [[consistent(R, t, i1, i2, m) for (i1, i2), _, m in pairs] for R, t in commanded]
        best = int(np.argmax([sum(int(k.sum()) for k in ks) for ks in keep]))
        for ((id1, id2), g, m), ok in zip(pairs, keep[best]):
            if not ok.all():
                g.inlier_matches = m[ok]
                db.update_two_view_geometry(id1, id2, g)
    finally:
        db.close()
    kept = sum(int(k.sum()) for k in keep[best])
    total = sum(len(k) for k in keep[best])
    return {"pairs": len(pairs), "kept": kept, "dropped": total - kept, "tolerance_px": tol_px, "candidate": best}


def run_sfm(images: list, names: list, camera: Camera, *, masks=None, auto_mask: bool = True,
            overlap: int = 5, closed: bool = True, min_registered: float = 0.9, max_features: int = 4000,
            workdir=None, seed: int = 0, commanded=None, log_file=None, progress=None, task=None) -> SfMResult:
    """Recover the pose of every shot of a turntable sweep.

    Parameters
    ----------
    images : list of (H, W, 3) float ndarray
        Linear images in sweep order (the size of camera.json).
    names : list of str
        A name per image (used in messages and results).
    camera : Camera
        Calibrated intrinsics, held fixed.
    masks : (H, W) bool ndarray or list of them, optional
        True where the pixel may be used (what turns). Combined with the automatic mask.
    auto_mask : bool
        Mask out pixels that do not change over the sweep (:func:`static_mask`) or do not change
        between a shot and both its neighbours (:func:`moving_masks`).
    overlap : int
        Each shot is matched with the next ``overlap`` shots.
    closed : bool
        The sweep is a full turn: match its end with its start (loop closure).
    min_registered : float
        Fraction of shots that must be registered; fewer raises :class:`WorkspaceError`.
    max_features : int
        SIFT features per image.
    workdir : path-like, optional
        Where COLMAP's database and images go (a temporary folder by default).
    seed : int
        COLMAP's random seed (repeatable runs).
    commanded : list of ((N, 3, 3), (N, 3)) ndarray pairs, optional
        Candidate poses the turntable's commands put the shots at (:func:`turntable_poses`, both
        turning directions): matches off their epipolar geometry are dropped before mapping
        (:func:`filter_matches`).
    log_file : path-like, optional
        Where COLMAP's own log goes (appended; its hundreds of lines per run would flood a
        terminal); None leaves it on stderr.
    progress : callable, optional
        Called with one line per COLMAP step (features, matching, mapping).
    task : reflab.core.task.Task, optional
        Progress and cancellation: stepped between COLMAP's phases, and COLMAP itself stops
        within a moment of a cancel (its cancellation token).

    Returns
    -------
    SfMResult
    """
    if len(images) != len(names):
        raise ValueError(f"run_sfm: {len(images)} images but {len(names)} names")
    if len(images) < 3:
        raise WorkspaceError(names[0] if names else "captures/turntable", expected="at least 3 turntable shots",
                             got=len(images))
    for im, name in zip(images, names):
        if im.shape[:2] != (camera.height, camera.width):
            raise WorkspaceError(name, expected=f"an image of camera.json's size {camera.width}x{camera.height}",
                                 got=f"{im.shape[1]}x{im.shape[0]}")
    if workdir is None:
        with tempfile.TemporaryDirectory(prefix="reflab-sfm-") as tmp:
            return _run(images, names, camera, masks, auto_mask, overlap, closed, min_registered, max_features,
                        Path(tmp), seed, commanded, log_file, progress, ensure(task))
    return _run(images, names, camera, masks, auto_mask, overlap, closed, min_registered, max_features,
                Path(workdir), seed, commanded, log_file, progress, ensure(task))


def write_colmap_model(model, folder, similarity=None) -> Path:
    """Write COLMAP's reconstruction (binary: cameras, images, points3D, ...) to ``folder``, moved by
    ``similarity`` (``X' = scale R X + T``) when given, replacing what was there all at once.

    COLMAP's GUI opens it (File > Import model) with the workspace as the image folder."""
    import shutil

    import pycolmap

    folder = Path(folder)
    if similarity is not None:
        model = pycolmap.Reconstruction(model)  # a copy: the caller's stays in the SfM frame
        model.transform(pycolmap.Sim3d(float(similarity.scale), pycolmap.Rotation3d(np.asarray(similarity.R, float)),
                                       np.asarray(similarity.T, float).reshape(3, 1)))
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    old = folder.parent / f".{folder.name}.old"
    try:
        model.write(str(tmp))
        if folder.exists():
            shutil.rmtree(old, ignore_errors=True)
            folder.rename(old)
        tmp.rename(folder)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
    return folder


@contextlib.contextmanager
def _colmap_token(task: Task):
    """A pycolmap CancellationToken cancelled (by a watcher thread) once ``task`` is; the task is
    checked again when COLMAP returns, so a cancelled phase raises :class:`reflab.core.task.Cancelled`."""
    import pycolmap

    token = pycolmap.CancellationToken()
    done = threading.Event()

    def watch():
        while not done.wait(0.05):
            if task.cancelled:
                token.cancel()
                return

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    try:
        yield token
    except InterruptedError:  # pycolmap's answer to a cancelled token
        if not task.cancelled:
            raise
    finally:
        done.set()
        thread.join()
    task.check()


@contextlib.contextmanager
def colmap_log(path):
    """Send file descriptor 2 (where COLMAP's glog writes, from every thread) to ``path``, appended.

    ``pycolmap.logging`` settings alone leave errors on stderr and name the files by date; a
    redirect gives one known file. Python's own stderr is flushed on both sides of the switch.
    """
    if path is None:
        yield
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(path, "ab") as f:
            f.write(f"--- reflab: COLMAP run at {time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode())
            f.flush()
            os.dup2(f.fileno(), 2)
            try:
                yield
            finally:
                sys.stderr.flush()
                os.dup2(saved, 2)
    finally:
        os.close(saved)


def _run(images, names, camera, masks, auto_mask, overlap, closed, min_registered, max_features, work: Path, seed,
         commanded, log_file=None, progress=None, task: Task | None = None):
    import cv2
    import pycolmap

    times = {}
    t0 = time.perf_counter()
    n = len(images)
    grey = _display(images)
    use = np.ones((n, camera.height, camera.width), dtype=bool)
    if masks is not None:
        use &= np.asarray(masks, dtype=bool)
    if auto_mask:
        use &= ~static_mask(grey)[None] & moving_masks(grey, closed)
    if not use.any(axis=(1, 2)).all():
        bad = [names[i] for i in np.flatnonzero(~use.any(axis=(1, 2)))]
        raise WorkspaceError(bad[0], expected="some pixels that turn with the turntable (the mask hides them all)",
                             got=f"{len(bad)} fully masked shots")
    img_dir, mask_dir = work / "images", work / "masks"
    img_dir.mkdir(parents=True, exist_ok=True)
    mask_dir.mkdir(parents=True, exist_ok=True)
    files = [f"{i:04d}.png" for i in range(n)]
    for f, g, m in zip(files, grey, use):
        cv2.imwrite(str(img_dir / f), (g * 255 + 0.5).astype(np.uint8))
        cv2.imwrite(str(mask_dir / (f + ".png")), m.astype(np.uint8) * 255)
    times["prepare_s"] = time.perf_counter() - t0

    db = work / "database.db"
    if db.exists():
        db.unlink()
    model, params = colmap_camera(camera)
    reader = pycolmap.ImageReaderOptions(camera_model=model, camera_params=params, mask_path=str(mask_dir))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = int(max_features)
    extraction.use_gpu = False
    # One thread in each COLMAP step: with more, the same shots gave other poses run to run
    # (floating-point order; the sweep's free-pose RMS 0.374-0.381 px over seven runs, the mirror
    # 0.14-0.19 mm, the demo's novel view 30.0-30.6 dB). Single-threaded, every run is the same
    # to the bit; the simulated lab's sweep at 480x360 costs 10 s instead of 6 s (mapping is faster).
    extraction.num_threads = 1
    say = progress or (lambda line: None)
    where = f" (COLMAP's log: {log_file})" if log_file is not None else ""
    say(f"structure from motion: SIFT features of {n} shots{where}")
    t = time.perf_counter()
    task = ensure(task)
    task.step(0, 3, "structure from motion: features")
    with colmap_log(log_file), _colmap_token(task) as token:
        pycolmap.extract_features(db, img_dir, image_names=files, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction,
                                  device=pycolmap.Device.cpu, cancellation_token=token)
    times["features_s"] = time.perf_counter() - t

    pairs_file = work / "pairs.txt"
    pairs_file.write_text("".join(f"{files[i]} {files[j]}\n" for i, j in loop_pairs(n, overlap, closed)))
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = 1
    say(f"structure from motion: matching {len(loop_pairs(n, overlap, closed))} pairs of shots "
        f"({times['features_s']:.1f} s so far on features)")
    t = time.perf_counter()
    task.step(1, 3, "structure from motion: matching")
    with colmap_log(log_file), _colmap_token(task) as token:
        pycolmap.match_image_pairs(db, matching_options=matching,
                                   pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pairs_file),
                                   device=pycolmap.Device.cpu, cancellation_token=token)
    times["matching_s"] = time.perf_counter() - t
    filtered = None
    if commanded is not None:
        t = time.perf_counter()
        filtered = filter_matches(db, files, camera, commanded)
        times["filter_s"] = time.perf_counter() - t

    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    options.mapper.abs_pose_refine_focal_length = False
    options.mapper.abs_pose_refine_extra_params = False
    options.random_seed = int(seed)
    options.num_threads = 1
    options.multiple_models = False
    say(f"structure from motion: incremental mapping ({times['matching_s']:.1f} s on matching)")
    t = time.perf_counter()
    (work / "sparse").mkdir(exist_ok=True)
    task.step(2, 3, "structure from motion: mapping")
    with colmap_log(log_file), _colmap_token(task) as token:
        models = pycolmap.incremental_mapping(db, img_dir, work / "sparse", options=options,
                                              cancellation_token=token)
    times["mapping_s"] = time.perf_counter() - t
    times["total_s"] = time.perf_counter() - t0
    result = _result(models, names, files, camera, min_registered, times)
    if filtered is not None:
        result.report["commanded_motion_filter"] = filtered
    return result


def _result(models, names, files, camera, min_registered, times) -> SfMResult:
    n = len(names)
    rec = max(models.values(), key=lambda r: r.num_reg_images()) if models else None
    R = np.full((n, 3, 3), np.nan)
    t = np.full((n, 3), np.nan)
    index = {f: i for i, f in enumerate(files)}
    points, errors, tracks, observations = np.zeros((0, 3)), np.zeros(0), [], None
    reproj = float("nan")
    if rec is not None:
        image_index = {}
        for image_id, image in rec.images.items():
            if not image.has_pose:
                continue
            pose = image.cam_from_world()
            i = index[image.name]
            image_index[image_id] = i
            R[i] = pose.rotation.matrix()
            t[i] = pose.translation
        pts = list(rec.points3D.values())
        points = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
        errors = np.array([p.error for p in pts], dtype=np.float64)
        tracks = [np.unique([image_index[e.image_id] for e in p.track.elements if e.image_id in image_index])
                  for p in pts]
        observations = _observations(rec, image_index, list(rec.points3D.keys()), camera)
        reproj = float(rec.compute_mean_reprojection_error()) if pts else float("nan")
    registered = np.all(np.isfinite(t), axis=1)
    report = {
        "images": n,
        "registered": int(registered.sum()),
        "unregistered": [names[i] for i in np.flatnonzero(~registered)],
        "reprojection_px": reproj if np.isfinite(reproj) else None,
        "points": int(len(points)),
        "mean_track_length": float(np.mean([len(tr) for tr in tracks])) if tracks else 0.0,
        "camera_model": colmap_camera(camera)[0],
        "time_s": {k: round(v, 3) for k, v in times.items()},
    }
    need = max(3, int(np.ceil(min_registered * n)))
    if registered.sum() < need:
        missing = report["unregistered"]
        raise WorkspaceError(
            Path(names[0]).parent if names else "captures/turntable",
            expected=f"at least {need} of {n} turntable shots registered by structure from motion "
                     "(check the masks hide only what does not turn, that the objects are textured, and that "
                     "consecutive shots overlap: smaller turntable steps)",
            got=f"{int(registered.sum())} registered; not registered: {', '.join(missing[:8])}"
                + (" ..." if len(missing) > 8 else ""))
    if rec is not None:  # the captures' names, so that COLMAP's GUI finds them from the workspace
        for image in rec.images.values():
            image.name = names[index[image.name]]
    return SfMResult(list(names), R, t, points, errors, tracks, observations, report, rec)


def _observations(rec, image_index: dict, point_ids: list, camera: Camera):
    """Every registered image's measurements of the reconstruction's points, as arrays."""
    from reflab.reconstruction.turntable import Observations

    row = {pid: k for k, pid in enumerate(point_ids)}
    point, image, uv = [], [], []
    for image_id, i in image_index.items():
        for p2 in rec.images[image_id].get_observation_points2D():
            point.append(row[p2.point3D_id])
            image.append(i)
            uv.append(p2.xy)
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2) - 0.5  # COLMAP's first pixel centre is at 0.5
    return Observations(np.asarray(point, dtype=int), np.asarray(image, dtype=int), camera.undistort(uv))


def load_sweep(folder) -> tuple[list, np.ndarray | None]:
    """Image paths of a turntable sweep in sweep order, and their commanded angles.

    ``folder/manifest.json`` (written by ``reflab capture``, docs/hardware.md) lists the shots with
    their ``file`` and ``angle``; without it the folder's images are taken in name order and the
    angles are unknown (None).
    """
    from reflab.core.workspace import MANIFEST, read_json

    folder = Path(folder)
    manifest = folder / MANIFEST
    if manifest.exists():
        shots = read_json(manifest).get("shots")
        if not isinstance(shots, list) or not shots:
            raise WorkspaceError(manifest, "shots", "a non-empty list of shots", got=shots)
        paths, angles = [], []
        for i, shot in enumerate(shots):
            if not isinstance(shot, dict) or "file" not in shot or "angle" not in shot:
                raise WorkspaceError(manifest, f"shots[{i}]", "an object with 'file' and 'angle'", got=shot)
            angle = shot["angle"]
            if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not np.isfinite(angle):
                raise WorkspaceError(manifest, f"shots[{i}].angle", "a finite number of degrees", got=angle)
            paths.append(folder / str(shot["file"]))
            angles.append(float(angle))
        order = np.argsort(np.mod(angles, 360.0), kind="stable")
        return [paths[i] for i in order], np.asarray(angles)[order]
    from reflab.core.images import image_files

    paths = image_files(folder)
    if not paths:
        raise WorkspaceError(folder, expected="turntable shots (captures/turntable/*.exr and its manifest.json, "
                                              "made by `reflab capture sweep`)", got="none")
    return paths, None
