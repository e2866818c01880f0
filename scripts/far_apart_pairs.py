"""Far-apart frame pairs aligned alone: how far the image features' pose and the edge solve
started from it are from the truth, against the edge solve from the identity.

Usage::

    python scripts/far_apart_pairs.py CLIP [--gap 10] [--every 2] [--out-json F.json]

Pairs (i, i + gap) of the clip (gap 10: 3 Hz from 30 Hz), i every ``--every`` frames. For
each pair: the pose from ORB, then SIFT keypoints matched and PnP (``features.relative_pose``,
what the tracker's recovery and confirmation start from), the ``align`` solve from that pose
(a global shutter: ``align`` has no velocity for the rolling shutter), and ``align`` from the
identity; each error (cm, degrees) against the interpolated ground truth, with ``align``'s
state. Prints one line a pair and the medians and 90th percentiles; writes JSON.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from edgevo_jax import Config, align
from edgevo_jax.datasets import groundtruth_pose_at, load_sequence
from edgevo_jax.frontend import features
from edgevo_jax.geometry import inverse_np, rotation_angle_np
from edgevo_jax.image.preprocess import to_gray
from edgevo_jax.io import poses7_to_matrices
from edgevo_jax.reports import write_json


def error(T: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    """(cm, degrees) of T against the true T_target_source."""
    E = inverse_np(true) @ T
    return 100.0 * float(np.linalg.norm(E[:3, 3])), float(np.degrees(rotation_angle_np(E)))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("clip", type=Path)
    p.add_argument("--gap", type=int, default=10)
    p.add_argument("--every", type=int, default=2)
    p.add_argument("--out-json", type=Path, default=Path("far_apart_pairs.json"))
    args = p.parse_args(argv)
    seq, config = load_sequence(args.clip), Config()
    intr = seq.intrinsics
    truth = [groundtruth_pose_at(seq, float(t), 0.02, interpolate=True) for t in seq.timestamps]
    rows = []
    for i in range(0, len(seq) - args.gap, args.every):
        j = i + args.gap
        if truth[i] is None or truth[j] is None:
            continue
        Ti, Tj = poses7_to_matrices(np.asarray([truth[i], truth[j]]))
        true = inverse_np(Tj) @ Ti
        (rgb0, d0), (rgb1, d1) = seq.load_frame(i), seq.load_frame(j)
        row: dict = {"i": i, "true_deg": float(np.degrees(rotation_angle_np(true)))}
        for kind in ("orb", "sift"):
            T = features.relative_pose(
                features.detect(to_gray(rgb0), kind=kind), d0,
                features.detect(to_gray(rgb1), kind=kind), intr,
                min_depth=config.min_depth, max_depth=config.max_depth)
            row[kind] = None if T is None else error(T, true)
            if T is not None:
                r = align(rgb0, d0, rgb1, d1, intrinsics=intr, init=T, config=config)
                row[f"{kind}_edges"] = error(r.transform, true) if r.success else None
                row[f"{kind}_state"] = r.state
        r = align(rgb0, d0, rgb1, d1, intrinsics=intr, config=config)
        row["identity_edges"] = error(r.transform, true) if r.success else None
        row["identity_state"] = r.state
        print({k: (tuple(round(x, 2) for x in v) if isinstance(v, tuple) else v)
               for k, v in row.items()}, flush=True)
        rows.append(row)
    summary = {}
    for key in ("orb", "orb_edges", "sift", "sift_edges", "identity_edges"):
        v = np.asarray([r[key] for r in rows if r.get(key)], np.float64).reshape(-1, 2)
        if len(v):
            summary[key] = {"pairs": len(v), "cm_median": float(np.median(v[:, 0])),
                            "cm_p90": float(np.percentile(v[:, 0], 90)),
                            "deg_median": float(np.median(v[:, 1])),
                            "deg_p90": float(np.percentile(v[:, 1], 90))}
            s = summary[key]
            print(f"{key:15s} {s['pairs']:3d} pairs: {s['cm_median']:.1f} cm "
                  f"(90th {s['cm_p90']:.1f}), {s['deg_median']:.1f} deg (90th {s['deg_p90']:.1f})")
    write_json(args.out_json, {"clip": str(args.clip), "gap": args.gap, "pairs": rows,
                               "summary": summary, "of": len(rows)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
