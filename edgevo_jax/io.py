"""TUM trajectory files and pose conversions (host side, numpy float64).

A pose7 is ``tx ty tz qx qy qz qw``: the translation and the unit quaternion (Hamilton,
scalar last) of T_world_cam, as in TUM's ``groundtruth.txt``.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from pathlib import Path
from types import TracebackType
from typing import IO, Self

import numpy as np

__all__ = [
    "TrajectoryWriter",
    "matrices_to_poses7",
    "poses7_to_matrices",
    "quat_to_rotmat",
    "read_trajectory",
    "rotmat_to_quat",
    "write_trajectory",
]

_SEP = re.compile(r"[,\s]+")


def _part_path(path: str | os.PathLike[str]) -> Path:
    return Path(os.fspath(path) + ".part")


def _format_line(t: float, pose7: np.ndarray) -> str:
    return f"{t:.6f} " + " ".join(f"{x:.7f}" for x in pose7) + "\n"


def _check_pose7(t: object, pose7: object) -> tuple[float, np.ndarray]:
    try:
        tf = float(t)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"timestamp must be a number, got {t!r}") from exc
    p = np.asarray(pose7, np.float64)
    if p.shape != (7,):
        raise ValueError(f"pose7 must have shape (7,), got {p.shape}")
    if not (np.isfinite(tf) and np.all(np.isfinite(p))):
        raise ValueError(f"refusing to write a non-finite pose: t={tf}, pose7={p.tolist()}")
    return tf, p


def read_trajectory(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory: timestamps (N,) and poses (N, 7) ``tx ty tz qx qy qz qw``.

    Blank lines and lines starting with '#' are skipped; fields may be separated by spaces,
    tabs or commas. Raises FileNotFoundError if the file is missing and ValueError naming
    ``path:line`` for a line that does not hold exactly 8 finite numbers, or whose quaternion
    is zero.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"trajectory file not found: {p}")
    rows: list[list[float]] = []
    with p.open("r", encoding="utf-8", errors="replace") as f:
        for lineno, raw in enumerate(f, start=1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            fields = [x for x in _SEP.split(line) if x]
            if len(fields) != 8:
                raise ValueError(
                    f"{p}:{lineno}: expected 8 numbers (timestamp tx ty tz qx qy qz qw), "
                    f"got {len(fields)}: {line!r}"
                )
            try:
                vals = [float(x) for x in fields]
            except ValueError as exc:
                raise ValueError(f"{p}:{lineno}: not a number in {line!r}") from exc
            if not all(np.isfinite(vals)):
                raise ValueError(f"{p}:{lineno}: non-finite value in {line!r}")
            if not any(vals[4:]):
                raise ValueError(f"{p}:{lineno}: zero quaternion (qx qy qz qw) in {line!r}")
            rows.append(vals)
    arr = np.asarray(rows, np.float64).reshape(-1, 8)
    return arr[:, 0].copy(), arr[:, 1:].copy()


def write_trajectory(
    path: str | os.PathLike[str], timestamps: np.ndarray, poses7: np.ndarray
) -> None:
    """Write a TUM trajectory atomically (via ``path + '.part'`` and os.replace).

    Raises ValueError on mismatched shapes or non-finite values (nothing is written then).
    """
    ts = np.asarray(timestamps, np.float64)
    ps = np.asarray(poses7, np.float64)
    if ts.ndim != 1 or ps.shape != (ts.shape[0], 7):
        raise ValueError(
            f"expected timestamps (N,) and poses7 (N, 7), got {ts.shape} and {ps.shape}"
        )
    bad = ~(np.isfinite(ts) & np.all(np.isfinite(ps), axis=1))
    if np.any(bad):
        k = int(np.argmax(bad))
        raise ValueError(f"refusing to write non-finite pose at row {k}: t={ts[k]}, {ps[k]}")
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    part = _part_path(out)
    with part.open("w", encoding="utf-8") as f:
        f.writelines(_format_line(t, p) for t, p in zip(ts.tolist(), ps, strict=True))
        f.flush()
        os.fsync(f.fileno())
    os.replace(part, out)


def check_output(path: str | os.PathLike[str], *, what: str = "output",
                 folder: bool = False, make_folders: bool = False) -> Path:
    """``path`` as a Path when it can be written, before anything is computed; ValueError
    naming ``what`` and the problem otherwise: a file path that is a folder (or a folder path
    that is a file), a file whose folder does not exist, or a place the process cannot write
    (checked by creating and removing a temporary file there: permission bits alone do not
    say, e.g. for root or a read-only file system). A folder that does not exist yet (the
    file's own folder too, with ``make_folders``: the caller makes it) is checked at its
    nearest existing parent. Writes nothing."""
    path = Path(path)
    if folder:
        if path.exists() and not path.is_dir():
            raise ValueError(f"{what} {path}: is a file, not a folder")
        place = path
        while not place.exists():
            place = place.parent
        if not place.is_dir():
            raise ValueError(f"{what} {path}: {place} is a file, not a folder")
    else:
        if path.is_dir():
            raise ValueError(f"{what} {path}: is a folder; give a file path in it")
        place = path.parent
        while make_folders and not place.exists():
            place = place.parent
        if not place.is_dir():
            raise ValueError(f"{what} {path}: the folder {place} does not exist")
    try:
        with tempfile.TemporaryFile(dir=place):
            pass
    except OSError as err:
        raise ValueError(f"{what} {path}: cannot write in {place} ({err.strerror})") from None
    if not folder and path.exists() and not os.access(path, os.W_OK):
        raise ValueError(f"{what} {path}: the file is not writable")
    return path


class TrajectoryWriter:
    """Incremental TUM trajectory writer.

    Each ``write`` appends one flushed line to ``path + '.part'``; a clean ``close()`` (or a
    ``with`` block that exits normally) syncs it to disk and renames it to ``path``, so a file
    under the final name is always whole. If the ``with`` block raises, the ``.part`` file is
    kept with every line written so far and the exception propagates. Missing folders are
    made; a path that cannot be written (a folder, a read-only place) is refused before
    anything is written (``check_output``).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        check_output(self.path.parent, what="trajectory folder", folder=True)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        check_output(self.path, what="trajectory")
        self.part_path = _part_path(self.path)
        self._file: IO[str] | None = self.part_path.open("w", encoding="utf-8")
        self.count = 0

    def write(self, t: float, pose7: np.ndarray) -> None:
        """Append one pose; ValueError if it is non-finite or the writer is closed."""
        if self._file is None:
            raise ValueError(f"TrajectoryWriter for {self.path} is closed")
        tf, p = _check_pose7(t, pose7)
        self._file.write(_format_line(tf, p))
        self._file.flush()
        self.count += 1

    def rewrite(self, timestamps: np.ndarray, poses7: np.ndarray) -> None:
        """Replace every line written so far by these poses (N timestamps, (N, 7) poses, the
        same count: earlier poses moved, e.g. into the keyframe map's frame); ValueError for
        another count, a non-finite pose or a closed writer."""
        if self._file is None:
            raise ValueError(f"TrajectoryWriter for {self.path} is closed")
        if len(timestamps) != self.count or len(poses7) != self.count:
            raise ValueError(f"rewrite needs the {self.count} poses written, got "
                             f"{len(timestamps)} timestamps and {len(poses7)} poses")
        lines = [_format_line(*_check_pose7(t, p)) for t, p in zip(timestamps, poses7,
                                                                     strict=True)]
        self._file.seek(0)
        self._file.truncate()
        self._file.write("".join(lines))
        self._file.flush()

    def close(self) -> None:
        """Finish: rename ``.part`` to the final path (idempotent)."""
        if self._file is None:
            return
        os.fsync(self._file.fileno())  # the data before the name: never a renamed empty file
        self._file.close()
        self._file = None
        os.replace(self.part_path, self.path)

    def abort(self) -> None:
        """Close without renaming: the ``.part`` file stays as it is (idempotent)."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) ``qx qy qz qw`` (normalised here) to rotation matrices (..., 3, 3)."""
    q = np.asarray(q, np.float64)
    if q.ndim == 0 or q.shape[-1] != 4:
        raise ValueError(f"quaternions must have shape (..., 4), got {q.shape}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if not np.all(np.isfinite(q)) or np.any(norm < 1e-12):
        raise ValueError("quaternions must be finite and non-zero")
    x, y, z, w = np.moveaxis(q / norm, -1, 0)
    r = np.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        axis=-1,
    )
    return r.reshape((*q.shape[:-1], 3, 3))


def rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) to unit quaternions (..., 4) ``qx qy qz qw`` with qw >= 0.

    Shepperd's method: the largest of the four squared components is used as the pivot.
    """
    r = np.asarray(r, np.float64)
    if r.ndim < 2 or r.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape (..., 3, 3), got {r.shape}")
    if not np.all(np.isfinite(r)):
        raise ValueError("rotation matrices must be finite")
    m = r.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    # Candidate (unnormalised) quaternions, each well conditioned for one pivot.
    cand = np.stack(
        [
            np.stack([m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0],
                      m[:, 1, 0] - m[:, 0, 1], 1 + tr], -1),
            np.stack([1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], m[:, 0, 1] + m[:, 1, 0],
                      m[:, 0, 2] + m[:, 2, 0], m[:, 2, 1] - m[:, 1, 2]], -1),
            np.stack([m[:, 0, 1] + m[:, 1, 0], 1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
                      m[:, 1, 2] + m[:, 2, 1], m[:, 0, 2] - m[:, 2, 0]], -1),
            np.stack([m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1],
                      1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2], m[:, 1, 0] - m[:, 0, 1]], -1),
        ],
        axis=1,
    )  # (M, 4 candidates, 4)
    pivots = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], -1)
    q = cand[np.arange(m.shape[0]), np.argmax(pivots, axis=-1)]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    return q.reshape((*r.shape[:-2], 4))


def poses7_to_matrices(poses7: np.ndarray) -> np.ndarray:
    """Poses (..., 7) ``tx ty tz qx qy qz qw`` to homogeneous matrices (..., 4, 4)."""
    p = np.asarray(poses7, np.float64)
    if p.ndim == 0 or p.shape[-1] != 7:
        raise ValueError(f"poses7 must have shape (..., 7), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("poses7 must be finite")
    t = np.zeros((*p.shape[:-1], 4, 4), np.float64)
    t[..., :3, :3] = quat_to_rotmat(p[..., 3:])
    t[..., :3, 3] = p[..., :3]
    t[..., 3, 3] = 1.0
    return t


def matrices_to_poses7(mats: np.ndarray) -> np.ndarray:
    """Homogeneous matrices (..., 4, 4) to poses (..., 7) with unit quaternions, qw >= 0."""
    m = np.asarray(mats, np.float64)
    if m.ndim < 2 or m.shape[-2:] != (4, 4):
        raise ValueError(f"pose matrices must have shape (..., 4, 4), got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError("pose matrices must be finite")
    return np.concatenate([m[..., :3, 3], rotmat_to_quat(m[..., :3, :3])], axis=-1)


def json_safe(obj: object) -> object:
    """For json.dumps: NaN / inf -> None, numpy arrays and scalars -> Python, recursively
    (JSON has no NaN)."""
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj
