"""Place recognition of the keyframe map (``map.recognition``: randomised ferns): its time per
query over 100 and 1,000 keyframes, and how often it ranks the right keyframe first on real
clips.

Usage::

    python scripts/place_recognition.py CLIP [CLIP ...] [--every 10] [--query-every 3]
                                        [--apart-s 0.5] [--out-json FILE]

Recall: in each clip, every ``--every``-th frame is a keyframe (its fern code, and its Canny
edges with depth as points); every ``--query-every``-th frame asks for the keyframes most
like it, among those more than ``--apart-s`` seconds from it (a revisit, not the frame next
door). The right keyframe is the one the query's camera would see best: of those with a
predicted overlap (``map.predicted_overlap``, at the two frames' ground-truth poses) of
``Config.map_overlap`` or more, the nearest view; else the highest overlap. Reported: the
share of queries whose right keyframe is first (top 1) and among the first
``Config.map_candidates`` (top 3), and of those with any keyframe at ``Config.map_overlap``
or more, the share with such a keyframe among the first three; and the top 3 split by the
change of viewpoint between the query and its right keyframe (``DISTANCE_BINS``,
``ANGLE_BINS``).
Timing: encoding a frame, then ``KeyframeMap.recognise`` and ``overlapping`` over maps of 100
and 1,000 keyframes (codes and points from the clips, repeated with a tenth of the ferns
redrawn), median and mean over 200 queries. Prints and writes JSON.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.tum import load_sequence
from edgevo_jax.frontend.selection import KeyframeEdges
from edgevo_jax.geometry import exp_np, inverse_np, rotation_angle_np
from edgevo_jax.image.preprocess import preprocess
from edgevo_jax.map import KeyframeMap, MapKeyframe, encode, make_ferns, predicted_overlap
from edgevo_jax.reports import script_record, write_json
from edgevo_jax.runs.measure import groundtruth_at

#: edge points per frame kept for the overlap (an even subsample of its edges with depth)
POINTS = 500


def frame_view(seq, i: int, ferns, config: Config):
    """Frame ``i``'s code and its edges with depth as points (3, N) in its camera."""
    rgb, depth = seq.rectify_frame(*seq.decode_frame(i))
    frame = preprocess(rgb, depth, config)
    code = encode(ferns, frame.gray, frame.depth)
    keep = np.flatnonzero(frame.edge_depth > 0)
    keep = keep[np.linspace(0, len(keep) - 1, min(POINTS, len(keep))).astype(int)]
    uv, z = frame.edge_uv[keep].astype(np.float64), frame.edge_depth[keep].astype(np.float64)
    fx, fy, cx, cy = seq.intrinsics
    points = np.stack([(uv[:, 0] - cx) / fx * z, (uv[:, 1] - cy) / fy * z, z])
    return code, points.astype(np.float32)


def recall(seq, *, every: int, query_every: int, apart_s: float, config: Config) -> dict:
    """The clip's recall measures (module doc)."""
    ferns = make_ferns()
    gt = groundtruth_at(seq, seq.timestamps)
    ok = [i for i in range(len(seq)) if np.all(np.isfinite(gt[i]))]
    views = {i: frame_view(seq, i, ferns, config) for i in ok if i % every == 0
             or i % query_every == 0}
    keys = [i for i in ok if i % every == 0]
    top1 = top3 = useful = has_useful = asked = 0
    viewpoints: list[tuple[float, float, bool]] = []  # (m, degrees, right one in the top 3)
    for q in (i for i in ok if i % query_every == 0):
        near = [k for k in keys if abs(seq.timestamps[k] - seq.timestamps[q]) > apart_s]
        if not near:
            continue
        share = np.array([predicted_overlap(views[k][1], inverse_np(gt[q]) @ gt[k],
                                            seq.intrinsics, (seq.height, seq.width))
                          for k in near])
        if share.max() <= 0:
            continue
        codes = np.stack([views[k][0] for k in near])
        score = np.count_nonzero(codes == views[q][0], axis=1)
        ranked = [near[j] for j in np.argsort(-score, kind="stable")]
        right = near[int(np.argmax(share))]
        over = [j for j in range(len(near)) if share[j] >= config.map_overlap]
        if over:  # of those that see the query well, the nearest view (as the map's queries)
            right = near[min(over, key=lambda j: view_distance(gt[near[j]], gt[q]))]
        first = ranked[:config.map_candidates]
        apart = inverse_np(gt[right]) @ gt[q]
        viewpoints.append((float(np.linalg.norm(apart[:3, 3])),
                           float(np.degrees(rotation_angle_np(apart))), right in first))
        asked += 1
        top1 += ranked[0] == right
        top3 += right in first
        if share.max() >= config.map_overlap:
            has_useful += 1
            useful += any(share[near.index(k)] >= config.map_overlap for k in first)
    return {"queries": asked, "keyframes": len(keys), "top1": top1 / max(asked, 1),
            "top3": top3 / max(asked, 1), "queries_with_a_keyframe_over_the_bar": has_useful,
            "one_over_the_bar_in_top3": useful / max(has_useful, 1),
            "top3_by_viewpoint": by_viewpoint(viewpoints)}


def view_distance(a: np.ndarray, b: np.ndarray) -> float:
    """How far two camera poses' views are apart: metres plus radians between the axes."""
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3])
                 + np.arccos(np.clip(a[:3, 2] @ b[:3, 2], -1.0, 1.0)))


#: bins of the change of viewpoint between a query and its right keyframe: metres, degrees
DISTANCE_BINS, ANGLE_BINS = (0.0, 0.1, 0.3, np.inf), (0.0, 5.0, 15.0, np.inf)


def by_viewpoint(rows: list[tuple[float, float, bool]]) -> list[dict]:
    """Top-3 recall by the change of viewpoint (``DISTANCE_BINS`` x ``ANGLE_BINS``): per bin
    its bounds, its queries and the share with the right keyframe among the first three."""
    out = []
    for d0, d1 in zip(DISTANCE_BINS[:-1], DISTANCE_BINS[1:], strict=True):
        for a0, a1 in zip(ANGLE_BINS[:-1], ANGLE_BINS[1:], strict=True):
            hits = [h for d, a, h in rows if d0 <= d < d1 and a0 <= a < a1]
            out.append({"metres": [d0, d1], "degrees": [a0, a1], "queries": len(hits),
                        "top3": float(np.mean(hits)) if hits else None})
    return out


def timing(seqs, config: Config) -> dict:
    """Query times over maps of 100 and 1,000 keyframes (module doc)."""
    ferns = make_ferns()
    views = [frame_view(s, i, ferns, config) for s in seqs for i in range(0, len(s), 5)]
    rng = np.random.default_rng(0)
    seq = seqs[0]
    rgb, depth = seq.rectify_frame(*seq.decode_frame(0))
    gray = preprocess(rgb, depth, config).gray
    t = []
    for _ in range(50):
        t0 = time.perf_counter()
        encode(ferns, gray, depth)
        t.append(time.perf_counter() - t0)
    out = {"encode_ms": {"median": 1e3 * float(np.median(t)), "mean": 1e3 * float(np.mean(t))}}
    for n in (100, 1000):
        kmap = KeyframeMap(seq.intrinsics, (seq.height, seq.width), max_keyframes=n)
        for k in range(n):
            code, points = views[k % len(views)]
            code = code.copy()
            redraw = rng.random(code.size) < 0.1
            code[redraw] = rng.integers(0, 16, int(redraw.sum()))
            pose = exp_np(np.r_[rng.normal(0, 0.5, 3), rng.normal(0, 0.3, 3)])
            n_pts = points.shape[1]
            edges = KeyframeEdges(np.zeros((2, n_pts), np.float32), 1.0 / points[2],
                                  np.zeros((2, n_pts), np.float32), np.ones(n_pts, bool))
            kmap.add(MapKeyframe(k, float(k), pose, edges, points, None, code))
        rec, ovl = [], []
        for q in range(200):
            code, _ = views[q % len(views)]
            t0 = time.perf_counter()
            kmap.recognise(code, k=config.map_candidates)
            t1 = time.perf_counter()
            kmap.overlapping(exp_np(np.r_[rng.normal(0, 0.5, 3), rng.normal(0, 0.3, 3)]), k=1,
                             min_overlap=config.map_overlap)
            rec.append(t1 - t0)
            ovl.append(time.perf_counter() - t1)
        out[str(n)] = {"recognise_ms": {"median": 1e3 * float(np.median(rec)),
                                        "mean": 1e3 * float(np.mean(rec))},
                       "overlapping_ms": {"median": 1e3 * float(np.median(ovl)),
                                          "mean": 1e3 * float(np.mean(ovl))},
                       "map_megabytes": kmap.nbytes / 1e6}
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Measure recall per clip and the query times; print and write them."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("clips", nargs="+", type=Path)
    p.add_argument("--every", type=int, default=10)
    p.add_argument("--query-every", type=int, default=3)
    p.add_argument("--apart-s", type=float, default=0.5)
    p.add_argument("--out-json", type=Path, default=Path("place_recognition.json"))
    args = p.parse_args(argv)
    enable_batch_exact()
    config = Config()
    seqs = [load_sequence(c) for c in args.clips]
    results = {}
    for seq in seqs:
        r = recall(seq, every=args.every, query_every=args.query_every,
                   apart_s=args.apart_s, config=config)
        results[seq.name] = r
        print(f"{seq.name}: {r['queries']} queries over {r['keyframes']} keyframes: right one "
              f"first {100 * r['top1']:.0f} %, in the first {config.map_candidates} "
              f"{100 * r['top3']:.0f} %; one over the {config.map_overlap:g} bar in the first "
              f"{config.map_candidates}: {100 * r['one_over_the_bar_in_top3']:.0f} % of "
              f"{r['queries_with_a_keyframe_over_the_bar']}", flush=True)
        for b in r["top3_by_viewpoint"]:
            if b["queries"]:
                print(f"  {b['metres'][0]:g}-{b['metres'][1]:g} m, {b['degrees'][0]:g}-"
                      f"{b['degrees'][1]:g} deg apart: {b['queries']} queries, top 3 "
                      f"{100 * b['top3']:.0f} %")
    times = timing(seqs, config)
    for n in ("100", "1000"):
        print(f"{n} keyframes: recognise {times[n]['recognise_ms']['mean']:.3f} ms mean "
              f"({times[n]['recognise_ms']['median']:.3f} median), overlapping "
              f"{times[n]['overlapping_ms']['mean']:.3f} ms mean; encode "
              f"{times['encode_ms']['mean']:.2f} ms")
    write_json(args.out_json, {
        **script_record("place_recognition.py", argv),
        "recall": results, "timing": times})
    return 0


if __name__ == "__main__":
    sys.exit(main())
