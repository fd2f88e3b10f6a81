"""The printed circle target: where its circle centres lie on the ground plane."""
from __future__ import annotations

import numpy as np


def target_points(cols: int, rows: int, spacing: float) -> np.ndarray:
    """(rows*cols, 3) centres of a symmetric circle grid, row-major, on the plane z = 0.

    Circle (column i, row j) is at ``(i * spacing, -j * spacing, 0)``, the order
    :func:`reflab.calibration.circles.detect_grid` returns (row by row, rows top to bottom).
    """
    j, i = np.mgrid[0:rows, 0:cols]
    return np.stack([i.ravel() * spacing, -j.ravel() * spacing, np.zeros(i.size)], axis=1).astype(np.float64)
