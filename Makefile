# Two commands do everything on a fresh machine: `make demo` and `make test`.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
SYSLIBS := libllvm19 libusb-1.0-0

.PHONY: demo test setup syslibs clean

demo: setup
	$(BIN)/reflab demo demo-workspace

test: setup
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest $(PYTEST_ARGS)

setup: syslibs $(STAMP)

# Mitsuba's LLVM back end needs libllvm19 (Dr.Jit crashes with bookworm's LLVM 15);
# Open3D needs libusb. Installed with apt where it is there.
syslibs:
	@./.ci/syslibs.sh $(SYSLIBS)

$(STAMP): pyproject.toml setup.py
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

clean:
	rm -rf $(VENV) demo-workspace
