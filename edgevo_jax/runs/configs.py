"""Configurations of a batch from JSON (``load_configs``): a list of objects of ``Config``
overrides or a grid of them (``configs_from_spec``), and what a configuration changes from
the defaults (``changed_fields``)."""

from __future__ import annotations

import dataclasses
import itertools
import json
from pathlib import Path

from ..config import Config

__all__ = ["changed_fields", "configs_from_spec", "load_configs"]


def load_configs(path: str | Path, base: Config | None = None) -> list[Config]:
    """Configurations from a JSON file (see ``configs_from_spec`` for the two forms)."""
    path = Path(path)
    try:
        spec = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err})") from None
    try:
        return configs_from_spec(spec, base)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


def configs_from_spec(spec: list | dict, base: Config | None = None) -> list[Config]:
    """Configurations from a list of objects of Config overrides, e.g.
    ``[{}, {"huber_delta": [2, 2, 2]}]``, or a grid ``{"base": {...}, "grid": {"eta": [0.5,
    0.6], "num_edges": [256, 512]}}`` (every combination, the last key varying fastest),
    applied to ``base`` (default ``Config()``). Values are parsed like ``--set`` (lists for
    tuple fields). ValueError naming the problem for anything else."""
    base = Config() if base is None else base
    if isinstance(spec, dict) and set(spec) <= {"base", "grid"}:
        root = base.with_overrides(_as_items(spec.get("base", {})))
        grid = spec.get("grid", {})
        if not isinstance(grid, dict) or not all(isinstance(v, list) and v
                                                 for v in grid.values()):
            raise ValueError("'grid' must map Config fields to non-empty lists")
        keys = list(grid)
        return [root.with_overrides(_as_items(dict(zip(keys, combo, strict=True))))
                for combo in itertools.product(*(grid[k] for k in keys))]
    if isinstance(spec, list) and spec and all(isinstance(x, dict) for x in spec):
        return [base.with_overrides(_as_items(x)) for x in spec]
    raise ValueError("expected a non-empty list of objects of Config overrides, or "
                     '{"base": {...}, "grid": {"field": [values, ...]}}')


def _as_items(overrides: dict) -> list[str]:
    """{"eta": 0.5, "huber_delta": [2, 2, 2]} -> ["eta=0.5", "huber_delta=2,2,2"]."""
    if not isinstance(overrides, dict):
        raise ValueError(f"expected an object of Config overrides, got {overrides!r}")
    items = []
    for key, value in overrides.items():
        if isinstance(value, list):
            value = ",".join(str(v) for v in value)
        elif isinstance(value, bool):
            value = "true" if value else "false"
        items.append(f"{key}={value}")
    return items


def changed_fields(config: Config, base: Config | None = None) -> dict:
    """The fields of ``config`` that differ from ``base`` (default ``Config()``)."""
    default = Config() if base is None else base
    return {f.name: getattr(config, f.name) for f in dataclasses.fields(config)
            if getattr(config, f.name) != getattr(default, f.name)}
