"""The simulated user: what a person marks by hand after the sweep, written as the GUI writes it.

After the turntable sweep the user marks, in two or more sweep shots, the corners of what
structure from motion cannot see (the mirror, the transparent sheet: no stable texture of their
own), and says once what they know about each surface: its name, matte, untextured, transparent
with its index, a mirror. Both go into ``WORKSPACE/marks.json``'s ``surfaces`` list
(docs/reconstruction.md, "Marks file"); `reflab reconstruct` reads it and writes scene.json.

The simulated user clicks the true corners projected into the shots with 1 px Gaussian noise
(the corners of each marked box's face toward the camera at angle 0, in the shots within 60
degrees of it), and points at each fitted surface in the input view (a pixel on it).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from reflab.hardware.sim.camera import rotate_about_z
from reflab.core.workspace import read_json, write_json

#: Marked surfaces: name -> (known thickness along the box's own y, what the user knows).
MARKED = {"mirror": (0.006, {"mirror": True}), "sheet": (0.003, {"ior": 1.46})}
#: Fitted surfaces the user names by pointing at them in the input view: name -> a point on it, what the user knows.
POINTED = {"ground": ((0.22, 0.12, 0.0), {"matte": True}), "box": ((-0.07, 0.03, 0.06), {}),
           "tile": ((0.11, -0.06, 0.008), {})}
MAX_ANGLE = 60.0


def _corner_labels() -> np.ndarray:
    return np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)


def surface_marks(lab, shots: list[tuple[str, float]], *, centre=(0.0, 0.0), noise: float = 1.0, seed: int = 0) -> list[dict]:
    """The ``surfaces`` entries of marks.json: marked corners of the mirror and sheet, pointed surfaces.

    Parameters
    ----------
    lab : reflab.hardware.sim.lab.SimLab
    shots : list of (image name relative to the workspace, turntable angle in degrees)
    """
    rng = np.random.default_rng(seed)
    labels = _corner_labels()  # lab.box_mesh's vertex order: corner k = centre + R (labels[k] * size / 2)
    out = []
    for name, (thickness, known) in MARKED.items():
        mesh = lab.scene[lab.scene.index(name)].mesh
        corners = []
        for k in np.flatnonzero(labels[:, 1] < 0):  # the face toward the camera at angle 0
            marks = {}
            for image, angle in shots:
                wrapped = (angle + 180.0) % 360.0 - 180.0
                if abs(wrapped) > MAX_ANGLE + 1e-9:
                    continue
                X = rotate_about_z(mesh.vertices[k][None], angle, centre)
                uv = lab.camera.project(X)[0] + rng.normal(0.0, noise, 2)
                if 0 <= uv[0] <= lab.camera.width - 1 and 0 <= uv[1] <= lab.camera.height - 1:
                    marks[image] = [round(float(uv[0]), 2), round(float(uv[1]), 2)]
            corners.append({"corner": labels[k].tolist(), "marks": marks})
        out.append(dict({"name": name, "shape": "box", "size": [None, thickness, None], "corners": corners}, **known))
    for name, (point, known) in POINTED.items():
        uv = lab.camera.project(np.array([point], dtype=np.float64))[0]
        out.append(dict({"name": name, "at": [round(float(uv[0]), 1), round(float(uv[1]), 1)]}, **known))
    return out


def mark_sweep(workspace, lab, manifest: dict, *, centre=(0.0, 0.0), seed: int = 0) -> Path:
    """Write the simulated user's marks for a sweep session into ``workspace/marks.json`` (kept: the rod marks)."""
    path = Path(workspace) / "marks.json"
    obj = read_json(path) if path.exists() else {}
    shots = [(f"captures/turntable/{rec['file']}", float(rec["angle"])) for rec in manifest["shots"]]
    obj["surfaces"] = surface_marks(lab, shots, centre=centre, seed=seed)
    return write_json(path, obj)
