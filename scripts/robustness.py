"""Track a TUM sequence with damaged frames and compare with the clean run.

Every ``--black``-th frame's image is replaced by a black one (no edges) and every
``--no-depth``-th frame's depth by zeros (no measurement), counting from the second frame so
that the run can start. Prints and writes JSON: per run the ATE on the undamaged frames, the
frames flagged (state and reason), whether any pose is non-finite, and the ratio of the
damaged run's ATE to the clean run's.

    python scripts/robustness.py [SEQ] [--black 3] [--no-depth 7] [--out robustness.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.tum import SHARED_TUM, EmptyDepthWarning, TumSequence, load_sequence
from edgevo_jax.io import json_safe, matrices_to_poses7
from edgevo_jax.metrics import ate
from edgevo_jax.pipeline.run import run_sequence


@dataclasses.dataclass(frozen=True, eq=False)
class DamagedSequence(TumSequence):
    """A TumSequence whose frame i decodes black when (i % black == black - 1) and with zero
    depth when (i % no_depth == no_depth - 1)."""

    black: int = 0
    no_depth: int = 0

    def damaged(self, i: int) -> tuple[bool, bool]:
        """(black image, zero depth) for frame i."""
        return (self.black > 0 and i % self.black == self.black - 1,
                self.no_depth > 0 and i % self.no_depth == self.no_depth - 1)

    def decode_frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        rgb, raw = super().decode_frame(i)
        is_black, no_depth = self.damaged(i)
        return (np.zeros_like(rgb) if is_black else rgb,
                np.zeros_like(raw) if no_depth else raw)


def run(seq: TumSequence, config: Config, keep: np.ndarray) -> dict:
    """Track ``seq``; the ATE over the frames in ``keep`` and the flags."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", EmptyDepthWarning)
        result = run_sequence(seq, config, progress=False)
    poses = result.poses
    gt_t, gt_p = seq.groundtruth
    est = matrices_to_poses7(poses[keep])
    flags = Counter(f"{r.state}: {r.reason}" for r in result.results if r.state != "OK")
    return {"ate_rmse_m": ate((gt_t, gt_p), (result.timestamps[keep], est))["rmse"],
            "frames": len(result.results), "non_finite_poses": int((~np.isfinite(poses)).sum()),
            "flagged": dict(flags), "keyframes": result.num_keyframes}


def main() -> None:
    enable_batch_exact()  # the CLI's arithmetic: trajectories as `edgevo run` gives them
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sequence", nargs="?", type=Path,
                   default=SHARED_TUM / "rgbd_dataset_freiburg3_teddy_first200")
    p.add_argument("--black", type=int, default=3)
    p.add_argument("--no-depth", type=int, default=7)
    p.add_argument("--out", type=Path, default=Path("robustness.json"))
    args = p.parse_args()
    config = Config()
    clean = load_sequence(args.sequence)
    fields = {f.name: getattr(clean, f.name) for f in dataclasses.fields(TumSequence)}
    damaged = DamagedSequence(**fields, black=args.black, no_depth=args.no_depth)
    keep = np.array([not any(damaged.damaged(i)) for i in range(len(clean))])
    out = {"sequence": clean.name, "black_every": args.black, "no_depth_every": args.no_depth,
           "frames_damaged": int((~keep).sum()), "clean": run(clean, config, keep),
           "damaged": run(damaged, config, keep)}
    out["ate_ratio"] = out["damaged"]["ate_rmse_m"] / out["clean"]["ate_rmse_m"]
    text = json.dumps(json_safe(out), indent=2)
    print(text)
    args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
