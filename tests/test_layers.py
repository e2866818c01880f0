"""The package's layers (docs/architecture.md): imports only point down, so the layout shows the
odometry and no cycle creeps in, between parts or between modules. Imports for annotations
only (under ``TYPE_CHECKING``) are not edges; imports inside functions are.

Also a command: ``python tests/test_layers.py`` prints the import cycles among the package's
modules (exit status 1) or that there are none."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "edgevo_jax"

#: top to bottom: each part may import only from parts after it
LAYERS = ["cli", "__init__", "pipeline", "backend", "viz", "runs", "peers", "tracking", "learn",
          "map", "window", "workers", "frontend",
          "image", "datasets", "derive", "solvers", "metrics", "reports", "io", "geometry",
          "_quaternion", "camera_file", "depth_registration", "camera", "config", "programs",
          "determinism", "hostmem", "provenance"]


def _part(module: list[str]) -> str:
    return module[0] if module else "__init__"


def _runtime_imports(tree: ast.AST):
    """ImportFrom nodes outside ``if TYPE_CHECKING:`` blocks."""
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            skip.update(id(n) for n in ast.walk(node))
    return [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and id(n) not in skip]


def _edges() -> set[tuple[str, str]]:
    edges = set()
    for path in PKG.rglob("*.py"):
        rel = list(path.relative_to(PKG).with_suffix("").parts)
        package = rel[:-1]  # the package the module sits in (for __init__: itself)
        here = _part(rel if rel[-1] != "__init__" else rel[:-1])
        for node in _runtime_imports(ast.parse(path.read_text())):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                target = base + (node.module.split(".") if node.module else [])
            elif node.module and node.module.split(".")[0] == "edgevo_jax":
                target = node.module.split(".")[1:]
            else:
                continue
            there = _part(target)
            if there != here:
                edges.add((here, there))
    return edges


def test_every_part_is_in_a_layer():
    parts = {_part(list(p.relative_to(PKG).with_suffix("").parts))
             for p in PKG.rglob("*.py") if "data" not in p.relative_to(PKG).parts}
    parts = {"__init__" if p == "__init__" else p for p in parts}
    assert parts <= set(LAYERS), sorted(parts - set(LAYERS))


def test_imports_only_point_down():
    rank = {name: i for i, name in enumerate(LAYERS)}
    up = sorted((a, b) for a, b in _edges() if rank[b] <= rank[a])
    assert not up, f"imports pointing up (importer, imported): {up}"


def test_the_check_sees_imports():
    """The walk finds real edges (a broken walk would pass the test above vacuously)."""
    edges = _edges()
    assert ("tracking", "frontend") in edges and ("frontend", "image") in edges
    assert ("window", "solvers") in edges and ("cli", "runs") in edges


# -- module-level import cycles -------------------------------------------------------------


def _is_type_checking(test: ast.expr) -> bool:
    return getattr(test, "id", None) == "TYPE_CHECKING" or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _runtime_import_nodes(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Import and ImportFrom nodes anywhere (module level, functions, classes) outside
    ``if TYPE_CHECKING:`` blocks."""
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            skip.update(id(n) for n in ast.walk(node))
    return [n for n in ast.walk(tree)
            if isinstance(n, ast.Import | ast.ImportFrom) and id(n) not in skip]


def _module_files() -> dict[str, Path]:
    """Every module of the package by dotted name (a package by its own name)."""
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        parts = path.relative_to(PKG.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The module ``name`` is, or the closest package above it (a name that is not a module:
    an attribute of the module before it)."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _imported(node: ast.Import | ast.ImportFrom, module: str, is_package: bool,
              modules: dict[str, Path]) -> set[str]:
    """The package's modules one import statement of ``module`` runs: ``from .x import y``
    and ``from edgevo_jax.x import y`` give ``x.y`` when that is a module, else ``x``;
    ``import edgevo_jax.x`` gives ``x``."""
    top = PKG.name
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names if a.name == top or a.name.startswith(top + ".")]
    else:
        if node.level:
            package = (module if is_package else module.rpartition(".")[0]).split(".")
            base = ".".join(package[: len(package) - (node.level - 1)]
                            + ([node.module] if node.module else []))
        elif node.module == top or (node.module or "").startswith(top + "."):
            base = node.module
        else:
            return set()
        names = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                 for a in node.names]
    return {m for m in (_resolve(n, modules) for n in names) if m and m != module}


def import_graph() -> dict[str, set[str]]:
    """module -> the package's modules it imports, at run time (module level or inside a
    function; not under ``TYPE_CHECKING``). A package's ``__init__`` is the package's name;
    the parent packages Python imports on the way are not edges."""
    modules = _module_files()
    return {name: set().union(*(_imported(node, name, path.name == "__init__.py", modules)
                                for node in _runtime_import_nodes(ast.parse(path.read_text()))))
            for name, path in modules.items()}


def _tangles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected parts of ``graph`` that hold a cycle (Tarjan's algorithm), each
    sorted, in order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    parts: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                part.append(w)
                if w == v:
                    break
            if len(part) > 1 or v in graph.get(v, ()):
                parts.append(sorted(part))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(parts)


def _cycle(graph: dict[str, set[str]], part: list[str]) -> list[str]:
    """The shortest cycle ``[a, b, ..., a]`` through the first module of a tangle."""
    members, start = set(part), part[0]
    paths, queue = {start: [start]}, [start]
    while queue:  # breadth first from start, within the part, back to start
        v = queue.pop(0)
        nxt = sorted(w for w in graph.get(v, ()) if w in members)
        if start in nxt:
            return paths[v] + [start]
        for w in nxt:
            if w not in paths:
                paths[w] = paths[v] + [w]
                queue.append(w)
    raise AssertionError(f"no cycle through {start} in {part}")  # a tangle always has one


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle ``[a, b, ..., a]`` per tangle of ``graph`` (modules that all reach each
    other through imports); empty when the imports form no cycle."""
    return [_cycle(graph, part) for part in _tangles(graph)]


def _describe_cycles(graph: dict[str, set[str]]) -> str:
    lines = []
    for part in _tangles(graph):
        cycle = _cycle(graph, part)
        rest = sorted(set(part) - set(cycle))
        lines.append("import cycle: " + " -> ".join(cycle)
                     + (f" (tangled with it: {', '.join(rest)})" if rest else ""))
    return "\n".join(lines)


def test_no_import_cycle():
    """No module imports a module that imports it back, directly or through others, at module
    level or inside a function (``python tests/test_layers.py`` prints the cycles)."""
    graph = import_graph()
    assert not import_cycles(graph), "\n" + _describe_cycles(graph)


def test_the_cycle_check_sees_imports_and_cycles():
    """The graph has the imports made inside functions and leaves out those for annotations
    only; the search finds a cycle, and only a cycle (a broken check would pass vacuously)."""
    graph = import_graph()
    assert len(graph) > 50 and "edgevo_jax.datasets" in graph
    assert "edgevo_jax.datasets.bag" in graph["edgevo_jax.datasets.source"]  # in open_source
    assert "edgevo_jax.runs.sweep" in graph["edgevo_jax.viz.sweep"]
    assert "edgevo_jax.datasets.base" not in graph["edgevo_jax.datasets.groundtruth"]
    assert import_cycles({"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set(), "e": {"a"}}) \
        == [["a", "b", "c", "a"]]
    assert import_cycles({"a": {"a"}}) == [["a", "a"]]
    assert import_cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def main() -> int:
    """Print the import cycles among the package's modules, or that there are none."""
    graph = import_graph()
    if import_cycles(graph):
        print(_describe_cycles(graph))
        return 1
    print(f"no import cycle among {len(graph)} modules")
    return 0


if __name__ == "__main__":
    sys.exit(main())
