"""Point lights: lights.json (docs/formats.md).

``intensity`` is radiant intensity per band as in Mitsuba 3's ``point`` emitter: the irradiance
term at distance d is ``intensity / d**2`` (docs/method.md eq. 2.1).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from reflab.core.workspace import WorkspaceError, as_array, object_items, read_json, write_json


@dataclass
class PointLight:
    position: np.ndarray
    intensity: np.ndarray
    sigma_position: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        self.position = np.asarray(self.position, dtype=np.float64).reshape(3)
        self.intensity = np.broadcast_to(np.asarray(self.intensity, dtype=np.float64), (3,)).copy()


@dataclass
class Lights:
    """The scene's point lights, in lights.json order (light index k = list index)."""

    lights: list[PointLight]

    def __len__(self):
        return len(self.lights)

    def __iter__(self):
        return iter(self.lights)

    def __getitem__(self, k):
        return self.lights[k]

    @property
    def positions(self) -> np.ndarray:
        """(K, 3) light positions."""
        return np.array([l.position for l in self.lights]).reshape(-1, 3)

    @property
    def intensities(self) -> np.ndarray:
        """(K, 3) radiant intensities per band."""
        return np.array([l.intensity for l in self.lights]).reshape(-1, 3)

    def to_json(self) -> dict:
        out = []
        for l in self.lights:
            obj = dict(l.extra)
            obj.update(type="point", position=l.position, intensity=l.intensity)
            if l.sigma_position is not None:
                obj["sigma_position"] = l.sigma_position
            out.append(obj)
        return {"lights": out}

    def save(self, path) -> Path:
        return write_json(path, self.to_json())

    @classmethod
    def from_json(cls, obj: dict, path="lights.json") -> "Lights":
        lights = []
        for where, item in object_items(obj.get("lights"), path, "lights", "lights"):
            if item.get("type", "point") != "point":
                raise WorkspaceError(path, f"{where}.type", "'point'", got=item.get("type"))
            for key in ("position", "intensity"):
                if key not in item:
                    raise WorkspaceError(path, f"{where}.{key}", "this field", got="missing")
            pos = as_array(item["position"], (3,), path, f"{where}.position")
            raw = item["intensity"]
            if isinstance(raw, (int, float)) and not isinstance(raw, bool):
                raw = [raw] * 3  # a grey lamp
            inten = as_array(raw, (3,), path, f"{where}.intensity", nonneg=True)
            sigma = item.get("sigma_position")
            if sigma is not None:
                sigma = as_array(sigma, (3, 3), path, f"{where}.sigma_position")
            extra = {k: v for k, v in item.items() if k not in ("type", "position", "intensity", "sigma_position")}
            lights.append(PointLight(pos, inten, sigma, extra))
        return cls(lights)

    @classmethod
    def load(cls, path) -> "Lights":
        return cls.from_json(read_json(path), path)
