"""Learn the depth residual's weight against the edges (``Config.depth_weight``) by gradients,
with ground truth, and test it in the plain tracker over seeds and frame rates.

Usage::

    python scripts/learn_depth_weight.py [CLIP ...] [--frame-steps 1,2,3] [--gaps 3]
                                         [--steps 40] [--batch 12] [--lr 0.1] [--seed 0]
                                         [--rot-weight 0.1] [--seeds 0,1,2,3,4] [--no-ate]
                                         [--eval-weights 2.5,...]
                                         [--out-json docs/learning/depth_weight.json]

CLIP defaults to the two shared clips (fr3_teddy first 200, fr1_rpy first 120). Each clip at
each frame step is split in time: keyframes in its first half train, in its second half are
held out. A chain is a keyframe i (its edges and depth points, as the tracker selects them,
seed ``config.seed + i``) and the next ``--gaps`` frames, solved in order by the plain
tracker's program (``align.track``): the first from the identity, each later one from the
one before, with the camera's rolling shutter (the previous frame's solved pose; the
keyframe itself for the first). Each pair's loss is ``learn.rpe_loss`` (translation m +
``--rot-weight`` x rotation rad) against the interpolated ground truth; its derivative in
log w comes from ``learn.depth_weight_gradient`` (implicit differentiation at the solve);
the fit averages it over the pairs solved within 5 cm and 5 deg of the truth (a solve
outside its basin has no useful local derivative).
Optimiser: optax adam on log w, ``--steps`` steps of ``--lr``, each over ``--batch`` training
chains drawn from ``--seed``.

Report (printed and written to ``--out-json``): w after each step, the held-out pairs' mean
and median translation (mm) and rotation (deg) error with w = 1 and with the learnt w, and,
unless ``--no-ate``, the ATE of full runs of the plain tracker (``run_sequence``, default
Config but ``depth_weight``) over ``--seeds`` and ``--frame-steps`` on each clip, both
weights (and each of ``--eval-weights``), with each run's silently wrong frames. Numbers
as they come, gain or not.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from edgevo_jax import Config
from edgevo_jax.datasets.base import camera_readout
from edgevo_jax.datasets.groundtruth import groundtruth_pose_at
from edgevo_jax.datasets.tum import SHARED_TUM
from edgevo_jax.derive import solve_knobs, solve_structure
from edgevo_jax.frontend.depth import depth_points
from edgevo_jax.frontend.selection import KeyframeEdges, keyframe_edges
from edgevo_jax.frontend.shutter import Shutter, shutter_rate
from edgevo_jax.geometry import inverse_np, rotation_angle_np
from edgevo_jax.image.preprocess import preprocess
from edgevo_jax.io import poses7_to_matrices
from edgevo_jax.learn import depth_weight_gradient
from edgevo_jax.pipeline.measure import accuracy, diverged_frames, groundtruth_at, load_clip
from edgevo_jax.pipeline.run import run_sequence
from edgevo_jax.provenance import machine_info
from edgevo_jax.reports import int_list, write_json

CLIPS = [SHARED_TUM / "rgbd_dataset_freiburg3_teddy_first200",
         SHARED_TUM / "rgbd_dataset_freiburg1_rpy_first120"]
#: pairs solved farther than this from the truth left the basin: a local derivative there
#: says nothing about the weight (they count in the held-out report, not in the fit)
BASIN_M, BASIN_DEG = 0.05, 5.0
_solve = jax.jit(depth_weight_gradient, static_argnames=("config", "rot_weight"))


def float_list(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("clips", nargs="*", type=Path, default=CLIPS)
    p.add_argument("--frame-steps", type=int_list, default=[1, 2, 3])
    p.add_argument("--gaps", type=int, default=3, help="frames tracked after each keyframe")
    p.add_argument("--steps", type=int, default=40, help="adam steps")
    p.add_argument("--batch", type=int, default=12, help="chains per step")
    p.add_argument("--lr", type=float, default=0.1, help="adam learning rate on log w")
    p.add_argument("--seed", type=int, default=0, help="minibatch draws")
    p.add_argument("--rot-weight", type=float, default=0.1)
    p.add_argument("--seeds", type=int_list, default=[0, 1, 2, 3, 4], help="tracker seeds")
    p.add_argument("--no-ate", action="store_true", help="skip the full runs")
    p.add_argument("--eval-weights", type=float_list, default=[],
                   help="more weights for the full runs (beside 1 and the learnt one)")
    p.add_argument("--out-json", type=Path, default=Path("docs/learning/depth_weight.json"))
    return p.parse_args(argv)


class Clip:
    """One clip at one frame step: its frames (preprocessed on demand), keyframes, truth."""

    def __init__(self, path: Path, step: int, config: Config):
        self.seq = load_clip(path, frame_step=step)
        self.name, self.step, self.config = self.seq.name, step, config
        self.intr = self.seq.intrinsics
        self.readout = camera_readout(self.seq)
        self.ts = np.asarray(self.seq.timestamps, np.float64)
        self._frames: dict[int, object] = {}
        self._kfs: dict[int, KeyframeEdges] = {}
        truth = [groundtruth_pose_at(self.seq, t, 0.02, interpolate=True) for t in self.ts]
        self.truth = [None if p is None else poses7_to_matrices(np.asarray(p)[None])[0]
                      for p in truth]

    def frame(self, i: int):
        if i not in self._frames:
            self._frames[i] = preprocess(*self.seq.load_frame(i), self.config)
        return self._frames[i]

    def keyframe(self, i: int) -> KeyframeEdges:
        if i not in self._kfs:
            c, f = self.config, self.frame(i)
            e = keyframe_edges(f, c, seed=c.seed + i, intr=self.intr)
            pts, normals = depth_points(f.depth, self.intr, c.depth_points,
                                        min_depth=c.min_depth, max_depth=c.max_depth,
                                        seed=c.seed + i)
            e = e._replace(depth_pts=pts, depth_normals=normals)
            self._kfs[i] = KeyframeEdges(*jax.tree.map(jnp.asarray, e))
        return self._kfs[i]

    def chains(self, gaps: int) -> tuple[list[int], list[int]]:
        """Keyframes whose chain has ground truth throughout: (training, held out)."""
        n = len(self.ts)
        ok = [i for i in range(n - gaps)
              if all(self.truth[j] is not None for j in range(i, i + gaps + 1))]
        return [i for i in ok if i + gaps < n // 2], [i for i in ok if i >= n // 2]


def solve_chain(clip: Clip, i: int, gaps: int, weight: float, rot_weight: float) -> list:
    """The chain of keyframe i at depth weight ``weight``: (loss, d loss / d log w,
    translation error m, rotation error deg) of each pair."""
    config = clip.config
    knobs = solve_knobs(config.replace(depth_weight=weight))
    kf = clip.keyframe(i)
    T = prev = np.eye(4)
    out = []
    for j in range(i + 1, i + gaps + 1):
        f = clip.frame(j)
        rate = shutter_rate(clip.readout, f.shape[0], clip.ts[j] - clip.ts[j - 1])
        shutter = Shutter(np.asarray(prev, np.float32), np.float32(rate))
        true = inverse_np(clip.truth[j]) @ clip.truth[i]
        res = _solve(kf, f.dist, f.edge_map, np.asarray(T, np.float32), clip.intr, knobs,
                     np.asarray(true, np.float32), config=solve_structure(config),
                     shutter=shutter, rot_weight=rot_weight)
        T_c_k = np.asarray(res.T_c_k, np.float64)
        err = inverse_np(true) @ T_c_k
        out.append((float(res.loss), float(res.grad_log_weight),
                    float(np.linalg.norm(err[:3, 3])), float(np.degrees(rotation_angle_np(err)))))
        T = prev = T_c_k
    return out


def held_out(clips: list[Clip], gaps: int, weight: float, rot_weight: float) -> dict:
    rows = []
    for clip in clips:
        for i in clip.chains(gaps)[1]:
            rows += solve_chain(clip, i, gaps, weight, rot_weight)
    a = np.asarray(rows)
    return {"pairs": len(rows), "loss_mean": float(a[:, 0].mean()),
            "t_mm_mean": 1e3 * float(a[:, 2].mean()),
            "t_mm_median": 1e3 * float(np.median(a[:, 2])),
            "r_deg_mean": float(a[:, 3].mean()), "r_deg_median": float(np.median(a[:, 3]))}


def ate_runs(paths: list[Path], steps: list[int], seeds: list[int], weight: float) -> dict:
    out: dict = {}
    for path in paths:
        for step in steps:
            seq = load_clip(path, frame_step=step)
            ates, wrong = [], []
            for seed in seeds:
                run = run_sequence(seq, Config(seed=seed, depth_weight=weight), progress=False)
                acc = accuracy(seq.groundtruth, run.timestamps, run.poses)
                ates.append(1e3 * acc["ate_rmse_m"])
                wrong.append(_silently_wrong(seq, run))
            out[f"{seq.name}@{step}"] = {"ate_mm": ates, "mean_mm": float(np.mean(ates)),
                                         "std_mm": float(np.std(ates)),
                                         "silently_wrong": wrong}
            print(f"  w={weight:.3g} {seq.name} step {step}: ATE {np.mean(ates):.2f} "
                  f"+- {np.std(ates):.2f} mm, silently wrong {sum(wrong)}", flush=True)
    return out


def _silently_wrong(seq, run) -> int:
    """Frames called OK off the truth's motion from the previous frame
    (``measure.diverged_frames``: silently wrong)."""
    gt = groundtruth_at(seq, np.asarray(run.timestamps, np.float64))
    return len(diverged_frames(np.asarray(run.poses), [r.state for r in run.results], gt))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    missing = [str(p) for p in args.clips if not p.is_dir()]
    if missing:
        print(f"no such clip folder: {', '.join(missing)}", file=sys.stderr)
        return 2
    config = Config()
    clips = [Clip(p, k, config) for p in args.clips for k in args.frame_steps]
    train = [(c, i) for c in clips for i in c.chains(args.gaps)[0]]
    print(f"{len(train)} training chains of {args.gaps} pairs over {len(clips)} clip-rates",
          flush=True)
    rng = np.random.default_rng(args.seed)
    opt = optax.adam(args.lr)
    log_w = jnp.zeros(())
    state = opt.init(log_w)
    history = []
    t0 = time.perf_counter()
    for step in range(args.steps):
        pick = rng.choice(len(train), min(args.batch, len(train)), replace=False)
        rows = [r for k in pick for r in solve_chain(*train[k], args.gaps,
                                                    float(jnp.exp(log_w)), args.rot_weight)]
        basin = [r for r in rows if r[2] <= BASIN_M and r[3] <= BASIN_DEG] or rows
        loss = float(np.mean([r[0] for r in basin]))
        grad = jnp.asarray(np.mean([r[1] for r in basin]))
        updates, state = opt.update(grad, state)
        log_w = optax.apply_updates(log_w, updates)
        history.append({"step": step, "pairs": len(basin), "loss": loss, "grad": float(grad),
                        "weight": float(jnp.exp(log_w))})
        print(f"step {step:3d}: loss {loss:.5f}, dL/dlog w {float(grad):+.2e}, "
              f"w {float(jnp.exp(log_w)):.3f} ({time.perf_counter() - t0:.0f} s)", flush=True)
    # the mean of the last quarter's weights: adam's steps on minibatches oscillate
    tail = [h["weight"] for h in history[-max(1, args.steps // 4):]]
    learnt = float(np.exp(np.mean(np.log(tail))))
    print(f"learnt depth_weight {learnt:.3f}", flush=True)
    report: dict = {"args": {k: str(v) for k, v in vars(args).items()}, "history": history,
                    "learnt_weight": learnt, "machine": machine_info()}
    report["held_out_pairs"] = {
        "w=1": held_out(clips, args.gaps, 1.0, args.rot_weight),
        "learnt": held_out(clips, args.gaps, learnt, args.rot_weight)}
    for name, h in report["held_out_pairs"].items():
        print(f"held-out pairs {name}: {h['pairs']} pairs, translation {h['t_mm_mean']:.2f} "
              f"mm mean ({h['t_mm_median']:.2f} median), rotation {h['r_deg_mean']:.3f} deg "
              f"mean ({h['r_deg_median']:.3f} median)", flush=True)
    if not args.no_ate:
        report["ate"] = {"w=1": ate_runs(args.clips, args.frame_steps, args.seeds, 1.0),
                         "learnt": ate_runs(args.clips, args.frame_steps, args.seeds, learnt)}
        for w in args.eval_weights:
            report["ate"][f"w={w:g}"] = ate_runs(args.clips, args.frame_steps, args.seeds, w)
    write_json(args.out_json, report)
    print(f"wrote {args.out_json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
