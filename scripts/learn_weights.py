"""Fit the tracker's learnable ``Params`` on TUM frame pairs and report the held-out RPE.

Usage::

    python scripts/learn_weights.py [SEQ_DIR] [--train 0:100] [--test 100:200] [--gaps 1,2,3]
                                    [--loss pairs|window] [--window 8] [--num-edges 256]
                                    [--steps 60] [--batch 32] [--lr 3e-3] [--seed 0]
                                    [--rot-weight 0.1] [--no-ate] [--control-runs 0]
                                    [--out-json docs/learning/learn_weights.json]
                                    [--out-png docs/learning/loss.png]

SEQ_DIR defaults to ``SHARED_TUM / rgbd_dataset_freiburg3_teddy_first200`` (the project's
development clip, not shipped).

Data. Each frame i of a range is a keyframe: its ``num_edges`` edges chosen by
``selection.keyframe_edges`` (fixed slots, the config's selection, seed = ``--seed`` + i)
with their gradient magnitudes. Pairs: frame i + k (k in ``--gaps``, inside the same range)
is tracked against keyframe i from the identity (no constant-velocity prior: frame-to-frame
motion is small, and a prior from the ground truth would leak the answer). Windows
(``--loss window``): frames i + 1 .. i + ``--window`` are tracked in order against keyframe
i, each from the constant-velocity prediction of the two before it (``learn.track_window``,
as the tracker does between keyframes; the identity for the first). The true relative poses
come from the ground truth nearest in time (frames without ground truth within 20 ms are
left out). Training items come from ``--train`` (frames 0-99), held-out ones from ``--test``
(frames 100-199); none crosses the two ranges.

Model. ``learn.track_differentiable(..., adjoint="unrolled", consistency="soft")`` (or
``track_window``), jitted and ``jax.vmap``-ped over a batch (the frames' distance pyramids
and direction maps are stacked once on the device and each item gathers its keyframe and
frames by index inside the jitted function). Loss: with ``--loss pairs`` (the default) the
mean ``learn.rpe_loss`` (translation m + ``--rot-weight`` x rotation rad) over a batch of
pairs; with ``--loss window`` the mean ``learn.window_rpe_loss`` of the window's
consecutive motions (keyframe -> first frame, first -> second, ...) over a batch of
windows. Optimiser: optax adam, ``--steps`` steps of ``--lr``, minibatches of ``--batch``
items drawn without replacement (reshuffled each epoch) from
``numpy.random.default_rng(--seed)``; float32. The same seed gives the same items, batches
and result (up to XLA's floating-point reduction order). ``reobs_a`` only enters edge
selection (not differentiated) and stays at its default.

Report (printed, and written to ``--out-json``): held-out pair RPE (mean and median
translation error in mm and rotation error in deg over the held-out pairs from the identity,
``learn.relative_pose_error``) with ``Params.default`` and with the fitted Params, the same on
the training pairs; the ATE (rigid alignment, TUM's ``evaluate_ate``) and the RPE per second
(``metrics.rpe``) of full tracker runs (``runner.run_sequence`` with the same config, the
plain tracker with its hard consistency test) over the held-out frames only, with the
default and with the fitted Params (``--no-ate`` skips them), and with ``--control-runs N``
N more with the defaults moved along random directions by as much as the fit moved them (how
much the ATE moves for a change of that size without fitting); the training loss per step
(also plotted to ``--out-png``), the fitted Params (``fitted_params``: what ``edgevo run
--params`` reads), and the time of a warm ``value_and_grad`` over one ``--batch``-item batch
(median of a few calls, printed apart from the first call's compile time). Numbers are
reported as they come, gain or not.

The data are the TUM RGB-D benchmark's (CC BY 4.0): J. Sturm, N. Engelhard, F. Endres,
W. Burgard, D. Cremers, "A Benchmark for the Evaluation of RGB-D SLAM Systems", IROS 2012.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets import groundtruth_pose_at, load_sequence, subsequence
from edgevo_jax.datasets.tum import SHARED_TUM
from edgevo_jax.frontend.selection import KeyframeEdges, keyframe_edges
from edgevo_jax.geometry import Pose, inverse_np
from edgevo_jax.image.interp import stack_edge_maps
from edgevo_jax.image.preprocess import preprocess
from edgevo_jax.io import json_safe, poses7_to_matrices
from edgevo_jax.learn import (
    edge_magnitudes,
    relative_pose_error,
    rpe_loss,
    track_differentiable,
    track_window,
    window_rpe_loss,
)
from edgevo_jax.learn.params import Params, params_to_dict
from edgevo_jax.pipeline.run import run_sequence, summarise

DEFAULT_SEQ = SHARED_TUM / "rgbd_dataset_freiburg3_teddy_first200"
GT_MAX_DIFF = 0.02  # s


def say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _range(text: str) -> tuple[int, int]:
    a, b = text.split(":")
    return int(a), int(b)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", nargs="?", type=Path, default=DEFAULT_SEQ,
                   help="TUM sequence folder (default: the shared fr3_teddy_first200 clip)")
    p.add_argument("--train", type=_range, default=(0, 100), help="training frames a:b")
    p.add_argument("--test", type=_range, default=(100, 200), help="held-out frames a:b")
    p.add_argument("--gaps", default="1,2,3", help="frame gaps k of the pairs (i, i + k)")
    p.add_argument("--loss", choices=("pairs", "window"), default="pairs",
                   help="fit on frame pairs or on windows tracked against a keyframe")
    p.add_argument("--window", type=int, default=8, help="frames per window (--loss window)")
    p.add_argument("--num-edges", type=int, default=256, help="keyframe edge slots")
    p.add_argument("--steps", type=int, default=60, help="adam steps")
    p.add_argument("--batch", type=int, default=32, help="pairs or windows per minibatch")
    p.add_argument("--lr", type=float, default=3e-3, help="adam learning rate")
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
    return p.parse_args(argv)


def build_data(seq, frames: list[int], keyframes: list[int], config: Config,
               seed: int) -> dict[str, Any]:
    """Preprocess ``frames`` once; keyframe edges for every keyframe used; stacked arrays."""
    index = {f: j for j, f in enumerate(frames)}
    dist_levels: list[list[np.ndarray]] = [[] for _ in range(config.num_levels)]
    grads, kfs = [], {}
    for f in frames:
        frame = preprocess(*seq.load_frame(f), config)
        for lvl, d in enumerate(frame.dist):
            dist_levels[lvl].append(d)
        grads.append(frame.edge_map)
        if f in keyframes:
            e = keyframe_edges(frame, config, seed=seed + f, intr=seq.intrinsics)
            kfs[f] = (e, edge_magnitudes(frame, e))
    k_index = {f: j for j, f in enumerate(keyframes)}
    stack = lambda xs: jnp.asarray(np.stack(xs))  # noqa: E731
    kf = KeyframeEdges(stack([np.asarray(kfs[f][0].uv, np.float32) for f in keyframes]),
                       stack([np.asarray(kfs[f][0].rho, np.float32) for f in keyframes]),
                       stack([np.asarray(kfs[f][0].grad, np.float32) for f in keyframes]),
                       stack([np.asarray(kfs[f][0].valid) for f in keyframes]))
    return {
        "dist": tuple(stack(d) for d in dist_levels),
        "edge_map": jax.tree.map(jnp.asarray, stack_edge_maps(grads)),
        "kf": kf,
        "mag": stack([kfs[f][1] for f in keyframes]),
        "kf_index": k_index,
        "frame_index": index,
    }


def pair_arrays(pairs: list[tuple[int, int]], gt: dict[int, np.ndarray], data: dict):
    """(kf slot, target frame slot, T_gt (P, 4, 4)) of the pairs."""
    ki = np.array([data["kf_index"][i] for i, _ in pairs], np.int32)
    fi = np.array([data["frame_index"][j] for _, j in pairs], np.int32)
    T = np.stack([inverse_np(gt[j]) @ gt[i] for i, j in pairs]).astype(np.float32)
    return jnp.asarray(ki), jnp.asarray(fi), jnp.asarray(T)


def window_arrays(windows: list[tuple[int, list[int]]], gt: dict[int, np.ndarray],
                  data: dict):
    """(kf slot, frame slots (B, W), true poses (B, W + 1, 4, 4)) of the windows: the poses
    T_kf_cam of the keyframe (identity) and of each frame, relative to the keyframe."""
    ki = np.array([data["kf_index"][i] for i, _ in windows], np.int32)
    fi = np.array([[data["frame_index"][j] for j in js] for _, js in windows], np.int32)
    P = np.stack([[inverse_np(gt[i]) @ gt[j] for j in (i, *js)] for i, js in windows])
    return jnp.asarray(ki), jnp.asarray(fi), jnp.asarray(P.astype(np.float32))


def make_functions(data: dict, intr, config: Config, rot_weight: float, loss_kind: str):
    """Jitted batch functions of (params, kf slots, frame slots, truth): the training loss's
    value_and_grad and value (pairs or windows), and the pair errors."""
    arrays = (data["kf"], data["mag"], data["dist"], data["edge_map"])
    eye = jnp.eye(4, dtype=jnp.float32)

    def gather(arrays, ki, fi):
        kf_all, mag_all, dist_all, ng_all = arrays
        kf = jax.tree.map(lambda x: x[ki], kf_all)
        dist = tuple(d[fi] for d in dist_all)
        return kf, mag_all[ki], dist, jax.tree.map(lambda x: x[fi], ng_all)

    def pair(params, arrays, ki, fi):
        kf, mag, dist, ng = gather(arrays, ki, fi)
        return track_differentiable(kf, dist, ng, eye, intr, params, config, mag=mag,
                                    adjoint="unrolled").T_c_k

    def window(params, arrays, ki, fi):  # fi (W,): poses T_kf_cam, keyframe first
        kf, mag, dist, ng = gather(arrays, ki, fi)
        T = track_window(kf, dist, ng, eye, eye, intr, params, config, mag=mag,
                         adjoint="unrolled").T_c_k
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

    vg, each, err = jax.jit(jax.value_and_grad(loss)), jax.jit(item_losses), jax.jit(errors)
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


def run_ate(seq, frames: tuple[int, int], config: Config, params: Params | None) -> dict:
    """ATE (m, TUM's evaluate_ate) and RPE per second of a full tracker run over ``frames``
    (the plain tracker: hard consistency test) with ``params`` (None: the defaults)."""
    part = subsequence(seq, *frames)
    t0 = time.perf_counter()
    run = run_sequence(part, config, progress=False, params=params)
    stats = summarise(run, part)
    return {"frames": len(run.results), "keyframes": run.num_keyframes,
            "lost": stats["lost"], "weak": stats["weak"],
            "ate_rmse_m": stats.get("ate_rmse_m"),
            "rpe_rmse_m_per_s": stats.get("rpe_rmse_m_per_s"),
            "rpe_rmse_deg_per_s": stats.get("rpe_rmse_deg_per_s"),
            "note": stats.get("ground_truth_note"),
            "run_s": time.perf_counter() - t0}


def control_runs(seq, frames: tuple[int, int], config: Config, params0: Params,
                 fitted: Params, n: int, seed: int) -> dict:
    """How much the held-out ATE moves for a change of Params of the fit's size without any
    fitting: ``n`` runs with the default Params moved along random directions (seeded by
    ``seed``) by as much as the fit moved them (the same norm over the fitted leaves)."""
    rng = np.random.default_rng(seed + 1)
    moved = [name for name in Params._fields if name != "reobs_a"]
    step = {k: np.asarray(getattr(fitted, k), np.float64) - np.asarray(getattr(params0, k))
            for k in moved}
    norm = float(np.sqrt(sum(np.sum(d * d) for d in step.values())))
    runs = []
    for _ in range(n):
        direction = {k: rng.normal(size=np.shape(d)) for k, d in step.items()}
        scale = norm / float(np.sqrt(sum(np.sum(d * d) for d in direction.values())))
        p = params0._replace(**{k: jnp.asarray(np.asarray(getattr(params0, k)) + scale * d,
                                               jnp.float32) for k, d in direction.items()})
        runs.append(run_ate(seq, frames, config, p))
    return {"step_norm": norm, "runs": runs,
            "note": "default Params moved along random directions by the fit's step norm"}


def save_plot(losses: list[float], full: list[float], path: Path, title: str,
              what: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 3), dpi=80)
    FigureCanvasAgg(fig)
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
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def main(argv: list[str] | None = None) -> int:
    enable_batch_exact()  # the CLI's arithmetic: trajectories as `edgevo run` gives them
    try:
        import optax
    except ImportError:
        say("optax is missing: pip install 'optax>=0.2' (or the package's 'learn' extra)")
        return 2
    args = parse_args(argv)
    if not args.sequence.is_dir():
        say(f"sequence folder not found: {args.sequence} (the fr3_teddy_first200 clip lives in "
            f"{SHARED_TUM}; pass another TUM folder as the first argument)")
        return 2
    t_start = time.perf_counter()
    seq = load_sequence(args.sequence)
    if seq.groundtruth is None:
        say(f"{seq.name} has no groundtruth.txt: nothing to fit against")
        return 2
    config = Config(num_edges=args.num_edges)
    gaps = [int(g) for g in args.gaps.split(",")]
    n = len(seq)
    ranges = {"train": (args.train[0], min(args.train[1], n)),
              "test": (args.test[0], min(args.test[1], n))}
    gt: dict[int, np.ndarray] = {}
    for a, b in ranges.values():
        for f in range(a, b):
            p = groundtruth_pose_at(seq, float(seq.timestamps[f]), GT_MAX_DIFF)
            if p is not None:
                gt[f] = poses7_to_matrices(p[None])[0]
    pairs_of = {name: [(i, i + k) for i in range(a, b) for k in gaps
                       if i + k < b and i in gt and i + k in gt]
                for name, (a, b) in ranges.items()}
    a, b = ranges["train"]
    windows = [(i, list(range(i + 1, i + 1 + args.window))) for i in range(a, b - args.window)
               if all(f in gt for f in range(i, i + 1 + args.window))]
    for name, pairs in pairs_of.items():
        if not pairs:
            say(f"no {name} pairs with ground truth in frames {ranges[name]} of {seq.name}")
            return 2
    if args.loss == "window" and not windows:
        say(f"no training window of {args.window} frames with ground truth in {ranges['train']}")
        return 2
    used = list(windows) if args.loss == "window" else []
    frames = sorted({f for pairs in pairs_of.values() for pr in pairs for f in pr}
                    | {f for i, js in used for f in (i, *js)})
    keyframes = sorted({i for pairs in pairs_of.values() for i, _ in pairs}
                       | {i for i, _ in used})
    items_name = "windows" if args.loss == "window" else "pairs"
    say(f"{seq.name}: {len(pairs_of['train'])} training and {len(pairs_of['test'])} held-out "
        f"pairs" + (f", {len(used)} training windows" if used else "")
        + f", {len(frames)} frames to preprocess")
    t0 = time.perf_counter()
    data = build_data(seq, frames, keyframes, config, args.seed)
    prep_s = time.perf_counter() - t0
    say(f"preprocessing and edge selection: {prep_s:.1f} s")

    vg, value, err = make_functions(data, seq.intrinsics, config, args.rot_weight, args.loss)
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

    opt = optax.adam(args.lr)
    # reobs_a only enters the (non-differentiated) selection: keep it fixed
    mask = Params(*(name != "reobs_a" for name in Params._fields))
    opt = optax.masked(opt, mask)
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
        test_frames = ranges["test"]
        ate = {"frames": list(test_frames),
               "default": run_ate(seq, test_frames, config, None),
               "fitted": run_ate(seq, test_frames, config, params),
               "note": "full runs of the plain tracker (hard consistency test) over the "
                       "held-out frames only, the same config as the fit"}
        d, f = ate["default"], ate["fitted"]
        print(f"held-out run over frames {test_frames[0]}-{test_frames[1] - 1}: ATE "
              f"{_mm(d['ate_rmse_m'])} -> {_mm(f['ate_rmse_m'])} mm, RPE "
              f"{_mm(d['rpe_rmse_m_per_s'])} -> {_mm(f['rpe_rmse_m_per_s'])} mm/s  "
              f"[default -> fitted]")
        if args.control_runs > 0:
            ate["control"] = control_runs(seq, test_frames, config, params0, params,
                                          args.control_runs, args.seed)
            c = [r["ate_rmse_m"] for r in ate["control"]["runs"]]
            print(f"control: default Params moved at random by the fit's step size, "
                  f"{len(c)} runs: ATE {', '.join(_mm(x) for x in c)} mm")

    fitted: dict[str, Any] = params_to_dict(params)
    fitted["huber_delta"] = np.exp(np.asarray(params.log_huber)).tolist()
    fitted["temperature"] = float(np.exp(np.asarray(params.log_temperature)))
    report = {
        "sequence": str(seq.root), "sequence_name": seq.name,
        "settings": {
            "train_frames": list(ranges["train"]), "test_frames": list(ranges["test"]),
            "gaps": gaps, "loss_kind": args.loss,
            "window": args.window if args.loss == "window" else None,
            "num_edges": args.num_edges, "steps": args.steps, "batch": batch,
            "lr": args.lr, "rot_weight": args.rot_weight, "seed": args.seed,
            "adjoint": "unrolled", "consistency": "soft",
            "T_init": "identity (pairs); constant velocity from the identity (windows)",
            "dtype": "float32", "iterations": list(config.iterations),
            "selection": config.selection, "optimizer": "optax.adam (reobs_a held fixed)",
            "loss": ("mean over the batch of window_rpe_loss (consecutive motions of the "
                     "window, keyframe first)" if args.loss == "window" else
                     "mean over the batch of rpe_loss") +
                    " = t_err (m) + rot_weight * r_err (rad)",
        },
        "pairs": {"train": len(pairs_of["train"]), "test": len(pairs_of["test"])},
        "training_items": {"kind": items_name, "count": n_train},
        "rpe": {"default": before, "fitted": after,
                "units": "t: mm, r: deg, of E = T_gt^-1 T_est per pair, tracked from the "
                         "identity"},
        "ate": ate,
        "loss_curve": {"minibatch": losses, f"all_training_{items_name}": full,
                       "note": "minibatch[s] is the loss of step s's batch before its update; "
                               f"all_training_{items_name}[s] the loss over every training "
                               "item after s steps (s = 0: default Params)"},
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
    args.out_json.parent.mkdir(parents=True, exist_ok=True)
    args.out_json.write_text(json.dumps(json_safe(report), indent=2) + "\n")
    save_plot(losses, full, args.out_png,
              f"{seq.name}: {n_train} {items_name}, batch {batch}, lr {args.lr}", items_name)
    print(f"wrote {args.out_json} and {args.out_png}")
    return 0


def _mm(metres: float | None) -> str:
    return "n/a" if metres is None else f"{metres * 1e3:.2f}"


if __name__ == "__main__":
    raise SystemExit(main())
