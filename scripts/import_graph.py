"""The import graph of the vprflow package, and the ties it cannot see.

    python scripts/import_graph.py [PACKAGE_DIR]

For the whole package and for ``stages/``: each module's floor (the longest chain of
imports below it inside that part; 0 imports none of it), the number of arrows, the
arrows that run back up a wing, the modules that take part in an import cycle, and the
string ties: string literals in the package of the form ``"vprflow.x.y:name"`` that
name a vprflow module (code reached by ``importlib``, which the graph does not show).
Imports inside functions count as arrows: they tie two files as firmly as any other;
so does ``lazy_import("vprflow.x.y")`` (:mod:`vprflow.core.lazy`).
``tests/repository/test_wings.py`` reads the graph with :func:`imports`.
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

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

TIE = re.compile(r"^(vprflow(?:\.\w+)+):(\w+)$")


def module_name(path: Path, package: Path) -> str:
    parts = path.relative_to(package.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules(package: Path) -> dict[str, Path]:
    return {module_name(p, package): p for p in sorted(package.rglob("*.py"))}


def lazy_import_target(node: ast.AST) -> str | None:
    """The module a ``lazy_import("name")`` call (:mod:`vprflow.core.lazy`) names."""
    if not (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)):
        return None
    f = node.func
    called = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
    return node.args[0].value if called == "lazy_import" else None


def imports(package: Path) -> dict[str, set[str]]:
    """Every module of ``package`` -> the modules of it that it imports anywhere (lazy
    imports in functions included: a cycle through one still ties the two files)."""
    found_modules = modules(package)
    top = package.name
    graph = {}
    for name, path in found_modules.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            targets = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                # `from vprflow.core import stores` imports the module core.stores
                targets = [f"{node.module}.{a.name}" for a in node.names] + [node.module]
            elif (lazy := lazy_import_target(node)) is not None:
                targets = [lazy]  # `x = lazy_import("vprflow.x")`, imported when first used
            found |= {t for t in targets if t in found_modules and t != name}
        graph[name] = {t for t in found if not name.startswith(t + ".") and t != top}
    return graph


def wing(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in RANKS) else None


def upward(graph: dict[str, set[str]]) -> list[str]:
    """The arrows that run from a wing to one of the same or a higher rank."""
    return sorted(
        f"{a} -> {b}"
        for a, targets in graph.items()
        for b in targets
        if wing(a) and wing(b) and wing(a) != wing(b) and RANKS[wing(b)] >= RANKS[wing(a)]
    )


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
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
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def floors(graph: dict[str, set[str]]) -> dict[str, int]:
    """Each module's longest chain of imports below it (modules in a cycle share one
    floor, counted once)."""
    component = {m: tuple(c) for c in cycles(graph) for m in c}
    memo: dict[str, int] = {}

    def floor(m: str) -> int:
        if m not in memo:
            memo[m] = 0  # a cycle ends the chain
            own = component.get(m, (m,))
            below = {t for o in own for t in graph[o]} - set(own)
            memo[m] = max((floor(t) + 1 for t in below), default=0)
        return memo[m]

    return {m: floor(m) for m in graph}


def string_ties(package: Path) -> list[tuple[str, str]]:
    """``(module, "vprflow.x.y:name")`` for every string literal of the package that
    names a module of it by ``module:name``."""
    found_modules = modules(package)
    ties = []
    for name, path in found_modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                match = TIE.match(node.value)
                if match and match.group(1) in found_modules:
                    ties.append((name, node.value))
            elif isinstance(node, ast.JoinedStr):  # f"{_PREFIX}.module:name"
                text = "".join(
                    v.value if isinstance(v, ast.Constant) else "{}" for v in node.values
                )
                if ":" in text and re.search(r"^(\{\}|vprflow)[\w.{}]*:[\w{}]+$", text):
                    ties.append((name, text))
    return ties


def dynamic_lookups(package: Path) -> list[str]:
    """Where the package looks code up by a computed name (``globals()``,
    ``importlib.import_module``, ``getattr`` on a module found so)."""
    found = []
    for name, path in modules(package).items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call):
                f = node.func
                called = (
                    f.id
                    if isinstance(f, ast.Name)
                    else f.attr
                    if isinstance(f, ast.Attribute)
                    else ""
                )
                if called in ("globals", "import_module"):
                    found.append(f"{name}:{node.lineno} {called}()")
    return found


def report(graph: dict[str, set[str]], ties: list[tuple[str, str]], title: str) -> str:
    lines = [f"== {title}: {len(graph)} modules"]
    level = floors(graph)
    for m in sorted(graph, key=lambda m: (-level[m], m)):
        lines.append(f"  floor {level[m]:2d}  {m}  ({len(graph[m])} arrows out)")
    lines.append(f"  arrows: {sum(map(len, graph.values()))}")
    lines.append(f"  highest floor: {max(level.values(), default=0)}")
    up = upward(graph)
    lines.append(f"  arrows back up a wing: {len(up)}" + "".join(f"\n    {a}" for a in up))
    found = cycles(graph)
    lines.append(f"  cycles: {len(found)}" + "".join(f"\n    {' <-> '.join(c)}" for c in found))
    by_module: dict[str, int] = {}
    for module, _ in ties:
        by_module[module] = by_module.get(module, 0) + 1
    lines.append(
        f"  string ties: {len(ties)}"
        + "".join(f"\n    {n:3d} in {m}" for m, n in sorted(by_module.items()))
    )
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    package = Path(argv[0]) if argv else Path(__file__).resolve().parents[1] / "src" / "vprflow"
    graph = imports(package)
    ties = string_ties(package)
    print(report(graph, ties, package.name))
    stages = f"{package.name}.stages"
    inner = {
        m: {t for t in targets if t.startswith(stages + ".")}
        for m, targets in graph.items()
        if m.startswith(stages + ".")
    }
    print(report(inner, [t for t in ties if t[0].startswith(stages)], stages))
    lookups = dynamic_lookups(package)
    print(f"== lookups by computed name: {len(lookups)}" + "".join(f"\n    {x}" for x in lookups))
    schema = package.parents[1] / "workflow" / "schemas" / "config.schema.yaml"
    if schema.exists():
        enums = re.findall(r"x-enum:\s*[\"']?(vprflow[\w.]*:\w+)", schema.read_text())
        print(f"== the schema's x-enum 'module:CONSTANT' strings (data): {len(enums)}")


if __name__ == "__main__":
    main(sys.argv[1:])
