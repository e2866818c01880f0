"""What a motion prior (``Odometry.track(..., prior=T_prev_cur)``) changes: a clip tracked at
a frame step with no prior (constant velocity), with the ground truth's motion between the
frames as the prior (an ideal IMU) and with that motion off by a fixed twist (a biased one).
Prints the ATE and the WEAK / LOST counts of each.

    python scripts/prior_bench.py ../shared/data/tum/rgbd_dataset_freiburg1_rpy_first120 --step 2
"""

from __future__ import annotations

import argparse

import numpy as np

from edgevo_jax import Config, Odometry, enable_batch_exact, load_sequence
from edgevo_jax.datasets.groundtruth import groundtruth_pose_at
from edgevo_jax.datasets.source import camera_readout
from edgevo_jax.geometry import exp_np, inverse_np, rotation_angle_np
from edgevo_jax.io import matrices_to_poses7, poses7_to_matrices
from edgevo_jax.metrics import ate

#: the biased prior's error, a twist [v, w] right-multiplied: 18.5 mm, 0.81 degrees
BIAS = np.array([0.012, -0.01, 0.01, 0.01, 0.0, -0.01])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("clip", help="a TUM folder with groundtruth.txt")
    ap.add_argument("--step", type=int, default=1, help="track every STEP-th frame")
    args = ap.parse_args(argv)
    enable_batch_exact()
    seq = load_sequence(args.clip)
    gt = {}
    for i in range(0, len(seq), args.step):  # the ground truth at each frame's own time
        pose7 = groundtruth_pose_at(seq, float(seq.timestamps[i]), interpolate=True)
        if pose7 is not None:
            gt[i] = poses7_to_matrices(np.asarray(pose7)[None])[0]
    idx = sorted(gt)
    frames = {i: seq.load_frame(i) for i in idx}
    bias = exp_np(BIAS)
    print(f"{seq.name}, every {args.step} frame(s), {len(idx)} frames; bias "
          f"{1e3 * np.linalg.norm(bias[:3, 3]):.1f} mm, "
          f"{np.degrees(rotation_angle_np(bias)):.2f} deg")
    for mode in ("none", "ground truth", "biased"):
        results = []
        with Odometry(Config(), seq.intrinsics, initial_pose=gt[idx[0]],
                      readout_s=camera_readout(seq)) as odo:
            for k, i in enumerate(idx):
                prior = None
                if k and mode != "none":
                    prior = inverse_np(gt[idx[k - 1]]) @ gt[i]
                    prior = prior @ bias if mode == "biased" else prior
                results.append(odo.track(*frames[i], seq.timestamps[i], prior=prior))
        est = matrices_to_poses7(np.array([r.pose for r in results]))
        gt_t, gt_p = seq.groundtruth
        err = ate(gt_t, gt_p, np.array([r.timestamp for r in results]), est)
        states = [r.state for r in results]
        print(f"  prior {mode:12s}: ATE {1e3 * err['rmse']:.1f} mm, WEAK "
              f"{states.count('WEAK')}, LOST {states.count('LOST')}")


if __name__ == "__main__":
    main()
