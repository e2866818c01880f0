"""Frame-to-keyframe edge tracking: the streaming ``Odometry`` and the sequence driver.

Per frame (DESIGN.md): host preprocessing -> one jitted device call (coarse-to-fine solve
against the keyframe's edges) -> host keyframe decision -> one trajectory line.
The jitted solve sees fixed shapes only, so it compiles once per configuration and image size.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from .camera import Intrinsics
from .config import Config
from .geometry import inverse_np
from .keyframes import keyframe_reason
from .preprocess import Frame, preprocess
from .selection import keyframe_edges
from .solve import KeyframeEdges, track

_track_jit = jax.jit(track, static_argnames="config")

OK, LOST = "OK", "LOST"


@dataclass(frozen=True)
class FrameResult:
    """What tracking one frame gives: pose T_world_cam (4, 4, float64), tracking state
    (``OK`` / ``LOST``) and the reason when lost, covariance (6, 6) of a left twist [v, w]
    of T_cur_kf, level-0 inliers, whether the frame became a keyframe (and why), and host
    timings in ms (preprocess, solve = device call including transfer, total)."""

    timestamp: float
    pose: np.ndarray
    state: str
    reason: str | None
    inliers: int
    covariance: np.ndarray | None
    keyframe: str | None
    preprocess_ms: float
    solve_ms: float
    total_ms: float


@dataclass
class _Keyframe:
    timestamp: float
    pose: np.ndarray  # T_world_kf
    edges: KeyframeEdges  # on device
    inlier_counts: list[int] = field(default_factory=list)


class Odometry:
    """Streaming RGB-D edge odometry.

    >>> odo = Odometry(Config(), Intrinsics(535.4, 539.2, 320.1, 247.6))
    >>> result = odo.track(rgb, depth_m, timestamp)  # doctest: +SKIP

    ``initial_pose`` (4, 4) is T_world_cam of the first frame (identity by default).
    """

    def __init__(
        self, config: Config, intrinsics: Intrinsics, initial_pose: np.ndarray | None = None
    ) -> None:
        self.config = config
        self.intrinsics = Intrinsics(*(float(x) for x in intrinsics)).validate()
        pose = np.eye(4) if initial_pose is None else np.asarray(initial_pose, np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError("initial_pose must be a finite 4x4 matrix")
        self._initial = pose
        self._kf: _Keyframe | None = None
        self._poses: list[np.ndarray] = []  # the last two T_world_cam, for constant velocity
        self._last_t: float | None = None
        self.num_keyframes = 0

    # -- public -------------------------------------------------------------------------
    def track(self, rgb: np.ndarray, depth: np.ndarray, timestamp: float) -> FrameResult:
        """Track one frame: rgb (H, W, 3) uint8, depth (H, W) in metres (0 = missing)."""
        t0 = time.perf_counter()
        frame = preprocess(rgb, depth, self.config)
        return self.track_frame(frame, timestamp, preprocess_ms=(time.perf_counter() - t0) * 1e3)

    def track_frame(self, frame: Frame, timestamp: float, *, preprocess_ms: float = 0.0
                    ) -> FrameResult:
        """Track one pre-processed frame (``preprocess_ms`` is only reported back)."""
        t_pre = time.perf_counter()
        t0 = t_pre - preprocess_ms * 1e-3
        timestamp = float(timestamp)
        if self._last_t is not None and timestamp <= self._last_t:
            raise ValueError(
                f"timestamp {timestamp:.6f} does not increase (last was {self._last_t:.6f})"
            )
        self._last_t = timestamp
        if self._kf is None:
            kf_reason = self._make_keyframe(frame, timestamp, self._initial)
            self._push(self._initial)
            if kf_reason is None:
                return self._result(timestamp, self._initial, LOST, "no edges with depth",
                                    0, None, None, t0, t_pre, t_pre)
            return self._result(timestamp, self._initial, OK, None, 0, None, "first",
                                t0, t_pre, t_pre)

        kf = self._kf
        predicted = self._predict()
        T_init = inverse_np(predicted) @ kf.pose  # T_cur_kf
        dist = tuple(jnp.asarray(d) for d in frame.dist)
        res = jax.device_get(
            _track_jit(kf.edges, dist, jnp.asarray(frame.nearest_grad),
                       jnp.asarray(T_init, jnp.float32), self.intrinsics, config=self.config)
        )
        t_solve = time.perf_counter()
        T_c_k = np.asarray(res.T_c_k, np.float64)
        inliers = int(res.inliers)
        lost = None
        if not np.all(np.isfinite(T_c_k)):
            lost = "non-finite pose"
        elif inliers < self.config.min_inliers:
            lost = f"too few inliers ({inliers})"
        if lost is None:
            pose = kf.pose @ inverse_np(_orthonormalise(T_c_k))
            reason = keyframe_reason(
                flow=float(res.flow), flow_t=float(res.flow_t), inliers=inliers,
                inlier_mean=float(np.mean(kf.inlier_counts)) if kf.inlier_counts else None,
                dt=timestamp - kf.timestamp, config=self.config,
            )
            kf.inlier_counts.append(inliers)
        else:
            pose, reason = predicted, "lost"
        made = reason if reason and self._make_keyframe(frame, timestamp, pose) else None
        self._push(pose)
        cov = np.asarray(res.covariance, np.float64) if lost is None else None
        return self._result(timestamp, pose, OK if lost is None else LOST, lost, inliers, cov,
                            made, t0, t_pre, t_solve)

    # -- internals ------------------------------------------------------------------------
    def _predict(self) -> np.ndarray:
        """Constant velocity: T_w_pred = T_w_last (T_w_prev^-1 T_w_last)."""
        if len(self._poses) < 2:
            return self._poses[-1]
        prev, last = self._poses
        return last @ (inverse_np(prev) @ last)

    def _push(self, pose: np.ndarray) -> None:
        self._poses = (self._poses + [pose])[-2:]

    def _make_keyframe(self, frame: Frame, timestamp: float, pose: np.ndarray) -> str | None:
        edges = keyframe_edges(frame, self.config, seed=self.config.seed + self.num_keyframes)
        if int(edges.valid.sum()) < self.config.min_inliers:
            return None  # keep the old keyframe: this one would have nothing to track
        self._kf = _Keyframe(timestamp, pose, KeyframeEdges(*(jnp.asarray(a) for a in edges)))
        self.num_keyframes += 1
        return "made"

    def _result(self, timestamp, pose, state, reason, inliers, cov, kf, t0, t_pre, t_solve):
        t_end = time.perf_counter()
        return FrameResult(
            timestamp=timestamp, pose=pose, state=state, reason=reason, inliers=inliers,
            covariance=cov, keyframe=kf, preprocess_ms=(t_pre - t0) * 1e3,
            solve_ms=(t_solve - t_pre) * 1e3, total_ms=(t_end - t0) * 1e3,
        )


def _orthonormalise(T: np.ndarray) -> np.ndarray:
    """Project the rotation block back onto SO(3) (float32 round-off from the device)."""
    u, _, vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return out

