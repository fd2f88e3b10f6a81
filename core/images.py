"""Image I/O: float32 OpenEXR by default, 16-bit PNG/TIFF read as value / 65535.

Arrays are float32, shape (H, W, 3), RGB order (OpenCV's BGR is hidden here). OpenEXR goes
through Mitsuba's Bitmap (the OpenCV 5 wheels are built without OpenEXR), with no variant set: a
variant starts Dr.Jit's LLVM back end, 0.15 s that a command reading an image does not need.

Two kinds of reader (docs/formats.md, Images): photometric stages need linear radiance
(:func:`read_image`, then :func:`check_radiance`); geometric stages take any image a camera
writes (``read_image(path, linear=False)``: 8-bit JPEG/PNG too, sRGB-decoded). Camera RAW files
(DNG, CR2, NEF, ARW, ...) are linear captures: :func:`read_raw` develops them through LibRaw
(rawpy) with no gamma curve.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from reflab.core.workspace import IMAGE_SUFFIXES, RAW_SUFFIXES, WorkspaceError, atomic_path


def _cv2():
    import cv2

    return cv2


def _mitsuba_core():
    import mitsuba as mi  # Bitmap is in Mitsuba's core: no variant needed

    return mi


def read_exr(path, dtype=np.float32) -> np.ndarray:
    """The pixels of an OpenEXR file as they are, (H, W, channels); RuntimeError when unreadable."""
    bmp = _mitsuba_core().Bitmap(str(path))
    return np.array(bmp, dtype=dtype, copy=True).reshape(bmp.height(), bmp.width(), -1)


def _write_exr(path: Path, img: np.ndarray) -> None:
    mi = _mitsuba_core()
    fmt = mi.Bitmap.PixelFormat.RGB if img.ndim == 3 else mi.Bitmap.PixelFormat.Y
    mi.Bitmap(np.ascontiguousarray(img, dtype=np.float32), fmt).write(str(path))


#: Files the geometric stages read (any image a camera writes).
CAMERA_SUFFIXES = IMAGE_SUFFIXES + (".jpg", ".jpeg")


def image_files(folder) -> list[Path]:
    """The images a camera may have written into ``folder``, in name order (hidden files left out)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in CAMERA_SUFFIXES and not p.name.startswith("."))


def _cut_off(path: Path) -> str:
    """What a cut-off JPEG or PNG lacks ("" for a complete file or another type).

    OpenCV decodes a cut-off JPEG anyway (grey below the cut, "Premature end of JPEG file" on
    stderr) and refuses a cut-off PNG only after libpng printed "Read Error" on stderr. A JPEG's
    last scan (SOS, FFDA) must be followed by its end-of-image marker (EOI, FFD9): 0xFF inside
    entropy-coded data is stuffed, so both occur only as markers. A PNG ends with its IEND chunk.
    """
    suffix = path.suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        data = path.read_bytes()
        ok = data.startswith(b"\xff\xd8") and data.rfind(b"\xff\xd9") > max(data.rfind(b"\xff\xda"), 0)
        return "" if ok else "a cut-off JPEG (no end-of-image marker)"
    if suffix == ".png":
        data = path.read_bytes()
        return "" if data.rfind(b"IEND") > 0 else "a cut-off PNG (no IEND chunk)"
    return ""


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer curve (IEC 61966-2-1) for linear values in [0, 1] (float64)."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """Invert the sRGB transfer curve (IEC 61966-2-1) for values in [0, 1] (float64)."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def read_raw(path) -> np.ndarray:
    """A camera RAW file as linear RGB, float32 (H, W, 3), in the sensor's orientation.

    LibRaw (rawpy) subtracts the black level, scales by the white level, applies the camera's
    as-shot white balance (green's multiplier 1) and its colour matrix to linear sRGB primaries,
    demosaics (AHD) and applies no gamma curve and no automatic brightening: a value of 1 is the
    white level in the green channel. Clipped highlights stay at their plateau (clip_level finds
    it). A per-band gain (another white balance, a grey card's) is absorbed by the lamps'
    intensities, which the lamp calibration measures from the same camera's photographs.
    """
    try:
        import rawpy
    except ImportError:  # pragma: no cover - a dependency since 0.2
        raise WorkspaceError(path, expected="rawpy installed to read camera RAW files (pip install rawpy)") from None
    try:
        with rawpy.imread(str(path)) as raw:
            rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True,
                                  output_color=rawpy.ColorSpace.sRGB, user_flip=0, highlight_mode=rawpy.HighlightMode.Clip,
                                  demosaic_algorithm=rawpy.DemosaicAlgorithm.AHD)
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        raise WorkspaceError(path, expected="a camera RAW file LibRaw can read", got=type(exc).__name__) from None
    return rgb.astype(np.float32) / 65535.0


def read_image(path, *, linear: bool = True) -> np.ndarray:
    """Read an RGB image as float32 (H, W, 3).

    EXR is taken as is; 16-bit PNG/TIFF are divided by 65535; camera RAW (:data:`RAW_SUFFIXES`)
    is developed linearly by :func:`read_raw` (clipped to [0, 1] with ``linear=False``, the range
    of a decoded 8-bit file). 8-bit images (JPEG, PNG) are
    refused with ``linear=True`` (they are not linear captures) and sRGB-decoded to [0, 1] with
    ``linear=False`` (geometric stages: detection needs shapes, not radiance). NaN or inf in the
    file, a file that cannot be decoded or a cut-off JPEG is an error naming the file.
    """
    path = Path(path)
    if not path.exists():
        raise WorkspaceError(path, expected="an image file", got="missing")
    if not os.access(path, os.R_OK) or path.is_dir():
        raise WorkspaceError(path, expected="a readable image file", got="no read permission" if path.is_file()
                             else "a folder")
    if path.suffix.lower() == ".exr":
        try:
            img = read_exr(path)
        except RuntimeError:
            raise WorkspaceError(path, expected="a readable OpenEXR image", got="a damaged or cut-off file") from None
        if img.shape[2] >= 3:
            img = img[:, :, :3]
        return _checked(path, np.repeat(img, 3, axis=2) if img.shape[2] == 1 else img)
    if path.suffix.lower() in RAW_SUFFIXES:
        img = read_raw(path)
        return _checked(path, img if linear else np.clip(img, 0.0, 1.0))
    cv2 = _cv2()
    kinds = "EXR, 16-bit PNG or TIFF" if linear else "EXR, PNG, TIFF or JPEG"
    cut = _cut_off(path)
    if cut:
        raise WorkspaceError(path, expected=f"a complete {kinds} image", got=cut)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise WorkspaceError(path, expected=f"a readable {kinds} image", got="a file that cannot be decoded")
    if img.dtype == np.uint16:
        img = img.astype(np.float32) / 65535.0
    elif img.dtype == np.uint8 and linear:
        raise WorkspaceError(path, expected="a linear image (float EXR or 16-bit PNG/TIFF); 8-bit JPEG/PNG serve "
                                            "the geometric stages only", got="8-bit")
    elif img.dtype == np.uint8:
        img = srgb_to_linear(img / 255.0).astype(np.float32)
    img = img.astype(np.float32, copy=False)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = img[:, :, :3]
    return _checked(path, np.ascontiguousarray(img[:, :, ::-1]))


def _checked(path: Path, img: np.ndarray) -> np.ndarray:
    if not np.all(np.isfinite(img)):
        raise WorkspaceError(path, expected="finite pixel values", got=f"{int((~np.isfinite(img)).sum())} NaN/inf")
    return img


#: A linear photograph with more than this share of negative values is not noise around black.
MAX_NEGATIVE_SHARE = 0.5


def check_radiance(image, path="image") -> np.ndarray:
    """Refuse what cannot be a linear photograph; return the image as float64.

    Small negative values are data (noise where a dark or ambient frame was subtracted:
    docs/formats.md, Images). Refused: NaN or inf, no pixel above 0 (all zero or black), more than
    :data:`MAX_NEGATIVE_SHARE` of the values below 0.
    """
    image = np.asarray(image, dtype=np.float64)
    if not np.all(np.isfinite(image)):
        raise WorkspaceError(path, "pixels", "finite values", got=f"{int((~np.isfinite(image)).sum())} NaN/inf")
    if not np.any(image > 0):
        raise WorkspaceError(path, "pixels", "a lit image (some pixel above 0)", got="all pixels are 0 (black)"
                             if not np.any(image) else "no pixel above 0 (black)")
    share = float(np.mean(image < 0))
    if share > MAX_NEGATIVE_SHARE:
        raise WorkspaceError(path, "pixels", "linear radiance (at most noise-level negative values after a dark-"
                             "frame subtraction)", got=f"{100 * share:.0f}% of the values negative")
    return image


def write_image(path, img: np.ndarray, *, allow_nan: bool = False) -> Path:
    """Write a float (H, W, 3) or (H, W) image atomically (EXR float32, PNG/TIFF 16-bit).

    ``allow_nan`` is for albedo AOVs, where NaN marks "unknown"; elsewhere NaN is refused.
    """
    path = Path(path)
    img = np.asarray(img, dtype=np.float32)
    if not allow_nan and not np.all(np.isfinite(img)):
        raise ValueError(f"{path}: refusing to write an image with NaN/inf pixels")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        with atomic_path(path) as tmp:
            _write_exr(tmp, img)
        return path
    if suffix not in (".png", ".tif", ".tiff"):
        raise ValueError(f"{path}: unknown image type {suffix!r} (use .exr, .png or .tif)")
    data = np.clip(np.nan_to_num(img) * 65535.0 + 0.5, 0, 65535).astype(np.uint16)
    if data.ndim == 3:
        data = data[:, :, ::-1]
    with atomic_path(path) as tmp:
        if not _cv2().imwrite(str(tmp), np.ascontiguousarray(data)):
            raise OSError(f"{path}: OpenCV could not write the image")
    return path


def to_display(img: np.ndarray, exposure: float | None = None) -> np.ndarray:
    """8-bit sRGB preview of a linear image (for PNG previews and the GUI)."""
    img = np.nan_to_num(np.asarray(img, dtype=np.float64))
    if exposure is None:
        exposure = 1.0 / max(np.percentile(img, 99.5), 1e-12)
    return (linear_to_srgb(np.clip(img * exposure, 0, 1)) * 255 + 0.5).astype(np.uint8)


def write_preview(path, img: np.ndarray, exposure: float | None = None) -> Path:
    """Write an 8-bit sRGB PNG preview of a linear image, atomically (for people, not for stages)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        if not _cv2().imwrite(str(tmp), to_display(img, exposure)[:, :, ::-1]):
            raise OSError(f"{path}: OpenCV could not write the preview")
    return path


def clip_level(image: np.ndarray, plateau: int = 3) -> float | None:
    """The level at which an image clips, or None when it does not.

    A sensor or a 16-bit file clips to a plateau: at least ``plateau`` values sit exactly on the
    image's maximum. A rendered or unclipped highlight has one brightest value.
    """
    image = np.asarray(image)
    top = float(image.max()) if image.size else 0.0
    return top if top > 0 and np.count_nonzero(image == top) >= plateau else None
