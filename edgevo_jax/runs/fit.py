"""Fitting the tracker's learnable ``Params`` on frames of TUM clips against their ground
truth, the parts of ``scripts/learn_weights.py`` (its docstring says what it measures):

- :class:`Part` (:func:`make_part`): frames a:b of one sequence with the true pose of each,
  and the frame pairs or windows they give;
- :func:`build_data`: every frame used preprocessed once, keyframe edges, all stacked on the
  device; :func:`pair_arrays` and :func:`window_arrays` index items into them;
- :func:`make_functions`: the jitted, vmapped training loss (pairs or windows), per-item
  losses and pair errors of the smooth mode (``learn.track_smooth``);
- :func:`evaluate` and :func:`mean_loss`: pair RPE and mean loss over all items in batches;
  :func:`train`: optax adam over minibatches;
- :func:`run_parts` and :func:`control_runs`: full runs of the plain tracker over held-out
  parts, with given Params or with the defaults moved at random by the fit's step;
- :func:`weight_curves`: the learnt weight against each input of the weighting model.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..datasets import subsequence
from ..frontend.robust import FEATURES, weighting_features, weighting_scale
from ..frontend.selection import KeyframeEdges, keyframe_edges
from ..geometry import Pose, inverse_np
from ..image.interp import stack_edge_maps
from ..image.preprocess import preprocess
from ..learn import (
    Smoothing,
    edge_magnitudes,
    relative_pose_error,
    rpe_loss,
    track_smooth,
    track_window,
    window_rpe_loss,
)
from ..learn.params import Params, weighting_of
from .measure import groundtruth_at
from .run import run_sequence, summarise

__all__ = ["FIXED", "GT_MAX_GAP", "Part", "build_data", "control_runs", "evaluate",
           "make_functions", "make_part", "mean_loss", "pair_arrays", "run_part", "run_parts",
           "train", "weight_curves", "window_arrays"]

GT_MAX_GAP = 0.02  # s between the ground-truth samples around a frame
#: Params the fit leaves at their defaults: edge selection only, and the temperature of
#: the other differentiable path (the smooth mode's temperatures are ``Smoothing``'s)
FIXED = ("reobs_a", "log_temperature")

Key = tuple[int, int]  # (sequence index, frame index)


class Part(NamedTuple):
    """Frames a:b of one sequence, with the true pose (4, 4) of each frame that has one."""

    seq: Any
    index: int  # of the sequence in the run
    frames: tuple[int, int]
    gt: dict[int, np.ndarray]

    def pairs(self, gaps: Sequence[int]) -> list[tuple[Key, Key]]:
        """(keyframe, frame) keys of the pairs (i, i + k), k in ``gaps``, inside the part,
        both with ground truth."""
        a, b = self.frames
        return [((self.index, i), (self.index, i + k)) for i in range(a, b) for k in gaps
                if i + k < b and i in self.gt and i + k in self.gt]

    def windows(self, size: int) -> list[tuple[Key, list[Key]]]:
        """(keyframe, [frames]) keys of the windows i, i + 1 .. i + ``size`` inside the part,
        every frame with ground truth."""
        a, b = self.frames
        return [((self.index, i), [(self.index, j) for j in range(i + 1, i + 1 + size)])
                for i in range(a, b - size)
                if all(f in self.gt for f in range(i, i + 1 + size))]


def make_part(seq: Any, index: int, frames: tuple[int, int]) -> Part:
    """Frames ``frames`` (clipped to the sequence) of ``seq``, its ``index``-th sequence,
    with the ground truth interpolated at each frame's timestamp (frames whose ground-truth
    samples around them lie more than ``GT_MAX_GAP`` s apart have none)."""
    a, b = max(0, frames[0]), min(frames[1], len(seq))
    poses = groundtruth_at(seq, seq.timestamps[a:b], max_diff=GT_MAX_GAP, interpolate=True)
    return Part(seq, index, (a, b), {a + k: T for k, T in enumerate(poses)
                                     if np.isfinite(T).all()})


def build_data(seqs: Sequence[Any], frames: Sequence[Key], keyframes: Sequence[Key],
               config: Config, seed: int, keep: dict | None = None) -> dict[str, Any]:
    """Preprocess ``frames`` ((sequence, frame) keys) once; keyframe edges (magnitudes and
    depth discontinuities included; seed ``seed`` + frame index) and the camera of every
    keyframe; stacked arrays, with the slot of each keyframe (``kf_index``) and frame
    (``frame_index``). ``keep``: a dict that receives each preprocessed ``Frame`` under its
    key. ValueError when the sequences' image sizes differ."""
    dist_levels: list[list[np.ndarray]] = [[] for _ in range(config.num_levels)]
    maps, kfs, shapes = [], {}, set()
    for key in frames:
        seq = seqs[key[0]]
        frame = preprocess(*seq.load_frame(key[1]), config)
        if keep is not None:
            keep[key] = frame
        shapes.add(frame.shape)
        for lvl, d in enumerate(frame.dist):
            dist_levels[lvl].append(d)
        maps.append(frame.edge_map)
        if key in keyframes:
            e = keyframe_edges(frame, config, seed=seed + key[1], intr=seq.intrinsics)
            kfs[key] = e._replace(mag=edge_magnitudes(frame, e))
    if len(shapes) > 1:
        raise ValueError(f"the sequences have different image sizes {sorted(shapes)}: "
                         f"fit on sequences of one camera size at a time")
    stack = lambda xs: jnp.asarray(np.stack(xs))  # noqa: E731
    kf = KeyframeEdges(*(stack([np.asarray(getattr(kfs[k], f), np.float32 if f != "valid"
                                           else bool) for k in keyframes])
                         for f in ("uv", "rho", "grad", "valid", "mag")),
                       disc=stack([np.asarray(kfs[k].disc, np.float32) for k in keyframes]))
    intr = stack([np.asarray(seqs[k[0]].intrinsics, np.float32) for k in keyframes])
    return {
        "dist": tuple(stack(d) for d in dist_levels),
        "edge_map": jax.tree.map(jnp.asarray, stack_edge_maps(maps)),
        "kf": kf, "intr": intr,
        "kf_index": {k: j for j, k in enumerate(keyframes)},
        "frame_index": {k: j for j, k in enumerate(frames)},
    }


def pair_arrays(pairs: Sequence[tuple[Key, Key]], gt: dict[Key, np.ndarray], data: dict
                ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(kf slot, target frame slot, T_gt (P, 4, 4)) of the pairs; gt by (sequence, frame)."""
    ki = np.array([data["kf_index"][i] for i, _ in pairs], np.int32)
    fi = np.array([data["frame_index"][j] for _, j in pairs], np.int32)
    T = np.stack([inverse_np(gt[j]) @ gt[i] for i, j in pairs]).astype(np.float32)
    return jnp.asarray(ki), jnp.asarray(fi), jnp.asarray(T)


def window_arrays(windows: Sequence[tuple[Key, list[Key]]], gt: dict[Key, np.ndarray],
                  data: dict) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(kf slot, frame slots (B, W), true poses (B, W + 1, 4, 4)) of the windows: the poses
    T_kf_cam of the keyframe (identity) and of each frame, relative to the keyframe."""
    ki = np.array([data["kf_index"][i] for i, _ in windows], np.int32)
    fi = np.array([[data["frame_index"][j] for j in js] for _, js in windows], np.int32)
    P = np.stack([[inverse_np(gt[i]) @ gt[j] for j in (i, *js)] for i, js in windows])
    return jnp.asarray(ki), jnp.asarray(fi), jnp.asarray(P.astype(np.float32))


def make_functions(data: dict, config: Config, smoothing: Smoothing, rot_weight: float,
                   loss_kind: str) -> tuple[Callable, Callable, Callable]:
    """Jitted batch functions of (params, kf slots, frame slots, truth) over ``data``
    (:func:`build_data`), each item tracked by ``learn.track_smooth`` from the identity
    (``loss_kind`` "window": in order by ``learn.track_window``): the training loss's
    value_and_grad (the mean ``rpe_loss``, or ``window_rpe_loss``, translation m +
    ``rot_weight`` x rotation rad), the per-item losses, and the pair errors (m, rad)."""
    arrays = (data["kf"], data["intr"], data["dist"], data["edge_map"])
    eye = jnp.eye(4, dtype=jnp.float32)
    options = {"smoothing": smoothing}

    def gather(arrays, ki, fi):
        kf_all, intr_all, dist_all, maps_all = arrays
        kf = jax.tree.map(lambda x: x[ki], kf_all)
        dist = tuple(d[fi] for d in dist_all)
        return kf, Intrinsics(*intr_all[ki]), dist, jax.tree.map(lambda x: x[fi], maps_all)

    def pair(params, arrays, ki, fi):
        kf, intr, dist, em = gather(arrays, ki, fi)
        return track_smooth(kf, dist, em, eye, intr, params, config, **options).T_c_k

    def window(params, arrays, ki, fi):  # fi (W,): poses T_kf_cam, keyframe first
        kf, intr, dist, em = gather(arrays, ki, fi)
        T = track_window(kf, dist, em, eye, eye, intr, params, config, track=track_smooth,
                         **options).T_c_k
        inv = Pose.from_matrix(T, orthonormalise=None).inverse().as_matrix()
        return jnp.concatenate([eye[None], inv])

    pairs = jax.vmap(pair, in_axes=(None, None, 0, 0))
    windows = jax.vmap(window, in_axes=(None, None, 0, 0))

    def item_losses(params, arrays, ki, fi, truth):
        if loss_kind == "window":
            one = lambda a, b: window_rpe_loss(a, b, rot_weight=rot_weight)  # noqa: E731
            return jax.vmap(one)(windows(params, arrays, ki, fi), truth)
        one = lambda a, b: rpe_loss(a, b, rot_weight=rot_weight)  # noqa: E731
        return jax.vmap(one)(pairs(params, arrays, ki, fi), truth)

    def loss(params, arrays, ki, fi, truth):
        return jnp.mean(item_losses(params, arrays, ki, fi, truth))

    def errors(params, arrays, ki, fi, T_gt):
        return jax.vmap(relative_pose_error)(pairs(params, arrays, ki, fi), T_gt)

    vg, err = jax.jit(jax.value_and_grad(loss)), jax.jit(errors)
    if loss_kind == "window":
        each = jax.jit(item_losses)
    else:  # a pair's loss from its errors: one program fewer to compile
        def each(params, arrays, ki, fi, T_gt):
            t, r = err(params, arrays, ki, fi, T_gt)
            return t + rot_weight * r
    return (lambda p, ki, fi, T: vg(p, arrays, ki, fi, T),
            lambda p, ki, fi, T: each(p, arrays, ki, fi, T),
            lambda p, ki, fi, T: err(p, arrays, ki, fi, T))


def _chunks(n: int, batch: int) -> Iterator[tuple[np.ndarray, int]]:
    """Index chunks of a fixed size (the last padded by repetition: one compilation) and how
    many of each are real."""
    for s in range(0, n, batch):
        yield np.arange(s, s + batch) % n, min(batch, n - s)


def evaluate(err_fn: Callable, params: Params, ki: Any, fi: Any, T_gt: Any, batch: int,
             rot_weight: float) -> dict[str, float]:
    """Pair RPE over all pairs (``err_fn``: :func:`make_functions`' third), in chunks of
    ``batch``: the number of pairs, their mean loss, and mean and median translation (mm)
    and rotation (degrees) errors."""
    n = int(ki.shape[0])
    t_all, r_all = [], []
    for idx, keep in _chunks(n, batch):
        t, r = err_fn(params, ki[idx], fi[idx], T_gt[idx])
        t_all.append(np.asarray(t)[:keep])
        r_all.append(np.asarray(r)[:keep])
    t_m, r_rad = np.concatenate(t_all), np.concatenate(r_all)
    t, r = t_m * 1e3, np.degrees(r_rad)
    return {"pairs": n, "loss": float(np.mean(t_m + rot_weight * r_rad)),
            "t_mean_mm": float(np.mean(t)), "t_median_mm": float(np.median(t)),
            "r_mean_deg": float(np.mean(r)), "r_median_deg": float(np.median(r))}


def mean_loss(losses_fn: Callable, params: Params, items: Sequence[Any], batch: int) -> float:
    """The training loss averaged over all ``items`` (in chunks of ``batch``)."""
    n = int(items[0].shape[0])
    parts = [np.asarray(losses_fn(params, *(x[idx] for x in items)))[:keep]
             for idx, keep in _chunks(n, batch)]
    return float(np.mean(np.concatenate(parts)))


def train(vg: Callable, value: Callable, params0: Params, items: Sequence[Any], *,
          steps: int, batch: int, lr: float, rng: np.random.Generator, start_loss: float,
          say: Callable[[str], None] = lambda _: None, what: str = "items"
          ) -> tuple[Params, list[float], list[float]]:
    """``steps`` optax adam steps of ``lr`` from ``params0`` over minibatches of ``batch``
    ``items`` drawn by ``rng`` without replacement (reshuffled each epoch), ``vg`` the loss's
    value_and_grad; a step whose gradient is not finite is skipped. Adam is masked off the
    ``FIXED`` leaves (``optax.masked`` passes their raw gradient through as the update:
    none in the smooth mode, which does not read them, so they stay at their defaults).
    Returns the Params, each step's minibatch loss before its update, and the loss over every
    item: ``start_loss`` (``mean_loss`` of ``value`` at ``params0``), then after each step;
    ``say`` gets a line per step (``what`` names the items)."""
    import optax

    n = int(items[0].shape[0])

    def batches():
        while True:
            order = rng.permutation(n)
            for s in range(0, n - batch + 1, batch):
                yield order[s:s + batch]

    draw = batches()
    opt = optax.masked(optax.adam(lr), Params(*(k not in FIXED for k in Params._fields)))
    state = opt.init(params0)
    params = params0
    losses: list[float] = []
    full = [start_loss]
    for step in range(steps):
        b = next(draw)
        loss_value, grads = vg(params, *(x[b] for x in items))
        losses.append(float(loss_value))
        if not all(bool(jnp.all(jnp.isfinite(g))) for g in grads):
            say(f"step {step + 1}: non-finite gradient, step skipped")
            full.append(full[-1])
            continue
        updates, state = opt.update(grads, state, params)
        params = optax.apply_updates(params, updates)
        full.append(mean_loss(value, params, items, batch))
        say(f"step {step + 1:3d}/{steps}: minibatch loss {float(loss_value):.5f}, "
            f"all training {what} {full[-1]:.5f}")
    return params, losses, full


def run_part(part: Part, config: Config, params: Params | None) -> dict:
    """ATE (m, TUM's evaluate_ate) and RPE per second of a full run of the plain tracker
    over the part's frames with ``params`` (None: the defaults)."""
    seq = subsequence(part.seq, *part.frames)
    t0 = time.perf_counter()
    run = run_sequence(seq, config, progress=False, params=params)
    stats = summarise(run, seq)
    return {"sequence": part.seq.name, "frame_range": list(part.frames),
            "frames": len(run.results), "keyframes": run.num_keyframes,
            "lost": stats["lost"], "weak": stats["weak"],
            "ate_rmse_m": stats.get("ate_rmse_m"),
            "rpe_rmse_m_per_s": stats.get("rpe_rmse_m_per_s"),
            "rpe_rmse_deg_per_s": stats.get("rpe_rmse_deg_per_s"),
            "note": stats.get("ground_truth_note"),
            "run_s": time.perf_counter() - t0}


def run_parts(parts: Sequence[Part], config: Config, params: Params | None) -> dict:
    """``run_part`` of every held-out part; the error metrics are their means (over the
    parts that have them), the counts their sums, each part under ``parts``."""
    runs = [run_part(p, config, params) for p in parts]
    out: dict[str, Any] = {}
    for key in ("ate_rmse_m", "rpe_rmse_m_per_s", "rpe_rmse_deg_per_s"):
        vals = [r[key] for r in runs if r[key] is not None]
        out[key] = float(np.mean(vals)) if vals else None
    for key in ("frames", "keyframes", "lost", "weak", "run_s"):
        out[key] = sum(r[key] for r in runs)
    out["parts"] = runs
    return out


def control_runs(parts: Sequence[Part], config: Config, params0: Params, fitted: Params,
                 n: int, seed: int) -> dict:
    """How much the held-out results move for a change of Params of the fit's size without
    any fitting: ``n`` runs with the default Params moved along random directions (seeded by
    ``seed``) by as much as the fit moved them (the same norm over the fitted leaves)."""
    rng = np.random.default_rng(seed + 1)
    moved = [name for name in Params._fields if name not in FIXED]
    step = {k: np.asarray(getattr(fitted, k), np.float64) - np.asarray(getattr(params0, k))
            for k in moved}
    norm = float(np.sqrt(sum(np.sum(d * d) for d in step.values())))
    runs = []
    for _ in range(n):
        direction = {k: rng.normal(size=np.shape(d)) for k, d in step.items()}
        scale = norm / float(np.sqrt(sum(np.sum(d * d) for d in direction.values())))
        p = params0._replace(**{k: jnp.asarray(np.asarray(getattr(params0, k)) + scale * d,
                                               jnp.float32) for k, d in direction.items()})
        runs.append(run_parts(parts, config, p))
    return {"step_norm": norm, "runs": runs,
            "note": "default Params moved along random directions by the fit's step norm"}


def weight_curves(params: Params, config: Config, data: dict, points: int = 41) -> dict:
    """The learnt weight (the model's scale of the Huber weight) against each input of the
    weighting model, the other inputs at their medians over the training keyframes' edges
    (residual: half the gate; level: 0); and each input's 5-95 % range over those edges."""
    kf = data["kf"]
    valid = np.asarray(kf.valid)
    mag, rho, disc = (np.asarray(x)[valid] for x in (kf.mag, kf.rho, kf.disc))
    gate = float(config.max_residual[0])
    model = weighting_of(params, config)
    features = np.asarray(weighting_features(
        jnp.asarray(mag), jnp.asarray(rho), jnp.asarray(disc),
        jnp.full(mag.shape, 0.5 * gate), gate, 0.0, float(model.mag_scale)))
    median = np.median(features, axis=1)
    lo, hi = np.percentile(features, [5, 95], axis=1)
    lo[3], hi[3], lo[4], hi[4] = 0.0, 1.0, 0.0, 1.0  # residual / gate, level feature
    out = {}
    for i, name in enumerate(FEATURES):
        x = np.linspace(lo[i], hi[i], points)
        f = np.repeat(median[:, None], points, axis=1)
        f[i] = x
        out[name] = {"feature": x.tolist(),
                     "weight": np.asarray(weighting_scale(model, jnp.asarray(f))).tolist(),
                     "edges_5_95": [float(lo[i]), float(hi[i])]}
    return out
