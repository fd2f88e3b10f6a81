"""Cameras a capture session can drive: OpenCV VideoCapture, a tethered camera's folder, the simulated lab.

Every camera returns linear float32 (H, W, 3) RGB from :meth:`capture` and describes itself
for the manifest with :meth:`describe`. ``open_camera`` builds one from the command line's
``--camera`` value (``opencv:N``, ``opencv:URL``, ``folder:PATH``); the simulated camera needs
a renderer and the rig's state, so the caller builds it (:class:`SimulatedCamera`).
"""
from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np

from reflab.core.images import srgb_to_linear
from reflab.core.workspace import IMAGE_SUFFIXES

#: Files a tethered camera may write that :func:`reflab.core.images.read_image` reads as linear.
FOLDER_SUFFIXES = IMAGE_SUFFIXES


class CameraError(RuntimeError):
    """The camera gave no usable image; the message says what to check."""


class OpenCVCamera:
    """A camera behind ``cv2.VideoCapture`` (a webcam index, a URL or an image-sequence pattern).

    8-bit frames are sRGB-encoded by almost every driver: they are linearised with the sRGB
    curve (the manifest says so); 16-bit frames are taken as linear. Frames are BGR in OpenCV and
    RGB here.

    Parameters
    ----------
    source : int or str
    width, height : int, optional
        Requested frame size.
    discard : int
        Frames read and dropped before each capture: drivers buffer a few stale frames, taken
        before the turntable or the lamps changed.
    """

    def __init__(self, source, *, width: int | None = None, height: int | None = None, discard: int = 3):
        import cv2

        self.source, self.discard = source, int(discard)
        self.cap = cv2.VideoCapture(source)
        if not self.cap.isOpened():
            raise CameraError(f"OpenCV cannot open camera {source!r}; check the index (0, 1, …), the cable and "
                              "that no other program uses the camera")
        if width and height:
            self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
            self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        self.encoding = None

    def capture(self, exposure: float | None = None) -> np.ndarray:
        import cv2

        if exposure is not None and not self.cap.set(cv2.CAP_PROP_EXPOSURE, float(exposure)):
            raise CameraError(f"camera {self.source!r} refused exposure {exposure} (CAP_PROP_EXPOSURE; its unit is the driver's)")
        for _ in range(self.discard):
            self.cap.grab()
        ok, frame = self.cap.read()
        if not ok or frame is None:
            raise CameraError(f"camera {self.source!r} returned no frame; check the cable and the camera's power")
        if frame.ndim == 2:
            frame = np.repeat(frame[:, :, None], 3, axis=2)
        rgb = np.ascontiguousarray(frame[:, :, 2::-1])
        if rgb.dtype == np.uint8:
            self.encoding = "sRGB 8-bit, linearised"
            return srgb_to_linear(rgb / 255.0).astype(np.float32)
        if rgb.dtype == np.uint16:
            self.encoding = "linear 16-bit"
            return (rgb / 65535.0).astype(np.float32)
        self.encoding = "float"
        return rgb.astype(np.float32)

    def describe(self) -> dict:
        return {"type": "opencv", "source": self.source, "encoding": self.encoding}

    def close(self) -> None:
        self.cap.release()


class FolderCamera:
    """A tethered camera that writes each shot into a folder (its own software, or ``trigger``).

    A new file counts once its size has not changed for ``settle_s`` and it reads as a complete
    image: the camera software may still be writing it. Raw formats (CR2, NEF …) must be converted to linear 16-bit TIFF or
    EXR by the tethering software (e.g. with dcraw -4 -T).

    Parameters
    ----------
    folder : path-like
    trigger : list of str, optional
        A command run to take each shot (e.g. ``["gphoto2", "--trigger-capture"]``); without it
        the user presses the shutter.
    timeout_s : float
        Longest wait for the new file.
    settle_s : float
        How long the size must stay unchanged.

    While it waits, ``cancelled()`` (set by the capture to its task's flag) is asked every 50 ms:
    a cancel stops the wait with :class:`reflab.core.task.Cancelled`.
    """

    def __init__(self, folder, *, trigger=None, timeout_s: float = 60.0, settle_s: float = 0.5):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise CameraError(f"{self.folder}: not a folder; the tethered camera's download folder must exist")
        self.trigger, self.timeout_s, self.settle_s = trigger, float(timeout_s), float(settle_s)
        self.cancelled = lambda: False

    def _images(self) -> dict[Path, int]:
        return {p: p.stat().st_size for p in self.folder.iterdir()
                if p.suffix.lower() in FOLDER_SUFFIXES and not p.name.startswith(".")}

    def capture(self, exposure: float | None = None) -> np.ndarray:
        from reflab.core.images import read_image
        from reflab.core.workspace import WorkspaceError

        before = set(self._images())
        if self.trigger:
            done = subprocess.run(self.trigger, capture_output=True, text=True, timeout=self.timeout_s)
            if done.returncode != 0:
                raise CameraError(f"trigger {' '.join(self.trigger)!r} failed ({done.returncode}): {done.stderr.strip()[:200]}")
        deadline = time.monotonic() + self.timeout_s
        seen: dict[Path, tuple[int, float]] = {}
        while time.monotonic() < deadline:
            now = time.monotonic()
            for path, size in self._images().items():
                if path in before:
                    continue
                if path not in seen or seen[path][0] != size:
                    seen[path] = (size, now)
                elif size > 0 and now - seen[path][1] >= self.settle_s:
                    try:
                        image = read_image(path)
                    except WorkspaceError:
                        seen[path] = (size, now)  # truncated: the writer paused longer than settle_s
                        continue
                    self.last_file = path
                    return image
            if self.cancelled():
                from reflab.core.task import Cancelled

                raise Cancelled("cancelled while waiting for the camera's shot")
            time.sleep(0.05)
        raise CameraError(f"no new complete image in {self.folder} within {self.timeout_s:g} s; check the tethering software "
                          f"saves to this folder as {'/'.join(FOLDER_SUFFIXES)}")

    def describe(self) -> dict:
        return {"type": "folder", "folder": str(self.folder), "trigger": self.trigger}

    def close(self) -> None:
        pass


def open_camera(spec: str, **options):
    """A camera from a ``--camera`` value: ``opencv:N`` / ``opencv:URL`` or ``folder:PATH``."""
    kind, _, arg = spec.partition(":")
    if kind == "opencv" and arg:
        return OpenCVCamera(int(arg) if arg.isdigit() else arg, **options)
    if kind == "folder" and arg:
        return FolderCamera(arg, **options)
    raise ValueError(f"--camera: expected sim, opencv:N or folder:PATH, got {spec!r}")
