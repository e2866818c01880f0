"""The camera file: a ``Camera`` as human-readable TOML (docs/camera_file.md), with what an
estimate of it came from, its 1-sigma uncertainties and the keys the data could not tell.

Read with Python's ``tomllib``; written by the small writer here (numbers as Python writes
them, so a written file reads back to the same floats). Host side, no JAX.

Keys (top level): ``fx fy cx cy`` (pixels, required); ``distortion`` (OpenCV k1 k2 p1 p2
[k3 ...]; absent: images undistorted already); ``readout_s`` (s); ``depth_scale`` (true depth
= scale * depth read); ``depth_time_offset_s`` (s, t_depth_true = t_depth_file + offset);
tables ``[depth_pose]`` (``rotation_deg``, a rotation vector in degrees, and
``translation_m``: T_color_depth, the depth camera's pose in the colour camera,
p_color = R p_depth + t), ``[source]`` (free-form), ``[uncertainty]`` (1-sigma per key) and
``[not_observable]`` (a reason per key).
"""

from __future__ import annotations

import json
import math
import os
import tomllib
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np

from .camera import Camera, Intrinsics

__all__ = [
    "CAMERA_KEYS",
    "CameraFile",
    "read_camera_file",
    "read_camera_toml",
    "write_camera_toml",
]

#: The keys an ``[uncertainty]`` or ``[not_observable]`` table may name: the top-level
#: numbers and the two of ``[depth_pose]``.
CAMERA_KEYS = ("fx", "fy", "cx", "cy", "distortion", "readout_s", "depth_scale",
               "depth_time_offset_s", "rotation_deg", "translation_m")
_TOP = ("fx", "fy", "cx", "cy", "distortion", "readout_s", "depth_scale",
        "depth_time_offset_s", "depth_pose", "source", "uncertainty", "not_observable")
_POSE = ("rotation_deg", "translation_m")
_VECTOR = {"distortion": None, "rotation_deg": 3, "translation_m": 3}  # list keys, lengths
_UNITS = {"fx": "pixels", "fy": "pixels", "cx": "pixels (column of the principal point)",
          "cy": "pixels (row of the principal point)",
          "distortion": "OpenCV k1 k2 p1 p2 [k3 ...] of the raw images",
          "readout_s": "s, rolling-shutter readout (0: global shutter)",
          "depth_scale": "true depth = depth_scale * depth read",
          "depth_time_offset_s": "s, t_depth_true = t_depth_file + offset",
          "rotation_deg": "rotation vector of T_color_depth, degrees",
          "translation_m": "translation of T_color_depth, metres"}


class CameraFile(NamedTuple):
    """A camera file's contents: the ``camera`` (validated), ``source`` (what the estimate
    came from: free-form key -> string, number, bool or list), ``uncertainty`` (key of
    ``CAMERA_KEYS`` -> 1-sigma, a float, or a tuple for the list keys) and ``not_observable``
    (key -> why the data could not tell it). The tables are empty dicts when absent."""

    camera: Camera
    source: dict[str, Any]
    uncertainty: dict[str, float | tuple[float, ...]]
    not_observable: dict[str, str]


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _unknown(where: str, keys: Any, known: tuple[str, ...]) -> str | None:
    bad = sorted(set(keys) - set(known))
    if not bad:
        return None
    return (f"unknown key{'s' if len(bad) > 1 else ''} {', '.join(bad)} in {where}; the "
            f"known keys are {', '.join(known)}")


def _number(where: str, key: str, v: Any) -> float:
    if not _is_number(v):
        raise ValueError(f"{where}{key} must be a number, got {v!r}")
    return float(v)


def _numbers(where: str, key: str, v: Any, n: int | None) -> tuple[float, ...]:
    if not (isinstance(v, list) and all(_is_number(x) for x in v)):
        raise ValueError(f"{where}{key} must be a list of numbers, got {v!r}")
    if n is not None and len(v) != n:
        raise ValueError(f"{where}{key} must have {n} numbers, got {len(v)}")
    return tuple(float(x) for x in v)


def _pose_matrix(rotation_deg: tuple[float, ...], translation_m: tuple[float, ...]
                 ) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.deg2rad(np.asarray(rotation_deg, np.float64)))[0]
    T[:3, 3] = translation_m
    return T


def _pose_vectors(T: np.ndarray) -> tuple[list[float], list[float]]:
    R = np.asarray(T[:3, :3], np.float64)
    half = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin, cos = float(np.linalg.norm(half)), 0.5 * (float(np.trace(R)) - 1.0)
    if cos < 0:  # beyond 90 degrees: the antisymmetric part loses the axis' sign near 180
        rvec = cv2.Rodrigues(np.ascontiguousarray(R))[0].ravel()
    else:  # (more accurate than cv2 for the small angles a depth pose has)
        rvec = half * (math.atan2(sin, cos) / sin if sin > 1e-300 else 1.0)
    # 15 digits: the degrees as they were written (0.5, not 0.5000000000000001)
    return [float(f"{x:.15g}") for x in np.rad2deg(rvec)], [float(x) for x in T[:3, 3]]


def _parse(data: dict[str, Any]) -> CameraFile:
    msg = _unknown("the camera file", data, _TOP)
    if msg:
        raise ValueError(msg)
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in data]
    if missing:
        raise ValueError(f"missing {', '.join(missing)} (the camera file needs fx, fy, cx, cy "
                         "in pixels)")
    intr = Intrinsics(*(_number("", k, data[k]) for k in ("fx", "fy", "cx", "cy")))
    dist = _numbers("", "distortion", data["distortion"], None) if "distortion" in data else None
    scalars = {k: _number("", k, data[k]) for k in ("readout_s", "depth_scale",
                                                   "depth_time_offset_s") if k in data}
    pose = None
    if "depth_pose" in data:
        table = data["depth_pose"]
        if not isinstance(table, dict):
            raise ValueError("depth_pose must be a table ([depth_pose] with rotation_deg and "
                             "translation_m)")
        msg = _unknown("[depth_pose]", table, _POSE)
        if msg:
            raise ValueError(msg)
        gone = [k for k in _POSE if k not in table]
        if gone:
            raise ValueError(f"[depth_pose] needs {' and '.join(_POSE)}, {' and '.join(gone)} "
                             "missing")
        pose = _pose_matrix(*(_numbers("depth_pose.", k, table[k], 3) for k in _POSE))
    camera = Camera(intr, dist, scalars.get("readout_s", 0.0), scalars.get("depth_scale", 1.0),
                    scalars.get("depth_time_offset_s", 0.0), pose).validate()

    tables: dict[str, dict[str, Any]] = {}
    for name in ("source", "uncertainty", "not_observable"):
        table = data.get(name, {})
        if not isinstance(table, dict):
            raise ValueError(f"{name} must be a table ([{name}])")
        tables[name] = table
    for name in ("uncertainty", "not_observable"):
        msg = _unknown(f"[{name}]", tables[name], CAMERA_KEYS)
        if msg:
            raise ValueError(msg)
    uncertainty: dict[str, float | tuple[float, ...]] = {}
    for k, v in tables["uncertainty"].items():
        n = len(dist) if k == "distortion" and dist is not None else _VECTOR.get(k)
        val = (_numbers("uncertainty.", k, v, n) if k in _VECTOR
               else (_number("uncertainty.", k, v),))
        if not all(math.isfinite(x) and x >= 0 for x in val):
            raise ValueError(f"uncertainty.{k} must be finite and >= 0 (a 1-sigma), got {v!r}")
        uncertainty[k] = val if k in _VECTOR else val[0]
    for k, v in tables["not_observable"].items():
        if not isinstance(v, str):
            raise ValueError(f"not_observable.{k} must be a string (the reason), got {v!r}")
    return CameraFile(camera, dict(tables["source"]), uncertainty,
                      dict(tables["not_observable"]))


def read_camera_file(path: str | os.PathLike[str]) -> CameraFile:
    """The camera file at ``path`` with its ``[source]``, ``[uncertainty]`` and
    ``[not_observable]`` tables. FileNotFoundError, or ValueError naming the file and what is
    wrong: not TOML, an unknown key (naming the known ones), a missing or mistyped value, a
    camera that ``Camera.validate`` refuses."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"camera file not found: {p}")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{p}: not a TOML camera file (docs/camera_file.md): {err}") from None
    try:
        return _parse(data)
    except ValueError as err:
        raise ValueError(f"{p}: {err}") from None


def read_camera_toml(path: str | os.PathLike[str]) -> Camera:
    """The ``Camera`` of the camera file at ``path`` (``read_camera_file`` without the
    tables; the same errors)."""
    return read_camera_file(path).camera


def _toml_value(v: Any, where: str) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        x = float(v)
        if not math.isfinite(x):
            raise ValueError(f"{where} must be finite, got {x}")
        return repr(x)
    if isinstance(v, str):
        return json.dumps(v).replace("\x7f", "\\u007f")
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x, where) for x in v) + "]"
    raise ValueError(f"{where}: cannot write a {type(v).__name__} to TOML (strings, numbers, "
                     "booleans and lists of them)")


def _toml_key(k: str) -> str:
    if not isinstance(k, str) or not k:
        raise ValueError(f"table keys must be non-empty strings, got {k!r}")
    bare = all(c.isascii() and (c.isalnum() or c in "_-") for c in k)
    return k if bare else json.dumps(k)


def write_camera_toml(
    path: str | os.PathLike[str],
    camera: Camera,
    *,
    source: dict[str, Any] | None = None,
    uncertainty: dict[str, float | tuple[float, ...]] | None = None,
    observable: dict[str, str] | None = None,
) -> Path:
    """Write ``camera`` (validated first) as a camera file at ``path``, which
    ``read_camera_file`` reads back to the same numbers (the depth pose through its rotation
    vector: to ~1e-15). ``source``: what the estimate came from (key -> string, number,
    bool or list of them); ``uncertainty``: 1-sigma per key of ``CAMERA_KEYS``;
    ``observable``: key -> the reason the data could not tell it (the ``[not_observable]``
    table). Every key is written, defaults included, with its unit as a comment. Returns the
    path. ValueError for a camera ``Camera.validate`` refuses or a table the reader would."""
    cam = camera.validate()
    fx, fy, cx, cy = cam.intrinsics
    lines = ["# edgevo camera file (docs/camera_file.md)"]

    def put(key: str, value: Any, where: str = "") -> None:
        lines.append(f"{key} = {_toml_value(value, where + key)}  # {_UNITS[key]}")

    for key, value in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)):
        put(key, value)
    if cam.distortion is not None:
        put("distortion", list(cam.distortion))
    put("readout_s", cam.readout_s)
    put("depth_scale", cam.depth_scale)
    put("depth_time_offset_s", cam.depth_time_offset_s)
    if cam.T_color_depth is not None:
        lines += ["", "[depth_pose]  # T_color_depth: p_color = R p_depth + t"]
        rot, trans = _pose_vectors(cam.T_color_depth)
        put("rotation_deg", rot, "depth_pose.")
        put("translation_m", trans, "depth_pose.")
    for name, table in (("source", source), ("uncertainty", uncertainty),
                        ("not_observable", observable)):
        if table:
            lines += ["", f"[{name}]"]
            lines += [f"{_toml_key(k)} = {_toml_value(v, f'{name}.{k}')}"
                      for k, v in table.items()]
    text = "\n".join(lines) + "\n"
    _parse(tomllib.loads(text))  # what the reader would refuse, refused before writing
    p = Path(path)
    p.write_text(text, encoding="utf-8")
    return p

