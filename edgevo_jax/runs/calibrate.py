"""Calibrate a source's camera from its own recording, without a target or ground truth:
track it with the starting camera, then solve the camera jointly with the poses of the
tracked (keyframe, frame) pairs on the tracker's own cost (``learn.camera``).

    calibration = calibrate(seq, config)          # a Calibration
    calibration.write("camera.toml")              # edgevo run SEQ --calibration camera.toml

What it estimates (``learn.camera.PARAMS``): the pinhole (fx, fy, cx, cy), the rolling
shutter's readout time, the time offset of the depth images and the depth scale; each with a
1-sigma uncertainty robust to noise shared by the pairs of one keyframe
(``learn.camera.sandwich_covariance``). A parameter whose uncertainty stays above its
resolution (``RESOLUTION``) is reported as not observable and kept at its start: the solve
is run again without it. The depth scale never is observable from one RGB-D camera alone:
scaling the world and the depth together leaves every image as it is (the poses'
translations absorb it); its line says so. The depth camera's pose (``T_color_depth``,
``fit`` name ``"T_color_depth"``) is estimated relative to the start's, with which the frames
were read. When a focal length is fitted, each keyframe is also paired with later frames
5-15 deg of rotation on (``wide_pairs``): a focal-length error shows only through the
motion between two images.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from ..camera import Camera, Intrinsics
from ..camera_file import write_camera_toml
from ..config import Config
from ..datasets.base import Source, camera_readout
from ..derive import readout_time, solve_knobs
from ..frontend.depth import depth_points
from ..frontend.selection import keyframe_edges
from ..geometry import Pose, inverse_np, log_np, rotation_angle_np
from ..image.preprocess import preprocess
from ..learn.camera import (
    PARAMS,
    PairData,
    camera_of,
    pad_pairs,
    sandwich_covariance,
    solve_camera,
)

__all__ = ["DEFAULT_FIT", "DEPTH_POSE", "RESOLUTION", "WIDE_ANGLES_DEG", "Calibration", "calibrate",
           "tracked_pairs", "wide_pairs"]

#: What ``calibrate`` fits unless told: the readout and the depth time offset. The focal
#: lengths are opt-in (``fit=("fx", "fy", ...)``): they are observable from the wide pairs
#: (``wide_pairs``) and come back on fr3_teddy, but on the fr1 fast clip fx came out 4 %
#: above its calibration, with or without its lens distortion, and tracked worse
#: (docs/decisions.md, "Calibrating the camera"). The principal point runs off along the
#: rotations (not recovered).
DEFAULT_FIT = ("readout_s", "depth_time_offset_s")

#: The rotations (deg) from a keyframe at which ``wide_pairs`` pairs it with a later frame
#: when a focal length is fitted. A focal-length error shows only through the motion between
#: the two images, at second order in the rotation (rotating by 15 deg, 1 % of f moves an
#: edge at the image's side by ~1.5 px, at the tracker's 3-5 deg by ~0.1); past ~15 deg the
#: two images of a 60-deg field of view share too little.
WIDE_ANGLES_DEG = (5.0, 10.0, 15.0)

#: The smallest 1-sigma that counts as knowing a parameter (``PARAMS`` order): 0.5 % of a
#: 500 px focal length, 2.5 px for the principal point, 4 ms for the readout and the time
#: offset (a fifth of a Kinect's 20 ms readout; a tenth of a 30 Hz frame's period), 1 % for
#: the depth scale, 0.25 deg and 3 mm for the depth camera's pose. Beyond it the estimate is
#: noise and the start is kept.
RESOLUTION = np.array([2.5, 2.5, 2.5, 2.5, 4e-3, 4e-3, 1e-2, *[np.radians(0.25)] * 3,
                       *[3e-3] * 3])
#: ``fit``'s name for the depth camera's pose (its six parameters together).
DEPTH_POSE = ("depth_rot_x", "depth_rot_y", "depth_rot_z", "depth_t_x", "depth_t_y",
              "depth_t_z")

#: Why a parameter can be unobservable, as its ``not_observable`` line says.
_WHY = {
    "fx": "the motion does not tell the focal length (too little rotation or depth range)",
    "fy": "the motion does not tell the focal length (too little rotation or depth range)",
    "cx": "the motion does not tell the principal point",
    "cy": "the motion does not tell the principal point",
    "readout_s": "the camera turns too little or too evenly (a rolling shutter shears the "
                 "image by the angular velocity; frames at one speed shear alike)",
    "depth_time_offset_s": "the camera moves too little between colour and depth images",
    "depth_scale": "one RGB-D camera cannot tell it: a world and depth scaled together "
                   "give the same images (a metric reference is needed)",
    **{name: "the motion does not tell the depth camera's pose (it takes rotation about "
             "more than one axis)" for name in DEPTH_POSE},
}


@dataclass
class Calibration:
    """A calibration's outcome: the ``camera`` found (the start's where not observable),
    the ``start`` camera, ``sigma`` (key -> 1-sigma of each estimated parameter),
    ``not_observable`` (key -> why), ``pairs`` and ``keyframes`` used, the robust cost per
    pair before and after, the solve's ``tries``, and ``seconds`` (tracking, solving)."""

    camera: Camera
    start: Camera
    sigma: dict[str, float]
    not_observable: dict[str, str]
    pairs: int
    keyframes: int
    cost_before: float
    cost_after: float
    tries: int
    seconds: dict[str, float] = field(default_factory=dict)
    source: dict[str, object] = field(default_factory=dict)

    def write(self, path: str | Path) -> None:
        """Write the camera file (docs/camera_file.md) with the uncertainties, the
        not-observable lines and what it came from (the depth pose's six as its
        ``rotation_deg`` and ``translation_m``)."""
        sigma = {k: v for k, v in self.sigma.items() if k not in DEPTH_POSE}
        why = {k: v for k, v in self.not_observable.items() if k not in DEPTH_POSE}
        for key, names, scale in (("rotation_deg", DEPTH_POSE[:3], math.degrees(1.0)),
                                  ("translation_m", DEPTH_POSE[3:], 1.0)):
            if all(n in self.sigma for n in names):
                sigma[key] = tuple(scale * self.sigma[n] for n in names)
            reasons = [self.not_observable[n] for n in names if n in self.not_observable]
            if reasons:
                why[key] = reasons[0]
        write_camera_toml(path, self.camera, source=self.source, uncertainty=sigma,
                          observable=why)

    def lines(self) -> list[str]:
        """The estimates as text, one line per parameter."""
        out = []
        for i, name in enumerate(PARAMS):
            value, start = _values(self.camera)[i], _values(self.start)[i]
            scale, unit = {"readout_s": (1e3, "ms"), "depth_time_offset_s": (1e3, "ms"),
                           "depth_scale": (1.0, "")}.get(name, (1.0, "px"))
            if name in DEPTH_POSE:
                scale, unit = (math.degrees(1.0), "deg") if "rot" in name else (1e3, "mm")
            if name in self.not_observable:
                out.append(f"  {name:20s} {scale * start:10.4f} {unit:3s} kept: not observable"
                           f" ({self.not_observable[name]})")
            elif name not in self.sigma:
                out.append(f"  {name:20s} {scale * start:10.4f} {unit:3s} kept (not fitted)")
            else:
                out.append(f"  {name:20s} {scale * value:10.4f} {unit:3s} +- "
                           f"{scale * self.sigma[name]:.4f} (start {scale * start:.4f})")
        return out


def _values(camera: Camera) -> np.ndarray:
    """The camera as ``PARAMS`` values (the depth pose as a rotation vector, rad, and a
    translation, m)."""
    fx, fy, cx, cy = camera.intrinsics
    pose = np.zeros(6)
    if camera.T_color_depth is not None:
        T = np.asarray(camera.T_color_depth, np.float64)
        pose = np.concatenate([cv2.Rodrigues(T[:3, :3])[0].ravel(), T[:3, 3]])
    return np.array([fx, fy, cx, cy, camera.readout_s, camera.depth_time_offset_s,
                     camera.depth_scale, *pose], np.float64)


def tracked_pairs(seq: Source, config: Config, max_frames: int | None, *,
                  progress: bool = False):
    """Track ``seq``; returns timestamps (N,), poses T_world_cam (N, 4, 4) and the
    (keyframe, frame) index pairs the tracker aligned: keyframes after the first frame
    (whose velocity is known), frames after their keyframe, frames not lost."""
    from .run import run_sequence

    keyframe_t: list[float] = []

    def on_frame(result, rgb, frame, odo) -> None:
        kf = odo.state.keyframe
        keyframe_t.append(float("nan") if kf is None else float(kf.timestamp))

    run = run_sequence(seq, config, progress=progress, max_frames=max_frames,
                       on_frame=on_frame)
    ts = np.asarray(run.timestamps, np.float64)
    index = {float(t): i for i, t in enumerate(ts)}
    pairs = []
    for i, (t_kf, r) in enumerate(zip(keyframe_t, run.results, strict=True)):
        j = index.get(float(t_kf))
        if j is not None and 0 < j < i and r.state != "LOST":
            pairs.append((j, i))
    return ts, np.asarray(run.poses, np.float64), pairs


def wide_pairs(poses: np.ndarray, pairs: list[tuple[int, int]],
               angles_deg: tuple[float, ...] = WIDE_ANGLES_DEG) -> list[tuple[int, int]]:
    """Pairs of each keyframe of ``pairs`` with a later tracked frame (one of ``pairs``'
    frames) whose tracked rotation from it is nearest each of ``angles_deg`` and within 25 %
    of it, where such a frame exists before the rotation first exceeds the largest angle;
    the pairs not already in ``pairs``. ``poses``: T_world_cam (N, 4, 4)."""
    tracked = np.array(sorted({i for _, i in pairs} | {j for j, _ in pairs}))
    reach = 1.25 * max(angles_deg)
    have = set(pairs)
    out: list[tuple[int, int]] = []
    for j in sorted({j for j, _ in pairs}):
        later = tracked[tracked > j]
        deg = np.degrees(rotation_angle_np(poses[j, :3, :3].T @ poses[later, :3, :3]))
        past = np.flatnonzero(deg > reach)
        if past.size:
            later, deg = later[:past[0]], deg[:past[0]]
        for target in angles_deg:
            off = np.abs(deg - target)
            if off.size and off.min() <= 0.25 * target:
                pair = (j, int(later[np.argmin(off)]))
                if pair not in have:
                    have.add(pair)
                    out.append(pair)
    return out


def pair_data(seq: Source, config: Config, ts: np.ndarray, poses: np.ndarray,
              pairs: list[tuple[int, int]], intr: Intrinsics,
              tick: Callable[[], None] | None = None, frames: dict | None = None) -> PairData:
    """The pairs' data (stacked ``PairData``, numpy) from the source's frames as the
    tracker sees them (``preprocess``) and the tracked poses (for the velocities).
    ``frames``: preprocessed frames by index, read from and added to (None: a new dict)."""
    depth_t = getattr(seq, "depth_timestamps", None)
    lags = np.zeros(len(ts))  # depth time - colour time; 0 where the source does not say
    if depth_t is not None:
        if len(depth_t) < len(ts):
            raise ValueError(f"{seq.name}: {len(depth_t)} depth timestamps for {len(ts)} "
                             "frames")
        lags = np.asarray(depth_t, np.float64)[:len(ts)] - ts
    frames = {} if frames is None else frames
    kf_data: dict[int, tuple] = {}
    needed = sorted({k for p in pairs for k in p})
    for k in needed:
        if k not in frames:
            frames[k] = preprocess(*seq.load_frame(k), config)
        if tick is not None:
            tick()

    def velocity(k: int) -> np.ndarray:
        dt = max(ts[k] - ts[k - 1], 1e-3)
        return log_np(inverse_np(poses[k - 1]) @ poses[k]) / dt

    for j in sorted({j for j, _ in pairs}):
        f = frames[j]
        e = keyframe_edges(f, config, seed=config.seed + j, intr=intr)
        pts, normals = depth_points(f.depth, intr, config.depth_points,
                                    min_depth=config.min_depth, max_depth=config.max_depth,
                                    seed=config.seed + j)
        z = np.where(pts[2] > 1e-6, pts[2], 1.0)
        dpix = np.stack([intr.fx * pts[0] / z + intr.cx, intr.fy * pts[1] / z + intr.cy])
        valid = np.asarray(e.valid)
        kz = 1.0 / np.where(valid, np.asarray(e.rho, np.float64), 1.0)
        kf_data[j] = (np.asarray(e.uv), kz, np.asarray(e.grad), valid, dpix, z, normals)
    rows = []
    for j, i in pairs:
        uv, kz, grad, valid, dpix, dz, normals = kf_data[j]
        f = frames[i]
        depth = np.asarray(f.depth, np.float32)
        rows.append(PairData(uv, kz, grad, valid, dpix, dz, normals, velocity(j), lags[j],
                             np.asarray(f.dist[0]), np.asarray(f.edge_map.code), depth,
                             velocity(i), lags[i]))
    stacked = {name: np.stack([np.asarray(getattr(r, name)) for r in rows])
               for name in PairData._fields}
    return PairData(**{name: a if name in ("valid", "code") else a.astype(np.float32)
                       for name, a in stacked.items()})


def calibrate(
    seq: Source,
    config: Config | None = None,
    *,
    max_frames: int | None = None,
    fit: tuple[str, ...] = DEFAULT_FIT,
    iterations: int = 20,
    rounds: int = 3,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
) -> Calibration:
    """Calibrate ``seq``'s camera from its own frames (the module doc): track the first
    ``max_frames`` (all: None) with ``config`` (default ``Config()``) and the source's camera
    as the start, then solve. The tracked pairs depend on the readout they were tracked
    with: while the readout found differs from it by more than half its resolution, track
    again with it and solve again (at most ``rounds`` rounds). ``fit``: the parameters to
    estimate (a subset of ``PARAMS``; the others are kept). ValueError when too few pairs
    were tracked (fewer than 10 or fewer than 5 keyframes)."""
    config = Config() if config is None else config
    fit = tuple(n for name in fit for n in (DEPTH_POSE if name == "T_color_depth" else (name,)))
    unknown = sorted(set(fit) - set(PARAMS))
    if unknown:
        raise ValueError(f"calibrate: cannot fit {', '.join(unknown)}; it fits "
                         f"{', '.join(PARAMS[:7])} and T_color_depth (or its "
                         f"{', '.join(DEPTH_POSE)})")
    say = log or (lambda s: None)
    intr = Intrinsics(*(float(v) for v in seq.intrinsics))
    readout = readout_time(config, camera_readout(seq))
    start = Camera(intr, getattr(seq, "distortion", None), readout,
                   float(getattr(seq, "depth_scale", 1.0)),
                   float(getattr(seq, "depth_time_offset_s", 0.0)),
                   getattr(seq, "T_color_depth", None))
    seconds = {"tracking": 0.0, "solving": 0.0}
    k_readout = PARAMS.index("readout_s")
    tracked_with = []
    frames: dict = {}  # preprocessed frames, shared by the rounds (the readout changes none)
    for round_ in range(1, rounds + 1):
        tracked_with.append(readout)
        out = _round(seq, dataclasses.replace(config, readout_s=readout), max_frames, intr,
                     readout, fit, iterations, progress, say, seconds, frames)
        theta, sigma, free = out["theta"], out["sigma"], out["free"]
        moved = free[k_readout] > 0 and abs(theta[k_readout] - readout) > \
            0.5 * RESOLUTION[k_readout]
        if not moved or round_ == rounds:
            break
        readout = max(float(theta[k_readout]), 0.0)
        say(f"the readout moved to {1e3 * readout:.1f} ms: tracking again with it")
    fx, fy, cx, cy, readout_new, offset, scale = theta[:7]
    pose = start.T_color_depth
    if np.any(theta[7:] != 0):  # the pose found relative to the start's (frames read with it)
        delta = np.eye(4)
        delta[:3, :3] = cv2.Rodrigues(np.asarray(theta[7:10], np.float64))[0]
        delta[:3, 3] = theta[10:13]
        pose = delta if pose is None else delta @ np.asarray(pose, np.float64)
    camera = start._replace(intrinsics=Intrinsics(fx, fy, cx, cy),
                            readout_s=max(readout_new, 0.0),
                            depth_time_offset_s=start.depth_time_offset_s + offset,
                            depth_scale=start.depth_scale * scale, T_color_depth=pose)
    n = out["pairs"]
    return Calibration(
        camera=camera, start=start,
        sigma={name: float(sigma[k]) for k, name in enumerate(PARAMS) if free[k] > 0},
        not_observable=out["not_observable"], pairs=n, keyframes=out["keyframes"],
        cost_before=out["cost_before"] / n, cost_after=out["cost_after"] / n,
        tries=out["tries"], seconds=seconds,
        source={"calibrated_from": seq.name, "frames": out["frames"], "pairs": n,
                "keyframes": out["keyframes"], "tracked_with_readout_s": tracked_with,
                "method": "joint Gauss-Newton of the pairs' poses and the camera on the "
                "tracker's level-0 cost (edgevo_jax.learn.camera)"})


def _round(seq: Source, config: Config, max_frames: int | None, intr: Intrinsics,
           readout: float, fit: tuple[str, ...], iterations: int, progress: bool,
           say: Callable[[str], None], seconds: dict[str, float], frames: dict) -> dict:
    """One round of ``calibrate``: track with ``config`` (its readout ``readout``), solve,
    and again without the parameters found not observable. Adds its times to
    ``seconds``."""
    t0 = time.perf_counter()
    say(f"tracking {seq.name} (readout {1e3 * readout:.1f} ms)")
    ts, poses, pairs = tracked_pairs(seq, config, max_frames, progress=progress)
    keyframes = len({j for j, _ in pairs})
    if len(pairs) < 10 or keyframes < 5:
        raise ValueError(f"calibrate: only {len(pairs)} frame-keyframe pairs over {keyframes} "
                         f"keyframes were tracked in {seq.name}; it needs at least 10 over 5 "
                         "(a longer recording, or one the tracker follows)")
    if {"fx", "fy"} & set(fit):
        wide = wide_pairs(poses, pairs)
        say(f"{len(wide)} wide pairs (rotations {', '.join(f'{a:g}' for a in WIDE_ANGLES_DEG)} "
            "deg from their keyframe) for the focal lengths")
        pairs = pairs + wide
    t1 = time.perf_counter()
    say(f"{len(pairs)} frame-keyframe pairs over {keyframes} keyframes; reading their frames")
    needed = len({k for p in pairs for k in p})
    with tqdm(total=needed, desc="frames", unit="frame", disable=not progress,
              leave=False) as bar:
        data = pair_data(seq, config, ts, poses, pairs, intr, tick=bar.update, frames=frames)
    T0 = np.stack([inverse_np(poses[i]) @ poses[j] for j, i in pairs]).astype(np.float32)
    data, T0, _ = pad_pairs(data, T0)
    T0 = jax.vmap(Pose.from_matrix)(jnp.asarray(T0))
    pairs_dev = PairData(*(jnp.asarray(a) for a in data))
    knobs = solve_knobs(config)
    clusters = np.array([j for j, _ in pairs] + [-1] * (len(T0.t) - len(pairs)))
    # the model's depth scale and time offset are relative to the start's (the frames were
    # read with it): 1 and 0; the readout absolute
    theta0 = np.array([*intr, readout, 0.0, 1.0, *np.zeros(6)], np.float64)
    free = np.array([name in fit for name in PARAMS], np.float64)
    # the depth scale is a gauge of the cost (module doc): never fitted, always said
    free[PARAMS.index("depth_scale")] = 0.0
    not_observable = {"depth_scale": _WHY["depth_scale"]}
    height = int(data.field.shape[1])
    cost_before = math.nan
    while True:
        say(f"solving {int(free.sum())} camera parameters with {len(pairs)} poses")
        with tqdm(total=iterations, desc="solve", unit="try", disable=not progress,
                  leave=False) as bar:
            x, system, tries, cost_start = solve_camera(
                theta0, free, T0, pairs_dev, knobs, height, iterations=iterations,
                on_try=lambda k, cost: (bar.update(), bar.set_postfix(cost=f"{cost:.4g}")))
        if math.isnan(cost_before):
            cost_before = cost_start
        cov = sandwich_covariance(system.pairs, clusters, free)
        sigma = np.sqrt(np.maximum(np.diag(cov), 0.0))
        weak = [k for k in np.flatnonzero(free) if not sigma[k] <= RESOLUTION[k]]
        if not weak:
            break
        found = camera_of(theta0, free, np.asarray(x.phi))
        for k in weak:
            free[k] = 0.0
            not_observable[PARAMS[k]] = (f"{_WHY[PARAMS[k]]}: it came out at {found[k]:.4g} "
                                         f"+- {sigma[k]:.3g}, more than the resolution "
                                         f"{RESOLUTION[k]:.3g}")
        if not free.any():
            x = x._replace(phi=jnp.zeros_like(x.phi))
            break
    seconds["tracking"] += t1 - t0
    seconds["solving"] += time.perf_counter() - t1
    return {"theta": camera_of(theta0, free, np.asarray(x.phi)), "sigma": sigma, "free": free,
            "not_observable": not_observable, "pairs": len(pairs), "keyframes": keyframes,
            "cost_before": cost_before, "cost_after": float(system.cost), "tries": tries,
            "frames": len(ts)}
