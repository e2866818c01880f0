"""Local mapping on and off over selection seeds, in one process (same-session comparisons).

Usage::

    python scripts/mapping_eval.py [SEQ_DIR[@ppN] ...] [--seeds 0,1,2] [--max-frames N]
        [--variant NAME=key=value;key=value ...] [--out-json mapping.json]

Default sequence: ``../shared/data/tum/rgbd_dataset_freiburg3_teddy_first200``. ``@ppN``
after a folder plays it forward and backward to N frames (``datasets.pingpong``). Default
variants: ``nomap`` (``mapping=false``) and ``map`` (the defaults: local mapping on); a
``--variant`` replaces them (repeatable), e.g. ``--variant "nodepthtest=activation_depth_step=0"``.

Each run goes through ``runner.run_sequence`` with ``Config`` overrides plus ``seed=S``. The
seeds are the outer loop and the variants alternate inside it, so a drift in this shared
machine's load spreads over every variant. Per run: ATE RMSE (TUM's ``evaluate_ate``:
0.02 s association, rigid alignment, no scale), the ATE after a similarity alignment and its
scale (the factor the estimate needs to fit the ground truth: above 1 when its translations
are short), warm median and p90 ms per frame, median mapping_ms per keyframe, keyframes and
lost frames. Per sequence and variant: the mean ATE over seeds and its ratio to the first
variant's. One line per run to stderr, the table to stdout, everything to ``--out-json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.pingpong import pingpong
from edgevo_jax.datasets.tum import SHARED_TUM, TumSequence, load_sequence
from edgevo_jax.io import json_safe, matrices_to_poses7
from edgevo_jax.metrics import ate
from edgevo_jax.pipeline.run import run_sequence, summarise
from edgevo_jax.provenance import machine_info

DEFAULT_VARIANTS = ("nomap=mapping=false", "map=")


def load(spec: str) -> TumSequence:
    """A sequence folder, or ``FOLDER@ppN`` for it played forward and backward to N frames."""
    path, _, n = spec.partition("@pp")
    seq = load_sequence(path)
    return pingpong(seq, int(n)) if n else seq


def similarity_ate(seq: TumSequence, timestamps: np.ndarray, poses: np.ndarray
                   ) -> tuple[float, float]:
    """(RMSE after a similarity alignment (m), its scale) of positions against the ground
    truth, associated as the ATE does (``ate(..., align="sim3")``: Umeyama 1991 with
    scale)."""
    a = ate(seq.groundtruth, (np.asarray(timestamps), matrices_to_poses7(np.asarray(poses))),
            align="sim3")
    return a["rmse"], a["scale"]


def parse_variant(spec: str) -> tuple[str, list[str]]:
    """``NAME=key=value;key=value`` -> (NAME, ["key=value", ...]) (no overrides after ``NAME=``)."""
    name, _, sets = spec.partition("=")
    if not name:
        raise ValueError(f"--variant needs NAME=..., got {spec!r}")
    return name, [s for s in sets.split(";") if s.strip()]


def main(argv: list[str] | None = None) -> int:
    """Run every sequence x seed x variant; print and write the results."""
    enable_batch_exact()  # the CLI's arithmetic: trajectories as `edgevo run` gives them
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sequences", nargs="*",
                   default=[str(SHARED_TUM / "rgbd_dataset_freiburg3_teddy_first200")])
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--variant", action="append", default=[])
    p.add_argument("--out-json", type=Path, default=Path("mapping_eval.json"))
    args = p.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    variants = dict(parse_variant(s) for s in (args.variant or DEFAULT_VARIANTS))
    runs = []
    for spec in args.sequences:
        seq = load(spec)
        for seed in seeds:
            for name, sets in variants.items():
                config = Config().with_overrides([*sets, f"seed={seed}"])
                run = run_sequence(seq, config, progress=False, max_frames=args.max_frames)
                st = summarise(run, seq)
                sim, scale = similarity_ate(seq, np.asarray(run.timestamps),
                                            np.asarray(run.poses))
                row = {"sequence": seq.name, "variant": name, "seed": seed,
                       "ate_m": st["ate_rmse_m"], "sim3_ate_m": sim, "scale": scale,
                       "ms_median": st["ms_per_frame"]["median"],
                       "ms_p90": st["ms_per_frame"]["p90"],
                       "mapping_ms_median": st["mapping_ms"]["median"],
                       "keyframes": st["keyframes"], "lost": st["lost"]}
                runs.append(row)
                print(f"{seq.name} seed {seed} {name}: ATE {row['ate_m'] * 1e3:.2f} mm, "
                      f"similarity {sim * 1e3:.2f} mm at scale {scale:.4f}, "
                      f"{row['ms_median']:.1f} ms/frame (p90 {row['ms_p90']:.1f}), mapping "
                      f"{row['mapping_ms_median']:.0f} ms/keyframe", file=sys.stderr, flush=True)
    summary = []
    print("| sequence | variant | mean ATE (mm) | vs first | per seed (mm) | scale | "
          "ms/frame | mapping ms |")
    print("|---|---|---|---|---|---|---|---|")
    for name_seq in dict.fromkeys(r["sequence"] for r in runs):
        base = None
        for name in variants:
            rs = [r for r in runs if r["sequence"] == name_seq and r["variant"] == name]
            mean = float(np.mean([r["ate_m"] for r in rs]))
            base = mean if base is None else base
            agg = {"sequence": name_seq, "variant": name, "mean_ate_m": mean,
                   "ratio": mean / base, "mean_scale": float(np.mean([r["scale"] for r in rs])),
                   "ms_median": float(np.median([r["ms_median"] for r in rs])),
                   "mapping_ms_median": float(np.median([r["mapping_ms_median"] for r in rs]))}
            summary.append(agg)
            per = " ".join(f"{r['ate_m'] * 1e3:.2f}" for r in rs)
            print(f"| {name_seq} | {name} | {mean * 1e3:.2f} | {agg['ratio']:.3f} | {per} | "
                  f"{agg['mean_scale']:.4f} | {agg['ms_median']:.1f} | "
                  f"{agg['mapping_ms_median']:.0f} |")
    out = {"command": sys.argv, "machine": machine_info(), "seeds": seeds,
           "variants": variants, "runs": runs, "summary": summary}
    args.out_json.write_text(json.dumps(json_safe(out), indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
