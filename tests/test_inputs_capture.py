"""Captures into a workspace that already holds a calibration and an input (issue 18).

A capture of another size than camera.json is refused before it starts (simulated camera) or at
its first shot, before the image is written (any camera); an existing input photograph is never
replaced without --overwrite.
"""
import hashlib

import numpy as np
import pytest

from reflab.app.cli import main
from reflab.hardware.capture import CaptureError, CaptureSession, plan_input
from reflab.hardware.grbl import GrblConfig, GrblController
from reflab.core.images import read_image, write_image
from reflab.hardware.sim.camera import SimulatedCamera, lab_renderer
from reflab.hardware.sim.device import SimulatedGrbl
from reflab.hardware.sim.lab import build_lab, write_lab
from reflab.core.workspace import read_json

SIM = ["--port", "sim", "--camera", "sim", "--depth", "1"]


def snapshot(folder):
    return {p.relative_to(folder): hashlib.sha1(p.read_bytes()).hexdigest() for p in folder.rglob("*") if p.is_file()}


@pytest.fixture
def workspace(tmp_path):
    """A 64x48 workspace (camera.json from the simulated lab) with an input photograph of its own."""
    write_lab(tmp_path, build_lab(64, 48, textured=False))
    write_image(tmp_path / "input.exr", np.full((48, 64, 3), 0.25, np.float32))
    return tmp_path


@pytest.mark.parametrize("kind", ["input", "sweep", "lights"])
def test_capture_of_another_size_is_refused_before_it_starts(workspace, kind, capsys):
    before = snapshot(workspace)
    assert main(["capture", kind, str(workspace), *SIM, "--size", "80x60", "--overwrite"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "camera.json" in err[0] and "64x48" in err[0] and "80x60" in err[0]
    assert snapshot(workspace) == before


def test_input_is_never_replaced_without_overwrite(workspace, capsys):
    before = snapshot(workspace)
    assert main(["capture", "input", str(workspace), *SIM]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "input.exr" in err[0] and "--overwrite" in err[0]
    assert snapshot(workspace) == before
    # With --overwrite: replaced by a capture at camera.json's size (no --size needed).
    assert main(["capture", "input", str(workspace), *SIM, "--overwrite"]) == 0
    img = read_image(workspace / "input.exr")
    assert img.shape == (48, 64, 3) and not np.allclose(img, 0.25)
    assert read_json(workspace / "captures" / "input" / "manifest.json")["status"] == "complete"


def test_a_camera_of_another_size_stops_at_its_first_shot(workspace):
    """Any camera whose size is not a setting (here the simulated one at 80x60, its renderer's size
    fixed): the shot is not written, the manifest says why."""
    lab = build_lab(80, 60, textured=False)
    cfg = GrblConfig(timeout_s=2.0, boot_wait_s=0.4, reconnect_delay_s=0.05, reconnects=2, feed_deg_per_min=36000.0)
    render = lab_renderer(lab, depth=1)
    with SimulatedGrbl(time_scale=20.0) as board, GrblController(board.port, cfg) as ctl:
        camera = SimulatedCamera(lambda angle, lamps: render(angle, lamps),
                                 lambda: (board.turntable("X"), cfg.lamp_states(board.lamp_outputs())))
        with pytest.raises(CaptureError, match="80x60 images, camera.json is calibrated for 64x48"):
            CaptureSession(workspace, "input", plan_input(2), ctl, camera, overwrite=True).run()
    folder = workspace / "captures" / "input"
    assert sorted(p.name for p in folder.iterdir()) == ["manifest.json"]
    manifest = read_json(folder / "manifest.json")
    assert manifest["status"] == "stopped" and manifest["shots"] == [] and "64x48" in manifest["error"]
    assert read_image(workspace / "input.exr").shape == (48, 64, 3)
