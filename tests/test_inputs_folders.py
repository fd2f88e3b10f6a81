"""Folders a user gets wrong (issue 18): a read-only workspace, one that does not exist.

Every stage checks before it starts: one line naming the folder and what to do, exit 2, nothing
written. A read-only folder is made with a private mount namespace (we run as root, so file
modes do not stop writes): `unshare -m sh -c 'mount --bind D D && mount -o remount,ro,bind D D && …'`.
"""
import hashlib
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from reflab.app.cli import main

ROOT = Path(__file__).resolve().parents[1]


def snapshot(folder: Path) -> dict:
    return {p.relative_to(folder): hashlib.sha1(p.read_bytes()).hexdigest() for p in folder.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    from reflab.hardware.sim.lab import build_lab, write_lab
    from reflab.inverse.forward.rendering import render
    from reflab.inverse.forward.trees import build_trees
    from reflab.core.images import write_image

    root = tmp_path_factory.mktemp("ws")
    lab = build_lab(64, 48, textured=False)
    write_lab(root, lab)
    img = render(build_trees(lab.scene, lab.camera, lab.lights, depth=2), [s.material for s in lab.scene],
                 lab.lights.intensities)
    write_image(root / "input.exr", img)
    return root


def _unshare_works(folder: Path) -> str:
    cmd = f"mount --bind {folder} {folder} && mount -o remount,ro,bind {folder} {folder} && true"
    try:
        proc = subprocess.run(["unshare", "-m", "sh", "-c", cmd], capture_output=True, text=True, timeout=30)
    except (FileNotFoundError, subprocess.TimeoutExpired) as exc:
        return f"unshare not available: {exc}"
    return "" if proc.returncode == 0 else f"cannot make a read-only bind mount here: {proc.stderr.strip()}"


COMMANDS = {
    "fit": ["fit", "{ws}"],
    "texture": ["texture", "{ws}"],
    "render": ["render", "{ws}"],
    "report": ["report", "{ws}"],
    "reconstruct": ["reconstruct", "{ws}", "--turntable-centre", "0,0"],
    "calibrate": ["calibrate", "camera", "{ws}", "--grid", "11x8"],
    "lights": ["calibrate", "lights", "{ws}", "--rod-height", "0.1"],
    "capture": ["capture", "input", "{ws}", "--port", "sim", "--camera", "sim", "--size", "64x48"],
}


def test_read_only_workspace_stops_every_stage_before_work(workspace, tmp_path):
    why = _unshare_works(workspace)
    if why:
        pytest.skip(why)
    before = snapshot(workspace)
    python = shlex.quote(sys.executable)
    lines = [f"mount --bind {workspace} {workspace}", f"mount -o remount,ro,bind {workspace} {workspace}"]
    for name, argv in COMMANDS.items():
        args = " ".join(shlex.quote(a.format(ws=workspace)) for a in argv)
        lines.append(f"{python} -m reflab.app.cli {args} >{tmp_path}/{name}.out 2>{tmp_path}/{name}.err; "
                     f"echo $? >{tmp_path}/{name}.rc")
    # A read-only workspace still renders elsewhere (the trees cache is skipped).
    lines.append(f"{python} -m reflab.app.cli render {workspace} -o {tmp_path}/elsewhere/out.exr >{tmp_path}/out.out "
                 f"2>{tmp_path}/out.err; echo $? >{tmp_path}/out.rc")
    subprocess.run(["unshare", "-m", "sh", "-c", " && ".join(lines[:2]) + "; " + "; ".join(lines[2:])],
                   cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, check=True, timeout=600)
    for name in COMMANDS:
        rc = int((tmp_path / f"{name}.rc").read_text())
        err = (tmp_path / f"{name}.err").read_text().strip().splitlines()
        assert rc == 2 and len(err) == 1, (name, rc, err)
        assert (tmp_path / f"{name}.out").read_text() == "", name  # stopped before any work to report
        assert str(workspace) in err[0] and "Read-only file system" in err[0] and "remount" in err[0], (name, err)
    assert int((tmp_path / "out.rc").read_text()) == 0, (tmp_path / "out.err").read_text()
    assert (tmp_path / "elsewhere" / "out.exr").is_file() and "not cached" in (tmp_path / "out.out").read_text()
    assert snapshot(workspace) == before


@pytest.mark.parametrize("name", [name for name in COMMANDS if name != "capture"])  # a capture starts a workspace
def test_a_workspace_that_does_not_exist_is_named_as_such(tmp_path, name, capsys):
    missing = tmp_path / "no-such-workspace"
    assert main([a.format(ws=missing) for a in COMMANDS[name]]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0] and "no such folder" in err[0] and "camera.json" not in err[0]
    assert not missing.exists()
