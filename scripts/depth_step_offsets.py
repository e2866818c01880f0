"""How far from a colour edge does the depth image put the depth step that belongs to it?

Usage::

    python scripts/depth_step_offsets.py [SEQ_DIR ...] [--frames 10] [--span 15]

Default sequences: the shared TUM clips in ``../shared/data/tum``. For ``--frames`` frames
evenly spread over each sequence, every culled edge (valid depth, gradient magnitude at least
the Canny high threshold) is sampled along its gradient from -span to +span px; where the
inverse depth jumps by more than 0.05 /m between two neighbouring samples somewhere on that
line (a depth step: 5 cm at 1 m), the distance of the largest jump from the edge pixel is
counted. Steps that belong to the edge pile up at small distances; unrelated steps nearby
spread evenly (the floor, the mean count over the last third of the span). Printed per
sequence: the histogram (1 px bins), the floor, and the first distance from which no bin
exceeds 1.25x the floor: how far the local map's depth-continuity test has to look
(``Config.activation_depth_reach``).
"""

from __future__ import annotations

import argparse

import numpy as np

from edgevo_jax import Config
from edgevo_jax.datasets.tum import SHARED_CLIPS, SHARED_TUM, load_sequence
from edgevo_jax.frontend.selection import cull
from edgevo_jax.image.preprocess import preprocess


def step_offsets(depth: np.ndarray, uv: np.ndarray, grad: np.ndarray, span: int,
                 min_jump: float = 0.05) -> np.ndarray:
    """Distances (px) from edges uv (2, K) along their gradients grad (2, K) to the largest
    inverse-depth jump within ``span`` px, for the edges with a jump over ``min_jump`` (1/m)
    and valid depth all along."""
    h, w = depth.shape
    s = np.arange(-span, span + 1)
    u = np.round(uv[0][None] + s[:, None] * grad[0][None]).astype(int)
    v = np.round(uv[1][None] + s[:, None] * grad[1][None]).astype(int)
    inside = np.all((u >= 0) & (u < w) & (v >= 0) & (v < h), axis=0)
    z = depth[np.clip(v, 0, h - 1), np.clip(u, 0, w - 1)]
    ok = inside & np.all(np.isfinite(z) & (z > 0), axis=0)
    jump = np.abs(np.diff(1.0 / np.where(ok[None] & (z > 0), z, 1.0), axis=0))
    sel = ok & (jump.max(0) > min_jump)
    k = jump[:, sel].argmax(0)
    return np.abs((s[k] + s[k + 1]) / 2.0)


def main(argv: list[str] | None = None) -> int:
    """Print the offset histogram of each sequence."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sequences", nargs="*", default=[str(SHARED_TUM / c) for c in SHARED_CLIPS])
    p.add_argument("--frames", type=int, default=10)
    p.add_argument("--span", type=int, default=15)
    args = p.parse_args(argv)
    config = Config()
    for path in args.sequences:
        seq = load_sequence(path)
        offsets = []
        for i in np.linspace(0, len(seq) - 1, min(args.frames, len(seq))).round().astype(int):
            frame = preprocess(*seq.load_frame(int(i)), config)
            idx = cull(frame, config)
            offsets.append(step_offsets(frame.depth, frame.edge_uv[idx].T,
                                        frame.edge_grad[idx].T, args.span))
        o = np.concatenate(offsets)
        hist = np.histogram(o, bins=np.arange(0, args.span + 1))[0]
        floor = hist[-(args.span // 3):].mean()
        over = np.flatnonzero(hist > 1.25 * floor)
        reach = int(over[-1]) + 1 if over.size else 0
        print(f"{seq.name}: {o.size} edges with a depth step within {args.span} px; "
              f"counts per px {hist.tolist()}; floor {floor:.0f}; above 1.25x floor up to "
              f"{reach} px")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
