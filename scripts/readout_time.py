"""Calibrate a camera's rolling-shutter readout time from a hand-held sequence, without ground
truth.

Usage::

    python scripts/readout_time.py SEQ [--frame-step K] [--max-frames N]
                                   [--readouts-ms 0,5,10,15,20,25,30,35,40,50]
                                   [--set KEY=VALUE ...] [--out-json FILE]

A rolling-shutter image is sheared by the camera's motion while its rows are read out
(``edgevo_jax.frontend.shutter``); with the right readout time tau, a keyframe and a frame
taken at different speeds align with lower residuals than with any other. The sequence is
tracked once (the default ``Config`` with the ``--set`` overrides: the source's own readout
time unless ``--set readout_s=...``), giving every frame's
pose and keyframe. Then, for every tau of the grid, each frame is aligned again to its
keyframe, from its tracked pose, with the keyframe's edges moved to its middle row's time
and the frame's rolling shutter modelled with tau (velocities from the tracked poses); the
mean level-0 robust cost per keyframe edge in view over those pairs is the criterion. Its
minimum, refined by a parabola through the three grid points around it, is the estimate.
The sequence needs rotation (the shear is proportional to the angular velocity) and changes
of speed (frames and keyframes taken at the same speed shear alike).

Prints the curve and the estimate; writes JSON.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.source import camera_readout, open_source
from edgevo_jax.derive import readout_time, solve_knobs, solve_structure
from edgevo_jax.frontend.align import track
from edgevo_jax.frontend.selection import KeyframeEdges, keyframe_edges
from edgevo_jax.frontend.shutter import Shutter, shutter_rate, unroll_edges
from edgevo_jax.geometry import inverse_np, log_np
from edgevo_jax.image.preprocess import preprocess
from edgevo_jax.io import json_safe
from edgevo_jax.pipeline.calibrate import tracked_pairs
from edgevo_jax.programs import program
from edgevo_jax.provenance import machine_info

DEFAULT_READOUTS_MS = (0, 5, 10, 15, 20, 25, 30, 35, 40, 50)

_track = program(track, static_argnames="config")


def pair_costs(seq: Any, config: Config, ts: np.ndarray, poses: np.ndarray,
               pairs: Sequence[tuple[int, int]], readouts_s: Sequence[float]
               ) -> np.ndarray:
    """(len(readouts_s), len(pairs)): each pair's level-0 robust cost per keyframe edge in
    view after aligning the frame to its keyframe from its tracked pose with each readout
    time (see the module doc)."""
    frames: dict[int, Any] = {}

    def frame(i: int):
        if i not in frames:
            frames[i] = preprocess(*seq.load_frame(i), config)
        return frames[i]

    intr, height = seq.intrinsics, seq.height
    structure, knobs = solve_structure(config), solve_knobs(config)
    edges = {j: keyframe_edges(frame(j), config, seed=config.seed + j, intr=intr)
             for j in sorted({j for j, _ in pairs})}
    out = np.zeros((len(readouts_s), len(pairs)))
    for a, tau in enumerate(readouts_s):
        for b, (j, i) in enumerate(pairs):
            kf = edges[j]
            if tau > 0:
                twist = log_np(inverse_np(poses[j - 1]) @ poses[j]) \
                    * shutter_rate(tau, height, ts[j] - ts[j - 1])
                kf = unroll_edges(kf, twist, intr, height)
            shutter = Shutter(np.asarray(inverse_np(poses[i - 1]) @ poses[j], np.float32),
                              np.float32(shutter_rate(tau, height, ts[i] - ts[i - 1])))
            f = frame(i)
            res = _track(KeyframeEdges(*kf), f.dist, f.edge_map,
                         np.asarray(inverse_np(poses[i]) @ poses[j], np.float32), intr,
                         config=structure, knobs=knobs, shutter=shutter)
            out[a, b] = float(res.cost) / max(float(res.visible), 1.0)
    return out


def estimate(readouts_s: Sequence[float], curve: Sequence[float]) -> float:
    """The minimum of a sampled curve: the vertex of the parabola through the lowest grid
    point and its two neighbours (the grid point itself at either end of the grid or where
    the three are not convex)."""
    x, y = np.asarray(readouts_s, np.float64), np.asarray(curve, np.float64)
    k = int(np.argmin(y))
    if k == 0 or k == len(x) - 1:
        return float(x[k])
    a, b, _ = np.polyfit(x[k - 1:k + 2], y[k - 1:k + 2], 2)
    return float(-b / (2 * a)) if a > 0 else float(x[k])


def main(argv: Sequence[str] | None = None) -> int:
    """Track, sweep the readout time, print and write the result."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", help="a TUM or ETH3D folder or a bag (edgevo run's sources)")
    p.add_argument("--frame-step", type=int, default=1)
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--readouts-ms", default=",".join(map(str, DEFAULT_READOUTS_MS)),
                   help="the readout times to try (ms, comma-separated)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a Config field of the tracking run (repeatable)")
    p.add_argument("--out-json", type=Path, default=Path("readout_time.json"))
    args = p.parse_args(argv)
    enable_batch_exact()
    readouts = [float(v) * 1e-3 for v in args.readouts_ms.split(",") if v.strip()]
    if len(readouts) < 3 or min(readouts) < 0:
        raise SystemExit("--readouts-ms needs at least three times >= 0")
    seq = open_source(args.sequence, frame_step=args.frame_step)
    config = Config().with_overrides(args.set)
    tracked_with = readout_time(config, camera_readout(seq))
    ts, poses, pairs = tracked_pairs(seq, config, args.max_frames)
    if len(pairs) < 5:
        raise SystemExit(f"{seq.name}: only {len(pairs)} frame-keyframe pairs tracked; the "
                         "calibration needs a longer sequence")
    costs = pair_costs(seq, config, ts, poses, pairs, readouts)
    curve = costs.mean(axis=1)
    best = estimate(readouts, curve)
    result = {
        "command": shlex.join(["python", "scripts/readout_time.py", *argv]),
        "machine": machine_info(), "sequence": seq.name, "pairs": len(pairs),
        "tracked_with_readout_s": tracked_with, "readouts_s": readouts,
        "cost_per_visible_edge": curve.tolist(), "estimate_s": best,
    }
    args.out_json.parent.mkdir(parents=True, exist_ok=True)
    args.out_json.write_text(json.dumps(json_safe(result), indent=1) + "\n")
    print(f"{seq.name}: {len(pairs)} frame-keyframe pairs (tracked with a readout of "
          f"{1e3 * tracked_with:.0f} ms)")
    for tau, c in zip(readouts, curve, strict=True):
        print(f"  readout {1e3 * tau:5.1f} ms: cost per edge in view {c:.4f}")
    print(f"estimate: {1e3 * best:.1f} ms (Config.readout_s={best:.4f}); wrote {args.out_json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
