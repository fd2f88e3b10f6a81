"""`reflab report` summarises what the stages wrote, with the numbers that are in the files."""
import json

import numpy as np
import pytest

from app.cli import main
from hardware.sim.lab import build_lab, write_lab
from hardware.workspace import write_json


def test_report_summarises_workspace(tmp_path, capsys):
    lab = build_lab(80, 60)
    write_lab(tmp_path, lab)
    write_json(tmp_path / "fit.json", {"method": "ftbo", "depth": 3, "time_s": 1.5, "rms": [0.01, 0.02, 0.03],
                                       "trace": [[0.1, [0.1, 0.1, 0.1]], [1.5, [0.01, 0.02, 0.03]]],
                                       "surfaces": [{"name": lab.scene[0].name, "undetermined": ["ns"]}]})
    assert main(["report", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert [s["name"] for s in report["scene"]] == lab.scene.names
    np.testing.assert_allclose([l["position"] for l in report["lights"]], lab.lights.positions)
    assert report["fit"]["undetermined"] == {lab.scene[0].name: ["ns"]} and report["fit"]["trace_points"] == 2
    assert "[fit]" in capsys.readouterr().out


def test_report_names_missing_workspace(tmp_path, capsys):
    assert main(["report", str(tmp_path / "nope")]) == 2
    assert "nope" in capsys.readouterr().err


def test_report_names_an_unreadable_file_instead_of_treating_it_as_absent(tmp_path, capsys):
    lab = build_lab(80, 60)
    write_lab(tmp_path, lab)
    (tmp_path / "fit.json").write_text('{"method": "ftbo", "rms": [0.1,')  # cut off mid-write
    assert main(["report", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert "fit" not in report and list(report["unreadable"]) == [str(tmp_path / "fit.json")]
    assert "JSONDecodeError" in report["unreadable"][str(tmp_path / "fit.json")]
    err = capsys.readouterr().err
    assert "fit.json is unreadable" in err
