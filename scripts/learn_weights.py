"""Fit the tracker's learnable ``Params`` on TUM frame pairs and report the held-out RPE.

Usage::

    python scripts/learn_weights.py [SEQ_DIR] [--train 0:100] [--test 100:200] [--gaps 1,2,3]
                                    [--num-edges 256] [--steps 60] [--batch 32] [--lr 3e-3]
                                    [--seed 0] [--rot-weight 0.1]
                                    [--out-json docs/learning/learn_weights.json]
                                    [--out-png docs/learning/loss.png]

SEQ_DIR defaults to ``SHARED_TUM / rgbd_dataset_freiburg3_teddy_first200`` (the project's
development clip, not shipped).

Data. Each frame i of a range is a keyframe: its ``num_edges`` edges chosen by
``selection.keyframe_edges`` (fixed slots, the config's selection, seed = ``--seed`` + i) and
their gradient magnitudes (``learn.edge_magnitudes``); frame i + k (k in ``--gaps``, inside
the same range) is the target. The true relative pose is T_cur_kf = inv(T_w_cur) @ T_w_kf
from the ground truth nearest in time (pairs where either frame has no ground truth within
20 ms are skipped). Training pairs come from ``--train`` (frames 0-99), held-out pairs from
``--test`` (frames 100-199); no pair crosses the two ranges. The initial pose of every pair
is the identity (no constant-velocity prior: frame-to-frame motion is small, and a prior
from the ground truth would leak the answer).

Model. ``learn.track_differentiable(..., adjoint="unrolled", consistency="soft")``, jitted
and ``jax.vmap``-ped over a batch of pairs (the frames' distance pyramids and nearest-edge
gradients are stacked once on the device and each pair gathers its keyframe and target by
index inside the jitted function). Loss: the mean ``learn.rpe_loss`` (translation m +
``--rot-weight`` x rotation rad) over the batch. Optimiser: optax adam, ``--steps`` steps of
``--lr``, minibatches of ``--batch`` training pairs drawn without replacement (reshuffled
each epoch) from ``numpy.random.default_rng(--seed)``; float32. The same seed gives the same
pairs, batches and result (up to XLA's floating-point reduction order). ``reobs_a`` only
enters edge selection (not differentiated) and stays at its default.

Report (printed, and written to ``--out-json``): held-out RPE (mean and median translation
error in mm and rotation error in deg over the held-out pairs, ``learn.relative_pose_error``)
with ``Params.default`` and with the fitted Params, the same on the training pairs, the
training loss per step (also plotted to ``--out-png``), the fitted Params, and the time of a
warm ``value_and_grad`` over one ``--batch``-pair batch (median of a few calls, printed apart
from the first call's compile time). Numbers are reported as they come, gain or not.

Not measured: ATE on the held-out frames. It needs the frame-by-frame tracker
(``runner.run_sequence``) to run with the fitted Params, and it does not take Params yet;
the JSON says so (``"ate"``).

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

from edgevo_jax import Config
from edgevo_jax.datasets import groundtruth_pose_at, load_sequence
from edgevo_jax.datasets.tum import SHARED_TUM
from edgevo_jax.geometry import inverse_np
from edgevo_jax.interp import stack_edge_maps
from edgevo_jax.io import json_safe, poses7_to_matrices
from edgevo_jax.learn import edge_magnitudes, relative_pose_error, rpe_loss, track_differentiable
from edgevo_jax.params import Params
from edgevo_jax.preprocess import preprocess
from edgevo_jax.selection import keyframe_edges
from edgevo_jax.solve import KeyframeEdges

DEFAULT_SEQ = SHARED_TUM / "rgbd_dataset_freiburg3_teddy_first200"
ATE_NOTE = "not measured: the frame-by-frame tracker does not take Params yet"
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
    p.add_argument("--num-edges", type=int, default=256, help="keyframe edge slots")
    p.add_argument("--steps", type=int, default=60, help="adam steps")
    p.add_argument("--batch", type=int, default=32, help="pairs per minibatch")
    p.add_argument("--lr", type=float, default=3e-3, help="adam learning rate")
    p.add_argument("--rot-weight", type=float, default=0.1,
                   help="loss = translation (m) + rot_weight * rotation (rad)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timing-reps", type=int, default=3, help="warm value_and_grad calls timed")
    p.add_argument("--out-json", type=Path, default=Path("docs/learning/learn_weights.json"))
    p.add_argument("--out-png", type=Path, default=Path("docs/learning/loss.png"))
    return p.parse_args(argv)


def build_data(seq, frames: list[int], pairs_of: dict[str, list[tuple[int, int]]],
               config: Config, seed: int) -> dict[str, Any]:
    """Preprocess ``frames`` once; keyframe edges for every keyframe used; stacked arrays."""
    index = {f: j for j, f in enumerate(frames)}
    keyframes = sorted({i for pairs in pairs_of.values() for i, _ in pairs})
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


def make_functions(data: dict, intr, config: Config, rot_weight: float):
    """Jitted batch functions of (params, kf slots, frame slots, T_gt)."""
    arrays = (data["kf"], data["mag"], data["dist"], data["edge_map"])

    def one(params, arrays, ki, fi):
        kf_all, mag_all, dist_all, ng_all = arrays
        kf = jax.tree.map(lambda x: x[ki], kf_all)
        dist = tuple(d[fi] for d in dist_all)
        ng = jax.tree.map(lambda x: x[fi], ng_all)
        out = track_differentiable(kf, dist, ng, jnp.eye(4, dtype=jnp.float32), intr,
                                   params, config, mag=mag_all[ki], adjoint="unrolled")
        return out.T_c_k

    batched = jax.vmap(one, in_axes=(None, None, 0, 0))

    def loss(params, arrays, ki, fi, T_gt):
        T_est = batched(params, arrays, ki, fi)
        losses = jax.vmap(lambda a, b: rpe_loss(a, b, rot_weight=rot_weight))(T_est, T_gt)
        return jnp.mean(losses)

    def errors(params, arrays, ki, fi, T_gt):
        return jax.vmap(relative_pose_error)(batched(params, arrays, ki, fi), T_gt)

    vg = jax.jit(jax.value_and_grad(loss))
    err = jax.jit(errors)
    return (lambda p, ki, fi, T: vg(p, arrays, ki, fi, T),
            lambda p, ki, fi, T: err(p, arrays, ki, fi, T))


def evaluate(err_fn, params, ki, fi, T_gt, batch: int,
             rot_weight: float) -> dict[str, float]:
    """RPE over all pairs, in chunks of ``batch`` (the last one padded by repetition), and
    the mean training loss over them."""
    n = int(ki.shape[0])
    t_all, r_all = [], []
    for s in range(0, n, batch):
        idx = np.arange(s, s + batch) % n  # fixed chunk shape: one compilation
        t, r = err_fn(params, ki[idx], fi[idx], T_gt[idx])
        keep = min(batch, n - s)
        t_all.append(np.asarray(t)[:keep])
        r_all.append(np.asarray(r)[:keep])
    t_m, r_rad = np.concatenate(t_all), np.concatenate(r_all)
    t, r = t_m * 1e3, np.degrees(r_rad)
    return {"pairs": n, "loss": float(np.mean(t_m + rot_weight * r_rad)),
            "t_mean_mm": float(np.mean(t)), "t_median_mm": float(np.median(t)),
            "r_mean_deg": float(np.mean(r)), "r_median_deg": float(np.median(r))}


def save_plot(losses: list[float], full: list[float], path: Path, title: str) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 3), dpi=80)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(np.arange(len(losses)), losses, marker="o", markersize=2, lw=0.8, alpha=0.6,
            label="minibatch (before its step)")
    ax.plot(np.arange(len(full)), full, lw=1.8, label="all training pairs")
    ax.set_xlabel("adam step")
    ax.set_ylabel("mean RPE loss")
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def main(argv: list[str] | None = None) -> int:
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
    for name, pairs in pairs_of.items():
        if not pairs:
            say(f"no {name} pairs with ground truth in frames {ranges[name]} of {seq.name}")
            return 2
    frames = sorted({f for pairs in pairs_of.values() for pr in pairs for f in pr})
    say(f"{seq.name}: {len(pairs_of['train'])} training and {len(pairs_of['test'])} held-out "
        f"pairs, {len(frames)} frames to preprocess")
    t0 = time.perf_counter()
    data = build_data(seq, frames, pairs_of, config, args.seed)
    prep_s = time.perf_counter() - t0
    say(f"preprocessing and edge selection: {prep_s:.1f} s")

    vg, err = make_functions(data, seq.intrinsics, config, args.rot_weight)
    train = pair_arrays(pairs_of["train"], gt, data)
    test = pair_arrays(pairs_of["test"], gt, data)
    n_train = len(pairs_of["train"])
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
    print(f"value_and_grad over {batch} pairs: first call (compile + run) {first_s:.2f} s, "
          f"warm {warm_s * 1e3:.1f} ms (median of {len(warm)})")

    t0 = time.perf_counter()
    before = {"test": evaluate(err, params0, *test, batch, args.rot_weight),
              "train": evaluate(err, params0, *train, batch, args.rot_weight)}
    eval_s = time.perf_counter() - t0

    opt = optax.adam(args.lr)
    # reobs_a only enters the (non-differentiated) selection: keep it fixed
    mask = Params(*(name != "reobs_a" for name in Params._fields))
    opt = optax.masked(opt, mask)
    state = opt.init(params0)
    params = params0
    losses: list[float] = []
    full = [before["train"]["loss"]]  # loss over every training pair, after each step
    t0 = time.perf_counter()
    for step in range(args.steps):
        b = next(draw)
        value, grads = vg(params, *(x[b] for x in train))
        if not all(bool(jnp.all(jnp.isfinite(g))) for g in grads):
            say(f"step {step + 1}: non-finite gradient, step skipped")
            losses.append(float(value))
            full.append(full[-1])
            continue
        updates, state = opt.update(grads, state, params)
        params = optax.apply_updates(params, updates)
        losses.append(float(value))
        full.append(evaluate(err, params, *train, batch, args.rot_weight)["loss"])
        say(f"step {step + 1:3d}/{args.steps}: minibatch loss {float(value):.5f}, "
            f"all training pairs {full[-1]:.5f}")
    train_s = time.perf_counter() - t0

    after = {"test": evaluate(err, params, *test, batch, args.rot_weight),
             "train": evaluate(err, params, *train, batch, args.rot_weight)}

    for split in ("test", "train"):
        b, a = before[split], after[split]
        label = "held-out" if split == "test" else "training"
        print(f"{label} RPE over {b['pairs']} pairs: translation {b['t_mean_mm']:.2f} -> "
              f"{a['t_mean_mm']:.2f} mm (mean), rotation {b['r_mean_deg']:.3f} -> "
              f"{a['r_mean_deg']:.3f} deg (mean)  [default -> fitted]")

    fitted = {name: np.asarray(v) for name, v in zip(Params._fields, params, strict=True)}
    fitted["huber_delta"] = np.exp(np.asarray(params.log_huber))
    fitted["temperature"] = float(np.exp(np.asarray(params.log_temperature)))
    report = {
        "sequence": str(seq.root), "sequence_name": seq.name,
        "settings": {
            "train_frames": list(ranges["train"]), "test_frames": list(ranges["test"]),
            "gaps": gaps, "num_edges": args.num_edges, "steps": args.steps, "batch": batch,
            "lr": args.lr, "rot_weight": args.rot_weight, "seed": args.seed,
            "adjoint": "unrolled", "consistency": "soft", "T_init": "identity",
            "dtype": "float32", "iterations": list(config.iterations),
            "selection": config.selection, "optimizer": "optax.adam (reobs_a held fixed)",
            "loss": "mean over the batch of rpe_loss = t_err (m) + rot_weight * r_err (rad)",
        },
        "pairs": {"train": len(pairs_of["train"]), "test": len(pairs_of["test"])},
        "rpe": {"default": before, "fitted": after,
                "units": "t: mm, r: deg, of E = T_gt^-1 T_est per pair"},
        "ate": ATE_NOTE,
        "loss_curve": {"minibatch": losses, "all_training_pairs": full,
                       "note": "minibatch[s] is the loss of step s's batch before its update; "
                               "all_training_pairs[s] the loss over every training pair "
                               "after s steps (s = 0: default Params)"},
        "fitted_params": fitted,
        "default_params": {name: np.asarray(v)
                           for name, v in zip(Params._fields, params0, strict=True)},
        "timing": {
            "value_and_grad_batch": batch,
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
              f"{seq.name}: {len(pairs_of['train'])} pairs, batch {batch}, lr {args.lr}")
    print(f"wrote {args.out_json} and {args.out_png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
