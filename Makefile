# Two commands do everything on a fresh machine: `make demo` and `make test`.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
# Qt's xcb platform plugin (the window on an X server) and what its libqxcb.so links (ldd); Xvfb
# for the test that opens the window on a real X server (tests/test_gui_xvfb.py).
QTXCB   := libxcb-cursor0 libxcb-icccm4 libxcb-keysyms1 libxcb-image0 libxcb-randr0 libxcb-render-util0 \
           libxcb-render0 libxcb-shape0 libxcb-shm0 libxcb-sync1 libxcb-util1 libxcb-xfixes0 libxcb-xkb1 \
           libxkbcommon-x11-0 libxkbcommon0 libx11-xcb1 libx11-6 libxcb1
SYSLIBS := libllvm19 libusb-1.0-0 $(QTXCB) xvfb

.PHONY: demo test setup syslibs clean

demo: setup
	$(BIN)/reflab demo demo-workspace

# The suite on PYTEST_JOBS processes (pytest-xdist), each test file on one of them (its module
# fixtures built once): 7.5 min on two cores against 12.9 min on one (408 tests, 2026-11-27).
PYTEST_JOBS ?= 2

test: setup
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest -n $(PYTEST_JOBS) --dist loadfile $(PYTEST_ARGS)

setup: syslibs $(STAMP)

# Mitsuba's LLVM back end needs libllvm19 (Dr.Jit crashes with bookworm's LLVM 15);
# Open3D needs libusb; `reflab gui` the xcb libraries. Installed with apt where it is there.
syslibs:
	@./.ci/syslibs.sh $(SYSLIBS)

$(STAMP): pyproject.toml setup.py
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

clean:
	rm -rf $(VENV) demo-workspace
