"""Fit the tracker's learnable ``Params`` on TUM frame pairs and report the held-out RPE.

Usage::

    python scripts/learn_weights.py [SEQ_DIR ...] [--test-sequences SEQ_DIR ...]
                                    [--frame-step 1] [--train 0:100] [--test 100:200] [--gaps 1,2,3]
                                    [--loss pairs|window] [--window 8] [--num-edges 256]
                                    [--gn-steps 6,6,6] [--steps 200] [--batch 32] [--lr 1e-2]
                                    [--seed 0] [--rot-weight 0.1] [--no-ate] [--control-runs 0]
                                    [--set KEY=VALUE ...]
                                    [--out-json docs/learning/learn_weights.json]
                                    [--out-png docs/learning/loss.png]
                                    [--out-weights-png docs/learning/weights.png]

SEQ_DIR defaults to ``SHARED_TUM / rgbd_dataset_freiburg3_teddy_first200`` (the project's
development clip, not shipped). Each SEQ_DIR gives training items from its ``--train`` frames
and held-out items from its ``--test`` frames; each ``--test-sequences`` folder is held out
whole (every frame). All sequences need one image size (the frames are stacked).
``--frame-step`` k keeps every k-th frame of each sequence (``load_sequence``'s: 15 Hz from
30 Hz at k = 2); the frame ranges count the kept frames. The config is ``Config(num_edges=
--num-edges)`` with ``--set KEY=VALUE`` overrides (as ``edgevo run --set``), for the fit and
the held-out runs alike.

Data. Each frame i of a range is a keyframe: its ``num_edges`` edges chosen by
``selection.keyframe_edges`` (fixed slots, the config's selection, seed = ``--seed`` + i)
with their gradient magnitudes and depth discontinuities. Pairs: frame i + k (k in
``--gaps``, inside the same range) is tracked against keyframe i from the identity (no
constant-velocity prior: frame-to-frame motion is small, and a prior from the ground truth
would leak the answer). Windows (``--loss window``): frames i + 1 .. i + ``--window`` are
tracked in order against keyframe i, each from the constant-velocity prediction of the two
before it (``learn.track_window``). The true poses are the ground truth interpolated at each
frame's timestamp (``groundtruth_pose_at(..., interpolate=True)``; frames whose ground-truth
samples around them lie more than 20 ms apart are left out). No item crosses two ranges.

Model. The smooth training mode, ``learn.track_smooth`` (``--gn-steps`` Gauss-Newton steps
per level, level 0 first, with ``learn.Smoothing``'s default temperatures), jitted and
``jax.vmap``-ped over a batch (the frames' distance pyramids and direction maps are stacked
once on the device; each item gathers its keyframe, frames and camera by index inside the
jitted function). Loss: with ``--loss pairs`` (the default) the mean ``learn.rpe_loss``
(translation m + ``--rot-weight`` x rotation rad) over a batch of pairs; with
``--loss window`` the mean ``learn.window_rpe_loss`` of the window's consecutive motions.
Optimiser: optax adam, ``--steps`` steps of ``--lr``, minibatches of ``--batch`` items drawn
without replacement (reshuffled each epoch) from ``numpy.random.default_rng(--seed)``;
float32. Trained: the Huber radii, eta and the weighting model; ``reobs_a`` (edge selection
only) and ``log_temperature`` (the other differentiable path's) stay at their defaults.

Report (printed, and written to ``--out-json``): the pair RPE of the training model over the
held-out and the training pairs (mean and median translation error in mm, rotation in deg)
with ``Params.default`` and with the fitted Params; the ATE and the RPE per second
(``metrics.rpe_per_second``) of full runs of the plain tracker (``runner.run_sequence``, hard
decisions, the same config) over the held-out frames of each sequence, with the default and the
fitted Params (``--no-ate`` skips them; several held-out parts: their mean, each part under
``parts``), and with ``--control-runs N`` N more with the defaults moved along random
directions by as much as the fit moved them; the training loss per step (plotted to
``--out-png``); the learnt weight against each input of the weighting model (plotted to
``--out-weights-png``, the other inputs at their medians over the training edges); the fitted
Params (``fitted_params``: what ``edgevo run --params`` reads); the time of a warm
``value_and_grad`` over one ``--batch``-item batch (median of a few calls) and of its first
call (compilation). Numbers are reported as they come, gain or not.

The data are the TUM RGB-D benchmark's (CC BY 4.0): J. Sturm, N. Engelhard, F. Endres,
W. Burgard, D. Cremers, "A Benchmark for the Evaluation of RGB-D SLAM Systems", IROS 2012.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.camera import Intrinsics
from edgevo_jax.datasets import subsequence
from edgevo_jax.datasets.tum import SHARED_TUM
from edgevo_jax.frontend.robust import FEATURES, weighting_features, weighting_scale
from edgevo_jax.frontend.selection import KeyframeEdges, keyframe_edges
from edgevo_jax.geometry import Pose, inverse_np
from edgevo_jax.image.interp import stack_edge_maps
from edgevo_jax.image.preprocess import preprocess
from edgevo_jax.learn import (
    Smoothing,
    edge_magnitudes,
    relative_pose_error,
    rpe_loss,
    track_smooth,
    track_window,
    window_rpe_loss,
)
from edgevo_jax.learn.params import Params, params_to_dict, weighting_of
from edgevo_jax.reports import write_json
from edgevo_jax.runs.measure import groundtruth_at, load_clip
from edgevo_jax.runs.run import run_sequence, summarise
from edgevo_jax.viz._canvas import figure, save

DEFAULT_SEQ = SHARED_TUM / "rgbd_dataset_freiburg3_teddy_first200"
GT_MAX_GAP = 0.02  # s between the ground-truth samples around a frame
#: Params the fit leaves at their defaults: edge selection only, and the temperature of
#: the other differentiable path (the smooth mode's temperatures are ``Smoothing``'s)
FIXED = ("reobs_a", "log_temperature")


def say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _range(text: str) -> tuple[int, int]:
    a, b = text.split(":")
    return int(a), int(b)


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequences", nargs="*", type=Path, default=[DEFAULT_SEQ],
                   help="TUM sequence folders, split into --train and --test frames "
                        "(default: the shared fr3_teddy_first200 clip)")
    p.add_argument("--test-sequences", nargs="*", type=Path, default=[],
                   help="TUM sequence folders held out whole")
    p.add_argument("--frame-step", type=_positive, default=1,
                   help="keep every k-th frame of each sequence (k = 2: 15 Hz from 30 Hz); "
                        "--train / --test count the kept frames")
    p.add_argument("--train", type=_range, default=(0, 100), help="training frames a:b")
    p.add_argument("--test", type=_range, default=(100, 200), help="held-out frames a:b")
    p.add_argument("--gaps", default="1,2,3", help="frame gaps k of the pairs (i, i + k)")
    p.add_argument("--loss", choices=("pairs", "window"), default="pairs",
                   help="fit on frame pairs or on windows tracked against a keyframe")
    p.add_argument("--window", type=int, default=8, help="frames per window (--loss window)")
    p.add_argument("--num-edges", type=int, default=256, help="keyframe edge slots")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="KEY=VALUE",
                   help="Config override, as edgevo run's --set (repeatable): the config of "
                        "the fit and of the held-out runs (e.g. mapping=false)")
    p.add_argument("--gn-steps", default=",".join(map(str, Smoothing().steps)),
                   help="Gauss-Newton steps per level of the smooth mode, level 0 first")
    # the training loss still falls at 60 steps (docs/learning: -4.7 % at 60, -8.5 % at 200)
    p.add_argument("--steps", type=int, default=200, help="adam steps")
    p.add_argument("--batch", type=int, default=32, help="pairs or windows per minibatch")
    # adam moves each parameter by ~lr per step; the weighting model's output layer starts
    # at zero and needs moves of ~1 to change an edge's weight by tens of percent in 60 steps
    p.add_argument("--lr", type=float, default=1e-2, help="adam learning rate")
    p.add_argument("--rot-weight", type=float, default=0.1,
                   help="loss = translation (m) + rot_weight * rotation (rad)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timing-reps", type=int, default=3, help="warm value_and_grad calls timed")
    p.add_argument("--no-ate", action="store_true",
                   help="skip the full tracker runs over the held-out frames")
    p.add_argument("--control-runs", type=int, default=0,
                   help="held-out runs with the defaults moved at random by the fit's step")
    p.add_argument("--out-json", type=Path, default=Path("docs/learning/learn_weights.json"))
    p.add_argument("--out-png", type=Path, default=Path("docs/learning/loss.png"))
    p.add_argument("--out-weights-png", type=Path, default=Path("docs/learning/weights.png"))
    return p.parse_args(argv)


class Part(NamedTuple):
    """Frames a:b of one sequence, with the true pose (4, 4) of each frame that has one."""

    seq: Any
    index: int  # of the sequence in the run
    frames: tuple[int, int]
    gt: dict[int, np.ndarray]

    def pairs(self, gaps: list[int]) -> list[tuple[tuple[int, int], tuple[int, int]]]:
        a, b = self.frames
        return [((self.index, i), (self.index, i + k)) for i in range(a, b) for k in gaps
                if i + k < b and i in self.gt and i + k in self.gt]

    def windows(self, size: int) -> list[tuple[tuple[int, int], list[tuple[int, int]]]]:
        a, b = self.frames
        return [((self.index, i), [(self.index, j) for j in range(i + 1, i + 1 + size)])
                for i in range(a, b - size)
                if all(f in self.gt for f in range(i, i + 1 + size))]


def make_part(seq, index: int, frames: tuple[int, int]) -> Part:
    a, b = max(0, frames[0]), min(frames[1], len(seq))
    poses = groundtruth_at(seq, seq.timestamps[a:b], max_diff=GT_MAX_GAP,
                           interpolate=True)
    return Part(seq, index, (a, b), {a + k: T for k, T in enumerate(poses)
                                     if np.isfinite(T).all()})


def build_data(seqs: list, frames: list[tuple[int, int]], keyframes: list[tuple[int, int]],
               config: Config, seed: int, keep: dict | None = None) -> dict[str, Any]:
    """Preprocess ``frames`` ((sequence, frame) keys) once; keyframe edges (magnitudes and
    depth discontinuities included) and the camera of every keyframe; stacked arrays.
    ``keep``: a dict that receives each preprocessed ``Frame`` under its key."""
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


def pair_arrays(pairs, gt: dict, data: dict):
    """(kf slot, target frame slot, T_gt (P, 4, 4)) of the pairs; gt by (sequence, frame)."""
    ki = np.array([data["kf_index"][i] for i, _ in pairs], np.int32)
    fi = np.array([data["frame_index"][j] for _, j in pairs], np.int32)
    T = np.stack([inverse_np(gt[j]) @ gt[i] for i, j in pairs]).astype(np.float32)
    return jnp.asarray(ki), jnp.asarray(fi), jnp.asarray(T)


def window_arrays(windows, gt: dict, data: dict):
    """(kf slot, frame slots (B, W), true poses (B, W + 1, 4, 4)) of the windows: the poses
    T_kf_cam of the keyframe (identity) and of each frame, relative to the keyframe."""
    ki = np.array([data["kf_index"][i] for i, _ in windows], np.int32)
    fi = np.array([[data["frame_index"][j] for j in js] for _, js in windows], np.int32)
    P = np.stack([[inverse_np(gt[i]) @ gt[j] for j in (i, *js)] for i, js in windows])
    return jnp.asarray(ki), jnp.asarray(fi), jnp.asarray(P.astype(np.float32))


def make_functions(data: dict, config: Config, smoothing: Smoothing, rot_weight: float,
                   loss_kind: str):
    """Jitted batch functions of (params, kf slots, frame slots, truth): the training loss's
    value_and_grad and per-item values (pairs or windows), and the pair errors."""
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


def _chunks(n: int, batch: int):
    """Index chunks of a fixed size (the last padded by repetition: one compilation) and how
    many of each are real."""
    for s in range(0, n, batch):
        yield np.arange(s, s + batch) % n, min(batch, n - s)


def evaluate(err_fn, params, ki, fi, T_gt, batch: int,
             rot_weight: float) -> dict[str, float]:
    """Pair RPE over all pairs, in chunks of ``batch``, and the mean pair loss over them."""
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


def mean_loss(losses_fn, params, items, batch: int) -> float:
    """The training loss averaged over all ``items`` (in chunks of ``batch``)."""
    n = int(items[0].shape[0])
    parts = [np.asarray(losses_fn(params, *(x[idx] for x in items)))[:keep]
             for idx, keep in _chunks(n, batch)]
    return float(np.mean(np.concatenate(parts)))


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


def run_parts(parts: list[Part], config: Config, params: Params | None) -> dict:
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


def control_runs(parts: list[Part], config: Config, params0: Params, fitted: Params, n: int,
                 seed: int) -> dict:
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


def save_plot(losses: list[float], full: list[float], path: Path, title: str,
              what: str) -> None:
    fig = figure((5, 3), dpi=80)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(np.arange(len(losses)), losses, marker="o", markersize=2, lw=0.8, alpha=0.6,
            label="minibatch (before its step)")
    ax.plot(np.arange(len(full)), full, lw=1.8, label=f"all training {what}")
    ax.set_xlabel("adam step")
    ax.set_ylabel("mean RPE loss")
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    save(fig, path, dpi=80)


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


def save_weights_plot(curves: dict, path: Path, title: str) -> None:
    fig = figure((9, 5), dpi=80)
    labels = {"gradient magnitude": "log(m / canny_high)", "depth": "log depth (m)",
              "depth discontinuity": "log(1 + 10 (max - min) / z)",
              "residual": "residual / gate", "level": "level / (L - 1)",
              "re-observation": "1 / (1 + exp(a - m))"}
    for i, (name, c) in enumerate(curves.items()):
        ax = fig.add_subplot(2, 3, i + 1)
        ax.plot(c["feature"], c["weight"], lw=1.8)
        ax.axhline(1.0, color="gray", lw=0.8, ls="--")
        ax.set_xlabel(labels.get(name, name), fontsize=8)
        ax.set_ylabel("weight scale", fontsize=8)
        ax.set_title(name, fontsize=9)
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save(fig, path, dpi=80)


def load_all(paths: list[Path], frame_step: int = 1) -> list | str:
    """The sequences (every ``frame_step``-th frame: ``load_sequence``'s), or the message
    naming the one that cannot be used."""
    seqs = []
    for path in paths:
        if not path.is_dir():
            return (f"sequence folder not found: {path} (the fr3_teddy_first200 clip lives in "
                    f"{SHARED_TUM}; pass another TUM folder as the first argument)")
        seq = load_clip(path, frame_step=frame_step)
        if seq.groundtruth is None:
            return f"{seq.name} has no groundtruth.txt: nothing to fit against"
        seqs.append(seq)
    return seqs


def main(argv: list[str] | None = None) -> int:
    enable_batch_exact()  # the CLI's arithmetic: trajectories as `edgevo run` gives them
    try:
        import optax
    except ImportError:
        say("optax is missing: pip install 'optax>=0.2' (or the package's 'learn' extra)")
        return 2
    args = parse_args(argv)
    t_start = time.perf_counter()
    seqs = load_all(list(args.sequences) + list(args.test_sequences), args.frame_step)
    if isinstance(seqs, str):
        say(seqs)
        return 2
    n_split = len(args.sequences)
    try:
        config = Config(num_edges=args.num_edges).with_overrides(args.overrides)
    except ValueError as e:
        say(str(e))
        return 2
    smoothing = Smoothing(steps=tuple(int(x) for x in args.gn_steps.split(",")))
    if len(smoothing.steps) != config.num_levels:
        say(f"--gn-steps needs {config.num_levels} numbers (one per level), got "
            f"{args.gn_steps}")
        return 2
    gaps = [int(g) for g in args.gaps.split(",")]
    train_parts = [make_part(s, i, args.train) for i, s in enumerate(seqs[:n_split])]
    test_parts = [make_part(s, i, args.test) for i, s in enumerate(seqs[:n_split])]
    test_parts += [make_part(s, n_split + i, (0, len(s)))
                   for i, s in enumerate(seqs[n_split:])]
    pairs_of = {"train": [p for part in train_parts for p in part.pairs(gaps)],
                "test": [p for part in test_parts for p in part.pairs(gaps)]}
    windows = [w for part in train_parts for w in part.windows(args.window)]
    for name, pairs in pairs_of.items():
        if not pairs:
            say(f"no {name} pairs with ground truth in frames "
                f"{args.train if name == 'train' else args.test} of the sequences")
            return 2
    if args.loss == "window" and not windows:
        say(f"no training window of {args.window} frames with ground truth in {args.train}")
        return 2
    gt = {(part.index, f): T for part in train_parts + test_parts for f, T in part.gt.items()}
    used = list(windows) if args.loss == "window" else []
    frames = sorted({f for pairs in pairs_of.values() for pr in pairs for f in pr}
                    | {f for i, js in used for f in (i, *js)})
    keyframes = sorted({i for pairs in pairs_of.values() for i, _ in pairs}
                       | {i for i, _ in used})
    items_name = "windows" if args.loss == "window" else "pairs"
    names = ", ".join(s.name for s in seqs)
    say(f"{names}: {len(pairs_of['train'])} training and {len(pairs_of['test'])} held-out "
        f"pairs" + (f", {len(used)} training windows" if used else "")
        + f", {len(frames)} frames to preprocess")
    t0 = time.perf_counter()
    try:
        data = build_data(seqs, frames, keyframes, config, args.seed)
    except ValueError as e:
        say(str(e))
        return 2
    prep_s = time.perf_counter() - t0
    say(f"preprocessing and edge selection: {prep_s:.1f} s")

    vg, value, err = make_functions(data, config, smoothing, args.rot_weight, args.loss)
    train_pairs = pair_arrays(pairs_of["train"], gt, data)
    test_pairs = pair_arrays(pairs_of["test"], gt, data)
    train = window_arrays(used, gt, data) if used else train_pairs
    n_train = int(train[0].shape[0])
    batch = min(args.batch, n_train)
    rng = np.random.default_rng(args.seed)

    def batches():
        while True:
            order = rng.permutation(n_train)
            for s in range(0, n_train - batch + 1, batch):
                yield order[s:s + batch]

    draw = batches()
    params0 = Params.default(config, jnp.float32)

    # timing: first call (compile + run), then warm calls on the same batch
    idx = np.arange(batch)
    t0 = time.perf_counter()
    jax.block_until_ready(vg(params0, *(x[idx] for x in train)))
    first_s = time.perf_counter() - t0
    warm = []
    for _ in range(max(args.timing_reps, 1)):
        t0 = time.perf_counter()
        jax.block_until_ready(vg(params0, *(x[idx] for x in train)))
        warm.append(time.perf_counter() - t0)
    warm_s = float(np.median(warm))
    print(f"value_and_grad over {batch} {items_name}: first call (compile + run) "
          f"{first_s:.2f} s, warm {warm_s * 1e3:.1f} ms (median of {len(warm)})")

    t0 = time.perf_counter()
    before = {"test": evaluate(err, params0, *test_pairs, batch, args.rot_weight),
              "train": evaluate(err, params0, *train_pairs, batch, args.rot_weight)}
    eval_s = time.perf_counter() - t0

    opt = optax.masked(optax.adam(args.lr), Params(*(n not in FIXED for n in Params._fields)))
    state = opt.init(params0)
    params = params0
    losses: list[float] = []
    full = [mean_loss(value, params0, train, batch)]  # over every training item, per step
    t0 = time.perf_counter()
    for step in range(args.steps):
        b = next(draw)
        loss_value, grads = vg(params, *(x[b] for x in train))
        if not all(bool(jnp.all(jnp.isfinite(g))) for g in grads):
            say(f"step {step + 1}: non-finite gradient, step skipped")
            losses.append(float(loss_value))
            full.append(full[-1])
            continue
        updates, state = opt.update(grads, state, params)
        params = optax.apply_updates(params, updates)
        losses.append(float(loss_value))
        full.append(mean_loss(value, params, train, batch))
        say(f"step {step + 1:3d}/{args.steps}: minibatch loss {float(loss_value):.5f}, "
            f"all training {items_name} {full[-1]:.5f}")
    train_s = time.perf_counter() - t0
    print(f"training loss over all {n_train} training {items_name}: {full[0]:.6f} -> "
          f"{full[-1]:.6f} ({100.0 * (full[-1] / full[0] - 1.0):+.1f} %)")

    after = {"test": evaluate(err, params, *test_pairs, batch, args.rot_weight),
             "train": evaluate(err, params, *train_pairs, batch, args.rot_weight)}
    for split in ("test", "train"):
        b, a = before[split], after[split]
        label = "held-out" if split == "test" else "training"
        print(f"{label} pair RPE over {b['pairs']} pairs: translation {b['t_mean_mm']:.2f} -> "
              f"{a['t_mean_mm']:.2f} mm (mean), rotation {b['r_mean_deg']:.3f} -> "
              f"{a['r_mean_deg']:.3f} deg (mean)  [default -> fitted]")

    ate: dict[str, Any] = {"skipped": "--no-ate"}
    if not args.no_ate:
        ate = {"frames": list(test_parts[0].frames) if len(test_parts) == 1 else
               [[p.seq.name, *p.frames] for p in test_parts],
               "default": run_parts(test_parts, config, None),
               "fitted": run_parts(test_parts, config, params),
               "note": "full runs of the plain tracker (hard decisions) over the held-out "
                       "frames only, the same config as the fit; several parts: means"}
        d, f = ate["default"], ate["fitted"]
        print(f"held-out runs: ATE {_mm(d['ate_rmse_m'])} -> {_mm(f['ate_rmse_m'])} mm, RPE "
              f"{_mm(d['rpe_rmse_m_per_s'])} -> {_mm(f['rpe_rmse_m_per_s'])} mm/s  "
              f"[default -> fitted]")
        if args.control_runs > 0:
            ate["control"] = control_runs(test_parts, config, params0, params,
                                          args.control_runs, args.seed)
            c = ate["control"]["runs"]
            print(f"control: default Params moved at random by the fit's step size, "
                  f"{len(c)} runs: RPE {', '.join(_mm(x['rpe_rmse_m_per_s']) for x in c)} "
                  f"mm/s, ATE {', '.join(_mm(x['ate_rmse_m']) for x in c)} mm")

    fitted: dict[str, Any] = params_to_dict(params)
    fitted["huber_delta"] = np.exp(np.asarray(params.log_huber)).tolist()
    curves = weight_curves(params, config, data)
    report = {
        "sequence": str(seqs[0].root), "sequence_name": seqs[0].name,
        "sequences": [str(s.root) for s in seqs[:n_split]],
        "test_sequences": [str(s.root) for s in seqs[n_split:]],
        "settings": {
            "train_frames": list(train_parts[0].frames if train_parts else args.train),
            "test_frames": list(test_parts[0].frames if test_parts else args.test),
            "frame_step": args.frame_step, "gaps": gaps, "loss_kind": args.loss,
            "window": args.window if args.loss == "window" else None,
            "num_edges": args.num_edges, "overrides": list(args.overrides),
            "steps": args.steps, "batch": batch,
            "lr": args.lr, "rot_weight": args.rot_weight, "seed": args.seed,
            "mode": "smooth (learn.track_smooth)", "smoothing": smoothing._asdict(),
            "T_init": "identity (pairs); constant velocity from the identity (windows)",
            "ground_truth": "interpolated at each frame's timestamp",
            "dtype": "float32", "selection": config.selection,
            "optimizer": f"optax.adam ({', '.join(FIXED)} held fixed)",
            "loss": ("mean over the batch of window_rpe_loss (consecutive motions of the "
                     "window, keyframe first)" if args.loss == "window" else
                     "mean over the batch of rpe_loss") +
                    " = t_err (m) + rot_weight * r_err (rad)",
        },
        "pairs": {"train": len(pairs_of["train"]), "test": len(pairs_of["test"])},
        "training_items": {"kind": items_name, "count": n_train},
        "rpe": {"default": before, "fitted": after,
                "units": "t: mm, r: deg, of E = T_gt^-1 T_est per pair, tracked from the "
                         "identity by the training model"},
        "ate": ate,
        "loss_curve": {"minibatch": losses, f"all_training_{items_name}": full,
                       "note": "minibatch[s] is the loss of step s's batch before its update; "
                               f"all_training_{items_name}[s] the loss over every training "
                               "item after s steps (s = 0: default Params)"},
        "weights": curves,
        "fitted_params": fitted,
        "default_params": params_to_dict(params0),
        "timing": {
            "value_and_grad_batch": batch,
            "value_and_grad_items": items_name,
            "value_and_grad_first_call_s": first_s,
            "value_and_grad_warm_s": warm_s,
            "value_and_grad_warm_all_s": warm,
            "preprocess_s": prep_s, "eval_default_s": eval_s, "train_s": train_s,
            "total_s": time.perf_counter() - t_start,
            "backend": jax.default_backend(), "device": str(jax.devices()[0]),
        },
    }
    write_json(args.out_json, report)
    save_plot(losses, full, args.out_png,
              f"{names}: {n_train} {items_name}, batch {batch}, lr {args.lr}", items_name)
    save_weights_plot(curves, args.out_weights_png,
                      f"learnt weight against each input (others at their medians), {names}")
    print(f"wrote {args.out_json}, {args.out_png} and {args.out_weights_png}")
    return 0


def _mm(metres: float | None) -> str:
    return "n/a" if metres is None else f"{metres * 1e3:.2f}"


if __name__ == "__main__":
    raise SystemExit(main())
