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
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.tum import SHARED_TUM
from edgevo_jax.learn import Smoothing
from edgevo_jax.learn.params import Params, params_to_dict
from edgevo_jax.reports import write_json
from edgevo_jax.runs.fit import (
    FIXED,
    build_data,
    control_runs,
    evaluate,
    make_functions,
    make_part,
    mean_loss,
    pair_arrays,
    run_parts,
    train,
    weight_curves,
    window_arrays,
)
from edgevo_jax.runs.measure import load_clip
from edgevo_jax.viz.learning import plot_loss_curve, plot_weight_curves

DEFAULT_SEQ = SHARED_TUM / "rgbd_dataset_freiburg3_teddy_first200"


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
        import optax  # noqa: F401  (before any work: the fit needs it)
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
    items = window_arrays(used, gt, data) if used else train_pairs
    n_train = int(items[0].shape[0])
    batch = min(args.batch, n_train)
    params0 = Params.default(config, jnp.float32)

    # timing: first call (compile + run), then warm calls on the same batch
    idx = np.arange(batch)
    t0 = time.perf_counter()
    jax.block_until_ready(vg(params0, *(x[idx] for x in items)))
    first_s = time.perf_counter() - t0
    warm = []
    for _ in range(max(args.timing_reps, 1)):
        t0 = time.perf_counter()
        jax.block_until_ready(vg(params0, *(x[idx] for x in items)))
        warm.append(time.perf_counter() - t0)
    warm_s = float(np.median(warm))
    print(f"value_and_grad over {batch} {items_name}: first call (compile + run) "
          f"{first_s:.2f} s, warm {warm_s * 1e3:.1f} ms (median of {len(warm)})")

    t0 = time.perf_counter()
    before = {"test": evaluate(err, params0, *test_pairs, batch, args.rot_weight),
              "train": evaluate(err, params0, *train_pairs, batch, args.rot_weight)}
    eval_s = time.perf_counter() - t0

    start_loss = mean_loss(value, params0, items, batch)  # over every training item
    t0 = time.perf_counter()
    params, losses, full = train(vg, value, params0, items, steps=args.steps, batch=batch,
                                 lr=args.lr, rng=np.random.default_rng(args.seed),
                                 start_loss=start_loss, say=say, what=items_name)
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
    plot_loss_curve(losses, full, args.out_png,
                    f"{names}: {n_train} {items_name}, batch {batch}, lr {args.lr}", items_name)
    plot_weight_curves(curves, args.out_weights_png,
                       f"learnt weight against each input (others at their medians), {names}")
    print(f"wrote {args.out_json}, {args.out_png} and {args.out_weights_png}")
    return 0


def _mm(metres: float | None) -> str:
    return "n/a" if metres is None else f"{metres * 1e3:.2f}"


if __name__ == "__main__":
    raise SystemExit(main())
