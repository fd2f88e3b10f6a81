"""Linear image I/O: float32 OpenEXR by default, 16-bit PNG/TIFF read as value / 65535.

Arrays are float32, shape (H, W, 3), RGB order, linear radiance (OpenCV's BGR is hidden here).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from hardware.workspace import WorkspaceError, atomic_path

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # must precede the first cv2 import


def _cv2():
    import cv2

    return cv2


def read_image(path) -> np.ndarray:
    """Read a linear RGB image as float32 (H, W, 3).

    EXR is taken as is; 16-bit PNG/TIFF are divided by 65535; 8-bit images are refused because
    they are not linear captures. NaN or inf in the file is an error naming the file.
    """
    path = Path(path)
    if not path.exists():
        raise WorkspaceError(path, expected="an image file", got="missing")
    cv2 = _cv2()
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise WorkspaceError(path, expected="a readable EXR, 16-bit PNG or TIFF image")
    if img.dtype == np.uint16:
        img = img.astype(np.float32) / 65535.0
    elif img.dtype == np.uint8:
        raise WorkspaceError(path, expected="a linear image (float EXR or 16-bit PNG/TIFF)", got="8-bit")
    img = img.astype(np.float32, copy=False)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = img[:, :, :3]
    img = np.ascontiguousarray(img[:, :, ::-1])
    if not np.all(np.isfinite(img)):
        raise WorkspaceError(path, expected="finite pixel values", got=f"{int((~np.isfinite(img)).sum())} NaN/inf")
    return img


def write_image(path, img: np.ndarray, *, allow_nan: bool = False) -> Path:
    """Write a float (H, W, 3) or (H, W) image atomically (EXR float32, PNG/TIFF 16-bit).

    ``allow_nan`` is for albedo AOVs, where NaN marks "unknown"; elsewhere NaN is refused.
    """
    path = Path(path)
    img = np.asarray(img, dtype=np.float32)
    if not allow_nan and not np.all(np.isfinite(img)):
        raise ValueError(f"{path}: refusing to write an image with NaN/inf pixels")
    if img.ndim == 3:
        img = img[:, :, ::-1]
    cv2 = _cv2()
    suffix = path.suffix.lower()
    if suffix == ".exr":
        data, params = img, [cv2.IMWRITE_EXR_TYPE, cv2.IMWRITE_EXR_TYPE_FLOAT]
    elif suffix in (".png", ".tif", ".tiff"):
        data, params = np.clip(np.nan_to_num(img) * 65535.0 + 0.5, 0, 65535).astype(np.uint16), []
    else:
        raise ValueError(f"{path}: unknown image type {suffix!r} (use .exr, .png or .tif)")
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(data), params):
            raise OSError(f"{path}: OpenCV could not write the image")
    return path


def to_display(img: np.ndarray, exposure: float | None = None) -> np.ndarray:
    """8-bit sRGB preview of a linear image (for PNG previews and the GUI)."""
    img = np.nan_to_num(np.asarray(img, dtype=np.float64))
    if exposure is None:
        exposure = 1.0 / max(np.percentile(img, 99.5), 1e-12)
    x = np.clip(img * exposure, 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (srgb * 255 + 0.5).astype(np.uint8)
