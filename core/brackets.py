"""Exposure brackets: several exposures of one view merged into one linear photograph.

Linear frames (camera RAW, EXR, 16-bit PNG/TIFF) are merged linearly (:func:`merge_linear`):
each frame divided by its exposure time, weighted by a hat that is zero in the noise floor and
at the clipping level, times the exposure time (a longer exposure collects more light, so its
ratio is the less noisy one). 8-bit frames (JPEG, 8-bit PNG/TIFF) go through the camera response
curve recovered from the frames themselves (:func:`merge_8bit`: OpenCV's Debevec or Robertson).
The exposure times come from the caller or from the files' EXIF (:func:`exif_exposure`).
docs/formats.md, "Exposure brackets".
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.core.options import float_list, nonneg_float, opt, positive_float
from reflab.core.task import Task, ensure
from reflab.core.workspace import RAW_SUFFIXES, OptionError, WorkspaceError

#: Ways to recover an 8-bit camera's response curve (OpenCV's photo module).
RESPONSES = ("debevec", "robertson")


@dataclass
class MergeOptions:
    """Options of :func:`merge` (``reflab merge``'s flags)."""

    output: Path
    inputs: list
    exposures: list | None = opt(None, "each file's exposure time, in the order of the files (default: the files' "
                                       "EXIF)", unit="s", type=float_list, metavar="T1,T2,...")
    white: float = opt(1.0, "linear frames: the value at which they clip (1 for camera RAW and 16-bit files)",
                       type=positive_float)
    noise_floor: float = opt(0.005, "linear frames: a value below this share of the white level is noise and "
                                    "counts for nothing", type=nonneg_float)
    clip: float = opt(0.97, "linear frames: a pixel whose brightest band is above this share of the white level is "
                            "clipped and counts for nothing", type=positive_float)
    reference_exposure: float = opt(1.0, "the merged image reads what an unclipped frame of this exposure would "
                                         "read", unit="s", type=positive_float)
    response: str = opt("debevec", "8-bit frames: how the camera response curve is recovered (OpenCV)",
                        choices=list(RESPONSES))


@dataclass
class MergeResult:
    """What :func:`merge` wrote and how: ``kind`` is "linear" or "8-bit", ``times_from`` says where
    the exposure times came from ("option" or "EXIF"), ``unseen`` the share of pixels that no frame
    saw between the noise floor and clipping (the nearest frame's ratio stands there), ``clipped``
    the share clipped in every frame, ``response`` the recovered curve (256 x 3, 8-bit only)."""

    path: Path
    image: np.ndarray
    kind: str
    exposures: list
    times_from: str
    unseen: float
    clipped: float
    response: np.ndarray | None = field(default=None, repr=False)


def hat_weights(frame: np.ndarray, *, white: float = 1.0, noise_floor: float = 0.005,
                clip: float = 0.97) -> np.ndarray:
    """The hat weight of each value of a linear frame (H, W, 3), in [0, 1].

    It rises from 0 at the noise floor (per band) to 1 halfway to the clipping level and falls to
    0 at the clipping level, judged on the pixel's brightest band: a demosaiced or colour-matrixed
    pixel with one clipped band has the others wrong too.
    """
    x = np.asarray(frame, dtype=np.float64) / white
    lo, hi = noise_floor, clip
    mid = 0.5 * (lo + hi)
    rise = np.clip((x - lo) / max(mid - lo, 1e-12), 0.0, 1.0)
    fall = np.clip((hi - x.max(axis=2, keepdims=True)) / max(hi - mid, 1e-12), 0.0, 1.0)
    return np.minimum(rise, fall)


def merge_linear(frames, exposures, *, white: float = 1.0, noise_floor: float = 0.005,
                 clip: float = 0.97) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge linear frames of one view into radiance per second of exposure (float64, H x W x 3).

    Each frame's value over its exposure time, weighted by :func:`hat_weights` times the exposure
    time. Where no frame has weight, the longest frame below clipping stands (dark pixels), else
    the shortest (a highlight clipped in every frame: a lower bound). Returns the image, the mask
    of those unseen values and the mask of pixels clipped in every frame (H, W).
    """
    t = np.asarray(exposures, dtype=np.float64)
    order = np.argsort(t)
    num = den = 0.0
    for f, ti in zip(frames, t):
        w = hat_weights(f, white=white, noise_floor=noise_floor, clip=clip) * ti
        num = num + w * (np.asarray(f, dtype=np.float64) / ti)
        den = den + w
    unseen = den <= 0
    # Where no frame counts: the longest unclipped frame, else the shortest (clipped everywhere).
    fallback = np.asarray(frames[order[0]], dtype=np.float64) / t[order[0]]
    clipped = np.ones(fallback.shape[:2], dtype=bool)
    for i in order:  # shortest to longest: a longer unclipped frame overwrites
        f = np.asarray(frames[i], dtype=np.float64)
        ok = f.max(axis=2) / white < clip
        fallback[ok] = f[ok] / t[i]
        clipped &= ~ok
    image = np.where(unseen, fallback, num / np.where(unseen, 1.0, den))
    return image, unseen, clipped


def merge_8bit(frames, exposures, response: str = "debevec") -> tuple[np.ndarray, np.ndarray]:
    """Merge 8-bit RGB frames (uint8, H x W x 3) through the camera response curve OpenCV recovers
    from them (Debevec & Malik 1997 or Robertson et al. 2003); radiance up to the curve's scale per
    band, float64. Returns the image and the curve (256 x 3: the radiance-times-time of each code)."""
    import cv2

    times = np.asarray(exposures, dtype=np.float32)
    bgr = [np.ascontiguousarray(f[:, :, ::-1]) for f in frames]
    if response == "debevec":
        curve = cv2.createCalibrateDebevec().process(bgr, times)
        hdr = cv2.createMergeDebevec().process(bgr, times, curve)
    else:
        curve = cv2.createCalibrateRobertson().process(bgr, times)
        hdr = cv2.createMergeRobertson().process(bgr, times, curve)
    image = np.asarray(hdr, dtype=np.float64)[:, :, ::-1]
    return np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0), np.asarray(curve).reshape(256, 3)[:, ::-1]


def exif_exposure(path) -> float | None:
    """The exposure time a file's metadata records, in seconds (None when it records none).

    Camera RAW through LibRaw (rawpy's ``other.shutter_speed``); JPEG, PNG and TIFF through Pillow
    (EXIF tag ExposureTime, 33434, in the first IFD or the Exif IFD).
    """
    path = Path(path)
    t = None
    if path.suffix.lower() in RAW_SUFFIXES:
        import rawpy

        try:
            with rawpy.imread(str(path)) as raw:
                t = float(raw.other.shutter_speed)
        except (rawpy.LibRawError, OSError, ValueError, AttributeError):
            return None
    elif path.suffix.lower() != ".exr":
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(path) as im:
                exif = im.getexif()
                t = exif.get(33434) or exif.get_ifd(0x8769).get(33434)
        except (OSError, UnidentifiedImageError, ValueError):
            return None
        try:
            t = float(t) if t is not None else None
        except (TypeError, ValueError, ZeroDivisionError):
            return None
    return t if t is not None and np.isfinite(t) and t > 0 else None


def read_frame(path) -> tuple[np.ndarray, str]:
    """One bracket frame: (float32 linear RGB, "linear") or (uint8 RGB, "8-bit")."""
    from reflab.core.images import _cut_off, read_image

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".jpg", ".jpeg", ".png", ".tif", ".tiff") and path.is_file():
        import cv2

        if _cut_off(path):
            raise WorkspaceError(path, expected="a complete image", got=_cut_off(path))
        data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if data is None:
            raise WorkspaceError(path, expected="a readable image", got="a file that cannot be decoded")
        if data.dtype == np.uint8:
            if data.ndim == 2:
                data = np.repeat(data[:, :, None], 3, axis=2)
            return np.ascontiguousarray(data[:, :, 2::-1]), "8-bit"
    return read_image(path), "linear"


def merge(options: MergeOptions, task: Task | None = None) -> MergeResult:
    """Read the bracket's files, merge them (linear or through the response curve) and write
    ``options.output`` atomically (EXR float32; 16-bit PNG/TIFF clip at 1)."""
    from reflab.core.images import write_image
    from reflab.core.workspace import check_folder

    task = ensure(task)
    o = options
    paths = [Path(p) for p in o.inputs]
    if len(paths) < 2:
        raise WorkspaceError(paths[0] if paths else "inputs", expected="two or more exposures of one view (a bracket)",
                             got="a single frame" if paths else "no file")
    if not 0 <= o.noise_floor < o.clip <= 1:
        raise OptionError("clip", f"must lie above the noise floor ({o.noise_floor:g}) and at most 1, got {o.clip:g}")
    out = Path(o.output)
    if out.suffix.lower() not in (".exr", ".png", ".tif", ".tiff"):
        raise WorkspaceError(out, expected="an image name ending in .exr (or .png/.tif, which clip at 1)",
                             got=out.suffix or "no suffix")
    check_folder(out.parent, write=True, create=True, what="folder for the merged image")
    if o.exposures is not None and len(o.exposures) != len(paths):
        raise OptionError("exposures", f"gives {len(o.exposures)} times for {len(paths)} files")
    if o.exposures is not None:
        bad = [t for t in o.exposures if not (np.isfinite(t) and t > 0)]
        if bad:
            raise OptionError("exposures", f"must be positive seconds, got {bad[0]:g}")
        times, times_from = [float(t) for t in o.exposures], "option"
    else:
        times, times_from = [], "EXIF"
        for p in paths:
            t = exif_exposure(p) if p.is_file() else None
            if t is None and p.is_file():
                raise WorkspaceError(p, expected="an exposure time in its EXIF (else give them all with --exposures)",
                                     got="none")
            times.append(t)
    frames, kinds = [], []
    for k, p in enumerate(paths):
        frame, kind = read_frame(p)
        if frames and frame.shape != frames[0].shape:
            raise WorkspaceError(p, expected=f"the size of {paths[0].name}, {frames[0].shape[1]}x{frames[0].shape[0]}",
                                 got=f"{frame.shape[1]}x{frame.shape[0]}")
        if kinds and kind != kinds[0]:
            raise WorkspaceError(p, expected=f"a {kinds[0]} frame like {paths[0].name} (one bracket, one kind)",
                                 got=kind)
        frames.append(frame)
        kinds.append(kind)
        task.step(k + 1, len(paths) + 1, f"read {p.name}")
    if len(set(times)) < 2:
        raise WorkspaceError(paths[1], expected="exposure times that differ (a bracket)", got=f"{times[0]:g} s each")
    curve = None
    if kinds[0] == "linear":
        image, unseen, clipped = merge_linear(frames, times, white=o.white, noise_floor=o.noise_floor, clip=o.clip)
        unseen = float(np.mean(unseen))
    else:
        image, curve = merge_8bit(frames, times, o.response)
        stack = np.stack([f.max(axis=2) for f in frames])
        clipped = np.all(stack >= 255, axis=0)
        unseen = float(np.mean(clipped | np.all(stack <= 0, axis=0)))
    image = image * o.reference_exposure
    task.check()
    write_image(out, image)
    task.step(len(paths) + 1, len(paths) + 1, f"wrote {out}")
    return MergeResult(out, image, kinds[0], times, times_from, unseen, float(np.mean(clipped)), curve)
