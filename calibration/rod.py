"""Rod shots from a capture session: which lamp lit each image, rod marks detected, lamp power.

`reflab capture lights` writes ``captures/lights/`` and its manifest (hardware/capture.py): at
each turntable angle a lamps-off frame of the room light ("room light") and one frame per lamp
with that lamp alone on ("lamp K"). This module reads that manifest so `reflab calibrate lights`
needs no file names and no lamp indices: each single-lamp shot's ``lamps`` says which lamp cast
its shadow; the lamps-off frame at the same angle, subtracted, leaves that lamp's light alone,
from which a reference card of known reflectance gives the lamp's radiant intensity.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reflab.calibration.camera import Camera
from reflab.calibration.lamps import Mark, detect_rod_marks, lamp_intensity
from reflab.core.workspace import Workspace, WorkspaceError, read_json


@dataclass
class RodShot:
    """One single-lamp image of the rod: its path relative to the workspace, the lamp, the room-light frame."""

    image: str
    light: int
    room: str | None = None


def rod_shots(root) -> list[RodShot]:
    """The single-lamp shots listed in ``root/captures/lights/manifest.json``, in capture order.

    Raises
    ------
    WorkspaceError
        No manifest, or a manifest with no shot that has exactly one lamp on.
    """
    root = Path(root)
    path = Workspace(root).manifest("lights")
    if not path.exists():
        raise WorkspaceError(path, expected="the manifest of `reflab capture lights` (or give rod images / --marks)",
                             got="missing")
    manifest = read_json(path)
    shots = manifest.get("shots")
    if not isinstance(shots, list):
        raise WorkspaceError(path, "shots", "a list of shots", got=shots)
    room = {}
    for rec in shots:
        if isinstance(rec, dict) and isinstance(rec.get("lamps"), list) and not any(rec["lamps"]):
            room[float(rec.get("angle", 0.0))] = f"captures/lights/{rec['file']}"
    out = []
    for i, rec in enumerate(shots):
        lamps = rec.get("lamps") if isinstance(rec, dict) else None
        if not isinstance(lamps, list) or "file" not in rec:
            raise WorkspaceError(path, f"shots[{i}]", "an object with 'file' and 'lamps'", got=rec)
        on = [k for k, state in enumerate(lamps) if state]
        if len(on) == 1:
            out.append(RodShot(f"captures/lights/{rec['file']}", on[0], room.get(float(rec.get("angle", 0.0)))))
    if not out:
        raise WorkspaceError(path, "shots", "shots with exactly one lamp on (one rod shadow each)", got="none")
    return out


def detect_marks(root, shots: list[RodShot], read_image) -> list[Mark]:
    """Rod foot and shadow tip detected in every shot (:func:`reflab.calibration.lamps.detect_rod_marks`),
    the shadow against the shot's lamps-off frame when there is one.

    Raises
    ------
    ValueError
        Naming the image where the rod or its shadow was not found.
    WorkspaceError
        Naming an image (or its lamps-off frame) that cannot be read.
    """
    marks = []
    for shot in shots:
        try:
            room = read_image(Path(root) / shot.room) if shot.room is not None else None
            base, tip = detect_rod_marks(read_image(Path(root) / shot.image), room=room)
        except WorkspaceError:  # an unreadable file: the caller may do without this shot
            raise
        except ValueError as exc:
            raise ValueError(f"{shot.image}: {exc}; mark it by hand in marks.json and rerun with --marks") from None
        marks.append(Mark(shot.image, shot.light, base, tip))
    return marks


def card_intensities(root, shots: list[RodShot], camera: Camera, positions: dict, kd, region, read_image):
    """Radiant intensity of each lamp from a reference card in its shots, room light subtracted.

    Parameters
    ----------
    positions : dict
        Lamp index -> located position (3,).
    kd : float
        The card's diffuse coefficient (reflectance / pi).
    region : (xmin, xmax, ymin, ymax)
        The card's extent on the ground, metres.

    Returns
    -------
    dict
        Lamp index -> (intensity (3,), spread (3,)): the median over that lamp's shots.
    """
    out = {}
    for k in sorted(positions):
        est = []
        for shot in shots:
            if shot.light != k:
                continue
            if shot.room is None:
                raise ValueError(f"{shot.image}: no lamps-off frame at its angle to subtract the room light; "
                                 "capture the lights session again (it takes one) or give --sheet images")
            lit = read_image(Path(root) / shot.image) - read_image(Path(root) / shot.room)
            est.append(lamp_intensity(lit, camera, positions[k], kd, region=region))
        out[k] = (np.median([e[0] for e in est], axis=0), np.max([e[1] for e in est], axis=0))
    return out
