"""Camera RAW photographs read as linear values (rawpy / LibRaw), from synthetic DNG files.

A DNG here is written by tifffile from a known linear image: the camera's RGB is the image times
an as-shot neutral (camera primaries = sRGB's, so the DNG's ColorMatrix1 is XYZ -> linear sRGB),
mosaicked on an RGGB pattern, over a black level of 512 and a white level of 16383 (14 bits).
"""
from __future__ import annotations

import shutil

import numpy as np
import pytest

pytest.importorskip("rawpy")
tifffile = pytest.importorskip("tifffile")

XYZ_TO_SRGB = np.array([[3.2404542, -1.5371385, -0.4985314], [-0.9692660, 1.8760108, 0.0415560],
                        [0.0556434, -0.2040259, 1.0572252]])
NEUTRAL = np.array([0.5, 1.0, 0.7])  # the sensor's response to white: red half as sensitive as green


def write_dng(path, linear: np.ndarray, black: int = 512, white: int = 16383, exposure: float | None = None):
    """A minimal uncompressed CFA DNG (1.4) of the linear sRGB image ``linear`` (H, W, 3), H and W even;
    ``exposure``: the EXIF ExposureTime (s) it records."""
    h, w, _ = linear.shape
    cfa = np.zeros((h, w), int)
    cfa[0::2, 1::2] = cfa[1::2, 0::2] = 1
    cfa[1::2, 1::2] = 2
    mosaic = np.take_along_axis(np.clip(linear * NEUTRAL, 0, 1), cfa[..., None], 2)[..., 0]
    raw = np.round(black + mosaic * (white - black)).astype(np.uint16)

    def rational(values):
        return [v for x in np.ravel(values) for v in (int(round(x * 10000)), 10000)]

    tags = [(254, "I", 1, 0, True),  # NewSubFileType: the main image
            (33421, "H", 2, (2, 2), True), (33422, "B", 4, (0, 1, 1, 2), True),  # CFA 2x2, RGGB
            (50706, "B", 4, (1, 4, 0, 0), True), (50707, "B", 4, (1, 1, 0, 0), True),  # DNG versions
            (50708, "s", 0, "reflab synthetic", True), (271, "s", 0, "reflab", True), (272, "s", 0, "synthetic", True),
            (50714, "H", 1, black, True), (50717, "H", 1, white, True),
            (50721, "2i", 9, rational(XYZ_TO_SRGB), True), (50778, "H", 1, 21, True),  # ColorMatrix1 under D65
            (50728, "2I", 3, rational(NEUTRAL), True)]  # AsShotNeutral
    if exposure is not None:
        tags.append((33434, "2I", 1, (int(round(exposure * 1e6)), 1000000), True))  # ExposureTime
    tifffile.imwrite(path, raw, photometric=32803, extratags=tags)
    return path


def test_dng_reads_back_linear_within_1_percent(tmp_path):
    from reflab.core.images import read_image

    yy, xx = np.mgrid[0:64, 0:96] / np.array([64.0, 96.0])[:, None, None]
    linear = np.stack([0.05 + 0.6 * xx, 0.2 + 0.5 * yy, 0.3 + 0.3 * xx * yy], axis=-1)
    img = read_image(write_dng(tmp_path / "shot.dng", linear))
    assert img.dtype == np.float32 and img.shape == linear.shape
    # Black level removed, white balance applied, no gamma: the known values within 1 %
    # (measured 0.07 % away from the border the demosaic cannot fill from both sides).
    rel = np.abs(img[4:-4, 4:-4] / linear[4:-4, 4:-4] - 1)
    assert rel.max() < 0.01
    # With a gamma curve left in, the mid-greys would be off by over 20 %.
    assert np.abs(read_image(tmp_path / "shot.dng", linear=False) - np.clip(img, 0, 1)).max() == 0


def test_damaged_raw_is_named(tmp_path):
    from reflab.core.images import read_image
    from reflab.core.workspace import WorkspaceError

    (tmp_path / "bad.nef").write_bytes(b"not a raw file at all" * 10)
    with pytest.raises(WorkspaceError, match="bad.nef"):
        read_image(tmp_path / "bad.nef")


def test_raw_input_fits_and_textures_as_its_exr(tmp_path):
    """input.dng goes through fit and texture as the same data written as input.exr does."""
    from conftest import lab_photo_workspace

    from reflab.core.images import read_image, write_image
    from reflab.core.workspace import Workspace
    from reflab.inverse.stages import FitOptions, TextureOptions, fit, texture

    raw_ws, exr_ws = Workspace(tmp_path / "raw"), Workspace(tmp_path / "exr")
    _, image = lab_photo_workspace(raw_ws.root, known_only=True)
    ws_image = raw_ws.input_file(".exr")
    write_dng(raw_ws.input_file(".dng"), np.asarray(image, float) / max(float(image.max()), 1e-9) * 0.9)
    ws_image.unlink()
    assert raw_ws.input_image == raw_ws.input_file(".dng")
    shutil.copytree(raw_ws.root, exr_ws.root)
    (exr_ws.input_file(".dng")).unlink()
    developed = read_image(raw_ws.input_file(".dng"))
    write_image(exr_ws.input_file(".exr"), developed)
    fits = [fit(FitOptions(ws.root, max_iterations=20, texture_rounds=1)).report for ws in (raw_ws, exr_ws)]
    assert fits[0]["image"]["file"].endswith("input.dng") and fits[1]["image"]["file"].endswith("input.exr")
    for x, y in zip(fits[0]["surfaces"], fits[1]["surfaces"]):
        assert x["name"] == y["name"] and x["material"] == y["material"]
    a = texture(TextureOptions(raw_ws.root)).result
    b = texture(TextureOptions(exr_ws.root)).result
    assert sorted(a.kd) == sorted(b.kd) and len(a.kd) == 3
    for s in a.kd:
        assert np.array_equal(a.mask[s], b.mask[s]) and np.abs(a.kd[s] - b.kd[s]).max() < 1e-6
