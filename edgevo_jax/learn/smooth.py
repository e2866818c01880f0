"""The smooth training mode: a tracker whose pose is a smooth function of ``Params``.

``track_smooth`` aligns keyframe edges to a frame as the tracker does (coarse to fine over
the pyramid, Huber-weighted distance residuals, the residual gate, the gradient-consistency
test, the per-edge weighting model), with every decision that makes the tracker's pose jump
under a small change of the parameters replaced by a smooth one:

- a fixed number of damped Gauss-Newton steps per level (``Smoothing.steps``, damping
  ``Smoothing.damping`` times diag H), without Levenberg-Marquardt's accept / reject and its
  stop: the pose after n steps is a composition of smooth maps;
- the residual gate r <= gate becomes sigmoid((gate - r) / (tau_gate * gate));
- the consistency test g(p) . g(p') >= eta becomes sigmoid((g(p) . g(p') - eta) / tau_c),
  and p' (the nearest frame edge, a nearest-pixel lookup of the direction map in the tracker)
  mixes the 2 x 2 pixels around the step target with weights softmax(-|p' - c|^2 / tau_px)
  (a jump of relative size ~exp(-1 / tau_px) remains where p' crosses a pixel boundary);
- the distance fields are read with a C1 interpolant (``interp.bicubic_with_grad``; the
  tracker's bilinear interpolant has kinks at pixel boundaries).

Each edge i of the keyframe (valid, in front of the camera and inside the frame) costs

    s_i m_i huber(r_i) + (1 - s_i) huber(gate),   s_i = gate_i(r_i) * consistency_i

with m_i the weighting model's scale; the Gauss-Newton step solves the normal equations of
that cost with the soft weights s_i m_i (``align.robust_system``). As the temperatures go to
zero, s_i tends to the tracker's hard decisions and the cost at any pose to the tracker's
cost at that pose (read with the same interpolant): ``smooth_system`` is the tracker's
``level_system`` in that limit (tested).

Held constant (hard, no gradient): which keyframe and which edges were selected and their
validity, whether an edge lies in the frame and in front of the camera, the number of
steps, and the step guard (no step with fewer than 6 edges in view). ``Params.reobs_a``
enters edge selection only and has no gradient here.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..camera import Intrinsics, unproject
from ..config import Config
from ..frontend.align import (
    KeyframeEdges,
    LevelSystem,
    TrackResult,
    damped_step,
    robust_system,
    track_result,
)
from ..frontend.residuals import point_jacobian, warp
from ..frontend.robust import edge_weights
from ..geometry import Pose
from ..image.interp import bicubic_with_grad, bilinear_with_grad, direction_table
from .params import Params, weighting_of

INTERPOLATIONS = ("bicubic", "bilinear")


class Smoothing(NamedTuple):
    """The smooth mode's temperatures and steps (static: hashable, a jit static argument).

    gate: the residual gate's temperature, a fraction of the gate (``max_residual[l]``);
    consistency: the temperature of the soft consistency test (dot product units);
    lookup: the temperature of the soft nearest-pixel lookup (px^2 of level 0);
    steps: Gauss-Newton steps per level (level 0 first, like ``Config.iterations``);
    damping: the fixed Levenberg damping lam of every step (H + lam diag H);
    interpolation: "bicubic" (C1) or "bilinear" (the tracker's)."""

    gate: float = 0.1
    consistency: float = 0.1
    lookup: float = 0.25
    steps: tuple[int, ...] = (6, 6, 6)
    damping: float = 1e-2
    interpolation: str = "bicubic"

    def cooled(self, factor: float) -> Smoothing:
        """The same mode with every temperature multiplied by ``factor``."""
        return self._replace(gate=self.gate * factor, consistency=self.consistency * factor,
                             lookup=self.lookup * factor)


DEFAULT_SMOOTHING = Smoothing()


def _read(field: jnp.ndarray, uv: jnp.ndarray, interpolation: str):
    if interpolation == "bicubic":
        return bicubic_with_grad(field, uv)
    return bilinear_with_grad(field, uv)


def soft_consistency_dots(grad_k: jnp.ndarray, code: jnp.ndarray, uv0: jnp.ndarray,
                          d: jnp.ndarray, g: jnp.ndarray, tau: float) -> jnp.ndarray:
    """g(p) . g(p') (K,) with the nearest edge p' found as the tracker finds it
    (``interp.edge_direction_at``: one step p' = uv0 - d g / |g| on the distance field, then
    the direction map at p'), but the map read softly: the 2 x 2 pixels around p' weighted
    by softmax(-|p' - c|^2 / tau) (tau px^2; tau -> 0 is the nearest pixel); a pixel with no
    edge direction counts -1, as the tracker's "none found". Smooth in uv0, d and g except
    where p' crosses a pixel boundary and the 2 x 2 pixels change: there the pixel left
    behind had weight ~exp(-1 / tau) of the nearest (2 % at the default 0.25), a jump of that
    size."""
    h, w = code.shape
    norm = jnp.sqrt(g[0] * g[0] + g[1] * g[1] + 1e-12)
    target = uv0 - g * (d / jnp.maximum(norm, 1e-6))
    u0 = jnp.clip(jnp.floor(jax.lax.stop_gradient(target[0])), 0, w - 2)
    v0 = jnp.clip(jnp.floor(jax.lax.stop_gradient(target[1])), 0, h - 2)
    cu = jnp.stack([u0, u0 + 1, u0, u0 + 1])  # (4, K) corner pixels
    cv = jnp.stack([v0, v0, v0 + 1, v0 + 1])
    sq = (jnp.clip(target[0], 0, w - 1) - cu) ** 2 + (jnp.clip(target[1], 0, h - 1) - cv) ** 2
    weights = jax.nn.softmax(-sq / tau, axis=0)
    c = jnp.take(code.reshape(-1), (cv * w + cu).astype(jnp.int32), mode="clip")
    g_near = jnp.take(direction_table(grad_k.dtype), c.astype(jnp.int32), axis=1)  # (2,4,K)
    dots = jnp.where(c > 0, grad_k[0] * g_near[0] + grad_k[1] * g_near[1], -1.0)
    return jnp.sum(weights * dots, axis=0)


class _Edges(NamedTuple):
    pts_k: jnp.ndarray  # (3, K) keyframe points
    kf: KeyframeEdges
    mag: jnp.ndarray  # (K,)
    disc: jnp.ndarray  # (K,)
    intr: Intrinsics  # level-0


def smooth_system(T: Pose, params: Params, edges: _Edges, field: jnp.ndarray,
                  code: jnp.ndarray, level: int, config: Config,
                  smoothing: Smoothing) -> LevelSystem:
    """The smooth mode's normal equations at T on ``level`` (module docstring): H, g of the
    soft-weighted Huber cost, the cost, and the number of edges in view (as inliers)."""
    intr = edges.intr.at_level(level)
    uv_l, pts = warp(intr, T, edges.pts_k)
    r, grad, inside = _read(field, uv_l, smoothing.interpolation)
    J = point_jacobian(intr, pts, grad)
    gate = config.max_residual[level]
    scale = 2.0**level
    dots = soft_consistency_dots(edges.kf.grad, code, (uv_l + 0.5) * scale - 0.5, r * scale,
                                 grad, smoothing.lookup)
    soft = (jax.nn.sigmoid((gate - r) / (smoothing.gate * gate))
            * jax.nn.sigmoid((dots - params.eta) / smoothing.consistency))
    weight, slope = edge_weights(weighting_of(params, config), edges.mag, edges.kf.rho,
                                 edges.disc, r, gate, level)
    in_view = edges.kf.valid & inside & (pts[2] > 1e-6)
    return robust_system(r, J, in_view, edges.kf.valid, params.huber_delta(level), gate,
                         weight=weight * soft, reject=1.0 - soft, weight_slope=slope * soft,
                         ordered=False)


def track_smooth(
    kf: KeyframeEdges,
    dist: tuple[jnp.ndarray, ...],
    edge_map,
    T_init: jnp.ndarray,
    intr: Intrinsics,
    params: Params,
    config: Config,
    *,
    smoothing: Smoothing = DEFAULT_SMOOTHING,
    mag: jnp.ndarray | None = None,
) -> TrackResult:
    """The smooth mode's alignment (module docstring) of keyframe edges ``kf`` to a frame's
    distance-field pyramid ``dist`` (one (H / 2**l, W / 2**l) field per level) and
    ``edge_map`` (``preprocess.EdgeMap``), from T_init (4, 4) = T_cur_kf, with ``params``.
    mag (K,): the edges' gradient magnitudes for the weighting model (default ``kf.mag``,
    zeros when that is None); their depth discontinuities are ``kf.disc`` (zeros when
    None). Differentiable in params (and the float inputs) by reverse mode through the fixed
    steps; ``config`` and ``smoothing`` are static under jit."""
    if smoothing.interpolation not in INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {INTERPOLATIONS}, "
                         f"got {smoothing.interpolation!r}")
    if len(smoothing.steps) != config.num_levels:
        raise ValueError(f"Smoothing.steps has {len(smoothing.steps)} levels, the config "
                         f"{config.num_levels}")
    dtype = dist[0].dtype
    intr = Intrinsics(*(jnp.asarray(v, dtype) for v in intr))
    mag = kf.mag if mag is None else mag
    mag = jnp.zeros_like(kf.rho) if mag is None else jnp.asarray(mag, kf.rho.dtype)
    disc = jnp.zeros_like(kf.rho) if kf.disc is None else kf.disc
    edges = _Edges(unproject(intr, kf.uv, kf.rho), kf, mag, disc, intr)
    T = start = Pose.from_matrix(jnp.asarray(T_init, dtype))
    for level in reversed(range(config.num_levels)):
        def system_at(T, level=level):
            return smooth_system(T, params, edges, dist[level], edge_map.code, level, config,
                                 smoothing)

        def step(T, _, system_at=system_at):
            return T.retract(damped_step(system_at(T), smoothing.damping)), None

        T, _ = jax.lax.scan(step, T, None, length=smoothing.steps[level])
    final = smooth_system(T, params, edges, dist[0], edge_map.code, 0, config, smoothing)
    return track_result(T, final, edges.pts_k, kf, dist[0].shape, intr, start)
