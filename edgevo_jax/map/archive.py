"""A keyframe map in a file: one versioned format, no pickle, written atomically.

The file is a NumPy ``.npz`` archive (``numpy.savez``, read with ``allow_pickle=False``).
``header``, the UTF-8 bytes of a JSON object, says what it is (``format`` ``"edgevo-map"``,
``version``), which library wrote it, the camera (intrinsics, image size), the settings that
shape a keyframe (``settings``, ``map_settings``: depth points, the ferns' count, tests and
seed) and how many keyframes it holds. The other arrays hold every keyframe in the order it
joined the map: its id, timestamp, pose T_world_kf, whether it is anchored, the best inlier
share a frame had against it and its fern code, one row each; its selected edges
(``KeyframeEdges``, one array per field, each keyframe with its own slot count), edge points
and ORB landmarks, ragged (concatenated, with ``.offsets``); and the covisibility of every
pair of keyframes that share a view, as the map had it (the weights taken when each keyframe
joined); and the pose graph's edges (``map.loops.Edge``: each keyframe's edge from its parent
and the loops kept, with what they measured and their information). docs/map-file.md
describes every array.

``save_map`` writes to a temporary file beside the target and renames it over the target
(``os.replace``): a crash leaves the old file or none. ``load_map`` refuses, with a
``MapFileError`` naming the file and the problem and before any keyframe is built, a file
that is not a map, a map of another format version, one truncated or corrupt, and one made
for another camera or with settings of another shape.
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..frontend.features import Landmarks
from ..frontend.selection import KeyframeEdges
from .loops import Edge
from .poses import Poses
from .recognition import NUM_FERNS, SEED, TESTS
from .store import KeyframeMap, MapKeyframe

__all__ = ["FORMAT", "VERSION", "MapFileError", "Saved", "library_version", "load_map",
           "map_settings", "read_cloud", "read_header", "read_keyframe_table", "save_map"]

FORMAT = "edgevo-map"
#: the format's version, which ``save_map`` writes
VERSION = 2
#: the versions a reader takes: 1 had no pose graph (loaded with none), any other is refused
READABLE = (1, 2)
#: intrinsics of a map and of a run agree within this (px)
INTRINSICS_TOL_PX = 1e-3
_EDGE_FIELDS = KeyframeEdges._fields
_OPTIONAL = ("mag", "depth_pts", "depth_normals", "disc")


class MapFileError(ValueError):
    """A map file that cannot be used here: the message names the file and the problem."""


class Saved(NamedTuple):
    """A map read from a file: its keyframes (``kmap``) and its pose graph's edges."""

    kmap: KeyframeMap
    edges: list[Edge]


def library_version() -> str:
    """This library's version as installed (``importlib.metadata``; "unknown" when it is
    run from a tree that is not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("edgevo_jax")
    except PackageNotFoundError:
        return "unknown"


def map_settings(config: Config) -> dict[str, Any]:
    """The settings that shape a map's keyframes, which a run that loads it must share: the
    depth residual's points per keyframe and the ferns' count, tests and seed (place
    recognition compares codes fern by fern)."""
    return {"depth_points": config.depth_points if config.depth_residual else 0,
            "ferns": NUM_FERNS, "fern_tests": TESTS, "fern_seed": SEED}


def save_map(path: str | os.PathLike[str], kmap: KeyframeMap, *,
             settings: Mapping[str, Any], library: str, edges: Sequence[Edge] = ()) -> int:
    """Write ``kmap`` (every keyframe it holds, with its pose as it is now) and the pose
    graph's measured ``edges`` between its keyframes to ``path`` atomically (module doc);
    ``settings``: the map-shaping settings (``map_settings``), ``library``: the writer's
    version. Returns the file's size in bytes. ValueError for a map with no keyframe, or an
    edge unmeasured or to a keyframe it does not hold."""
    keys = kmap.ids
    if not keys:
        raise ValueError("the keyframe map holds no keyframe: nothing to save")
    entries = [kmap[k] for k in keys]
    arrays = _keyframe_arrays(entries)
    pairs = [(a, b, wgt) for a in keys for b, wgt in sorted(kmap.covisible(a).items())
             if a < b]
    arrays["covisible"] = np.array([(a, b) for a, b, _ in pairs], np.int64).reshape(-1, 2)
    arrays["covisible.weight"] = np.array([wgt for *_, wgt in pairs], np.float64)
    arrays.update(_graph_arrays(edges, set(keys)))
    h, w = kmap.shape
    header = {"format": FORMAT, "version": VERSION, "library": library,
              "camera": {"intrinsics": [float(v) for v in kmap.intrinsics], "width": int(w),
                         "height": int(h)},
              "settings": dict(settings), "keyframes": len(entries)}
    arrays["header"] = np.frombuffer(json.dumps(header, sort_keys=True).encode(), np.uint8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        # the old file's permissions, else a plain file's (mkstemp makes it owner-only)
        os.chmod(tmp, path.stat().st_mode & 0o777 if path.exists() else 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path.stat().st_size


def read_header(path: str | os.PathLike[str]) -> dict:
    """The header of the map file at ``path`` (module doc), checked to be this format's
    version; MapFileError otherwise."""
    with _opened(path) as data:
        return _header(path, data)


def read_keyframe_table(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """The keyframes' ids, timestamps, poses and anchored flags of the map file at
    ``path`` (one row each), checked as ``load_map`` checks them, without building the map
    (``edgevo map info``)."""
    with _opened(path) as data:
        header = _header(path, data)
        n = int(header["keyframes"])
        out = {}
        for name, shape in (("id", (n,)), ("timestamp", (n,)), ("pose", (n, 4, 4)),
                            ("anchored", (n,))):
            out[name] = data[name]
            if out[name].shape != shape:
                raise MapFileError(f"{path}: array {name!r} has shape {out[name].shape}, a "
                                   f"map of {n} keyframes needs {shape}")
    return out


def read_cloud(path: str | os.PathLike[str]) -> tuple[np.ndarray, list[np.ndarray]]:
    """The keyframes' poses (N, 4, 4) T_world_kf and their edges' points, each (P_i, 3)
    float32 in its camera (m), of the map file at ``path`` (``map.export``)."""
    table = read_keyframe_table(path)
    with _opened(path) as data:
        arrays = {k: data[k] for k in ("points", "points.offsets")}
    n = len(table["pose"])
    if arrays["points.offsets"].shape != (n + 1,) or arrays["points"].ndim != 2 or \
            arrays["points"].shape[1] != 3:
        raise MapFileError(f"{path}: the ragged array 'points' does not add up")
    return table["pose"], [_row(path, arrays, "points", i) for i in range(n)]


def load_map(path: str | os.PathLike[str], *, intrinsics: Intrinsics | None = None,
             shape: tuple[int, int] | None = None,
             settings: Mapping[str, Any] | None = None, max_keyframes: int,
             poses: Poses | None = None) -> Saved:
    """The keyframe map saved at ``path`` and its pose graph's edges, for a run of a camera
    with ``intrinsics`` and frames of ``shape`` (H, W) and the map-shaping ``settings`` (each
    None: not checked); its keyframes' poses join ``poses`` (a new record where None).
    MapFileError (module doc) for a file that does not fit."""
    with _opened(path) as data:
        header = _header(path, data)
        _check_fit(path, header, intrinsics, shape, settings)
        arrays = {k: data[k] for k in data.files if k != "header"}
    entries = _entries(path, header, arrays)
    cam = header["camera"]
    kmap = KeyframeMap(Intrinsics(*cam["intrinsics"]), (cam["height"], cam["width"]),
                       max_keyframes=max(max_keyframes, len(entries)), poses=poses)
    for kf in entries:
        kmap.add(kf)
    pairs, weights = arrays.get("covisible"), arrays.get("covisible.weight")
    if pairs is None or weights is None or pairs.ndim != 2 or pairs.shape[1:] != (2,) \
            or len(pairs) != len(weights) or not set(pairs.ravel().tolist()) <= set(kmap.ids):
        raise MapFileError(f"{path}: the covisibility arrays are missing or do not fit")
    links: dict[int, dict[int, float]] = {k: {} for k in kmap.ids}
    for (a, b), wgt in zip(pairs.tolist(), weights.tolist(), strict=True):
        links[a][b] = links[b][a] = wgt
    for key, weights_of in links.items():
        kmap.covisible_as(key, weights_of)
    edges = [] if header["version"] == 1 else _graph(path, arrays, set(kmap.ids))
    return Saved(kmap, edges)


# -- writing ----------------------------------------------------------------------------------
def _keyframe_arrays(entries: list[MapKeyframe]) -> dict[str, np.ndarray]:
    out = {"id": np.array([e.id for e in entries], np.int64),
           "timestamp": np.array([e.timestamp for e in entries], np.float64),
           "pose": np.stack([np.asarray(e.pose, np.float64) for e in entries]),
           "anchored": np.array([e.anchored for e in entries], bool),
           "share": np.array([e.share for e in entries], np.float64),
           "described": np.array([e.code is not None for e in entries], bool),
           "code": np.stack([np.zeros(NUM_FERNS, np.uint8) if e.code is None
                             else np.asarray(e.code, np.uint8) for e in entries])}
    for name in _EDGE_FIELDS:  # each keyframe's own slot count: along the last axis
        values = [getattr(e.edges, name) for e in entries]
        present = [v is not None for v in values]
        if any(present) and not all(present):
            raise ValueError(f"keyframes differ in whether their edges have {name!r}")
        if all(present):
            out.update(_ragged(f"edges.{name}", [np.moveaxis(np.asarray(v), -1, 0)
                                                 for v in values]))
    out.update(_ragged("points", [np.asarray(e.points, np.float32).T for e in entries]))
    has = [e.landmarks is not None for e in entries]
    out["landmarks"] = np.array(has, bool)
    lms = [e.landmarks for e in entries if e.landmarks is not None]
    width = lms[0].descriptors.shape[1] if lms else 32
    empty = Landmarks(np.zeros((0, 3)), np.zeros((0, width), np.uint8),
                      np.zeros((0, 2), np.float32))
    lms = [e.landmarks if e.landmarks is not None else empty for e in entries]
    for field in Landmarks._fields:
        out.update(_ragged(f"landmarks.{field}", [np.asarray(getattr(lm, field)) for lm in lms]))
    return out


def _graph_arrays(edges: Sequence[Edge], keys: set[int]) -> dict[str, np.ndarray]:
    """The pose graph's edges as arrays: ``graph.pairs`` (M, 2) int64 (older, newer),
    ``graph.measured`` (M, 4, 4), ``graph.information`` (M, 6, 6), ``graph.loop`` (M,)."""
    for e in edges:
        if e.measured is None or e.i not in keys or e.j not in keys:
            raise ValueError(f"the pose graph's edge {e.i}-{e.j} is unmeasured or leaves the "
                             "map")
    return {"graph.pairs": np.array([(e.i, e.j) for e in edges], np.int64).reshape(-1, 2),
            "graph.measured": np.array([e.measured for e in edges], np.float64
                                       ).reshape(-1, 4, 4),
            "graph.information": np.array([e.information for e in edges], np.float64
                                          ).reshape(-1, 6, 6),
            "graph.loop": np.array([e.loop for e in edges], bool)}


def _ragged(name: str, parts: list[np.ndarray]) -> dict[str, np.ndarray]:
    """Arrays of rows (n_i, ...) as one concatenation and the offsets (len + 1,)."""
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)
    return {name: np.concatenate(parts), f"{name}.offsets": offsets}


# -- reading ----------------------------------------------------------------------------------
class _opened:
    """``np.load`` of a map file as a context, every failure to read it a MapFileError."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)

    def __enter__(self):
        if not self.path.is_file():
            raise MapFileError(f"{self.path}: no such map file")
        self.file = open(self.path, "rb")  # noqa: SIM115 (closed in __exit__ or below)
        if self.file.read(4) != b"PK\x03\x04":  # a zip archive's first bytes
            self.file.close()
            raise MapFileError(f"{self.path}: not a map file (a map is a .npz archive, as "
                               "--save-map writes it; this file is not one)")
        self.file.seek(0)
        try:
            self.data = np.load(self.file, allow_pickle=False)
        except (zipfile.BadZipFile, ValueError, OSError, EOFError) as err:
            self.file.close()
            raise MapFileError(f"{self.path}: not a readable map file (truncated or corrupt: "
                               f"{err})") from err
        if not hasattr(self.data, "files"):
            self.file.close()
            raise MapFileError(f"{self.path}: not a map file (a single array, not an archive)")
        return _Reader(self.path, self.data)

    def __exit__(self, *exc) -> None:
        self.data.close()
        self.file.close()


class _Reader:
    """The archive's arrays by name; reading one that is damaged is a MapFileError."""

    def __init__(self, path: Path, data) -> None:
        self.path, self._data, self.files = path, data, list(data.files)

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self.files:
            raise MapFileError(f"{self.path}: the map file has no {name!r} array (truncated "
                               "or written by something else)")
        try:
            return self._data[name]
        except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as err:
            raise MapFileError(f"{self.path}: array {name!r} cannot be read (truncated or "
                               f"corrupt: {err})") from err


def _header(path, data: _Reader) -> dict:
    try:
        header = json.loads(bytes(data["header"]).decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise MapFileError(f"{path}: the map file's header is not JSON ({err})") from err
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise MapFileError(f"{path}: not an edgevo map file (format "
                           f"{header.get('format') if isinstance(header, dict) else None!r})")
    if header.get("version") not in READABLE:
        raise MapFileError(f"{path}: map file format version {header.get('version')!r}; this "
                           f"library ({FORMAT} version {VERSION}) reads versions "
                           f"{', '.join(map(str, READABLE))}")
    for key in ("camera", "settings", "keyframes", "library"):
        if key not in header:
            raise MapFileError(f"{path}: the map file's header has no {key!r}")
    return header


def _check_fit(path, header: dict, intrinsics: Intrinsics | None,
               shape: tuple[int, int] | None, settings: Mapping[str, Any] | None) -> None:
    """MapFileError where the map's camera or settings are not the run's."""
    cam = header["camera"]
    if shape is not None and (int(shape[0]), int(shape[1])) != (cam["height"], cam["width"]):
        raise MapFileError(f"{path}: the map was made from {cam['width']}x{cam['height']} "
                           f"images, this run's are {shape[1]}x{shape[0]}: another camera")
    if intrinsics is not None:
        mine = np.asarray([float(v) for v in intrinsics])
        theirs = np.asarray(cam["intrinsics"], np.float64)
        if mine.shape != theirs.shape or np.max(np.abs(mine - theirs)) > INTRINSICS_TOL_PX:
            raise MapFileError(f"{path}: the map's camera has intrinsics (fx, fy, cx, cy) "
                               f"{tuple(theirs)}, this run's {tuple(mine)}: another camera")
    if settings is not None:
        differ = {k: (header["settings"].get(k), v) for k, v in settings.items()
                  if header["settings"].get(k) != v}
        if differ:
            said = ", ".join(f"{k} {a!r} in the map, {b!r} here" for k, (a, b) in differ.items())
            raise MapFileError(f"{path}: the map was made with other settings: {said}")


def _entries(path, header: dict, a: dict[str, np.ndarray]) -> list[MapKeyframe]:
    """The keyframes of the arrays ``a``, checked to agree with each other."""
    n = int(header["keyframes"])
    want = {"id": (n,), "timestamp": (n,), "pose": (n, 4, 4), "anchored": (n,),
            "share": (n,), "described": (n,), "code": (n, NUM_FERNS), "landmarks": (n,),
            "points.offsets": (n + 1,)}
    for name, shp in want.items():
        if name not in a or a[name].shape != shp:
            got = a[name].shape if name in a else None
            raise MapFileError(f"{path}: array {name!r} has shape {got}, a map of {n} "
                               f"keyframes needs {shp}")
    if not np.all(np.isfinite(a["pose"])) or not np.all(np.isfinite(a["timestamp"])):
        raise MapFileError(f"{path}: a keyframe's pose or timestamp is not finite")
    for name in ("uv", "rho", "grad", "valid"):
        if f"edges.{name}" not in a:
            raise MapFileError(f"{path}: the keyframes' edges ({name!r}) are missing")
    present = [name for name in _EDGE_FIELDS if f"edges.{name}" in a]
    out = []
    for i in range(n):
        edges = KeyframeEdges(**{k: np.ascontiguousarray(np.moveaxis(
            _row(path, a, f"edges.{k}", i), 0, -1)) for k in present})
        lm = None
        if a["landmarks"][i]:
            lm = Landmarks(*(_row(path, a, f"landmarks.{f}", i) for f in Landmarks._fields))
        out.append(MapKeyframe(
            int(a["id"][i]), float(a["timestamp"][i]), a["pose"][i].copy(), edges,
            np.ascontiguousarray(_row(path, a, "points", i).T), lm,
            a["code"][i].copy() if a["described"][i] else None, bool(a["anchored"][i]),
            float(a["share"][i])))
    return out


def _graph(path, a: dict[str, np.ndarray], keys: set[int]) -> list[Edge]:
    """The pose graph's edges of the arrays ``a`` (``_graph_arrays``), checked to fit
    together and to join keyframes of the map (``keys``)."""
    names = ("graph.pairs", "graph.measured", "graph.information", "graph.loop")
    if any(n not in a for n in names):
        raise MapFileError(f"{path}: the pose graph's arrays are missing")
    pairs, measured, info, loop = (a[n] for n in names)
    m = len(pairs)
    if pairs.shape != (m, 2) or measured.shape != (m, 4, 4) or info.shape != (m, 6, 6) \
            or loop.shape != (m,):
        raise MapFileError(f"{path}: the pose graph's arrays do not fit together")
    if not set(pairs.ravel().tolist()) <= keys:
        raise MapFileError(f"{path}: a pose graph edge joins a keyframe the map does not hold")
    if not (np.all(np.isfinite(measured)) and np.all(np.isfinite(info))):
        raise MapFileError(f"{path}: a pose graph edge is not finite")
    return [Edge(int(i), int(j), measured[n].copy(), info[n].copy(), bool(loop[n]))
            for n, (i, j) in enumerate(pairs.tolist())]


def _row(path, a: dict[str, np.ndarray], name: str, i: int) -> np.ndarray:
    offsets = a.get(f"{name}.offsets")
    values = a.get(name)
    if offsets is None or values is None or offsets[-1] != len(values) or \
            np.any(np.diff(offsets) < 0) or len(offsets) <= i + 1:
        raise MapFileError(f"{path}: the ragged array {name!r} does not add up")
    return values[offsets[i]:offsets[i + 1]]
