"""The calibration stages as library functions: options in, a typed result out, a Task for progress.

:func:`calibrate_camera` writes camera.json from views of the circle target (Tsai);
:func:`calibrate_lights` writes lights.json (and marks.json when it detects marks) from rod
shadows. The CLI (``reflab calibrate``), the GUI and the demo call these; each checks its
:class:`reflab.core.task.Task` between images and writes its file only once everything succeeded.
Bad options raise :class:`reflab.core.workspace.OptionError` naming the options field, bad files
:class:`reflab.core.workspace.WorkspaceError`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.core.options import opt
from reflab.core.task import Task, ensure
from reflab.core.workspace import OptionError


@dataclass
class CameraOptions:
    """Options of :func:`calibrate_camera`.

    ``grid`` is ``"COLSxROWS"`` or ``(cols, rows)``; ``images`` default to
    ``captures/calibration/*``; ``reference`` indexes the image taken from the input view's pose.
    """

    workspace: Path
    grid: str | tuple = opt("11x8", "circles per row and column of the target, COLSxROWS (e.g. 11x8)",
                            metavar="COLSxROWS", required=True)
    spacing: float = opt(0.015, "circle spacing of the target", unit="m")
    images: list | None = None
    radius: float | None = opt(None, "printed circle radius (default: estimated from the images)", unit="m",
                                  type=float)
    reference: int = opt(0, "index of the image taken from the input photograph's pose")
    pixel_size: float = opt(0.005, "sensor element size, Tsai's dx = dy", unit="mm")
    bias_correction: bool = opt(True, "fit projected circle centres (as OpenCV does) instead of ellipse centres",
                                flag="--no-bias-correction")


@dataclass
class CameraResult:
    """What :func:`calibrate_camera` wrote and how well the camera fits."""

    path: Path
    camera: object  # reflab.calibration.camera.Camera
    calibration: object  # reflab.calibration.tsai.CalibrationResult
    images: list  # every image considered
    used: list  # indices into images of the views with a detected grid (calibration.views index this)
    skipped: list = field(default_factory=list)  # (path, reason) of unreadable images or without a grid
    unreadable: list = field(default_factory=list)  # (path, message) of images that could not be read

    @property
    def views(self) -> list:
        """(path, rms px, worst px) of every view the calibration kept."""
        res = self.calibration
        return [(self.images[self.used[j]], float(r), float(w)) for j, r, w in zip(res.views, res.rms, res.worst)]

    @property
    def rejected(self) -> list:
        """(path, rms px) of the views left out for reprojecting far worse than the others."""
        return [(self.images[self.used[j]], float(r)) for j, r in self.calibration.rejected.items()]

    @property
    def rms_px(self) -> float:
        return float(self.calibration.rms_all)


@dataclass
class LightsOptions:
    """Options of :func:`calibrate_lights`.

    With ``images`` it detects the rod's foot and shadow tip in each (lamp ``light``: one index
    for every image, or a list with one per image), merges them into marks.json and uses every
    mark there; with ``marks`` it reads that file instead; with neither it detects them in the
    single-lamp shots of captures/lights/ (the lamp of each from its manifest) and merges them into
    marks.json likewise (calibration/rod.py), or, without a lights session, uses the marks already in
    marks.json. ``light`` None: each image's lamp from the lights session's manifest where it is one
    of its shots, else 0. A shot that cannot be read is skipped (``LightsResult.unreadable``) while
    its lamp keeps two others. ``rod_height`` overrides, or fills in, marks.json's. Intensity comes
    from ``sheet`` images (one per lamp, of a sheet of Lambertian ``sheet_reflectance``), else,
    with ``sheet_reflectance`` and ``sheet_region`` alone, from that card lying in the rod shots
    (each lamp's frame minus the lamps-off frame at its angle), else ``intensity`` (data sheet),
    else the previous lights.json, else 1.
    """

    workspace: Path
    images: list | None = None
    rod_height: float | None = opt(None, "rod height (default: marks.json's)", unit="m", type=float, typical=0.10)
    marks: Path | None = opt(None, "marks.json to use instead of detecting marks", type=Path)
    light: int | list | None = opt(None, "lamp index of the images given (default: the lamp captures/lights/"
                                         "manifest.json gives for a shot of the lights session, else 0)", type=int)
    mark_sigma: float | None = opt(None, "marking noise for the covariance (default: from the residuals)", unit="px",
                                   type=float)
    intensity: list | None = opt(None, "radiant intensity from the data sheet, every lamp (1 or 3 values)",
                                 unit="W/sr", type=float, nargs="+")
    sheet: list | None = opt(None, "per lamp in index order, an image of the reference sheet lit by that lamp alone",
                             type=Path, nargs="+")
    sheet_reflectance: float | None = opt(None, "the sheet's Lambertian reflectance (0..1; kd = reflectance / pi)",
                                          type=float)
    sheet_region: tuple | None = opt(None, "the sheet's extent on the ground (default: all visible ground)", unit="m",
                                     type=float, nargs=4, metavar=("XMIN", "XMAX", "YMIN", "YMAX"))


@dataclass
class LampReport:
    """One located lamp."""

    index: int
    position: np.ndarray
    sigma_mm: np.ndarray
    intensity: np.ndarray
    intensity_known: bool
    outliers: list


@dataclass
class LightsResult:
    """What :func:`calibrate_lights` wrote."""

    path: Path
    lights: object  # reflab.calibration.lights.Lights
    lamps: list  # LampReport per lamp
    marks_path: Path | None = None  # marks.json when this run wrote it
    detected: list = field(default_factory=list)  # (image name, light, base, tip) of marks detected now
    unreadable: list = field(default_factory=list)  # (image name, message) of rod shots skipped: cannot be read


def _rows_run_down(centres, cols: int, rows: int) -> bool:
    """Whether a detected grid's rows (``cols`` circles each) run closer to the image's vertical than
    to its horizontal: what a COLSxROWS given swapped (``--grid 7x9`` for a 9x7 target) looks like."""
    grid = np.asarray(centres).reshape(rows, cols, 2)
    along_row = grid[:, -1] - grid[:, 0]
    return bool(np.sum(np.abs(along_row[:, 1])) > np.sum(np.abs(along_row[:, 0])))


def calibrate_camera(options: CameraOptions, task: Task | None = None) -> CameraResult:
    """Calibrate the camera from views of the circle target and write camera.json."""
    from reflab.calibration.circles import detect_grid, parse_grid
    from reflab.calibration.target import target_points
    from reflab.calibration.tsai import CalibrationError, calibrate
    from reflab.core.images import image_files, read_image
    from reflab.core.workspace import Workspace, WorkspaceError, check_folder

    task = ensure(task)
    o = options
    ws = Workspace(check_folder(o.workspace, write=True, create=True))  # a first calibration may start it
    cols, rows = parse_grid(o.grid) if isinstance(o.grid, str) else (int(o.grid[0]), int(o.grid[1]))
    if not o.spacing > 0:
        raise OptionError("spacing", f"must be a positive number of metres, got {o.spacing}")
    paths = [Path(p) for p in o.images] if o.images else image_files(ws.captures_of("calibration"))
    if not paths and not ws.root.exists():
        raise WorkspaceError(ws.root, expected="an existing workspace folder (check the path), or target images given",
                             got="no such folder")
    if not paths:
        raise ValueError(f"no target images given and none in {ws.captures_of('calibration')}")
    if not 0 <= o.reference < len(paths):
        raise OptionError("reference", f"{o.reference} is not an image index (0..{len(paths) - 1})")
    used, obs, areas, blobs, reasons, skipped, unreadable = [], [], [], [], "", [], []
    size = None
    for i, path in enumerate(paths):
        task.step(i, len(paths) + 1, f"detecting the target in {path.name}")
        try:  # any image a camera writes (8-bit JPEG too); one unreadable photo is not fatal
            img = read_image(path, linear=False)
        except WorkspaceError as exc:
            if i == o.reference:
                raise
            unreadable.append((path, str(exc)))
            continue
        shape = (img.shape[1], img.shape[0])
        if size is None:
            size = shape
        elif shape != size:
            raise ValueError(f"{path}: image is {shape[0]}x{shape[1]}, the others {size[0]}x{size[1]}")
        det = detect_grid(img, cols, rows)
        blobs.append(det.n_blobs)
        if not det.found:
            reasons += det.reason
            skipped.append((path, f"grid {cols}x{rows} not found: {det.reason}"))
            continue
        used.append(i)
        obs.append(det.centres)
        areas.append(det.areas)
    if not blobs:
        raise ValueError(f"none of the {len(paths)} target images could be read")
    if not used and (np.median(blobs) != cols * rows or "grid size" in reasons):
        raise OptionError("grid", f"grid {cols}x{rows} ({cols * rows} circles) found in none of {len(paths)} images; "
                                  f"they show about {int(np.median(blobs))} dark blobs: check the grid size (COLSxROWS)")
    if o.reference not in used:
        raise ValueError(f"the reference image {paths[o.reference]} has no detectable grid; "
                         "its pose is the one camera.json needs")
    # The reference view (the target laid square to the camera) fixes the world frame: rows running
    # down it is a grid given swapped, which would turn that frame 90° without a word.
    if cols != rows and _rows_run_down(obs[used.index(o.reference)], cols, rows):
        raise OptionError("grid", f"{cols}x{rows}: in the reference view the rows of {cols} circles run down the image, so "
                                  f"the target is most likely {rows}x{cols} (COLSxROWS: circles along a row first; a "
                                  f"camera rolled 90° is the other reading); camera.json was not written")
    task.step(len(paths), len(paths) + 1, "calibrating")
    try:
        res = calibrate(obs, target_points(cols, rows, o.spacing), size, radius=o.radius,
                        pixel_size=o.pixel_size, reference=used.index(o.reference),
                        bias_correction=o.bias_correction, areas=areas, check=task.check)
    except CalibrationError as exc:
        if exc.view is None:
            raise
        raise ValueError(f"{paths[used[exc.view]]}: {exc}") from None
    task.check()
    cam = res.camera
    cam.extra["calibration"] = dict(res.report([str(paths[i]) for i in used]), grid=[cols, rows],
                                    spacing=o.spacing, reference_image=str(paths[o.reference]),
                                    skipped=[str(p) for i, p in enumerate(paths) if i not in used])
    out = cam.save(ws.camera)
    task.step(1, 1, f"wrote {out}")
    return CameraResult(out, cam, res, paths, used, skipped, unreadable)


def calibrate_lights(options: LightsOptions, task: Task | None = None) -> LightsResult:
    """Locate every lamp from rod shadows (and its intensity) and write lights.json."""
    from reflab.calibration.camera import Camera
    from reflab.calibration.lamps import lamp_intensity, locate_lamps, read_marks, write_marks
    from reflab.calibration.lights import Lights, PointLight
    from reflab.calibration.rod import RodShot, card_intensities, detect_marks, rod_shots
    from reflab.core.images import read_image
    from reflab.core.workspace import Workspace, WorkspaceError, check_folder, read_json

    task = ensure(task)
    o = options
    ws = Workspace(check_folder(o.workspace, write=True))
    camera = Camera.load(ws.require(ws.camera, "reflab calibrate camera"))
    images = [Path(p) for p in o.images or []]
    marks_path = Path(o.marks) if o.marks else ws.marks
    height, marks = read_marks(marks_path, o.rod_height) if o.marks else (None, [])
    detected, shots, unreadable = [], None, []
    if images and o.marks:
        raise OptionError("marks", "give either images to detect marks in or a marks file, not both")
    geometric = lambda path: read_image(path, linear=False)  # noqa: E731 -- marks need no linear values
    if not o.marks:
        if marks_path.exists() and "marks" in read_json(marks_path):  # rod marks made (and corrected) before
            height, marks = read_marks(marks_path, o.rod_height)
        if images:
            names = [str(p.resolve().relative_to(ws.root.resolve())) if p.resolve().is_relative_to(ws.root.resolve())
                     else str(p) for p in images]
            if o.light is None:  # a shot of the lights session: its lamp (and room frame) from the manifest
                session = {s.image: s for s in rod_shots(ws.root)} if ws.manifest("lights").exists() else {}
                shots = [session.get(name, RodShot(name, 0)) for name in names]
            else:
                lamps = list(o.light) if isinstance(o.light, (list, tuple)) else [o.light] * len(images)
                if len(lamps) != len(images):
                    raise OptionError("light", f"{len(lamps)} lamp indices for {len(images)} images")
                shots = [RodShot(name, int(k)) for name, k in zip(names, lamps)]
        elif ws.manifest("lights").exists() or not marks:
            shots = rod_shots(ws.root)  # the lights session's shots: its manifest says which lamp lit each
        # (no images and no session: the marks of marks.json, made by hand, are used as they are)
        found = []
        for i, shot in enumerate(shots or []):
            task.step(i, len(shots) + 1, f"detecting the rod in {Path(shot.image).name}")
            try:
                found += detect_marks(ws.root, [shot], geometric)
            except WorkspaceError as exc:  # a cut-off file: the lamp's other shots may do without it
                unreadable.append((shot.image, str(exc), shot.light))
        names = {m.image for m in found}
        marks = [m for m in marks if m.image not in names] + found
        for image, message, light in unreadable:
            if sum(m.light == light for m in marks) < 2:
                raise ValueError(f"{message}; without it lamp {light} has fewer than 2 rod shots: retake it")
        detected = [(m.image, m.light, m.base, m.tip) for m in found]
    if o.rod_height is not None:
        height = o.rod_height
    if height is None or not height > 0:
        raise OptionError("rod_height", f"must be a positive number of metres (got {height})")
    if not marks:
        raise OptionError("marks", f"no marks: give rod images or a marks file (nothing in {marks_path})")
    # Written before locating, so that a user can correct a bad mark there and rerun with marks.
    written_marks = write_marks(marks_path, height, marks) if not o.marks else None
    if o.sheet and o.sheet_reflectance is None:
        raise OptionError("sheet_reflectance", "needed with sheet images (the sheet's Lambertian reflectance)")
    if o.intensity and len(o.intensity) not in (1, 3):
        raise OptionError("intensity", f"takes 1 or 3 values, got {len(o.intensity)}")
    task.step(len(images), len(images) + 1, "locating the lamps")
    fits = locate_lamps(camera, marks, height, mark_sigma=o.mark_sigma)
    if [f.light for f in fits] != list(range(len(fits))):
        raise ValueError(f"lamp indices in the marks are {[f.light for f in fits]}; expected 0..{len(fits) - 1}")
    if o.sheet and len(o.sheet) != len(fits):
        raise OptionError("sheet", f"{len(o.sheet)} images for {len(fits)} lamps")
    cards = {}
    if not o.sheet and o.sheet_reflectance is not None:  # the card in the rod shots, room light subtracted
        if o.sheet_region is None:
            raise OptionError("sheet_region", "needed with a sheet reflectance and no sheet images (the card on the table)")
        cards = card_intensities(ws.root, shots if shots is not None else rod_shots(ws.root), camera,
                                 {f.light: f.position for f in fits}, o.sheet_reflectance / np.pi, o.sheet_region,
                                 read_image)
    old = Lights.load(ws.lights) if ws.lights.exists() else None
    lights, reports = [], []
    for k, fit in enumerate(fits):
        task.check()
        extra = {"calibration": fit.report()}
        known = True
        if o.sheet:
            inten, spread = lamp_intensity(read_image(o.sheet[k]), camera, fit.position,
                                           o.sheet_reflectance / np.pi, region=o.sheet_region)
            extra["calibration"]["intensity_spread"] = spread
        elif cards:
            inten, spread = cards[fit.light]
            extra["calibration"]["intensity_spread"] = spread
        elif o.intensity:
            inten = np.broadcast_to(np.asarray(o.intensity, float), (3,)).copy()
        elif old is not None and k < len(old):
            inten = old[k].intensity
        else:
            inten, known = np.ones(3), False
        lights.append(PointLight(fit.position, inten, fit.covariance, extra))
        reports.append(LampReport(k, fit.position, np.sqrt(np.diag(fit.covariance)) * 1000, np.asarray(inten),
                                  known, list(fit.outliers or [])))
    task.check()
    out = Lights(lights).save(ws.lights)
    task.step(1, 1, f"wrote {out}")
    return LightsResult(out, Lights(lights), reports, written_marks, detected,
                        [(image, message) for image, message, _ in unreadable])
