"""The house's layers (docs/architecture.md), read from the import graph of every product module.

Every ``import`` and ``from ... import`` is read with ``ast``, those inside functions included.
Layers: hardware < calibration < reconstruction < inverse < app; a module may import its own
layer and lower ones. The simulated twin (``hardware/sim``) may import any stage, and only app/
(plus tests and docs) may import it. No cycle between modules.
"""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ["hardware", "calibration", "reconstruction", "inverse", "app"]
TWIN = "hardware.sim"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    out = {}
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
            if target is not None and target != module:
                found.add(target)
    return found


GRAPH = {m: _imports(m, p) for m, p in MODULES.items()}


def _layer(module: str) -> int:
    return LAYERS.index(module.split(".")[0])


def _is_twin(module: str) -> bool:
    return module == TWIN or module.startswith(TWIN + ".")


def test_the_graph_is_read():
    assert len(MODULES) > 40
    assert "calibration.camera" in GRAPH["reconstruction.stages"]  # module level
    assert "inverse.trees" in GRAPH["inverse.stages"]  # inside a function


def test_no_upward_import():
    bad = [f"{m} imports {t}" for m, targets in GRAPH.items() if not _is_twin(m)
           for t in sorted(targets) if _layer(t) > _layer(m)]
    assert not bad, "upward imports (hardware < calibration < reconstruction < inverse < app):\n" + "\n".join(bad)


def test_only_app_imports_the_twin():
    bad = [f"{m} imports {t}" for m, targets in GRAPH.items() if not _is_twin(m) and not m.startswith("app")
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
    # A package's __init__ re-exporting its modules is not a cycle of ideas: leave those edges out.
    graph = {m: {t for t in ts if not (MODULES[t].name == "__init__.py" and m.startswith(t + "."))}
             for m, ts in GRAPH.items()}
    cycles = _cycles(graph)
    new = [c for c in cycles if c not in KNOWN_CYCLES]
    assert not new, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in new)
    gone = [c for c in KNOWN_CYCLES if c not in cycles]
    assert not gone, f"no longer a cycle, remove it from KNOWN_CYCLES: {gone}"


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


@pytest.mark.parametrize("layer", LAYERS[:-1])
def test_layer_packages_exist(layer):
    assert any(m.split(".")[0] == layer for m in MODULES)
