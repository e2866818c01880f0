"""The package's layers (DESIGN.md): imports only point down, so the layout shows the
odometry and no cycle creeps in. Imports for annotations only (under ``TYPE_CHECKING``) are
not edges."""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "edgevo_jax"

#: top to bottom: each part may import only from parts after it
LAYERS = ["cli", "__init__", "viz", "pipeline", "peers", "learn", "backend", "frontend",
          "image", "datasets", "derive", "solvers", "metrics", "reports", "io", "geometry",
          "_quaternion", "camera", "config", "programs", "determinism", "hostmem",
          "provenance"]


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
    assert ("pipeline", "frontend") in edges and ("frontend", "image") in edges
    assert ("backend", "solvers") in edges and ("cli", "pipeline") in edges
