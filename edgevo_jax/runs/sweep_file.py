"""A sweep file read and checked (the format: ``pipeline.sweep``'s doc): its sources, frame
steps, seeds and grid of ``Config`` fields as a ``Sweep``, and the runs it lists, each with
the stable key its outputs are named by. A function of the file alone: nothing is opened or
run here (``pipeline.sweep`` does that)."""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import os
import re
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..config import Config
from ..datasets.source import REALSENSE
from ..io import json_safe
from .configs import _as_items

#: keys of a sweep file's top level
SWEEP_KEYS = ("sources", "frame_steps", "seeds", "max_frames", "chunk", "base", "grid")
#: keys of a source table beside ``path``
SOURCE_KEYS = ("camera", "intrinsics", "depth_factor", "rgb_topic", "depth_topic",
               "info_topic", "groundtruth")


class SweepError(ValueError):
    """A sweep file that cannot be run as written; the message names the file and the key."""


@dataclass(frozen=True)
class SweepSource:
    """One source of a sweep: ``path`` (resolved against the sweep file's folder) and
    ``options`` for ``open_source`` (sorted (name, value) pairs; paths resolved);
    ``written``: the source as the file gives it (part of the runs' keys)."""

    path: str
    options: tuple[tuple[str, object], ...]
    written: str

    @property
    def label(self) -> str:
        """The source's folder or file name."""
        return Path(self.path).name


@dataclass(frozen=True)
class SweepRun:
    """One run: indices into the sweep's ``sources`` and ``settings``, its frame step and
    seed, its whole ``config`` and its stable ``key`` (file names under the output folder)."""

    key: str
    source: int
    frame_step: int
    seed: int
    setting: int
    config: Config


@dataclass(frozen=True)
class Sweep:
    """A parsed sweep file (the format: ``pipeline.sweep``'s doc). ``settings``: the grid's
    combinations as (field, value as written) pairs, each applied to ``base``."""

    path: Path
    sources: tuple[SweepSource, ...]
    frame_steps: tuple[int, ...]
    seeds: tuple[int, ...]
    settings: tuple[tuple[tuple[str, object], ...], ...]
    base: Config
    max_frames: int | None
    chunk: int

    def setting_label(self, setting: int) -> str:
        """``field=value`` of a setting, comma-separated ("base" for the base alone)."""
        items = self.settings[setting]
        return ", ".join(f"{k}={_show(v)}" for k, v in items) if items else "base"

    def runs(self) -> list[SweepRun]:
        """Every run, ordered source, frame step, seed, setting."""
        configs = [self.base.with_overrides(_as_items(dict(s))) for s in self.settings]
        out = []
        for (src, source), step, seed, (k, config) in itertools.product(
                enumerate(self.sources), self.frame_steps, self.seeds, enumerate(configs)):
            config = config.replace(seed=seed)
            digest = hashlib.sha256(json.dumps(json_safe({
                "source": source.written, "frame_step": step, "max_frames": self.max_frames,
                "config": dataclasses.asdict(config)}), sort_keys=True).encode()).hexdigest()
            name = re.sub(r"[^A-Za-z0-9_.-]", "_", source.label)
            out.append(SweepRun(f"{name}-step{step}-seed{seed}-{digest[:12]}", src, step,
                                seed, k, config))
        return out


def load_sweep(path: str | os.PathLike[str]) -> Sweep:
    """Parse and check a sweep file (the format: ``pipeline.sweep``'s doc). SweepError naming
    the file and the key for anything that cannot run: TOML syntax, an unknown key or
    ``Config`` field, a value of the wrong type, an empty list or grid, a source that does not
    exist; sources are only checked to exist here (``pipeline.sweep.open_sources`` opens
    them)."""
    path = Path(path)
    try:
        spec = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"sweep file not found: {path}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise SweepError(f"{path}: not valid TOML ({err})") from None

    def fail(message: str) -> SweepError:
        return SweepError(f"{path}: {message}")

    unknown = sorted(set(spec) - set(SWEEP_KEYS))
    if unknown:
        raise fail(f"unknown key(s) {', '.join(unknown)}; a sweep file has "
                   f"{', '.join(SWEEP_KEYS)}")
    if "sources" not in spec:
        raise fail("no sources: give sources = [\"path\", ...]")
    sources = tuple(_source(item, path.parent, fail) for item in _list(spec, "sources", fail))
    steps = tuple(_positive(v, "frame_steps", fail)
                  for v in _list(spec, "frame_steps", fail, default=[1]))
    base_items = spec.get("base", {})
    if not isinstance(base_items, dict):
        raise fail("[base] must be a table of Config fields")
    try:
        base = Config().with_overrides(_as_items(base_items))
    except ValueError as err:
        raise fail(f"[base]: {err}") from None
    seeds = tuple(_whole(v, "seeds", fail)
                  for v in _list(spec, "seeds", fail, default=[base.seed]))
    grid = spec.get("grid", None)
    if grid is None:
        settings: tuple = ((),)
    else:
        if not isinstance(grid, dict) or not grid:
            raise fail("[grid] is empty: give Config fields lists of values, or leave [grid] "
                       "out to run the base settings alone")
        if "seed" in grid:
            raise fail("[grid] seed: give the seeds as seeds = [...] at the top level")
        for key, values in grid.items():
            if not isinstance(values, list) or not values:
                raise fail(f"[grid] {key} must be a non-empty list of values, got {values!r}")
        settings = tuple(tuple(zip(grid, combo, strict=True))
                         for combo in itertools.product(*grid.values()))
        for items in settings:
            try:
                base.with_overrides(_as_items(dict(items)))
            except ValueError as err:
                raise fail(f"[grid]: {err}") from None
    max_frames = spec.get("max_frames")
    if max_frames is not None:
        max_frames = _positive(max_frames, "max_frames", fail)
    chunk = _positive(spec.get("chunk", 2), "chunk", fail)
    if len(set(steps)) != len(steps) or len(set(seeds)) != len(seeds):
        raise fail("frame_steps and seeds must not repeat a value")
    return Sweep(path, sources, steps, seeds, settings, base, max_frames, chunk)


def _list(spec: dict, key: str, fail: Callable[[str], SweepError], *,
          default: list | None = None) -> list:
    values = spec.get(key, default)
    if not isinstance(values, list) or not values:
        raise fail(f"{key} must be a non-empty list, got {values!r}")
    return values


def _whole(value: object, key: str, fail: Callable[[str], SweepError]) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise fail(f"{key}: expected whole numbers, got {value!r}")
    return value


def _positive(value: object, key: str, fail: Callable[[str], SweepError]) -> int:
    if _whole(value, key, fail) < 1:
        raise fail(f"{key}: expected whole numbers >= 1, got {value!r}")
    return int(value)  # type: ignore[arg-type]


def _source(item: object, root: Path, fail: Callable[[str], SweepError]) -> SweepSource:
    """A source entry: a path string or a table with ``path`` and ``SOURCE_KEYS``."""
    table = {"path": item} if isinstance(item, str) else item
    if not isinstance(table, dict) or not isinstance(table.get("path"), str):
        raise fail(f"sources: expected a path or a table with path = \"...\", got {item!r}")
    unknown = sorted(set(table) - {"path", *SOURCE_KEYS})
    if unknown:
        raise fail(f"source {table['path']}: unknown key(s) {', '.join(unknown)}; a source "
                   f"has path and {', '.join(SOURCE_KEYS)}")
    text = table["path"]
    if text == REALSENSE or text.startswith(REALSENSE + ":"):
        raise fail(f"source {text}: a live camera cannot be swept (every run must read the "
                   "same frames); record it to a bag and sweep the bag")
    resolved = root / Path(text).expanduser()
    if not resolved.exists():
        raise fail(f"source {text}: not found (looked for {resolved})")
    options = {}
    for key in SOURCE_KEYS:
        if key in table:
            value = table[key]
            if key in ("groundtruth",) or (key == "camera" and isinstance(value, str)
                                           and (root / value).is_file()):
                value = str(root / Path(value).expanduser())
            options[key] = value
    written = json.dumps(table, sort_keys=True)
    return SweepSource(str(resolved), tuple(sorted(options.items())), written)


def _show(value: object) -> str:
    if isinstance(value, list):
        return ",".join(_show(v) for v in value)
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)
