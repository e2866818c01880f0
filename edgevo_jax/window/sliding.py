"""The sliding window of keyframes that the tracker hands each new keyframe to (EdgeVO's local
mapping): activation, joint refinement, marginalisation, on the host around three jitted calls.

On a new keyframe (``SlidingWindow.add_keyframe``):
1. Window full (``window_size`` keyframes): one keyframe leaves. The newest two always stay;
   of the others, one with under ``drop_visible_ratio`` of its edges visible in the newest
   keyframe goes (the fewest first), else the one whose centre is farthest from the newest's.
   It is marginalised (``prior.marginalize_keyframe``: its pose and the inverse depths of
   its active edges, through the Schur complement) into the prior, and so are the active
   edges of the remaining keyframes that neither of the newest two sees (their depth block is
   diagonal, so that Schur complement is H_cc - H_cp D^-1 H_cp^T, no inverse but 1 / d).
   Linearisation: first-estimate Jacobians: a prior's H is fixed when it is made; its
   gradient moves with the offset from that point (``prior.prior_terms``).
2. The new keyframe joins; the tracked edges of the earlier ones are re-projected into it
   (its level-0 distance field and nearest-edge gradients): each edge seen there under the
   residual gate and with consistent gradients counts one more track, and edges are activated
   per ``activation_cell`` cell by the three rules of ``activation.activate``. Only edges
   whose sensor depth is continuous across them can be activated (``depth_continuous``):
   an edge on a depth step is an occluding contour (it slides over the object when the
   camera moves) or carries the far side's depth, so no fixed point explains its residuals.
3. With a full window: ``refine.refine`` moves the poses, the active inverse depths and
   (``mapping_intrinsics``) the intrinsics, the oldest keyframe held fixed; each keyframe keeps
   its ``active_per_keyframe`` longest-tracked active edges in the problem (fixed shapes: one
   compilation). The tracker then continues from the refined pose of the new keyframe.

Every array handed to JAX has a fixed shape per configuration: one compilation each for the
activation, the refinement and the marginalisation (of the keyframe and of the stale edges,
from one evaluation of the window's residuals).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import Intrinsics, unproject
from ..config import Config
from ..derive import MappingConfig, join_window, split_window, window_config
from ..frontend.selection import KeyframeEdges
from ..frontend.shutter import RowMotion
from ..geometry import Pose, inverse_np, orthonormalise_np
from ..hostmem import to_host
from ..image.preprocess import EdgeMap, Frame
from ..programs import program
from .activation import activate, reproject
from .prior import Prior, append_keyframe_to_prior, marginalize_keyframe, no_prior
from .problem import WindowProblem
from .refine import refine


@dataclass
class _WindowKeyframe:
    """One keyframe of the window (host copies, float64 pose): its tracked edges (K slots) are
    the candidates for activation; ``active``, ``track`` and the refined ``rho`` per slot."""

    pose: np.ndarray  # T_w_k
    uv: np.ndarray  # (2, K)
    rho: np.ndarray  # (K,)
    grad: np.ndarray  # (2, K)
    valid: np.ndarray  # (K,)
    dist0: jnp.ndarray  # (H, W) level-0 distance field, on device
    edge_map: EdgeMap  # on device
    active: np.ndarray = field(default=None)  # type: ignore[assignment]
    track: np.ndarray = field(default=None)  # type: ignore[assignment]
    rho_sensor: np.ndarray = field(default=None)  # type: ignore[assignment]
    activatable: np.ndarray = field(default=None)  # type: ignore[assignment]  # valid, continuous
    row_twist: np.ndarray = field(default=None)  # type: ignore[assignment]  # (6,) per row
    key: object = None  # the caller's handle of the keyframe (``SlidingWindow.move``)

    def __post_init__(self) -> None:
        k = self.rho.shape[0]
        self.rho_sensor = self.rho.copy() if self.rho_sensor is None else self.rho_sensor
        self.active = np.zeros(k, bool) if self.active is None else self.active
        self.track = np.zeros(k, np.int32) if self.track is None else self.track
        self.activatable = self.valid.copy() if self.activatable is None else self.activatable
        self.row_twist = np.zeros(6) if self.row_twist is None else self.row_twist


def depth_continuous(depth: np.ndarray, uv: np.ndarray, grad: np.ndarray, *,
                     max_step: float, reach: int) -> np.ndarray:
    """(K,) bool: edges (pixels uv (2, K), normalised gradients grad (2, K)) whose sensor
    depth is continuous across them: at 1..``reach`` px to either side along the gradient
    and at the edge pixel itself the depth (metres, (H, W), 0 or NaN = missing) is present
    and its inverse is planar, |rho(p + s g) + rho(p - s g) - 2 rho(p)| <= ``max_step``
    (1/m) for every s. Inverse depth is affine in the pixels on any plane, so a slanted
    surface passes and a step (an occluding contour, or a pixel that took the far side's
    depth) fails; pixels outside the image count as missing."""
    h, w = depth.shape

    def rho_at(s: float) -> np.ndarray:
        u = np.round(uv[0] + s * grad[0]).astype(np.int64)
        v = np.round(uv[1] + s * grad[1]).astype(np.int64)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        z = depth[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)].astype(np.float64)
        ok = inside & np.isfinite(z) & (z > 0)
        return np.where(ok, 1.0 / np.where(ok, z, 1.0), np.nan)

    r0 = rho_at(0.0)
    planar = np.isfinite(r0)
    for s in range(1, reach + 1):
        planar &= np.abs(rho_at(s) + rho_at(-s) - 2.0 * r0) <= max_step  # NaN: False
    return planar


def _candidate_slots(edges: KeyframeEdges, k: int):
    """A keyframe's tracked edges as K = ``k`` activation candidates (every keyframe the same
    K: fixed shapes): all of them with the selecting modes; with ``selection=all``, K evenly
    spaced ones (deterministic). Returns uv (2, K), rho (K,), grad (2, K), valid (K,)."""
    idx = np.flatnonzero(np.asarray(edges.valid))
    if idx.size > k:
        idx = idx[np.linspace(0, idx.size - 1, k).round().astype(int)]
    m = idx.size
    uv, grad = np.zeros((2, k), np.float32), np.zeros((2, k), np.float32)
    rho, valid = np.ones(k, np.float32), np.arange(k) < m
    uv[:, :m] = np.asarray(edges.uv)[:, idx]
    grad[:, :m] = np.asarray(edges.grad)[:, idx]
    rho[:m] = np.asarray(edges.rho)[idx]
    return uv, rho, grad, valid


def _activation_step(intr, T_new_host, uv, rho, grad, valid, active, track, field_new,
                     nearest_new, twist_new, *, width, height, cell, max_angle_deg, gate):
    """For (h, K) host edges re-projected into the new keyframe (T_new_host (h, 4, 4)): the
    track counts, one more where an edge is seen again there (under the gate, gradients
    within the angle), and the activation mask over the edges not active yet; ``valid`` is
    each host's ``activatable`` mask (valid slots on continuous depth); ``twist_new`` (6,)
    the new keyframe's rolling-shutter motion per row, or None."""
    rows = None if twist_new is None else RowMotion(
        twist_new, jnp.asarray(0.5 * (height - 1), twist_new.dtype),
        jnp.zeros((), twist_new.dtype))

    def one(T, uv_h, rho_h, grad_h):
        pts = unproject(intr, uv_h, rho_h)
        return reproject(intr, Pose.from_matrix(T, orthonormalise="quaternion"), pts, grad_h,
                         field_new, nearest_new, rows)

    uv_new, r, cos, vis = jax.vmap(one)(T_new_host, uv, rho, grad)
    seen = valid & vis & (r <= gate) & (cos >= math.cos(math.radians(max_angle_deg)))
    track = track + seen.astype(track.dtype)
    h, k = r.shape
    act = activate(uv_new.transpose(1, 0, 2).reshape(2, h * k), r.reshape(-1), cos.reshape(-1),
                   track.reshape(-1), (valid & ~active & vis).reshape(-1), width=width,
                   height=height, cell=cell, max_angle_deg=max_angle_deg)
    return track, act.reshape(h, k)


_activation_jit = program(_activation_step, static_argnames=(
    "width", "height", "cell", "max_angle_deg"))

def _refine(problem: WindowProblem, numbers, prior: Prior, *, config: MappingConfig):
    """``refine.refine`` with the numbers of ``derive.split_window`` traced."""
    return refine(problem, join_window(config, numbers), prior)


_refine_jit = program(_refine, static_argnames="config")


def _permute_prior(prior: Prior, order: jnp.ndarray) -> Prior:
    """The prior in the layout of the window's keyframes taken in ``order`` (n,) int."""
    n = order.shape[0]
    idx = jnp.concatenate([(6 * order[:, None] + jnp.arange(6)).reshape(-1),
                           6 * n + jnp.arange(4)])
    return Prior(H=prior.H[jnp.ix_(idx, idx)], b=prior.b[idx], poses=prior.poses[order],
                 intrinsics=prior.intrinsics, mask=prior.mask[idx])


def _marginalize(problem: WindowProblem, numbers, prior: Prior, order: jnp.ndarray,
                 stale: jnp.ndarray, *, config: MappingConfig) -> Prior:
    """``marginalize_keyframe`` of keyframe 0 of ``problem`` (the window taken in the new
    ``order``), with the prior permuted to that order first, and of the ``stale`` (n - 1, A)
    edges of the window without it (numbers: ``split_window``)."""
    return marginalize_keyframe(problem, 0, join_window(config, numbers),
                                _permute_prior(prior, order), stale=stale)


_marginalize_jit = program(_marginalize, static_argnames="config")


@dataclass
class SlidingWindow:
    """The window of keyframes (module doc). ``intrinsics`` is the window's current estimate
    (fx, fy, cx, cy); ``add_keyframe`` returns the new keyframe's refined pose."""

    config: Config
    intrinsics: np.ndarray
    shape: tuple[int, int]
    window: list[_WindowKeyframe] = field(default_factory=list)
    prior: Prior | None = None
    #: the camera has a rolling shutter: keyframes bring their motion per row
    #: (``add_keyframe(..., row_twist=...)``), which the window's residuals model
    rolling_shutter: bool = False

    def __post_init__(self) -> None:
        self.intrinsics = np.asarray(self.intrinsics, np.float32)
        self._mcfg = window_config(self.config)
        self.rolling_shutter = bool(self.rolling_shutter)
        self._structure, self._numbers = split_window(self._mcfg)

    @property
    def camera(self) -> Intrinsics:
        """The window's intrinsics estimate as an Intrinsics of floats."""
        return Intrinsics(*(float(x) for x in self.intrinsics))

    def add_keyframe(self, pose: np.ndarray, edges: KeyframeEdges, frame: Frame,
                     row_twist: np.ndarray | None = None, *, key: object = None
                     ) -> tuple[np.ndarray, dict]:
        """Take a new keyframe (pose T_w_k (4, 4); its tracked edges, numpy, at its middle
        row's time; its frame; with a rolling shutter its motion per level-0 row (6,); ``key``:
        the caller's handle of it, for ``move``) into the window; returns its pose after
        refinement and the step's stats (whether it refined; then inliers, tries and
        costs)."""
        cfg = self.config
        stats: dict = {"refined": False}
        if len(self.window) == cfg.window_size:
            self._drop(pose)
        uv, rho, grad, valid = _candidate_slots(edges, cfg.num_edges)
        activatable = valid
        if cfg.activation_depth_step > 0 and frame.depth is not None:
            activatable = valid & depth_continuous(
                frame.depth, uv, grad, max_step=cfg.activation_depth_step,
                reach=cfg.activation_depth_reach)
        dist0 = jax.device_put(frame.dist[0])
        new = _WindowKeyframe(
            pose=np.asarray(pose, np.float64), uv=uv, rho=rho, grad=grad, valid=valid,
            dist0=dist0, edge_map=EdgeMap(dist0, jax.device_put(frame.edge_map.code)),
            activatable=activatable,
            row_twist=np.zeros(6) if row_twist is None else np.asarray(row_twist, np.float64),
            key=key)
        if self.prior is not None:
            self.prior = jax.device_put(append_keyframe_to_prior(
                self.prior, np.asarray(new.pose, np.float32)))
        self._activate(new)
        self.window.append(new)
        if len(self.window) == cfg.window_size:
            stats.update(self._refine())
        return self.window[-1].pose, stats

    def move(self, corrections: dict) -> None:
        """Move keyframes of the window with a correction of the map (a loop closed): each
        whose ``key`` is in ``corrections`` takes the pose C @ T_w_k (C = T_world_new_world_old
        (4, 4)), and so does its linearisation point in the prior. The prior's information
        stays as it was: it is in world-frame left twists, which a correction of a few
        centimetres and degrees turns by as little (first-estimate Jacobians alike)."""
        prior_poses = None if self.prior is None else np.array(self.prior.poses, np.float64)
        for k, kf in enumerate(self.window):
            C = corrections.get(kf.key)
            if C is None:
                continue
            kf.pose = np.asarray(C, np.float64) @ kf.pose
            if prior_poses is not None and k < len(prior_poses):
                prior_poses[k] = np.asarray(C, np.float64) @ prior_poses[k]
        if prior_poses is not None:
            self.prior = self.prior._replace(poses=jax.device_put(
                prior_poses.astype(np.asarray(self.prior.poses).dtype)))

    def warm_up(self) -> None:
        """Compile (or load from the compilation cache) and run once each jitted step of
        the window and the host-to-device conversions around them, on a throwaway window of
        empty keyframes in the shapes of this configuration and image size: no keyframe of
        the run waits for a compilation. This window is not touched."""
        cfg, (height, width) = self.config, self.shape
        n, K = cfg.window_size, cfg.num_edges
        field0 = jax.device_put(np.zeros((height, width), np.float32))
        edge_map = EdgeMap(field0, jax.device_put(np.zeros((height, width), np.uint8)))

        def empty() -> _WindowKeyframe:
            return _WindowKeyframe(
                pose=np.eye(4), uv=np.zeros((2, K), np.float32), rho=np.ones(K, np.float32),
                grad=np.zeros((2, K), np.float32), valid=np.zeros(K, bool), dist0=field0,
                edge_map=edge_map)

        scratch = SlidingWindow(self.config, self.intrinsics, self.shape,
                           rolling_shutter=self.rolling_shutter)
        scratch.window = [empty() for _ in range(n - 1)]
        scratch._activate(empty())
        scratch.window.append(empty())
        problem, _ = scratch._problem()
        prior = _marginalize_jit(problem, self._numbers, no_prior(problem),
                                 np.arange(n, dtype=np.int32),
                                 np.ones((n - 1, cfg.active_per_keyframe), bool),
                                 config=self._structure)
        scratch.prior = jax.device_put(append_keyframe_to_prior(prior, np.eye(4, dtype=np.float32)))
        scratch._refine()

    # -- steps ----------------------------------------------------------------------------
    def _activate(self, new: _WindowKeyframe) -> None:
        """Re-project the window's edges into the new keyframe; count tracks; activate."""
        if not self.window:
            return
        hosts = self._stack_hosts()
        h = len(self.window)
        T = np.stack([inverse_np(new.pose) @ kf.pose for kf in self.window]).astype(np.float32)
        T = self._pad_hosts(T, np.eye(4, dtype=np.float32))
        height, width = self.shape
        track, act = _activation_jit(
            self.camera, T, hosts["uv"], hosts["rho"], hosts["grad"], hosts["activatable"],
            hosts["active"], hosts["track"], new.dist0, new.edge_map,
            np.asarray(new.row_twist, np.float32) if self.rolling_shutter else None,
            width=width, height=height, cell=self.config.activation_cell,
            max_angle_deg=float(self.config.activation_max_angle_deg),
            gate=np.float32(self.config.max_residual[0]))
        track, act = np.asarray(track), np.asarray(act)
        for k, kf in enumerate(self.window[:h]):
            kf.track = track[k].astype(np.int32)
            kf.active = kf.active | act[k]

    def _problem(self) -> tuple[WindowProblem, list[np.ndarray]]:
        """The window as a WindowProblem: each keyframe's longest-tracked active edges in
        ``active_per_keyframe`` slots; returns it and the slots' edge indices per keyframe."""
        A = self.config.active_per_keyframe
        uv, rho, grad, valid, sensor, picks = [], [], [], [], [], []
        for kf in self.window:
            idx = np.flatnonzero(kf.active)
            idx = idx[np.argsort(-kf.track[idx], kind="stable")[:A]]
            picks.append(idx)
            m = idx.size
            u = np.zeros((2, A), np.float32)
            g = np.zeros((2, A), np.float32)
            r, r0 = np.ones(A, np.float32), np.ones(A, np.float32)
            u[:, :m], g[:, :m], r[:m] = kf.uv[:, idx], kf.grad[:, idx], kf.rho[idx]
            r0[:m] = kf.rho_sensor[idx]
            uv.append(u)
            grad.append(g)
            rho.append(r)
            sensor.append(r0)
            valid.append(np.arange(A) < m)
        put = jax.device_put  # a transfer; jnp.asarray compiles a program per new shape
        problem = WindowProblem(
            poses=put(np.stack([kf.pose for kf in self.window]).astype(np.float32)),
            uv=put(np.stack(uv)), rho=put(np.stack(rho)), valid=put(np.stack(valid)),
            fields=tuple(kf.dist0 for kf in self.window),  # per keyframe: nothing copied
            intrinsics=put(np.asarray(self.intrinsics)), grad=put(np.stack(grad)),
            edge_map=tuple(kf.edge_map for kf in self.window),
            rho_prior=put(np.stack(sensor)),
            row_twists=put(np.stack([kf.row_twist for kf in self.window]).astype(np.float32))
            if self.rolling_shutter else None)
        return problem, picks

    def _refine(self) -> dict:
        problem, picks = self._problem()
        prior = self.prior if self.prior is not None else no_prior(problem)
        out, st = _refine_jit(problem, self._numbers, prior, config=self._structure)
        poses, rho, intr = to_host((out.poses, out.rho, out.intrinsics))
        if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(rho))
                and np.all(np.isfinite(intr))):
            return {"refined": False, "note": "non-finite refinement, kept the estimate"}
        for k, kf in enumerate(self.window):
            if k != self._mcfg.gauge_index:  # float32 round trip: keep the fixed pose exact
                kf.pose = orthonormalise_np(np.asarray(poses[k], np.float64))
            kf.rho[picks[k]] = rho[k, :picks[k].size]
        self.intrinsics = np.asarray(intr, np.float32)
        return {"refined": True, "inliers": int(st["inliers"]),
                "iterations": int(st["iterations"]), "cost_before": float(st["cost_before"]),
                "cost_after": float(st["cost_after"])}

    def _drop(self, new_pose: np.ndarray) -> None:
        """Marginalise one keyframe (module doc) and the edges that the newest two (the
        incoming keyframe, pose ``new_pose``, and the window's last) do not see."""
        cfg = self.config
        candidates = list(range(len(self.window) - 1))  # the window's last stays
        visible = [self._visible(self.window[k], new_pose).sum()
                   / max(int(self.window[k].valid.sum()), 1) for k in candidates]
        if min(visible) < cfg.drop_visible_ratio:
            drop = candidates[int(np.argmin(visible))]
        else:
            c = new_pose[:3, 3]
            drop = candidates[int(np.argmax([np.linalg.norm(self.window[k].pose[:3, 3] - c)
                                             for k in candidates]))]
        order = np.array([drop] + [k for k in range(len(self.window)) if k != drop])
        self.window = [self.window[k] for k in order]
        problem, picks = self._problem()
        self.window, picks = self.window[1:], picks[1:]
        stale = np.zeros((len(self.window), cfg.active_per_keyframe), bool)
        for k, kf in enumerate(self.window[:-1]):
            seen = self._visible(kf, new_pose) | self._visible(kf, self.window[-1].pose)
            gone = picks[k][~seen[picks[k]]]
            stale[k, :picks[k].size] = ~seen[picks[k]]
            kf.active[gone] = False
        if self.prior is None:  # the zero prior, made in the new order already
            prior, order = no_prior(problem), np.arange(order.size)
        else:
            prior = self.prior
        self.prior = _marginalize_jit(problem, self._numbers, prior, order.astype(np.int32),
                                      stale, config=self._structure)

    # -- helpers --------------------------------------------------------------------------
    def _visible(self, host: _WindowKeyframe, T_w_target: np.ndarray) -> np.ndarray:
        """(K,) the host's valid edges that project into the image of a camera at pose
        T_w_target (numpy)."""
        fx, fy, cx, cy = (float(x) for x in self.intrinsics)
        z = 1.0 / np.where(host.valid, host.rho, 1.0)
        P = np.stack([(host.uv[0] - cx) / fx * z, (host.uv[1] - cy) / fy * z, z])
        T = inverse_np(T_w_target) @ host.pose
        Q = T[:3, :3] @ P + T[:3, 3:]
        front = Q[2] > 1e-6
        zq = np.where(front, Q[2], 1.0)
        u, v = fx * Q[0] / zq + cx, fy * Q[1] / zq + cy
        height, width = self.shape
        return host.valid & front & (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)

    def _pad_hosts(self, a: np.ndarray, fill: np.ndarray) -> np.ndarray:
        """Stack of per-host arrays padded to window_size - 1 hosts (fixed shapes)."""
        missing = self.config.window_size - 1 - a.shape[0]
        return np.concatenate([a, np.broadcast_to(fill, (missing, *a.shape[1:]))]) \
            if missing > 0 else a

    def _stack_hosts(self) -> dict[str, np.ndarray]:
        out = {}
        for name, fill in (("uv", 0.0), ("rho", 1.0), ("grad", 0.0), ("activatable", False),
                           ("active", False), ("track", 0)):
            a = np.stack([getattr(kf, name) for kf in self.window])
            out[name] = self._pad_hosts(a, np.full(a.shape[1:], fill, a.dtype))
        return out

