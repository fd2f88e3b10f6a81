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

#: Files a tethered camera may write that :func:`hardware.images.read_image` reads as linear.
FOLDER_SUFFIXES = (".exr", ".png", ".tif", ".tiff")


class CameraError(RuntimeError):
    """The camera gave no usable image; the message says what to check."""


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """Invert the sRGB transfer curve (IEC 61966-2-1) for values in [0, 1]."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


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
    """

    def __init__(self, folder, *, trigger=None, timeout_s: float = 60.0, settle_s: float = 0.5):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise CameraError(f"{self.folder}: not a folder; the tethered camera's download folder must exist")
        self.trigger, self.timeout_s, self.settle_s = trigger, float(timeout_s), float(settle_s)

    def _images(self) -> dict[Path, int]:
        return {p: p.stat().st_size for p in self.folder.iterdir()
                if p.suffix.lower() in FOLDER_SUFFIXES and not p.name.startswith(".")}

    def capture(self, exposure: float | None = None) -> np.ndarray:
        from hardware.images import read_image
        from hardware.workspace import WorkspaceError

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
            time.sleep(0.05)
        raise CameraError(f"no new complete image in {self.folder} within {self.timeout_s:g} s; check the tethering software "
                          f"saves to this folder as {'/'.join(FOLDER_SUFFIXES)}")

    def describe(self) -> dict:
        return {"type": "folder", "folder": str(self.folder), "trigger": self.trigger}

    def close(self) -> None:
        pass


class SimulatedCamera:
    """The virtual lab seen at the rig's current turntable angle and lamp states.

    Parameters
    ----------
    render : callable
        ``render(angle_deg, lamps) -> (H, W, 3)`` linear radiance (see :func:`lab_renderer`).
    state : callable
        ``state() -> (angle_deg, lamps)``: the rig as it physically is (the simulated board's
        axis and outputs), so that a move or lamp command that did not happen shows in the image.
    ambient : float
        Room light added to every pixel, lamps on or off (what a lamps-off frame removes).
    reference_exposure : float
        The exposure at which a pixel holds the radiance itself; pixels scale with exposure.
    lab : dict, optional
        How the lab was built (e.g. its print grain, what stays still), recorded by :meth:`describe`.
    """

    def __init__(self, render, state, *, ambient: float = 0.0, reference_exposure: float = 1.0, lab: dict | None = None):
        self.render, self.state, self.lab = render, state, lab
        self.ambient, self.reference_exposure = float(ambient), float(reference_exposure)
        self.last_state = None

    def capture(self, exposure: float | None = None) -> np.ndarray:
        angle, lamps = self.state()
        self.last_state = (float(angle), [bool(x) for x in lamps])
        scale = (self.reference_exposure if exposure is None else float(exposure)) / self.reference_exposure
        img = (np.asarray(self.render(angle, lamps), dtype=np.float64) + self.ambient) * scale
        return img.astype(np.float32)

    def describe(self) -> dict:
        out = {"type": "simulated", "ambient": self.ambient, "reference_exposure": self.reference_exposure}
        return out if self.lab is None else dict(out, lab=self.lab)

    def close(self) -> None:
        pass


def rotate_about_z(points: np.ndarray, degrees: float, centre) -> np.ndarray:
    """Points (N, 3) turned by ``degrees`` (counter-clockwise seen from +z) about the vertical axis through ``centre``."""
    a = np.radians(degrees)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    c = np.array([centre[0], centre[1], 0.0], dtype=np.float64)
    return (np.asarray(points, dtype=np.float64) - c) @ R.T + c


def lab_renderer(lab, *, depth: int = 2, centre=(0.0, 0.0), fixed=("ground",)):
    """A ``render(angle, lamps)`` for :class:`SimulatedCamera` from a :class:`hardware.simlab.SimLab`.

    The surfaces not named in ``fixed`` stand on the turntable: their meshes and textures turn
    with it about the vertical axis through ``centre`` (x, y in metres). Lamps that are off are
    left out; with every lamp off the image is black.
    """
    from calibration.lights import Lights
    from hardware.reference import render_reference
    from reconstruction.scene import Mesh, Scene, Surface

    unknown = set(fixed) - set(lab.scene.names)
    if unknown:
        raise ValueError(f"lab_renderer: no surface named {sorted(unknown)} (surfaces: {lab.scene.names})")
    turning = [s.name not in fixed for s in lab.scene]

    def render(angle: float, lamps) -> np.ndarray:
        lamps = list(lamps)
        if len(lamps) != len(lab.lights):
            raise ValueError(f"{len(lamps)} lamp states for a lab with {len(lab.lights)} lamps")
        on = [light for light, state in zip(lab.lights, lamps) if state]
        if not on:
            return np.zeros((lab.camera.height, lab.camera.width, 3))
        surfaces = [Surface(s.name, s.mesh_path, s.material, s.textured,
                            Mesh(rotate_about_z(s.mesh.vertices, angle, centre), s.mesh.triangles) if moves else s.mesh)
                    for s, moves in zip(lab.scene, turning)]

        def albedo(index: int, points: np.ndarray) -> np.ndarray:
            # A turned surface shows at p the texture its unturned self has at R^-1 p.
            return lab.albedo(index, rotate_about_z(points, -angle, centre) if turning[index] else points)

        return render_reference(Scene(surfaces), lab.camera, Lights(on), depth, albedo)

    return render


def open_camera(spec: str, **options):
    """A camera from a ``--camera`` value: ``opencv:N`` / ``opencv:URL`` or ``folder:PATH``."""
    kind, _, arg = spec.partition(":")
    if kind == "opencv" and arg:
        return OpenCVCamera(int(arg) if arg.isdigit() else arg, **options)
    if kind == "folder" and arg:
        return FolderCamera(arg, **options)
    raise ValueError(f"--camera: expected sim, opencv:N or folder:PATH, got {spec!r}")
