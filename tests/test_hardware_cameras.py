"""OpenCV and tethered-folder cameras: linear values from known encodings, waiting out half-written files."""
import threading
import time

import cv2
import numpy as np
import pytest

from reflab.hardware.cameras import CameraError, FolderCamera, OpenCVCamera, open_camera, srgb_to_linear
from reflab.core.images import write_image


def test_srgb_curve_against_the_standard_values():
    # IEC 61966-2-1: code 0.5 is 21.4 % linear; the linear segment below 0.04045.
    np.testing.assert_allclose(srgb_to_linear([0.0, 0.04045, 0.5, 1.0]), [0.0, 0.04045 / 12.92, 0.21404, 1.0], atol=1e-5)


def test_opencv_camera_linearises_8bit_frames_and_swaps_to_rgb(tmp_path):
    for i, bgr in enumerate([(0, 128, 255), (64, 10, 200)]):
        cv2.imwrite(str(tmp_path / f"f{i:03d}.png"), np.full((6, 8, 3), bgr, np.uint8))
    cam = open_camera(f"opencv:{tmp_path}/f%03d.png", discard=0)
    first = cam.capture()
    assert first.shape == (6, 8, 3) and first.dtype == np.float32
    np.testing.assert_allclose(first[3, 4], srgb_to_linear(np.array([255, 128, 0]) / 255.0), atol=1e-6)
    second = cam.capture()
    np.testing.assert_allclose(second[0, 0], srgb_to_linear(np.array([200, 10, 64]) / 255.0), atol=1e-6)
    assert cam.describe()["encoding"] == "sRGB 8-bit, linearised"
    with pytest.raises(CameraError, match="returned no frame"):
        cam.capture()
    cam.close()
    with pytest.raises(CameraError, match="cannot open camera"):
        OpenCVCamera(str(tmp_path / "none%03d.png"))


def test_folder_camera_waits_until_the_file_is_complete(tmp_path):
    img = np.random.default_rng(1).random((5, 7, 3)).astype(np.float32)
    write_image(tmp_path / "old.exr", img * 0)  # already there: not a new shot
    src = tmp_path / "staging.exr"
    write_image(src, img)
    data = src.read_bytes()
    src.unlink()

    def tether():  # writes the file in two halves, as a slow download does
        time.sleep(0.2)
        with open(tmp_path / "IMG_0001.exr", "wb") as f:
            f.write(data[: len(data) // 2])
            f.flush()
            time.sleep(0.4)
            f.write(data[len(data) // 2:])

    writer = threading.Thread(target=tether)
    writer.start()
    cam = FolderCamera(tmp_path, timeout_s=5.0, settle_s=0.3)
    got = cam.capture()
    writer.join()
    np.testing.assert_array_equal(got, img)
    assert cam.last_file.name == "IMG_0001.exr"


def test_folder_camera_timeout_and_bad_specs(tmp_path):
    with pytest.raises(CameraError, match="no new complete image in .* within 0.3 s"):
        FolderCamera(tmp_path, timeout_s=0.3).capture()
    with pytest.raises(CameraError, match="trigger .* failed"):
        FolderCamera(tmp_path, trigger=["false"], timeout_s=1.0).capture()
    with pytest.raises(CameraError, match="not a folder"):
        FolderCamera(tmp_path / "missing")
    with pytest.raises(ValueError, match="expected sim, opencv:N or folder:PATH"):
        open_camera("webcam")
