"""One picture of each kind of capture of a `reflab demo` workspace, for docs/simulated-lab.md.

    .venv/bin/python docs/figures/simulated_lab_captures.py WORKSPACE [OUTDIR (default docs/img)]

Writes capture-target-flat.png, capture-target-wedge.png, capture-rod.png,
capture-sweep-marks.png (a sweep shot with the corners the simulated user marked in it, red,
and the pixels where the surfaces were named, green) and capture-input.png.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from reflab.core.images import read_image, write_preview  # noqa: E402
from reflab.core.workspace import read_json  # noqa: E402


def _dot(img: np.ndarray, uv, colour, r: int = 2) -> None:
    u, v = int(round(uv[0])), int(round(uv[1]))
    img[max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1] = colour


def main(ws: Path, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    cal = read_json(ws / "captures" / "calibration" / "manifest.json")["shots"]
    flat = next(s for s in cal if s["role"] == "target flat")
    wedge = next(s for s in cal if s["role"] == "target on wedge" and s["angle"] == 90.0)
    rod = next(s for s in read_json(ws / "captures" / "lights" / "manifest.json")["shots"] if s["role"] == "lamp 1")
    sweep_name = "captures/turntable/0004.exr"
    for name, path in (("target-flat", ws / "captures" / "calibration" / flat["file"]),
                       ("target-wedge", ws / "captures" / "calibration" / wedge["file"]),
                       ("rod", ws / "captures" / "lights" / rod["file"]), ("input", ws / "input.exr")):
        write_preview(out / f"capture-{name}.png", read_image(path))
    img = read_image(ws / sweep_name).astype(np.float64)
    img = img / np.percentile(img, 99.9)
    for item in read_json(ws / "marks.json")["surfaces"]:
        for corner in item.get("corners", []):
            if sweep_name in corner["marks"]:
                _dot(img, corner["marks"][sweep_name], [4.0, 0.0, 0.0])
    input_view = read_image(ws / "input.exr").astype(np.float64)
    input_view = input_view / np.percentile(input_view, 99.9)
    for item in read_json(ws / "marks.json")["surfaces"]:
        if "at" in item:
            _dot(input_view, item["at"], [0.0, 4.0, 0.0], 3)
    write_preview(out / "capture-sweep-marks.png", img, exposure=1.0)
    write_preview(out / "capture-input.png", input_view, exposure=1.0)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]) if len(sys.argv) > 2 else Path(__file__).resolve().parents[1] / "img")
