"""The calibrated camera: camera.json (OpenCV conventions, docs/formats.md) and its rays.

World to camera: ``X_cam = R @ X_world + t``; camera x right, y down, z forward; pixel (0, 0) is
the centre of the top-left pixel; metres. Images are raw (distorted); rays go through pixel
centres after removing distortion.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.calibration.rotations import look_rotation
from reflab.core.workspace import WorkspaceError, as_array, as_float, read_json, write_json


@dataclass
class Camera:
    """A calibrated pinhole camera with OpenCV's 5-term distortion.

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    K : (3, 3) ndarray
        Intrinsic matrix.
    dist : (5,) ndarray
        ``k1, k2, p1, p2, k3``.
    R : (3, 3) ndarray
        World-to-camera rotation.
    t : (3,) ndarray
        World-to-camera translation.
    tsai : dict or None
        Tsai's parameters when the camera came from a Tsai calibration (kept, not used here).
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tsai: dict | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=np.float64)
        self.dist = np.zeros(5) if self.dist is None else np.asarray(self.dist, dtype=np.float64)
        self.R = np.asarray(self.R, dtype=np.float64)
        self.t = np.asarray(self.t, dtype=np.float64).reshape(3)

    # ---------------------------------------------------------------- geometry
    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return -self.R.T @ self.t

    @classmethod
    def look_at(cls, width, height, fov_x_deg, eye, target, up=(0, 0, 1), dist=None) -> "Camera":
        """A camera at ``eye`` looking at ``target`` with horizontal field of view ``fov_x_deg``."""
        eye, target = (np.asarray(v, dtype=np.float64) for v in (eye, target))
        R = look_rotation(target - eye, up)
        f = 0.5 * width / np.tan(np.radians(fov_x_deg) / 2)
        K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
        return cls(width, height, K, dist, R, -R @ eye)

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera at another resolution (same field of view, pixel-centre convention)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 1] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return Camera(width, height, K, self.dist.copy(), self.R.copy(), self.t.copy())

    def binned(self, factor: int) -> "Camera":
        """The camera of the image binned ``factor`` × ``factor`` (block means, right and bottom
        remainders cropped): binned pixel j's centre is the centre of original pixels [j·f, (j+1)·f)."""
        f = int(factor)
        if f < 1:
            raise ValueError(f"binning factor must be >= 1, got {factor!r}")
        K = self.K.copy()
        K[:2, :2] /= f
        K[:2, 2] = (K[:2, 2] + 0.5) / f - 0.5
        return Camera(self.width // f, self.height // f, K, self.dist.copy(), self.R.copy(), self.t.copy())

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Normalised image coordinates (x, y) with distortion removed, for pixels ``uv`` (N, 2)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if len(uv) == 0:  # cv2.undistortPoints answers None
            return np.zeros((0, 2))
        if not np.any(self.dist):
            Kinv = np.linalg.inv(self.K)
            if Kinv[0, 1] != 0 or Kinv[1, 0] != 0:  # skewed: the product as it always was
                return uv @ Kinv[:2, :2].T + Kinv[:2, 2]
            # Spelled out: (N, 2) @ a transposed (2, 2) view takes numpy's slow generic loop.
            # Without skew these are its floats exactly (its terms with a zero factor add 0).
            xy = np.empty_like(uv)
            xy[:, 0] = uv[:, 0] * Kinv[0, 0] + Kinv[0, 2]
            xy[:, 1] = uv[:, 1] * Kinv[1, 1] + Kinv[1, 2]
            return xy
        import cv2

        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        out = cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, self.dist, None, None, None, crit)
        return out.reshape(-1, 2)

    def pixel_rays(self, rows: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """World-space rays through every pixel centre, row-major (pixel index = v * width + u).

        Parameters
        ----------
        rows : (r0, r1), optional
            Only image rows ``r0 <= v < r1`` (a tile); the rays are those rows of the whole image's.

        Returns
        -------
        origins : (H*W, 3) ndarray
        directions : (H*W, 3) ndarray, unit length
        """
        r0, r1 = (0, self.height) if rows is None else (int(rows[0]), int(rows[1]))
        if not 0 <= r0 <= r1 <= self.height:
            raise ValueError(f"rows must lie within [0, {self.height}] with r0 <= r1, got {rows!r}")
        u = np.arange(self.width, dtype=np.float64)
        v = np.arange(r0, r1, dtype=np.float64)
        Kinv = np.linalg.inv(self.K)
        if np.any(self.dist) or Kinv[0, 1] != 0 or Kinv[1, 0] != 0:
            uu, vv = np.meshgrid(u, v)
            return self.rays(np.stack([uu.ravel(), vv.ravel()], axis=1))
        # Without distortion or skew, x depends on the column only and y on the row only: filled
        # by broadcasting, the same floats as undistort's (u·a + v·0 + c is u·a + c exactly).
        d_cam = np.empty((r1 - r0, self.width, 3))
        d_cam[:, :, 0] = u * Kinv[0, 0] + Kinv[0, 2]
        d_cam[:, :, 1] = (v * Kinv[1, 1] + Kinv[1, 2])[:, None]
        d_cam[:, :, 2] = 1.0
        return self._rays(d_cam.reshape(-1, 3))

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-space rays through pixel positions ``uv`` (N, 2), distortion removed."""
        xy = self.undistort(uv)
        d_cam = np.empty((len(xy), 3))
        d_cam[:, :2] = xy
        d_cam[:, 2] = 1.0
        return self._rays(d_cam)

    def _rays(self, d_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit world directions of camera-frame directions ``d_cam`` (N, 3)."""
        # The product and the norm as they always were (BLAS, np.linalg.norm): the same rays to
        # the last bit, so a fit or texture does not move with how the pixels were enumerated.
        d = d_cam @ self.R  # R.T @ d_cam for each row
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        origins = np.empty_like(d)
        origins[:] = self.center
        return origins, d

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel positions (N, 2) of world points (N, 3), distortion applied."""
        import cv2

        pts = np.asarray(points, dtype=np.float64).reshape(-1, 1, 3)
        rvec, _ = cv2.Rodrigues(self.R)
        uv, _ = cv2.projectPoints(pts, rvec, self.t, self.K, self.dist)
        return uv.reshape(-1, 2)

    # ---------------------------------------------------------------- file format
    def to_json(self) -> dict:
        obj = dict(self.extra)
        obj.update(width=int(self.width), height=int(self.height), K=self.K, dist=self.dist, R=self.R, t=self.t)
        if self.tsai is not None:
            obj["tsai"] = self.tsai
        return obj

    def save(self, path) -> Path:
        return write_json(path, self.to_json())

    @classmethod
    def from_json(cls, obj: dict, path="camera.json") -> "Camera":
        def need(key):
            if key not in obj:
                raise WorkspaceError(path, key, "this field", got="missing")
            return obj[key]

        width, height = need("width"), need("height")
        for key, val in (("width", width), ("height", height)):
            if isinstance(val, bool) or not isinstance(val, int) or val <= 0:
                raise WorkspaceError(path, key, "a positive integer", got=val)
        K = as_array(need("K"), (3, 3), path, "K")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise WorkspaceError(path, "K", "[[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0", got=obj["K"])
        dist = obj.get("dist")
        dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
        if dist.ndim != 1 or len(dist) not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
            raise WorkspaceError(path, "dist", "4, 5, 8, 12 or 14 finite OpenCV distortion coefficients", got=obj.get("dist"))
        R = as_array(need("R"), (3, 3), path, "R")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise WorkspaceError(path, "R", "a rotation matrix (orthonormal, det +1)", got=obj["R"])
        t = as_array(need("t"), (3,), path, "t")
        tsai = obj.get("tsai")
        if tsai is not None:
            for key in ("f", "kappa1", "sx", "Cx", "Cy", "dx", "dy"):
                as_float(tsai.get(key), path, f"tsai.{key}")
        known = {"width", "height", "K", "dist", "R", "t", "tsai"}
        extra = {k: v for k, v in obj.items() if k not in known}
        return cls(width, height, K, dist, R, t, tsai, extra)

    @classmethod
    def load(cls, path) -> "Camera":
        return cls.from_json(read_json(path), path)
