"""`reflab gui` starts on a real X server (Xvfb, Qt's xcb platform), not only off screen (issue 31).

The other GUI tests run Qt's offscreen platform and never load the xcb plugin, whose missing system
libraries (libxcb-cursor0, libxcb-icccm4, libxcb-keysyms1: the Makefile's QTXCB) abort the window
at start on a plain Debian X server. Here the window runs as a user starts it, and a screenshot of
the X server's root window must show it: not blank, most of the screen the window's light grey.
"""
import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

XVFB = shutil.which("Xvfb")
pytestmark = pytest.mark.skipif(XVFB is None, reason="Xvfb is not installed (apt-get install xvfb; make setup does)")

GRAB = """
import sys
from PySide6.QtGui import QGuiApplication
app = QGuiApplication([sys.argv[0], "-platform", "xcb"])
sys.exit(0 if app.primaryScreen().grabWindow(0).save(sys.argv[1]) else 1)
"""


@pytest.fixture
def xserver():
    """An Xvfb display of its own (``-displayfd``: the server picks a free number and says it)."""
    read, write = os.pipe()
    proc = subprocess.Popen([XVFB, "-displayfd", str(write), "-screen", "0", "1280x900x24", "-nolisten", "tcp"],
                            pass_fds=(write,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(write)
    with os.fdopen(read) as f:
        number = f.readline().strip()
    if not number:
        proc.kill()
        pytest.skip("Xvfb did not start")
    yield f":{number}"
    proc.terminate()
    proc.wait(10)


def screenshot(display: str, path) -> np.ndarray | None:
    import cv2

    env = dict(os.environ, DISPLAY=display, QT_QPA_PLATFORM="xcb")
    if subprocess.run([sys.executable, "-c", GRAB, str(path)], env=env, capture_output=True).returncode != 0:
        return None
    return cv2.imread(str(path))


def test_reflab_gui_opens_its_window_on_an_x_server(xserver, tmp_path):
    env = dict(os.environ, DISPLAY=xserver, QT_QPA_PLATFORM="xcb")
    gui = subprocess.Popen([sys.executable, "-m", "reflab.app.cli", "gui", str(tmp_path / "ws"), "--size", "80x60"],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        # Wait for the window to be drawn (a condition, with a generous bound on a busy machine).
        deadline, shot = time.monotonic() + 120, None
        while time.monotonic() < deadline and gui.poll() is None:
            shot = screenshot(xserver, tmp_path / "screen.png")
            if shot is not None and np.mean(shot > 200) > 0.5:
                break
        assert gui.poll() is None, f"reflab gui exited with {gui.returncode}: {gui.stdout.read()[-2000:]}"
        assert shot is not None, "no screenshot of the X server"
        # Not blank: most of the screen is the window's light background, and it holds text and widgets.
        assert np.mean(shot > 200) > 0.5 and shot.std() > 20 and len(np.unique(shot.reshape(-1, 3), axis=0)) > 50
    finally:
        gui.terminate()
        gui.wait(30)
