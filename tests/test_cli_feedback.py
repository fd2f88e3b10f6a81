"""What the command line says (issue 31): a render replacing an earlier one says so, a port or lamp
wiring the board cannot use is bad input (exit 2), and a --grid given swapped is refused in one line
before camera.json is written."""
from __future__ import annotations

import json

import pytest

from reflab.app.cli import main
from reflab.hardware.sim.lab import build_lab, write_lab

from test_calibration_camera import rendered  # noqa: F401 - six rendered 11x8 target views


def test_render_without_output_says_it_replaced_the_earlier_render(tmp_path, capsys):
    write_lab(tmp_path, build_lab(40, 30), materials=False)
    assert main(["render", str(tmp_path), "--depth", "1"]) == 0
    first = capsys.readouterr()
    assert "replaced" not in first.err + first.out and (tmp_path / "render.exr").is_file()
    assert main(["render", str(tmp_path), "--depth", "1"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len([l for l in err if "replaced the earlier" in l]) == 1 and str(tmp_path / "render.exr") in err[-1]
    assert main(["render", str(tmp_path), "--depth", "1", "-o", str(tmp_path / "other.exr")]) == 0
    assert main(["render", str(tmp_path), "--depth", "1", "-o", str(tmp_path / "other.exr")]) == 0
    assert "replaced" not in capsys.readouterr().err  # a file named by -o is the user's choice


def test_hardware_input_errors_exit_2_like_every_other_input_error(tmp_path, capsys):
    assert main(["hardware", "--port", str(tmp_path / "no-such-port"), "status"]) == 2
    assert "cannot open" in capsys.readouterr().err
    config = tmp_path / "hardware.json"
    config.write_text(json.dumps({"lamps": ["flood", "mist"]}))  # M9 switches both off: refused at connect
    assert main(["hardware", "--port", "sim", "--config", str(config), "status"]) == 2
    assert "cannot both be used" in capsys.readouterr().err


def test_a_swapped_grid_is_refused_in_one_line_before_camera_json(rendered, tmp_path, capsys):  # noqa: F811
    ws, _, _ = rendered
    imgs = sorted(str(p) for p in (ws / "captures" / "calibration").glob("0*.exr"))
    out = tmp_path / "ws"
    assert main(["calibrate", "camera", str(out), *imgs, "--grid", "8x11", "--spacing", "0.015"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("reflab calibrate camera: error: --grid: 8x11") and "11x8" in err[0], err
    assert not (out / "camera.json").exists()
    assert main(["calibrate", "camera", str(out), *imgs, "--grid", "11x8", "--spacing", "0.015"]) == 0
    assert (out / "camera.json").is_file()
