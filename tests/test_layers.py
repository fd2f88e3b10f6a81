"""The house's layers (docs/architecture.md), read from the import graph of every product module.

Every ``import`` and ``from ... import`` is read with ``ast``, those inside functions included.
Layers: core < hardware < calibration < reconstruction < inverse < app; a module may import its own
layer and lower ones. Importing ``a.b.c`` runs the ``__init__`` of ``a`` and ``a.b`` too: those are
edges of the graph, so a package whose ``__init__`` imports its own modules makes a cycle. The simulated twin (``hardware/sim``) may import any stage, and only app/
(plus tests and docs) may import it. No cycle between modules.
"""
import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ["core", "hardware", "calibration", "reconstruction", "inverse", "app"]
TWIN = "reflab.hardware.sim"


def _module_name(path: Path) -> str:
    parts = ["reflab", *path.relative_to(ROOT).with_suffix("").parts]
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    out = {"reflab": ROOT / "__init__.py"}
    for top in LAYERS:
        for path in sorted((ROOT / top).rglob("*.py")):
            out[_module_name(path)] = path
    return out


MODULES = _modules()


def _resolve(name: str) -> str | None:
    """The product module ``name`` refers to (a module, else its package), or None if outside."""
    while name:
        if name in MODULES:
            return name
        name = name.rpartition(".")[0]
    return None


def _imports(module: str, path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = package.split(".")
                base = ".".join(pkg[:len(pkg) - node.level + 1] + ([base] if base else []))
            names = [f"{base}.{a.name}" for a in node.names] + [base]
        else:
            continue
        for name in names:
            target = _resolve(name)
            while target is not None and target != "reflab":  # the module, then each package above it
                if target != module and not module.startswith(target + "."):
                    found.add(target)
                target = target.rpartition(".")[0]
    return found


GRAPH = {m: _imports(m, p) for m, p in MODULES.items()}


def _layer(module: str) -> int:
    return LAYERS.index(module.split(".")[1])


def _is_twin(module: str) -> bool:
    return module == TWIN or module.startswith(TWIN + ".")


def test_the_graph_is_read():
    assert len(MODULES) > 40
    assert "reflab.calibration.camera" in GRAPH["reflab.reconstruction.stages"]  # module level
    assert "reflab.inverse.forward.trees" in GRAPH["reflab.inverse.stages"]  # inside a function


def test_no_upward_import():
    bad = [f"{m} imports {t}" for m, targets in GRAPH.items() if not _is_twin(m) and m != "reflab"
           for t in sorted(targets) if _layer(t) > _layer(m)]
    assert not bad, "upward imports (core < hardware < calibration < reconstruction < inverse < app):\n" + "\n".join(bad)


def test_only_app_imports_the_twin():
    bad = [f"{m} imports {t}" for m, targets in GRAPH.items() if not _is_twin(m) and not m.startswith("reflab.app")
           for t in sorted(targets) if _is_twin(t)]
    assert not bad, "product code imports the simulated twin (hardware/sim):\n" + "\n".join(bad)


def _cycles(graph: dict) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


#: Cycles being taken apart elsewhere, named so that no other joins them; remove an entry once it
#: is gone (the test says so).
KNOWN_CYCLES = []


def test_no_import_cycle():
    cycles = _cycles(GRAPH)
    new = [c for c in cycles if c not in KNOWN_CYCLES]
    assert not new, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in new)
    gone = [c for c in KNOWN_CYCLES if c not in cycles]
    assert not gone, f"no longer a cycle, remove it from KNOWN_CYCLES: {gone}"


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


@pytest.mark.parametrize("layer", LAYERS[:-1])
def test_layer_packages_exist(layer):
    assert any(m.split(".")[1] == layer for m in MODULES if m != "reflab")


# ---------------------------------------------------------------------- the workspace's file names
#: Workspace files named in the contracts, as (Workspace attribute, arguments) -> the name it must give.
OWNED = {("camera",): "camera.json", ("lights",): "lights.json", ("scene",): "scene.json", ("fit",): "fit.json",
         ("marks",): "marks.json", ("sfm",): "sfm.json", ("sparse",): "sparse.ply", ("report",): "report.html",
         ("report_json",): "report.json", ("plan",): "plan.json", ("hardware",): "hardware.json", ("truth_materials",): "truth.json",
         ("texture_index",): "textures/index.json", ("input_image",): "input.exr", ("render",): "render.exr",
         ("view", "novel"): "novel.exr", ("view", "relit"): "relit.exr", ("mesh", "floor"): "meshes/floor.ply",
         ("trees_cache", "key"): "cache/trees-key.npz", ("manifest", "sweep"): "captures/turntable/manifest.json"}
#: Files whose literal workspace names are still to go (none left: the report's sections take
#: theirs from the Workspace object too), named so that no other file joins them; remove an
#: entry once its file has none left (the test says so).
KNOWN_LITERALS: set = set()
#: Folders of the workspace whose contents only the Workspace object names.
FOLDERS = ("captures", "meshes", "textures", "truth", "cache")


def _workspace_names(ws) -> set[str]:
    out = set()
    for key, want in OWNED.items():
        got = getattr(ws, key[0])
        got = got(*key[1:]) if callable(got) else got
        for path in got if isinstance(got, tuple) else (got,):
            out.add(path.relative_to(ws.root).as_posix())
    return out


def test_the_workspace_owns_every_file_name_of_the_contracts(tmp_path):
    """Each file name of docs/formats.md (the workspace contract) is a path the Workspace object gives."""
    from reflab.core.workspace import Workspace

    names = _workspace_names(Workspace(tmp_path))
    assert set(OWNED.values()) <= names
    assert {p.name for p in Workspace(tmp_path).view("novel") + Workspace(tmp_path).view("relit")} >= {
        "novel_camera.json", "relit_lights.json"}
    docs = [ROOT / "docs" / "formats.md"]
    said = set()
    for doc in (d for d in docs if d.exists()):
        said |= set(re.findall(r"(?<![\w/.-])([a-z_]+\.(?:json|ply|exr|html|npz))\b", doc.read_text()))
    said -= {"floor.ply", "sheet.ply"}  # examples of meshes/<name>.ply
    owned = {n.rpartition("/")[2] for n in names} | {"novel_camera.json", "relit_lights.json", "manifest.json"}
    assert said and not said - owned, f"named in the contracts but not by Workspace: {sorted(said - owned)}"


#: File names that only the Workspace object writes out.
NAMES = {v.rpartition("/")[2] for v in OWNED.values()} - {"floor.ply", "trees-key.npz"} | {"novel_camera.json",
                                                                                           "relit_lights.json"}


def _is_workspace_name(text: str) -> bool:
    return text in NAMES or any(text == f or text.startswith(f + "/") for f in FOLDERS)


def _literal_paths(source: str, name: str) -> list[str]:
    """Workspace names written as literals where a path is built: ``x / "fit.json"``, ``Path("fit.json")``,
    ``src.path("sparse.ply")``; a message naming a file is no path."""
    def text(node):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            return node.value
        if isinstance(node, ast.JoinedStr):
            return "".join(v.value if isinstance(v, ast.Constant) else "{}" for v in node.values)
        return None

    found = []
    for node in ast.walk(ast.parse(source, name)):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            operands = [node.right]
        elif isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", None)) in (
                "Path", "joinpath", "with_name", "path", "json", "image", "truth"):  # the last four: readers by name
            operands = node.args
        else:
            continue
        found += [f"{name}:{node.lineno}: {t!r}" for t in map(text, operands)
                  if t is not None and _is_workspace_name(t.rpartition("/")[2] if t.startswith("{}") else t)]
    return found


def test_product_code_takes_workspace_paths_from_the_workspace_object():
    found = {}
    for module, path in MODULES.items():
        name = path.relative_to(ROOT).as_posix()
        hits = [] if module == "reflab.core.workspace" or _is_twin(module) else _literal_paths(path.read_text(), name)
        if hits:
            found[name] = hits
    new = [h for f, hits in found.items() if f not in KNOWN_LITERALS for h in hits]
    assert not new, "workspace file names outside core/workspace.py (use Workspace):\n" + "\n".join(new)
    gone = sorted(KNOWN_LITERALS - set(found))
    assert not gone, f"no literal workspace name left, remove it from KNOWN_LITERALS: {gone}"


def test_literal_finder_finds_a_literal():
    source = 'a = root / "fit.json"\nb = Path(f"captures/{a}/x.exr")\nc = root / "sub"\nprint("wrote fit.json")\n'
    assert _literal_paths(source, "probe.py") == ["probe.py:1: 'fit.json'", "probe.py:2: 'captures/{}/x.exr'"]


# ---------------------------------------------------------------------- one copy of each geometry helper
#: Files that still write a rotation matrix out by hand (none left: the GUI's orbit uses
#: reflab.calibration.rotations too); remove an entry once its file uses reflab.calibration.rotations.
KNOWN_ROTATIONS: set = set()
HAND_ROTATION = re.compile(r"np\.cos\((\w+)\),\s*-np\.sin\(\1\)")


def test_rotations_come_from_the_one_copy():
    """A rotation matrix written out (``[cos a, -sin a, 0], ...``) outside calibration/rotations.py is a copy."""
    assert HAND_ROTATION.search("R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], ...])")
    found = {path.relative_to(ROOT).as_posix() for module, path in MODULES.items()
             if module != "reflab.calibration.rotations" and HAND_ROTATION.search(path.read_text())}
    assert not found - KNOWN_ROTATIONS, f"use reflab.calibration.rotations.axis_rotation in {sorted(found - KNOWN_ROTATIONS)}"
    assert not KNOWN_ROTATIONS - found, f"no copy left, remove it from KNOWN_ROTATIONS: {sorted(KNOWN_ROTATIONS - found)}"


# ---------------------------------------------------------------------- thin commands
#: A command module is arguments -> options -> stage -> print -> exit code: about 100 lines or fewer.
COMMAND_LINES = 110


def test_command_modules_are_thin():
    """Every module of app/commands (a command with subcommands is a package of them, e.g. calibrate)."""
    commands = sorted((ROOT / "app" / "commands").rglob("*.py"))
    assert len(commands) > 10 and ROOT / "app" / "commands" / "calibrate" / "lights.py" in commands
    long = {p.relative_to(ROOT).as_posix(): n for p in commands if (n := len(p.read_text().splitlines())) > COMMAND_LINES}
    assert not long, f"command modules over {COMMAND_LINES} lines (move the work into a stage): {long}"


def test_open3d_loads_without_its_plotly_viewer():
    """reflab.core.open3d_env: no stage draws with plotly/dash, 0.3 s of every command that reads a
    mesh; the viewer still loads when called (its stand-in imports the real module)."""
    import subprocess
    import sys

    code = ("import sys; from reflab.core.open3d_env import open3d; o3d = open3d(); "
            "assert 'dash' not in sys.modules and 'plotly' not in sys.modules, 'viewer loaded'; "
            "o3d.io.read_triangle_mesh; from open3d.visualization import draw_plotly as d; "
            "assert sys.modules['open3d.visualization.draw_plotly']._reflab_stand_in; "
            "from reflab.core.open3d_env import _real_plotly; assert hasattr(_real_plotly(), 'get_plotly_fig'); "
            "assert 'dash' in sys.modules; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(ROOT))
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
