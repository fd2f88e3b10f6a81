"""The repository explains itself: its references to its own docs, modules and names resolve.

- no tracked text file points outside the repository at the project's steering folder (tests may
  name its ``third_party`` sources, and skip without them);
- every ``docs/<page>.md``, ``docs/<path>.png`` or ``docs/<path>.py`` that a tracked file names exists;
- every module path ``<layer>/<...>.py`` that the docs (docs/*.md, README.md) name exists;
- every dotted ``reflab.<module>[.<attribute>]`` that the docs name imports and resolves.

Each check is a function of one file, so that the last test can show each one failing on a file
with a broken reference.
"""
from __future__ import annotations

import importlib
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("core", "hardware", "calibration", "reconstruction", "inverse", "app")
#: The steering folder beside the repository, spelled in two pieces so that this file does not name it.
OUTSIDE = ".." + "/shared"

_DOC_FILE = re.compile(r"(?<![\w/.-])(docs/[\w./-]*?\.(?:md|png|py))(?![\w-])")
_MODULE_FILE = re.compile(r"(?<![\w/.-])((?:%s)/(?:\w+/)*\w+\.py)(?![\w-])" % "|".join(LAYERS))
_DOTTED = re.compile(r"(?<![\w./-])(reflab(?:\.[A-Za-z_]\w*)+)")


def _tracked_text_files() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        pytest.skip(f"not a git checkout ({exc}): the tracked files are unknown")
    files = []
    for name in out.decode().split("\0"):
        path = ROOT / name
        if name and path.is_file() and _text(path) is not None:
            files.append(path)
    return files


def _text(path: Path) -> str | None:
    """The file's text, or None for a binary file."""
    data = path.read_bytes()
    if b"\0" in data:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def _docs() -> list[Path]:
    return sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]


def outside_references(path: Path, rel: str) -> list[str]:
    """Places in ``path`` (``rel`` to the repository root) that name the steering folder; a test may
    name its third-party sources."""
    text = _text(path) or ""
    allowed = rel.startswith("tests/")
    return [f"{rel}:{text.count(chr(10), 0, m.start()) + 1}" for m in re.finditer(re.escape(OUTSIDE), text)
            if not (allowed and text.startswith("/third_party", m.end()))]


def missing_doc_files(path: Path, root: Path = ROOT) -> list[str]:
    """``docs/...`` pages, figures and scripts named in ``path`` that are not under ``root``."""
    return sorted({m for m in _DOC_FILE.findall(_text(path) or "") if not (root / m).exists()})


def missing_module_files(path: Path, root: Path = ROOT) -> list[str]:
    """``<layer>/<...>.py`` module paths named in ``path`` that are not under ``root``."""
    return sorted({m for m in _MODULE_FILE.findall(_text(path) or "") if not (root / m).is_file()})


def _resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        name = ".".join(parts[:n])
        try:
            obj = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name and (name == exc.name or name.startswith(exc.name + ".")):
                continue  # not a module: an attribute of a shorter one, or nothing
            raise  # a module that exists but cannot import (a missing dependency) is no bad reference
        for attr in parts[n:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def unresolved_names(path: Path) -> list[str]:
    """``reflab.<module>[.<attribute>...]`` names in ``path`` that do not resolve."""
    return sorted({m for m in _DOTTED.findall(_text(path) or "") if not _resolves(m)})


def test_nothing_points_at_the_steering_folder():
    bad = [hit for f in _tracked_text_files() for hit in outside_references(f, f.relative_to(ROOT).as_posix())]
    assert not bad, f"the repository must explain itself (docs/method.md, docs/formats.md), not point at {OUTSIDE}: {bad}"


def test_every_named_doc_file_exists():
    files = _tracked_text_files()
    bad = {f.relative_to(ROOT).as_posix(): m for f in files if (m := missing_doc_files(f))}
    assert any(f.name == "README.md" for f in files)
    assert not bad, f"docs files named but missing: {bad}"


def test_every_module_path_in_the_docs_exists():
    bad = {f.relative_to(ROOT).as_posix(): m for f in _docs() if (m := missing_module_files(f))}
    assert not bad, f"module paths in the docs that are not in the tree: {bad}"


def test_every_dotted_name_in_the_docs_resolves():
    bad = {f.relative_to(ROOT).as_posix(): m for f in _docs() if (m := unresolved_names(f))}
    assert not bad, f"reflab.<module> names in the docs that do not resolve: {bad}"


def test_the_checks_find_broken_references(tmp_path):
    """Each check on a file with one good and one broken reference of its kind names the broken one only."""
    page, d = tmp_path / "page.md", "docs"  # d: this file names no missing docs file itself
    page.write_text(f"see {OUTSIDE}/METHOD.md and {OUTSIDE}/third_party/grbl\n"
                    f"{d}/formats.md, {d}/no-such-page.md, {d}/figures/fit_speed.py, {d}/img/missing.png\n"
                    "inverse/fit/ftbo.py and inverse/fitting.py; app/commands/<name>.py is a pattern\n"
                    "reflab.inverse.stages.fit, reflab.core.workspace.Workspace.plan, reflab.inverse.fitting.fit, "
                    "reflab.core.task.NoSuchName.\n")
    assert outside_references(page, f"{d}/page.md") == [f"{d}/page.md:1", f"{d}/page.md:1"]
    assert outside_references(page, "tests/test_x.py") == ["tests/test_x.py:1"]
    assert missing_doc_files(page) == [f"{d}/img/missing.png", f"{d}/no-such-page.md"]
    assert missing_module_files(page) == ["inverse/fitting.py"]
    assert unresolved_names(page) == ["reflab.core.task.NoSuchName", "reflab.inverse.fitting.fit"]
