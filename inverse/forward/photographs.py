"""Several photographs of one scene as one system (docs/method.md §6, docs/formats.md "inputs/").

The reference photograph (input.exr with camera.json and lights.json) and every further one in
``inputs/`` (``NAME.exr`` with ``NAME.json`` = ``{"camera": ..., "lights": ...}``, the camera that
took it and the lamps that were lit, in the scene's frame) see the same surfaces. Their trees
are built one photograph at a time (each cached like the reference's) and then **stacked**: the
photographs lie one below the other in one tall image, each tree's pixel index moves to its
photograph's rows, and every later stage (the factorized system, F-TBO / NF-TBO, σ, the outlier
pass, the texture's sparse system) sees one photograph with more rows and no more unknowns.

Lamps go into *slots*: a photograph's lamp takes a slot of the same colour (intensity
proportional per band) not yet used by that photograph, else a new one; the scalar ratio of the
two intensities is folded into the node's ``light_dist2``, which the model only ever divides the
intensity by. The same physical lamp moved by the turntable, or lit alone, keeps its slot, so the
per-node light arrays stay as wide as the most lamps one photograph has, not the sum over photographs.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.core.workspace import IMAGE_SUFFIXES, Workspace, WorkspaceError, read_json

#: Two intensities are one lamp colour when their per-band ratios agree this closely.
SAME_COLOUR = 1e-9
#: Name of the reference photograph in fit.json's ``photographs``.
REFERENCE = "input"


@dataclass
class Photograph:
    """One photograph of the scene: its name, image file, camera and lit lamps (scene frame)."""

    name: str
    image: Path
    camera: object  # reflab.calibration.camera.Camera
    lights: object  # reflab.calibration.lights.Lights
    shot: dict | None = None  # the rig shot it is ({"angle_deg", "lamps"}), when the sidecar says


def input_names(workspace) -> list[str]:
    """Names of the further photographs in ``inputs/``: each ``NAME.json`` (sorted)."""
    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    if not ws.inputs.is_dir():
        return []
    return sorted(p.stem for p in ws.inputs.glob("*.json"))


def load_photographs(workspace, *, reference_only: bool = False) -> list[Photograph]:
    """The reference photograph, then every further one of ``inputs/`` (unless ``reference_only``).

    A sidecar without its image, an image without its sidecar, a sidecar whose ``camera`` or
    ``lights`` is malformed, or one that lights no lamp raises :class:`WorkspaceError` naming it.
    """
    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights

    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    camera = Camera.load(ws.require(ws.camera, "reflab calibrate camera"))
    lights = Lights.load(ws.require(ws.lights, "reflab calibrate lights"))
    photos = [Photograph(REFERENCE, ws.require(ws.input_image, "reflab capture input"), camera, lights)]
    if reference_only:
        return photos
    names = input_names(ws)
    if ws.inputs.is_dir():
        orphans = sorted(p.name for p in ws.inputs.iterdir()
                         if p.suffix.lower() in IMAGE_SUFFIXES and p.stem not in names)
        if orphans:
            raise WorkspaceError(ws.inputs / orphans[0], expected=f"a sidecar {Path(orphans[0]).stem}.json beside it "
                                 "({\"camera\": ..., \"lights\": ...})", got="missing")
    for name in names:
        side = ws.input_sidecar(name)
        obj = read_json(side)
        for key in ("camera", "lights"):
            if not isinstance(obj.get(key), dict):
                raise WorkspaceError(side, key, "an object (the camera.json / lights.json form)", got=obj.get(key, "missing"))
        camera = Camera.from_json(obj["camera"], side)
        lights = Lights.from_json(obj["lights"], side)
        if len(lights) == 0 or not np.any(lights.intensities > 0):
            raise WorkspaceError(side, "lights", "at least one lit lamp", got="none")
        image = ws.input_photo(name)
        if not image.exists():
            raise WorkspaceError(image, expected=f"the photograph that {side.name} describes", got="missing")
        photos.append(Photograph(name, image, camera, lights, obj.get("shot") if isinstance(obj.get("shot"), dict) else None))
    return photos


@dataclass
class Block:
    """Where one photograph lies in the stacked image: rows ``row0 .. row0 + height`` of it."""

    name: str
    row0: int
    width: int
    height: int
    lights: int  # lamps lit


@dataclass
class Stack:
    """Photographs stacked into one tall image and one set of trees.

    Attributes
    ----------
    trees : Trees
        The stacked trees: ``width`` the widest photograph's, ``height`` the sum of heights.
    intensities : (K, 3) ndarray
        The lamp slots' intensities.
    blocks : list of Block
    valid : (H·W,) bool ndarray
        False on the padding right of a narrower photograph.
    reach : (H·W,) float ndarray, optional
        Each pixel's probability that its trees were built, when a further photograph's were
        built for a uniform share of its pixels alone (:func:`reflab.inverse.fit.sampling.tiles`);
        None: every pixel's.
    even : (H·W,) bool ndarray, optional
        With ``reach``: the colour lobes' uniform sample of each textured surface
        (:func:`reflab.inverse.fit.sampling.even_of`), whose trees were built too.
    """

    trees: object
    intensities: np.ndarray
    blocks: list = field(default_factory=list)
    valid: np.ndarray | None = None
    reach: np.ndarray | None = None
    even: np.ndarray | None = None

    @property
    def width(self) -> int:
        return int(self.trees.width)

    @property
    def height(self) -> int:
        return int(self.trees.height)

    def image(self, images) -> np.ndarray:
        """The photographs' (h, w, 3) images as one (H, W, 3) float64 image (zero on padding)."""
        if len(images) == 1:
            return np.asarray(images[0], dtype=np.float64)
        out = np.zeros((self.height, self.width, 3))
        for b, img in zip(self.blocks, images):
            out[b.row0:b.row0 + b.height, :b.width] = img
        return out

    def pixels(self, i: int) -> np.ndarray:
        """Flat pixel indices (in the stacked image) of photograph ``i``'s own pixels."""
        b = self.blocks[i]
        v, u = np.mgrid[b.row0:b.row0 + b.height, 0:b.width]
        return (v * self.width + u).ravel()

    def photograph_of(self, pixel) -> np.ndarray:
        """Index of the photograph each flat pixel index lies in."""
        return photograph_of(pixel, [b.row0 for b in self.blocks], self.width)

    def split(self, image) -> list:
        """A stacked (H, W, …) image cut back into the photographs' own images."""
        return [image[b.row0:b.row0 + b.height, :b.width] for b in self.blocks]


def lamp_slots(lights_list) -> tuple[np.ndarray, list]:
    """(K, 3) slot intensities, and per photograph, each lamp's (slot, scale) with lamp = scale · slot."""
    slots, assign = [], []
    for lights in lights_list:
        taken, mine = set(), []
        for inten in np.asarray(lights.intensities, dtype=np.float64).reshape(-1, 3):
            scale = float(inten.max())
            found = None
            for k, ref in enumerate(slots):
                if k in taken or scale <= 0:
                    continue
                ratio = inten / ref
                if np.all(np.isfinite(ratio)) and np.ptp(ratio) <= SAME_COLOUR * ratio.max():
                    found = (k, float(ratio.mean()))
                    break
            if found is None:
                slots.append(inten if scale > 0 else np.ones(3))
                found = (len(slots) - 1, 1.0 if scale > 0 else 0.0)
            taken.add(found[0])
            mine.append(found)
        assign.append(mine)
    return np.array(slots, dtype=np.float64).reshape(-1, 3), assign


def slot_lights(trees, mine, n_slots: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One photograph's (light_dir, light_dist2, visible) moved to the stack's ``n_slots`` lamp
    slots, ``mine`` its lamps' (slot, scale) from :func:`lamp_slots`."""
    n = len(trees.pixel)
    ld = np.repeat(np.asarray(trees.normal, dtype=np.float64)[:, None, :], n_slots, axis=1)  # unlit slots: any finite direction
    d2 = np.ones((n, n_slots))
    vis = np.zeros((n, n_slots), dtype=bool)
    for j, (slot, scale) in enumerate(mine):
        ld[:, slot] = trees.light_dir[:, j]
        vis[:, slot] = np.asarray(trees.visible[:, j], dtype=bool) & (scale > 0)
        # I_lamp / d² = I_slot / (d² / scale)
        d2[:, slot] = trees.light_dist2[:, j] / (scale if scale > 0 else 1.0)
    return ld, d2, vis


def stack_trees(trees_list, lights_list, names=None) -> Stack:
    """Stack the trees of several photographs (see the module's description).

    One photograph's trees come back as they are, with its lamps as the slots.
    """
    from reflab.inverse.forward.trees import Trees

    names = list(names) if names is not None else [f"photo{i}" for i in range(len(trees_list))]
    if len(trees_list) == 1:
        t = trees_list[0]
        return Stack(t, np.asarray(lights_list[0].intensities, dtype=np.float64).reshape(-1, 3),
                     [Block(names[0], 0, t.width, t.height, len(lights_list[0]))], None)
    slots, assign = lamp_slots(lights_list)
    K = len(slots)
    width = max(int(t.width) for t in trees_list)
    depth = max(int(t.depth) for t in trees_list)
    blocks, row0 = [], 0
    paths, path_id = [], {}
    parts = {k: [] for k in ("pixel", "surface", "point", "normal", "view", "level", "fresnel", "path",
                             "parent", "triangle", "barycentric", "light_dir", "light_dist2", "visible")}
    offset = 0
    for t, lights, mine, name in zip(trees_list, lights_list, assign, names):
        n = len(t.pixel)
        v, u = np.divmod(np.asarray(t.pixel, dtype=np.int64), int(t.width))
        parts["pixel"].append((v + row0) * width + u)
        for key in ("surface", "point", "normal", "view", "level", "fresnel", "triangle", "barycentric"):
            parts[key].append(np.asarray(getattr(t, key)))
        remap = np.array([path_id.setdefault(p, len(path_id)) for p in t.paths], dtype=np.int64)
        parts["path"].append(remap[np.asarray(t.path, dtype=np.int64)] if n else np.zeros(0, np.int64))
        parent = np.asarray(t.parent, dtype=np.int64)
        parts["parent"].append(np.where(parent >= 0, parent + offset, -1))
        ld, d2, vis = slot_lights(t, mine, K)
        parts["light_dir"].append(ld)
        parts["light_dist2"].append(d2)
        parts["visible"].append(vis)
        blocks.append(Block(name, row0, int(t.width), int(t.height), len(lights)))
        row0 += int(t.height)
        offset += n
    paths = [None] * len(path_id)
    for p, i in path_id.items():
        paths[i] = p
    arrays = {k: np.concatenate(v) for k, v in parts.items()}
    arrays["visible"] = arrays["visible"].astype(trees_list[0].visible.dtype)
    key = hashlib.sha256("|".join(t.key for t in trees_list).encode()).hexdigest()[:16]
    stats = {"cache": ",".join(str(t.stats.get("cache", "built")) for t in trees_list),
             "build_s": float(sum(t.stats.get("build_s", 0.0) or 0.0 for t in trees_list)),
             "photographs": len(trees_list),
             # the reference photograph's pixels are the stacked image's first ones
             "reference_pixels": int(trees_list[0].height) * width,
             "block_row0": [b.row0 for b in blocks]}  # σ's sandwich over whole photographs
    trees = Trees(width, row0, depth, paths=paths, stats=stats, key=key, **arrays)
    valid = np.zeros(width * row0, dtype=bool)
    for b in blocks:
        v, u = np.mgrid[b.row0:b.row0 + b.height, 0:b.width]
        valid[(v * width + u).ravel()] = True
    return Stack(trees, slots, blocks, None if valid.all() else valid)


def photograph_of(pixel, row0, width: int) -> np.ndarray:
    """Index of the stacked photograph each flat pixel index lies in, the photographs starting at
    the image rows ``row0`` (``stats["block_row0"]`` of stacked trees) of an image ``width`` wide."""
    return np.searchsorted(np.asarray(row0), np.asarray(pixel, dtype=np.int64) // int(width), side="right") - 1


def photograph_count(trees) -> int:
    """How many photographs ``trees`` hold: :func:`stack_trees`' ``stats["photographs"]`` (kept by
    the trees of some of their pixels), 1 for one photograph's own trees."""
    stats = getattr(trees, "stats", None)
    return int(stats.get("photographs", 1)) if isinstance(stats, dict) else 1


def turned_view(camera, lights, angle_deg: float, centre_xy, *, direction: float = 1.0, lit=None):
    """The camera and lamps of a photograph taken with the turntable turned by ``angle_deg``,
    in the scene's frame (docs/formats.md "inputs/"): the objects turned by ``direction · angle``
    about the vertical axis through ``centre_xy`` are seen as if the camera and the lamps had turned
    the other way. ``lit``: indices of the lamps that are on (default: all).

    Returns
    -------
    camera : Camera
    lights : Lights
    """
    from dataclasses import replace

    from reflab.calibration.lights import Lights, PointLight
    from reflab.calibration.rotations import axis_rotation
    from reflab.reconstruction.sfm import turntable_poses

    R, t = turntable_poses(camera, [angle_deg], centre_xy, direction)
    cam = replace(camera, R=R[0], t=t[0], extra={})
    Rz = axis_rotation((0.0, 0.0, 1.0), -direction * float(angle_deg))
    c = np.array([centre_xy[0], centre_xy[1], 0.0])
    lit = range(len(lights)) if lit is None else lit
    lamps = [PointLight(Rz @ (np.asarray(lights[k].position, dtype=np.float64) - c) + c,
                        np.asarray(lights[k].intensity, dtype=np.float64)) for k in lit]
    return cam, Lights(lamps)


def write_input(workspace, name: str, image, camera, lights, shot: dict | None = None) -> tuple[Path, Path]:
    """Write a further photograph ``inputs/<name>.exr`` and its sidecar ``inputs/<name>.json``
    (image first: a sidecar names a photograph that is there)."""
    from reflab.core.images import write_image
    from reflab.core.workspace import write_json

    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    ws.inputs.mkdir(parents=True, exist_ok=True)
    img = write_image(ws.inputs / f"{name}.exr", image)
    obj = {"camera": camera.to_json(), "lights": lights.to_json()}
    if shot is not None:
        obj["shot"] = shot
    side = write_json(ws.input_sidecar(name), obj)
    return Path(img), Path(side)


def taken_shots(photos) -> list:
    """The rig shots (turntable angle, lamps lit) the photographs already are: the reference is
    angle 0 with every lamp; a further photograph says so in its sidecar's ``shot`` (written by
    ``reflab capture inputs``), else it is not matched to a rig shot."""
    from types import SimpleNamespace

    out = [SimpleNamespace(angle=0.0, lamps=tuple(range(len(photos[0].lights))))] if photos else []
    for p in photos[1:]:
        shot = getattr(p, "shot", None)
        if isinstance(shot, dict) and "angle_deg" in shot and "lamps" in shot:
            out.append(SimpleNamespace(angle=float(shot["angle_deg"]), lamps=tuple(int(k) for k in shot["lamps"])))
    return out


def inputs_from_capture(workspace, *, centre=None, direction: float | None = None, log=None) -> list:
    """Write ``inputs/`` from a finished ``captures/inputs`` session: each shot's photograph with
    its sidecar, the camera and lamps turned from camera.json and lights.json about the turntable
    axis (``centre``/``direction``, by default the axis reconstruct found) by the shot's angle
    from the reference input's, and only its lit lamps. A photograph larger (or smaller) than
    camera.json's size, with its aspect ratio, gets camera.json's camera at its size
    (:meth:`reflab.calibration.camera.Camera.scaled`: the camera's full resolution where it was
    calibrated binned or at a lower one). Returns the names written."""
    from reflab.calibration.camera import Camera
    from reflab.calibration.lights import Lights
    from reflab.core.images import read_image

    ws = workspace if isinstance(workspace, Workspace) else Workspace(workspace)
    manifest = read_json(ws.require(ws.manifest("inputs"), "reflab capture inputs"))
    if manifest.get("status") != "complete":
        raise WorkspaceError(ws.manifest("inputs"), "status", "'complete' (finish it with --resume)",
                             got=manifest.get("status"))
    if centre is None or direction is None:
        from reflab.reconstruction.stages import turntable_axis

        found, d = turntable_axis(ws)
        centre = found if centre is None else centre
        direction = d if direction is None else direction
    start = 0.0
    if ws.manifest("input").exists():
        shots = read_json(ws.manifest("input")).get("shots") or []
        start = float(next((s["angle"] for s in shots if s.get("role") == "input"), 0.0))
    camera = Camera.load(ws.require(ws.camera, "reflab calibrate camera"))
    lights = Lights.load(ws.require(ws.lights, "reflab calibrate lights"))
    names = []
    for shot in manifest.get("shots", []):
        lit = [k for k, on in enumerate(shot["lamps"]) if on]
        angle = float(shot["angle"]) - start
        cam, li = turned_view(camera, lights, angle, centre, direction=direction, lit=lit)
        path = ws.captures_of("inputs") / shot["file"]
        image = read_image(path)
        height, width = image.shape[:2]
        if (width, height) != (cam.width, cam.height):
            if width * cam.height != height * cam.width:
                raise WorkspaceError(path, "size", f"camera.json's aspect ratio ({cam.width}x{cam.height} or a "
                                                   "multiple)", got=f"{width}x{height}")
            cam = cam.scaled(width, height)
        name = Path(shot["file"]).stem
        write_input(ws, name, image, cam, li, {"angle_deg": angle, "lamps": lit})
        names.append(name)
        if log is not None:
            log(f"inputs/{name}: turntable {angle:g} deg from the input's view, lamps {lit}")
    return names
