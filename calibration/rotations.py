"""Rotations, once for every stage: axis-angle (Rodrigues) both ways, the nearest rotation to a
matrix, and a rotation about one axis in degrees. float64 throughout.

It lives in ``calibration`` because that is the lowest layer that needs it (Tsai's poses);
reconstruction (the turntable axis, fitted boxes) and the simulated lab import it from here.
"""
from __future__ import annotations

import numpy as np


def rodrigues(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrices of axis-angle vectors: (3,) -> (3, 3), (V, 3) -> (V, 3, 3)."""
    rvec = np.asarray(rvec, dtype=np.float64)
    r = rvec.reshape(-1, 3)
    theta = np.linalg.norm(r, axis=1)
    k = r / np.maximum(theta, 1e-300)[:, None]
    Kx = np.zeros((len(r), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], (1 - np.cos(theta))[:, None, None]
    R = np.eye(3) + s * Kx + c * Kx @ Kx
    return R[0] if rvec.ndim == 1 else R


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix (inverse of :func:`rodrigues`)."""
    import cv2

    return cv2.Rodrigues(np.asarray(R, dtype=np.float64))[0].ravel()


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to ``M`` in the Frobenius norm (SVD, determinant +1)."""
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def perpendicular_basis(axis) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (e1, e2) with (e1, e2, axis) right-handed and orthonormal, for a unit ``axis``."""
    axis = np.asarray(axis, dtype=np.float64)
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def look_rotation(direction, up) -> np.ndarray:
    """World-to-camera rotation (rows x right, y down, z forward) of a camera looking along
    ``direction`` with ``up`` pointing up in the image; ValueError when they are parallel."""
    z = np.asarray(direction, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: the up vector is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def axis_rotation(axis, degrees) -> np.ndarray:
    """Rotation by ``degrees`` (counter-clockwise looking down ``axis``): (3, 3), or (N, 3, 3) for N angles."""
    u = np.asarray(axis, dtype=np.float64)
    u = u / np.linalg.norm(u)
    a = np.radians(np.asarray(degrees, dtype=np.float64))
    return rodrigues(a[..., None] * u)
