"""Tracking a run of frames against one keyframe on the device: the constant-velocity
prediction in keyframe-relative poses and a ``lax.scan`` over a chunk of frames.

The prediction is made from the last two frames' poses relative to the keyframe,
A = T_(i-1)_kf and B = T_(i-2)_kf: T_i_kf = A B^-1 A (constant velocity; in world poses
T_w_i = T_w_(i-1) T_w_(i-2)^-1 T_w_(i-1)). The frame-by-frame driver and the scan both
predict with ``predict_matrix`` (``geometry.predict``) from the same float32 inputs, so that
they give the same trajectory: the scan is the driver's loop moved onto the device, valid
until the host makes a decision that changes the state (a new keyframe, a loss, a recovery),
after which the host re-tracks the rest of the chunk (``run.track_in_chunks``).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from ..camera import Intrinsics
from ..config import Config
from ..derive import SolveKnobs, SolveStructure
from ..geometry import Pose, predict
from ..image.preprocess import EdgeMap
from ..programs import program
from .align import TrackResult, track
from .selection import KeyframeEdges
from .shutter import Shutter


def predict_matrix(A: jnp.ndarray, B: jnp.ndarray) -> jnp.ndarray:
    """Constant velocity in keyframe-relative poses (``geometry.predict``) on the matrices
    the scan carries: T_i_kf = A B^-1 A (4, 4), with A = T_(i-1)_kf and B = T_(i-2)_kf
    (4, 4, rigid: their last rows are not read)."""
    return predict(Pose.from_matrix(A, orthonormalise=None),
                   Pose.from_matrix(B, orthonormalise=None)).as_matrix()


def track_next(
    kf: KeyframeEdges,
    dist: tuple[jnp.ndarray, ...],
    edge_map: EdgeMap,
    A: jnp.ndarray,
    B: jnp.ndarray,
    intr: Intrinsics,
    knobs: SolveKnobs,
    rate: jnp.ndarray | None = None,
    *,
    config: Config | SolveStructure,
) -> TrackResult:
    """Track one frame (dist pyramid, ``preprocess.EdgeMap``) from the constant-velocity
    prediction of its last two keyframe-relative poses A, B (see ``predict_matrix``).
    ``rate``: the rolling shutter's readout time per row over the time since the previous
    frame (``shutter.Shutter``, with A as the previous pose); None: a global shutter."""
    shutter = None if rate is None else Shutter(A, rate)
    return track(kf, dist, edge_map, predict_matrix(A, B), intr, config, knobs, shutter)


def track_chunk(
    kf: KeyframeEdges,
    dist: tuple[jnp.ndarray, ...],
    edge_map: EdgeMap,
    A: jnp.ndarray,
    B: jnp.ndarray,
    intr: Intrinsics,
    knobs: SolveKnobs,
    rates: jnp.ndarray | None = None,
    *,
    config: Config | SolveStructure,
) -> TrackResult:
    """Track C frames in order against one keyframe: dist holds one (C, H / 2**l, W / 2**l)
    array per level, edge_map holds (C, H, W) arrays. Each frame starts from the prediction of
    the two before it (A, B for the first), as ``track_next`` does. Returns the C
    TrackResults stacked on a leading axis. ``rates`` (C,): each frame's rolling-shutter
    rate (``track_next``); None: a global shutter."""

    def step(carry, frame):
        a, b = carry
        res = track_next(kf, frame[0], frame[1], a, b, intr, knobs, frame[2], config=config)
        return (res.T_c_k, a), res

    _, out = jax.lax.scan(step, (A, B), (tuple(dist), edge_map, rates))
    return out


def batch_of_one(fn):
    """``fn`` run as ``jax.vmap(fn)`` on a batch of one, jitted (``config`` static).

    XLA's batched kernels sum in another order than the unbatched ones (poses differ by
    ~5e-8, which a Levenberg-Marquardt accept / reject can amplify); a batched program
    gives the same result for a run whatever the batch size. Running single frames and
    chunks this way makes one run's trajectory the same alone and in a batch (``batch.py``).
    """

    def one(*args, config: Config | SolveStructure):
        out = jax.vmap(partial(fn, config=config))(*jax.tree.map(lambda a: a[None], args))
        return jax.tree.map(lambda a: a[0], out)

    one.__name__ = f"{fn.__name__}_jit"
    one.__doc__ = f"``{fn.__name__}`` jitted, run as a batch of one (``batch_of_one``).\n\n" \
        + (fn.__doc__ or "")
    return program(one, static_argnames="config")


track_next_jit = batch_of_one(track_next)
track_chunk_jit = batch_of_one(track_chunk)
