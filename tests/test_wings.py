"""The package's shape: wings whose imports flow one way, no import cycle, and the flat
module paths of 0.1 still importable (with a warning) for one release."""

import ast
import importlib
import sys
import warnings
from pathlib import Path

import pytest

import vprflow

PACKAGE = Path(vprflow.__file__).parent

# A wing may import only from wings of a lower rank (and from itself).
RANKS = {
    "core": 0,
    "data": 1,
    "models": 1,
    "search": 1,
    "aggregation": 2,
    "evaluation": 2,
    "planning": 3,
    "stages": 4,
}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, set[str]]:
    """Every vprflow module -> the vprflow modules it imports anywhere (lazy imports in
    functions included: a cycle through one still ties the two files)."""
    modules = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            targets = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                # `from vprflow.core import stores` imports the module core.stores
                targets = [f"{node.module}.{a.name}" for a in node.names] + [node.module]
            found |= {t for t in targets if t in modules and t != name}
        graph[name] = {t for t in found if not name.startswith(t + ".") and t != "vprflow"}
    return graph


def _wing(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in RANKS) else None


def test_every_folder_of_the_package_is_a_ranked_wing():
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders == set(RANKS)
    flat = {p.stem for p in PACKAGE.glob("*.py")}
    assert flat == {"__init__"}, "modules belong in a wing"


def test_the_import_graph_is_read():
    graph = _imports()
    assert "vprflow.core.stores" in graph["vprflow.stages.gather"]
    assert "vprflow.data.ground_truth" in graph["vprflow.stages.dataset"]
    assert sum(map(len, graph.values())) > 100


def test_imports_between_wings_flow_down_only():
    upward = [
        f"{a} -> {b}"
        for a, targets in _imports().items()
        for b in targets
        if _wing(a) and _wing(b) and _wing(a) != _wing(b) and RANKS[_wing(b)] >= RANKS[_wing(a)]
    ]
    assert upward == []


def test_no_module_takes_part_in_an_import_cycle():
    graph = _imports()
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    assert cycles == []


@pytest.mark.parametrize("old", sorted(vprflow.MOVED))
def test_an_old_module_path_imports_the_moved_module_with_a_warning(old):
    sys.modules.pop(f"vprflow.{old}", None)
    with pytest.warns(
        DeprecationWarning, match=f"vprflow.{old} moved to vprflow.{vprflow.MOVED[old]}"
    ):
        module = importlib.import_module(f"vprflow.{old}")
    assert module is importlib.import_module(f"vprflow.{vprflow.MOVED[old]}")


def test_every_moved_module_exists():
    for new in vprflow.MOVED.values():
        assert (PACKAGE / (new.replace(".", "/") + ".py")).exists() or (
            PACKAGE / new.replace(".", "/") / "__init__.py"
        ).exists(), new


def test_the_old_hub_names_of_vprflow_models_resolve_with_a_warning():
    from vprflow.models import hub

    with pytest.warns(DeprecationWarning, match="vprflow.models.hub.load_pretrained"):
        from vprflow.models import load_pretrained
    assert load_pretrained is hub.load_pretrained


def test_new_paths_import_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        importlib.import_module("vprflow.planning.plan")
        importlib.import_module("vprflow.stages.jobs")
