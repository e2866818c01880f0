"""What benchmarks and experiments write and read on the command line: result files (JSON
with NaN as null, text), markdown tables of formatted numbers, and integer lists such as
``--seeds 0-4`` or ``--steps 1,2,3,5``."""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import re
import shlex
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .io import json_safe
from .provenance import machine_info

__all__ = ["digest", "fmt", "int_list", "markdown_table", "script_parser", "script_record",
           "write_json", "write_text"]

_INT_ITEM = re.compile(r"^(-?\d+)\s*(?:-\s*(-?\d+))?$")


def digest(run, poses: np.ndarray | None = None) -> str:
    """SHA-256 (hex) of a run's float64 poses (``poses``: others of the same frames, e.g. its
    online ones) and each frame's state, reason and keyframe reason: equal digests are equal
    trajectories and verdicts, to the bit."""
    h = hashlib.sha256(np.ascontiguousarray(run.poses if poses is None else poses,
                                            np.float64).tobytes())
    h.update(repr([(r.state, r.reason, r.keyframe) for r in run.results]).encode())
    return h.hexdigest()


def fmt(value: object, spec: str, *, missing: str = "n/a") -> str:
    """``format(value, spec)``, or ``missing`` for None and for a NaN or infinite number."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return missing
    return format(value, spec)


def markdown_table(head: Sequence[str], rows: Sequence[Sequence[str]], *,
                   align: str | None = None) -> str:
    """A markdown table: the ``head`` row, the separator (``align``: one character per
    column, ``r`` right-aligned ``---:``, anything else ``---``; default all ``---``) and one
    line per row of cells, ``| a | b |``. ValueError when a row or ``align`` has another
    number of cells than ``head``."""
    n = len(head)
    align = align or "l" * n
    if len(align) != n or any(len(r) != n for r in rows):
        raise ValueError(f"{n} columns in the head; align {align!r}, rows of "
                         f"{sorted({len(r) for r in rows})} cells")
    line = lambda cells: "| " + " | ".join(cells) + " |"  # noqa: E731
    sep = "|" + "".join("---:|" if a == "r" else "---|" for a in align)
    return "\n".join([line(head), sep, *(line(r) for r in rows)])


def write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` to ``path``, its parent folders made; returns the path."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return out


def write_json(path: str | os.PathLike[str], obj: object, *, indent: int | None = 2) -> Path:
    """Write ``obj`` as JSON to ``path`` (parent folders made): NaN and infinities as null,
    numpy arrays and scalars as lists and numbers (``io.json_safe``), a final newline."""
    return write_text(path, json.dumps(json_safe(obj), indent=indent, allow_nan=False) + "\n")


def script_record(script: str, argv: Sequence[str]) -> dict[str, object]:
    """The head of a script's JSON: the command that made it (``python scripts/<script>``
    and its arguments, shell-quoted) and the machine it ran on (``provenance.machine_info``)."""
    return {"command": shlex.join(["python", f"scripts/{script}", *argv]),
            "machine": machine_info()}


def script_parser(doc: str, *, seeds: str | None = None) -> argparse.ArgumentParser:
    """A script's argument parser, described by the first paragraph of ``doc`` (its module
    doc). With ``seeds`` (e.g. ``"0-4"``, the default of ``--seeds``) the two options of a
    script that runs the tracker over seeds: ``--seeds`` (``int_list``) and ``--set
    KEY=VALUE`` (repeatable: a Config field for every run, as ``edgevo run --set`` takes it)."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    if seeds is not None:
        p.add_argument("--seeds", type=int_list, default=int_list(seeds))
        p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                       help="a Config field for every run, as edgevo run --set takes it")
    return p


def int_list(spec: str) -> list[int]:
    """``"0-4"``, ``"0,1,2"`` or a mix (``"0-2,5"``; ``"-1"`` is minus one) -> the integers
    in order, duplicates dropped. ValueError for an empty list, a malformed item or a
    decreasing range."""
    out: list[int] = []
    for item in (s.strip() for s in spec.split(",")):
        if not item:
            continue
        m = _INT_ITEM.match(item)
        if m is None:
            raise ValueError(f"expected integers like 0-4 or 0,1,2, got {spec!r}")
        a = int(m.group(1))
        b = a if m.group(2) is None else int(m.group(2))
        if b < a:
            raise ValueError(f"decreasing range {item!r} in {spec!r}")
        out.extend(v for v in range(a, b + 1) if v not in out)
    if not out:
        raise ValueError(f"no integers in {spec!r}")
    return out
