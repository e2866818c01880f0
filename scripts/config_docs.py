"""Write docs/config.md, the table of every ``Config`` field, from the docstrings in
edgevo_jax/config.py.

Usage::

    python scripts/config_docs.py            # rewrite docs/config.md
    python scripts/config_docs.py --check    # exit 1 when docs/config.md is stale

Each field of ``Config`` carries the string literal right under it (an attribute docstring):
``[unit] meaning. Why: the reason for the default.``, the unit in brackets (``-`` for none),
the reason optional. Fields are grouped by the ``# --- group ---`` comments above them. A
field without a docstring, or one without ``[unit]`` and a meaning, is an error naming it.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import re
import sys
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[1]
CONFIG_PY = ROOT / "edgevo_jax" / "config.py"
OUT = ROOT / "docs" / "config.md"
_GROUP = re.compile(r"^\s*#\s*---\s*(.+?)\s*---\s*$")
_DOC = re.compile(r"^\[([^\]]+)\]\s+(\S.*)$", re.S)


class FieldDoc(NamedTuple):
    """One field's entry: group (its ``# --- group ---``), name, type and default as written
    in the source, unit, meaning and the reason for the default ("" when none is given)."""

    group: str
    name: str
    type: str
    default: str
    unit: str
    meaning: str
    why: str


def field_docs(source: str, class_name: str = "Config") -> list[FieldDoc]:
    """Every annotated field of ``class_name`` in ``source`` with its docstring, in order.
    ValueError naming the field when one has no docstring or the docstring no unit or
    meaning."""
    tree = ast.parse(source)
    cls = next((n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == class_name),
               None)
    if cls is None:
        raise ValueError(f"no class {class_name} in the source")
    lines = source.splitlines()
    out: list[FieldDoc] = []
    group, seen_line = "", cls.lineno
    body = cls.body
    for k, node in enumerate(body):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        for line in lines[seen_line:node.lineno - 1]:
            m = _GROUP.match(line)
            if m:
                group = m.group(1)
        seen_line = node.lineno
        name = node.target.id
        nxt = body[k + 1] if k + 1 < len(body) else None
        if not (isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)):
            raise ValueError(f"{class_name}.{name} has no docstring: add '\"\"\"[unit] "
                             "meaning. Why: ...\"\"\"' under it")
        text = " ".join(nxt.value.value.split())
        m = _DOC.match(text)
        if m is None:
            raise ValueError(f"{class_name}.{name}: its docstring must start with [unit] and "
                             f"then say what the field means, got {text!r}")
        unit, rest = m.groups()
        meaning, _, why = rest.partition(" Why: ")
        default = "" if node.value is None else ast.get_source_segment(source, node.value)
        out.append(FieldDoc(group, name, ast.unparse(node.annotation), default or "",
                            unit.strip(), meaning.strip(), why.strip()))
    return out


def _cell(text: str) -> str:
    return text.replace("``", "`").replace("|", "\\|")


def render(docs: list[FieldDoc]) -> str:
    """docs/config.md's text."""
    parts = [
        "# `Config` fields\n",
        "Written by `python scripts/config_docs.py` from the docstrings in "
        "`edgevo_jax/config.py`; do not edit by hand. Set a field with "
        "`Config(name=value)`, `config.replace(name=value)` or "
        "`edgevo run --set name=value`; the measurements behind the defaults are in "
        "`docs/decisions.md`. Unit `-`: none (a count's unit names what it counts; "
        "`px of each level`: pixels of that pyramid level).\n",
    ]
    group = None
    for d in docs:
        if d.group != group:
            group = d.group
            parts.append(f"## {group or 'other'}\n")
            parts.append("| field | type | default | unit | meaning | why this default |")
            parts.append("|---|---|---|---|---|---|")
        parts.append(f"| `{d.name}` | `{_cell(d.type)}` | `{_cell(d.default)}` | "
                     f"{_cell(d.unit)} | {_cell(d.meaning)} | {_cell(d.why)} |")
        if docs.index(d) + 1 == len(docs) or docs[docs.index(d) + 1].group != group:
            parts.append("")
    return "\n".join(parts).rstrip() + "\n"


def current() -> str:
    """docs/config.md as the code says it should read; ValueError when a field of ``Config``
    has no entry."""
    sys.path.insert(0, str(ROOT))
    from edgevo_jax.config import Config

    docs = field_docs(CONFIG_PY.read_text())
    names = [f.name for f in dataclasses.fields(Config)]
    if [d.name for d in docs] != names:
        missing = sorted(set(names) - {d.name for d in docs})
        raise ValueError(f"Config fields without an entry: {', '.join(missing) or '(order)'}")
    return render(docs)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--check", action="store_true",
                   help="exit 1 if docs/config.md differs from what the code says")
    args = p.parse_args(argv)
    text = current()
    if args.check:
        stale = not OUT.is_file() or OUT.read_text() != text
        print(f"{OUT} is {'stale: run python scripts/config_docs.py' if stale else 'current'}")
        return int(stale)
    OUT.write_text(text)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
