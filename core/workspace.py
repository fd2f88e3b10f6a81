"""The workspace folder, its validation errors and atomic writes.

Every stage reads and writes one folder (docs/formats.md, "Workspace"). A stage that finds a bad
file raises :class:`WorkspaceError`, whose message names the file, the field and what was
expected; a stage never leaves a half-written file (:func:`atomic_write`).
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np


class WorkspaceError(ValueError):
    """A workspace file is missing or malformed.

    Parameters
    ----------
    path : path-like
        The file at fault.
    field : str, optional
        The field inside it (JSON path such as ``surfaces[2].material.kd``).
    expected : str, optional
        What was expected there.
    got : object, optional
        What was found instead (shortened in the message).
    """

    def __init__(self, path, field: str | None = None, expected: str | None = None, got: Any = None):
        self.path, self.field, self.expected, self.got = Path(path), field, expected, got
        msg = str(path)
        if field:
            msg += f": field '{field}'"
        if expected:
            msg += f": expected {expected}"
        if got is not None:
            text = repr(got)
            msg += f", got {text[:80] + '...' if len(text) > 80 else text}"
        super().__init__(msg)


#: Camera RAW files, read as linear values through LibRaw (reflab.core.images.read_raw).
RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw")
#: Linear image files (the input photograph, captures), in order of preference.
IMAGE_SUFFIXES = (".exr", ".png", ".tif", ".tiff") + RAW_SUFFIXES

#: The file in each capture folder that lists its shots (docs/hardware.md).
MANIFEST = "manifest.json"

#: Scoring view -> the file of its camera or lamps (docs/formats.md, "The simulated lab's truth").
VIEWS = {"novel": "novel_camera.json", "relit": "relit_lights.json"}

#: Capture kind -> folder under WORKSPACE/captures (docs/formats.md).
CAPTURE_FOLDERS = {"calibration": "calibration", "lights": "lights", "sweep": "turntable", "input": "input",
                   "inputs": "inputs"}


class OptionError(ValueError):
    """A stage option with a bad value, named by its options field (``spacing``, ``rod_height``).

    The message reads ``"<option>: <what is wrong>"`` in a library call or the GUI; the CLI shows
    :attr:`cli_text`, the same with the command-line flag (``--rod-height: ...``).
    """

    def __init__(self, option: str, message: str):
        self.option, self.message = option, message
        super().__init__(f"{option}: {message}")

    @property
    def cli_text(self) -> str:
        return f"--{self.option.replace('_', '-')}: {self.message}"


class Workspace:
    """Paths of one scene's workspace: every file name of docs/formats.md."""

    def __init__(self, root):
        self.root = Path(root)

    camera = property(lambda self: self.root / "camera.json")
    lights = property(lambda self: self.root / "lights.json")
    scene = property(lambda self: self.root / "scene.json")
    meshes = property(lambda self: self.root / "meshes")
    fit = property(lambda self: self.root / "fit.json")
    textures = property(lambda self: self.root / "textures")
    captures = property(lambda self: self.root / "captures")
    marks = property(lambda self: self.root / "marks.json")
    sfm = property(lambda self: self.root / "sfm.json")
    sparse = property(lambda self: self.root / "sparse.ply")
    colmap_model = property(lambda self: self.root / "sparse" / "0")  # COLMAP's own model (COLMAP's GUI opens it)
    hardware = property(lambda self: self.root / "hardware.json")
    truth = property(lambda self: self.root / "truth")
    report = property(lambda self: self.root / "report.html")
    report_json = property(lambda self: self.root / "report.json")  # report.html's summary
    truth_materials = property(lambda self: self.root / "truth.json")  # the simulated lab's true materials
    truth_albedo = property(lambda self: self.truth / "albedo.exr")  # the simulated lab's true kd at the input view
    texture_index = property(lambda self: self.textures / "index.json")
    cache = property(lambda self: self.root / "cache")
    logs = property(lambda self: self.root / "logs")  # tools' own logs (logs/colmap.log)
    plan = property(lambda self: self.root / "plan.json")  # reflab plan's further shots
    inputs = property(lambda self: self.root / "inputs")  # further photographs and their camera/lamps

    def input_sidecar(self, name: str) -> Path:
        """``inputs/<name>.json``: the camera and the lit lamps of the further photograph ``name``."""
        return self.inputs / f"{name}.json"

    def input_photo(self, name: str) -> Path:
        """``inputs/<name>.exr`` (or a 16-bit PNG/TIFF of that name): the further photograph ``name``."""
        for suffix in IMAGE_SUFFIXES:
            if (self.inputs / f"{name}{suffix}").exists():
                return self.inputs / f"{name}{suffix}"
        return self.inputs / f"{name}.exr"

    def captures_of(self, kind: str) -> Path:
        """``captures/<folder>`` of a capture kind (calibration, lights, sweep, input, inputs)."""
        if kind not in CAPTURE_FOLDERS:
            raise ValueError(f"capture kind must be one of {sorted(CAPTURE_FOLDERS)}, got {kind!r}")
        return self.captures / CAPTURE_FOLDERS[kind]

    def manifest(self, kind: str) -> Path:
        """``captures/<folder>/manifest.json`` of a capture kind."""
        return self.captures_of(kind) / MANIFEST

    def mesh(self, name: str) -> Path:
        """``meshes/<name>.ply``, the mesh of surface ``name`` (scene.json names it relative to the root)."""
        return self.meshes / f"{name}.ply"

    def render(self, aov: str | None = None) -> Path:
        """The default output of ``reflab render`` (render.exr, or albedo.exr for the albedo AOV)."""
        return self.root / ("albedo.exr" if aov == "albedo" else "render.exr")

    def export(self, fmt: str) -> Path:
        """The default output folder of ``reflab export --format FMT`` (export-FMT/; docs/export.md)."""
        return self.root / f"export-{fmt}"

    def view(self, which: str) -> tuple[Path, Path]:
        """A view that scores the recovered model (docs/formats.md, "The simulated lab's truth"): ``novel``
        -> (novel_camera.json, novel.exr), ``relit`` -> (relit_lights.json, relit.exr); in truth/
        (``Workspace(ws.truth).view(...)``) the truth, in the workspace the model's render."""
        if which not in VIEWS:
            raise ValueError(f"view must be one of {sorted(VIEWS)}, got {which!r}")
        return self.root / VIEWS[which], self.root / f"{which}.exr"

    def trees_cache(self, key: str) -> Path:
        """Cached pixel-intensity trees named by their inputs' hash (reflab.inverse.forward.trees.trees_for_workspace)."""
        return self.cache / f"trees-{key}.npz"

    @property
    def input_image(self) -> Path:
        """The input photograph: input.exr, else a 16-bit PNG/TIFF named input.*."""
        for suffix in IMAGE_SUFFIXES:
            if self.input_file(suffix).exists():
                return self.input_file(suffix)
        return self.input_file()

    def input_file(self, suffix: str = ".exr") -> Path:
        """Where the input photograph goes in the format of ``suffix`` (``input_image`` finds it)."""
        return self.root / f"input{suffix}"

    def require(self, path: Path, made_by: str) -> Path:
        """Return ``path`` or stop with a message naming the stage that makes it."""
        if not path.exists():
            raise WorkspaceError(path, expected=f"this file (made by `{made_by}`)", got="missing")
        return path


def check_writable(folder) -> Path:
    """Stop (WorkspaceError naming ``folder`` and what to do) unless a file can be created there.

    Tried, not guessed: ``os.access`` misses read-only bind mounts in some kernels and every
    permission for root. Call it before a stage starts, so that it fails before computing.
    """
    folder = Path(folder)
    try:
        fd, probe = tempfile.mkstemp(prefix=".reflab-write-probe.", dir=folder)
    except OSError as exc:
        raise WorkspaceError(folder, expected="a folder this user can write (remount it read-write, fix its "
                                              "permissions, or copy the workspace somewhere writable)",
                             got=exc.strerror or str(exc)) from None
    os.close(fd)
    os.unlink(probe)
    return folder


def check_folder(path, *, write: bool = False, create: bool = False, what: str = "workspace folder") -> Path:
    """Check a folder a stage reads (and writes) before the stage starts.

    ``create``: the folder may not exist yet (then its nearest existing parent must be writable).
    A missing folder is reported as such, not as the first file the stage would have looked for.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise WorkspaceError(path, expected=f"a {what}", got="a file")
    if not path.exists():
        if not create:
            raise WorkspaceError(path, expected=f"an existing {what} (check the path)", got="no such folder")
        check_writable(next(p for p in path.absolute().parents if p.is_dir()))
        return path
    if not os.access(path, os.R_OK | os.X_OK):
        raise WorkspaceError(path, expected=f"a readable {what} (fix its permissions)", got="no read permission")
    if write:
        check_writable(path)
    return path


@contextlib.contextmanager
def atomic_write(path, mode: str = "wb") -> Iterator[Any]:
    """Open a temporary file beside ``path``; rename it over ``path`` only on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_path(path) -> Iterator[Path]:
    """A temporary path with ``path``'s suffix, for writers that take a file name (cv2, open3d)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _jsonable(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_json(path, obj) -> Path:
    """Write ``obj`` as indented JSON, atomically. NaN and inf are refused, never written."""
    text = json.dumps(obj, indent=2, default=_jsonable, allow_nan=False)
    with atomic_write(path, "w") as f:
        f.write(text + "\n")
    return Path(path)


def read_json(path) -> dict:
    """Read a JSON object, naming the file in any error."""
    path = Path(path)
    if not path.exists():
        raise WorkspaceError(path, expected="an existing file", got="missing")
    try:
        obj = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise WorkspaceError(path, expected=f"valid JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(obj, dict):
        raise WorkspaceError(path, expected="a JSON object at the top level", got=type(obj).__name__)
    return obj


def field(obj: dict, key: str, path, where: str = "", required: bool = True, default=None):
    """``obj[key]`` or a :class:`WorkspaceError` naming ``where.key``."""
    name = f"{where}.{key}" if where else key
    if key not in obj:
        if required:
            raise WorkspaceError(path, name, "this field", got="missing")
        return default
    return obj[key]


def object_items(items, path, name: str, what: str, item_expected: str = "an object") -> Iterator[tuple[str, dict]]:
    """Yield ``(where, item)`` for a non-empty JSON list of objects, naming ``name[i]`` in errors.

    ``what`` describes the list (e.g. "lights"); ``item_expected`` what each element must be.
    """
    if not isinstance(items, list) or not items:
        raise WorkspaceError(path, name, f"a non-empty list of {what}", got=items)
    for i, item in enumerate(items):
        where = f"{name}[{i}]"
        if not isinstance(item, dict):
            raise WorkspaceError(path, where, item_expected, got=item)
        yield where, item


def as_array(value, shape: tuple, path, name: str, *, nonneg: bool = False) -> np.ndarray:
    """Convert a JSON value to a float64 array of ``shape`` (-1 = any), finite, optionally ≥ 0."""
    want = "x".join("N" if s == -1 else str(s) for s in shape)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise WorkspaceError(path, name, f"numbers of shape {want}", got=value) from None
    if arr.ndim != len(shape) or any(s not in (-1, a) for s, a in zip(shape, arr.shape)):
        raise WorkspaceError(path, name, f"shape {want}", got=value)
    if not np.all(np.isfinite(arr)):
        raise WorkspaceError(path, name, "finite numbers (no NaN or inf)", got=value)
    if nonneg and np.any(arr < 0):
        raise WorkspaceError(path, name, "non-negative numbers", got=value)
    return arr


def as_float(value, path, name: str, *, positive: bool = False) -> float:
    """A finite JSON number, optionally > 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise WorkspaceError(path, name, "a finite number", got=value)
    if positive and value <= 0:
        raise WorkspaceError(path, name, "a positive number", got=value)
    return float(value)
