"""The command line's conventions (issue 29): one options table per stage read by the CLI and the
GUI, one meaning per flag, global options anywhere, --version, -q, the exit-status table, Ctrl-C."""
import dataclasses
import os
import signal
import subprocess
import sys

import pytest

from reflab.app.cli import EXIT_CODES, build_parser, main
from reflab.calibration.stages import CameraOptions
from reflab.core import options as table
from reflab.inverse.stages import FitOptions


def _set_default(monkeypatch, cls, name, value):
    field = {f.name: f for f in dataclasses.fields(cls)}[name]
    monkeypatch.setattr(field, "default", value)


def test_a_default_changed_in_the_table_reaches_the_cli_and_the_gui(qtbot, tmp_path, monkeypatch):
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    pytest.importorskip("pytestqt")
    from PySide6.QtWidgets import QDoubleSpinBox, QLineEdit, QSpinBox

    from reflab.app.gui import MainWindow

    parser = build_parser()
    assert parser.parse_args(["fit", "ws"]).texture_rounds == 2
    assert parser.parse_args(["calibrate", "camera", "ws", "--grid", "9x7"]).spacing == 0.015
    _set_default(monkeypatch, FitOptions, "texture_rounds", 5)
    _set_default(monkeypatch, CameraOptions, "spacing", 0.025)
    _set_default(monkeypatch, CameraOptions, "grid", "9x7")
    parser = build_parser()
    assert parser.parse_args(["fit", "ws"]).texture_rounds == 5
    args = parser.parse_args(["calibrate", "camera", "ws", "--grid", "5x4"])
    assert args.spacing == 0.025 and args.grid == "5x4"
    assert "(default 5)" in parser._subparsers._group_actions[0].choices["fit"].format_help()
    window = MainWindow(tmp_path / "ws", port="sim", camera="sim", size=(80, 60), live_preview_ms=0)
    qtbot.addWidget(window)
    assert window.findChild(QSpinBox, "option_fit_texture_rounds").value() == 5
    assert window.findChild(QDoubleSpinBox, "option_calibrate_camera_spacing").value() == pytest.approx(0.025)
    assert window.findChild(QLineEdit, "option_calibrate_camera_grid").text() == "9x7"
    assert window.findChild(QDoubleSpinBox, "option_calibrate_camera_spacing").suffix() == " m"


def test_flags_come_from_the_tables_with_one_name_each():
    parser = build_parser()
    # the same target and axis under one name everywhere; the old spellings stay, hidden
    new = parser.parse_args(["reconstruct", "ws", "--grid", "9x7", "--turntable-centre", "0.1,0"])
    old = parser.parse_args(["reconstruct", "ws", "--target", "9x7"])
    assert new.target == old.target == "9x7" and new.turntable_centre == [0.1, 0.0]
    cap = ["capture", "sweep", "ws", "--port", "sim", "--camera", "sim"]
    assert parser.parse_args(cap + ["--turntable-centre", "0.1,0.2"]).centre == [0.1, 0.2]
    assert parser.parse_args(cap + ["--centre", "0.1,0.2"]).centre == [0.1, 0.2]
    assert parser.parse_args(cap + ["--sim-depth", "2"]).depth == parser.parse_args(cap + ["--depth", "2"]).depth == 2
    assert parser.parse_args(cap).centre == [0.0, 0.0] and parser.parse_args(cap).count == 36
    help_text = parser._subparsers._group_actions[0].choices["capture"].format_help()
    assert "--sim-depth" in help_text and "--centre" not in help_text and "--depth" not in help_text
    # bools that default to True keep their off-switch; the options get the field's value
    args = parser.parse_args(["reconstruct", "ws", "--free-poses", "--no-fit", "--mesh", "box=b.ply"])
    from reflab.reconstruction.stages import ReconstructOptions

    o = table.options_from_args(ReconstructOptions, args, workspace="ws")
    assert o.rigid_turntable is False and o.fit_surfaces is False and str(o.meshes["box"]) == "b.ply"
    assert table.options_from_args(ReconstructOptions, parser.parse_args(["reconstruct", "ws"]), workspace="ws") \
        == ReconstructOptions("ws")
    # the render contract: -o, --camera C.json, --lights, --aov
    r = parser.parse_args(["render", "ws", "--camera", "c.json", "--lights", "l.json", "--aov", "albedo", "-o", "o.exr"])
    assert (r.camera, r.lights, r.aov, r.output) == ("c.json", "l.json", "albedo", "o.exr")


def test_an_option_error_names_the_commands_flag(tmp_path, capsys):
    assert main(["reconstruct", str(tmp_path), "--grid", "1x1"]) == 2
    assert "reflab reconstruct: error: --grid: need at least 2 circles" in capsys.readouterr().err


def test_version(capsys):
    import reflab

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.strip() == f"reflab {reflab.__version__}"


def test_exit_codes_are_listed_in_help(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert "exit status:" in out
    for code, text in EXIT_CODES:
        assert f"  {code:<4} {text}" in out
    assert [c for c, _ in EXIT_CODES] == [0, 1, 2, 3, 130]


def test_global_options_go_anywhere_on_the_line(capsys):
    """`reflab hardware status --port sim` is `reflab hardware --port sim status`; -q after the command."""
    assert main(["hardware", "status", "--port", "sim"]) == 0
    after = capsys.readouterr().out
    assert main(["hardware", "--port", "sim", "status"]) == 0
    before = capsys.readouterr().out
    assert "Idle  angle 0.000 deg" in after and "Idle  angle 0.000 deg" in before
    assert main(["hardware", "status", "--port", "sim", "-q"]) == 0
    assert main(["-q", "hardware", "--port", "sim", "status"]) == 0
    assert capsys.readouterr().out == ""
    assert main(["hardware", "status"]) == 2
    assert "--port is required" in capsys.readouterr().err
    parser = build_parser()
    assert parser.parse_args(["fit", "ws", "-v"]).verbose == 1 and parser.parse_args(["-v", "fit", "ws"]).verbose == 1
    assert parser.parse_args(["calibrate", "camera", "ws", "--grid", "9x7", "-q"]).quiet == 1


def test_quiet_keeps_warnings_on_stderr(tmp_path, capsys):
    """-q silences the info lines (stdout) and keeps warnings (stderr)."""
    (tmp_path / "fit.json").write_text('{"method": "ftbo", "rms": [0.1,')  # cut off mid-write
    assert main(["report", str(tmp_path), "--no-render"]) == 0
    loud = capsys.readouterr()
    assert "wrote" in loud.out and "fit.json is unreadable" in loud.err and "unreadable" not in loud.out
    assert main(["report", str(tmp_path), "--no-render", "-q"]) == 0
    quiet = capsys.readouterr()
    assert quiet.out == "" and quiet.err == loud.err


def test_ctrl_c_cancels_the_fit_and_writes_nothing(lab_workspace):
    """SIGINT once the stage runs: the task is cancelled, exit 130 with one line, no fit.json."""
    root, _, _ = lab_workspace
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)}
    proc = subprocess.Popen([sys.executable, "-m", "reflab.app.cli", "-v", "fit", str(root)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        for line in proc.stdout:  # the handler is in place once this line is out
            if "fit: running (Ctrl-C cancels)" in line:
                break
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=300)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "reflab fit: cancelled; nothing half-written"
    assert not (root / "fit.json").exists() and not list(root.glob(".fit*"))
