"""`reflab reconstruct` keeps COLMAP's own log in WORKSPACE/logs/colmap.log (issue 18).

The terminal gets one progress line per COLMAP step; COLMAP's hundreds of glog lines (written to
file descriptor 2 by its threads, past Python's sys.stderr) go to the file. The shots here are
8-bit PNGs, as a camera writes them: the geometric stages read them; one is cut off and skipped
with a warning. They are noise, so structure from motion registers too few of them: the run ends
with one line and no sfm.json.
"""
import json

import cv2
import numpy as np

from reflab.app.cli import main
from reflab.calibration.camera import Camera


def test_colmap_log_goes_to_the_workspace(tmp_path, capfd):
    ws = tmp_path / "ws"
    Camera.look_at(160, 120, 60.0, (0.0, -0.4, 0.3), (0.0, 0.0, 0.0)).save(ws / "camera.json")
    folder = ws / "captures" / "turntable"
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    shots = []
    for i in range(5):
        cv2.imwrite(str(folder / f"{i:04d}.png"), (rng.random((120, 160, 3)) * 255).astype(np.uint8))
        shots.append({"file": f"{i:04d}.png", "angle": 72.0 * i, "role": "sweep"})
    data = (folder / "0002.png").read_bytes()
    (folder / "0002.png").write_bytes(data[: len(data) // 2])
    (folder / "manifest.json").write_text(json.dumps({"kind": "sweep", "shots": shots}))
    assert main(["reconstruct", str(ws), "--turntable-centre", "0,0"]) == 2
    out, err = capfd.readouterr()
    assert "warning: skipping" in out and "0002.png" in out
    assert "structure from motion: SIFT features of 4 shots" in out and "logs/colmap.log" in out
    assert "incremental mapping" in out
    err = err.strip().splitlines()
    assert len(err) == 1 and "registered" in err[0], err  # the stage's message, no COLMAP line
    log = (ws / "logs" / "colmap.log").read_text()
    assert log.count("--- reflab: COLMAP run") == 3 and "Feature extraction" in log and len(log.splitlines()) > 10
    assert not (ws / "sfm.json").exists() and not (ws / "sparse.ply").exists()
