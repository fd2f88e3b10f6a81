"""Forward-model timings on the simulated lab (docs/forward-model.md, "Benchmarks").

Usage: ``.venv/bin/python docs/figures/forward_benchmark.py [--depth D] [--repeats N] [--casters]``.
The same table as ``python -m reflab.inverse.forward.benchmarks WORKSPACE``, for the simulated lab's scene
(built here: product code does not import the simulated twin).
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from reflab.hardware.sim.lab import build_lab  # noqa: E402
from reflab.inverse.forward.benchmarks import main  # noqa: E402

if __name__ == "__main__":
    lab = build_lab()
    raise SystemExit(main(sys.argv[1:], scene=(lab.scene, lab.camera, lab.lights), name="simulated lab"))
