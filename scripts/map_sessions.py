"""Maps that last, measured (``--save-map``, ``--map``): a recording cut in two sessions,
a run that never sees the map's place, and the digests of a save and a load.

Usage::

    python scripts/map_sessions.py split CLIP [--at 100] [--seeds 0-4] [--out-json FILE]
    python scripts/map_sessions.py never CLIP --map-of CLIP2 [--rounds 3] [--out-json FILE]
    python scripts/map_sessions.py digests CLIP [--at 5] [--out-json FILE]
    python scripts/map_sessions.py loop CLIP [--depth-scale 1.06] [--seeds 0-4]

``split``: the clip's frames before ``--at`` and from it on are two sessions, cut as a user
cuts a recording (``subsequence``: the same files); each order in turn, per seed: the first
session runs from the truth's first pose and saves its map, the second starts at the
identity in that map (so only the map can put it in the truth's frame). Printed and kept:
the index of the second session's first frame placed in the map (``found_in_loaded``),
its frames WEAK, both sessions' poses together after one rigid alignment to the truth
(ATE) against one uninterrupted run of the clip with the same seed, and the ratio.

``never``: ``CLIP`` under ``CLIP2``'s camera (its intrinsics; ``--camera-of clip``: both
under ``CLIP``'s) against a map of ``CLIP2``, and the same run with no map, ``--rounds``
times interleaved: whether it was ever placed (it should not be), its states, and the mean
and median ms a frame of both (warm: the first frames left out, ``measure.frame_stats``)
and their ratio.

``loop``: a loop between two sessions after real drift: the clip there and back
(``datasets.there_and_back``: its even frames forward, its odd frames back, the way back
through a depth sensor reading ``--depth-scale`` short, ``perturb.perturbed_copy``); the
way there is the first session, its map saved; the way back, from the identity in that
map, is found in it where it starts and drifts back to where the first session began. Per
seed, the second session with loops and without (``loops=false``): where it was found, the
loops it closed to keyframes of the loaded map (and any wrong, ``measure.wrong_loops``),
and both sessions' ATE after one rigid alignment.

``digests``: the clip's frames before ``--at`` saved as a map and the rest run in it: the
map saved, loaded and saved again (the same bytes?), the second session run twice in the
same map (the same trajectory?), and run once more saving its map at every frame (the
trajectory changed?), as sha256 digests.
"""

from __future__ import annotations

import dataclasses
import hashlib
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets import there_and_back
from edgevo_jax.datasets.perturb import perturbed_copy
from edgevo_jax.datasets.tum import load_sequence, subsequence
from edgevo_jax.map.archive import (
    library_version,
    load_map,
    map_settings,
    read_keyframe_table,
    save_map,
)
from edgevo_jax.reports import digest, script_parser, script_record, write_json
from edgevo_jax.runs.measure import accuracy, frame_stats, wrong_loops
from edgevo_jax.runs.run import RunResult, run_sequence


def session(seq, config: Config, *, map_file: Path | None = None,
            save_to: Path | None = None, save_each: bool = False) -> RunResult:
    """``seq`` tracked as ``edgevo run`` tracks it but from the identity (its truth hidden),
    in ``map_file`` where given, its map saved to ``save_to`` at the end (and after every
    frame with ``save_each``)."""
    def save(result, rgb, frame, odo) -> None:
        if odo.has_keyframe:
            odo.save_map(save_to)

    return run_sequence(dataclasses.replace(seq, groundtruth=None), config, progress=False,
                        map_file=map_file, save_map=save_to,
                        on_frame=save if save_each else None)


def _states(run: RunResult) -> dict[str, int]:
    return {s: sum(r.state == s for r in run.results) for s in ("OK", "WEAK", "LOST")}


def split(args, tmp: Path) -> dict:
    """Both orders of the two sessions, every seed (module doc)."""
    seq = load_sequence(args.clip)
    halves = {"first": subsequence(seq, 0, args.at), "second": subsequence(seq, args.at,
                                                                            len(seq))}
    rows = []
    for seed in args.seeds:
        config = Config().with_overrides([*args.set, f"seed={seed}"])
        whole = run_sequence(seq, config, progress=False)
        ate_whole = accuracy(seq.groundtruth, whole.timestamps, whole.poses)["ate_rmse_m"]
        for saved, later in (("first", "second"), ("second", "first")):
            path = tmp / f"{saved}_{seed}.npz"
            one = run_sequence(halves[saved], config, progress=False, save_map=path)
            two = session(halves[later], config, map_file=path)
            t = np.concatenate([one.timestamps, halves[later].timestamps])
            poses = np.concatenate([one.poses, two.poses])
            ate = accuracy(seq.groundtruth, t, poses)["ate_rmse_m"]
            found = two.found_in_loaded
            row = {"seed": seed, "map_of": saved, "found_in_loaded": found,
                   "weak_before_found": sum(r.state == "WEAK" for r in two.results[:found or 0]),
                   "states": _states(two),
                   "ate_m": ate, "ate_whole_m": ate_whole, "ratio": ate / ate_whole,
                   "placed": next((r.placed for r in two.results if r.placed), None)}
            rows.append(row)
            print(f"seed {seed}, map of the {saved} session: found at frame {found}; both "
                  f"sessions {1e3 * ate:.2f} mm, one run {1e3 * ate_whole:.2f} mm "
                  f"({row['ratio']:.2f}x); states {row['states']}", flush=True)
    for saved in ("first", "second"):
        mine = [r for r in rows if r["map_of"] == saved]
        print(f"map of the {saved}: found at {[r['found_in_loaded'] for r in mine]}, ratio "
              f"{min(r['ratio'] for r in mine):.2f}-{max(r['ratio'] for r in mine):.2f}")
    return {"clip": str(args.clip), "at": args.at, "runs": rows}


def never(args, tmp: Path) -> dict:
    """A run of one place against the map of another, with the same camera (module doc)."""
    if args.camera_of == "map":
        other = load_sequence(args.map_of)
        seq = load_sequence(args.clip, intrinsics=other.intrinsics)
    else:
        seq = load_sequence(args.clip)
        other = load_sequence(args.map_of, intrinsics=seq.intrinsics)
    config = Config().with_overrides(args.set)
    path = tmp / "other.npz"
    run_sequence(other, config, progress=False, save_map=path)
    rows = []
    for n in range(args.rounds):
        plain = session(seq, config)
        inmap = session(seq, config, map_file=path)
        a, b = frame_stats(plain.frame_ms), frame_stats(inmap.frame_ms)
        rows.append({"round": n, "found_in_loaded": inmap.found_in_loaded,
                     "states": _states(inmap),
                     "ms_without": a, "ms_with": b, "ratio_mean": b["mean"] / a["mean"],
                     "ratio_median": b["median"] / a["median"]})
        print(f"round {n}: found {inmap.found_in_loaded}; states {rows[-1]['states']}; ms a "
              f"frame {b['mean']:.2f} (median {b['median']:.2f}) in the map, {a['mean']:.2f} "
              f"({a['median']:.2f}) without: {rows[-1]['ratio_mean']:.2f}x "
              f"({rows[-1]['ratio_median']:.2f}x)", flush=True)
    with_ms = sum(r["ms_with"]["mean"] for r in rows)
    without_ms = sum(r["ms_without"]["mean"] for r in rows)
    print(f"over {len(rows)} rounds: mean ms a frame {with_ms / len(rows):.2f} in the map, "
          f"{without_ms / len(rows):.2f} without: {with_ms / without_ms:.2f}x")
    return {"clip": str(args.clip), "map_of": str(args.map_of), "camera_of": args.camera_of,
            "ratio_of_means": with_ms / without_ms, "runs": rows}


def loop(args, tmp: Path) -> dict:
    """Two sessions there and back, a loop between them after drift (module doc)."""
    clip = load_sequence(args.clip)
    biased = tmp / args.clip.name  # the name keeps the camera
    perturbed_copy(args.clip, biased, depth_scale=args.depth_scale)
    seq = there_and_back(clip, load_sequence(biased))
    half = (len(clip) + 1) // 2  # the even frames: the way there
    there, back = subsequence(seq, 0, half), subsequence(seq, half, len(seq))
    rows = []
    for seed in args.seeds:
        config = Config().with_overrides([*args.set, f"seed={seed}"])
        path = tmp / f"there_{seed}.npz"
        one = run_sequence(there, config, progress=False, save_map=path)
        loaded = set(read_keyframe_table(path)["id"].tolist())
        row: dict = {"seed": seed}
        for name, cfg in (("loops", config), ("map_only", config.replace(loops=False))):
            two = session(back, cfg, map_file=path)
            closed = (two.loops or {"closed": []})["closed"]
            t = np.concatenate([one.timestamps, back.timestamps])
            ate = accuracy(seq.groundtruth, t, np.concatenate([one.poses, two.poses]))
            row[name] = m = {
                "found_in_loaded": two.found_in_loaded, "ate_m": ate["ate_rmse_m"],
                "loops_old_new": sum(e["older"] in loaded for e in closed),
                "loops_closed": len(closed),
                "loops_wrong": wrong_loops(two.loops, seq),
                "digest": digest(two)}
            print(f"seed {seed} {name:8s}: found at frame {m['found_in_loaded']}; both "
                  f"sessions {1e3 * m['ate_m']:.1f} mm; loops {m['loops_closed']} closed, "
                  f"{m['loops_old_new']} to the loaded map, {m['loops_wrong']} wrong",
                  flush=True)
        rows.append(row)
    ratio = [r["loops"]["ate_m"] / r["map_only"]["ate_m"] for r in rows]
    print(f"ATE loops / map only: {min(ratio):.2f}-{max(ratio):.2f}; a loop to the loaded "
          f"map in {sum(r['loops']['loops_old_new'] > 0 for r in rows)} of {len(rows)} seeds")
    return {"clip": str(args.clip), "depth_scale": args.depth_scale, "runs": rows}


def digests(args, tmp: Path) -> dict:
    """Save, load, save; two runs in one map; saving at every frame (module doc)."""
    seq = load_sequence(args.clip)
    config = Config().with_overrides(args.set)
    first, second = subsequence(seq, 0, args.at), subsequence(seq, args.at, len(seq))
    path, again = tmp / "map.npz", tmp / "again.npz"
    run_sequence(first, config, progress=False, save_map=path)
    loaded = load_map(path, intrinsics=seq.intrinsics, settings=map_settings(config),
                      max_keyframes=config.map_max_keyframes)
    save_map(again, loaded.kmap, settings=map_settings(config), library=library_version(),
             edges=loaded.edges)
    runs = [session(second, config, map_file=path) for _ in range(2)]
    saving = session(second, config, map_file=path, save_to=tmp / "each.npz", save_each=True)
    out = {"map": hashlib.sha256(path.read_bytes()).hexdigest(),
           "map_saved_again": hashlib.sha256(again.read_bytes()).hexdigest(),
           "runs": [digest(r) for r in runs],
           "saving_each_frame": digest(saving),
           "found_in_loaded": [r.found_in_loaded for r in (*runs, saving)]}
    print(f"map {out['map'][:16]}, saved again {out['map_saved_again'][:16]} "
          f"({'the same' if out['map'] == out['map_saved_again'] else 'DIFFERENT'}); runs "
          f"{[d[:16] for d in out['runs']]}, saving at every frame "
          f"{out['saving_each_frame'][:16]}; found at {out['found_in_loaded']}")
    return {"clip": str(args.clip), "at": args.at, **out}


def main(argv: Sequence[str] | None = None) -> int:
    """Run the measurement asked for; print it and write it to JSON."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = script_parser(__doc__, seeds="0-4")
    p.add_argument("what", choices=("split", "never", "loop", "digests"))
    p.add_argument("clip", type=Path)
    p.add_argument("--at", type=int, default=None, help="the second session's first frame")
    p.add_argument("--map-of", type=Path, default=None, help="never: the map's clip")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--camera-of", choices=("map", "clip"), default="map",
                   help="never: both run under the camera of the map's clip or of CLIP")
    p.add_argument("--depth-scale", type=float, default=1.06,
                   help="loop: the way back's true depth over the depth read")
    p.add_argument("--out-json", type=Path, default=None)
    args = p.parse_args(argv)
    if args.what == "never" and args.map_of is None:
        p.error("never needs --map-of")
    args.at = args.at if args.at is not None else (100 if args.what == "split" else 5)
    enable_batch_exact()
    with tempfile.TemporaryDirectory() as tmp:
        record = {"split": split, "never": never, "loop": loop,
                  "digests": digests}[args.what](args, Path(tmp))
    write_json(args.out_json or Path(f"map_sessions_{args.what}.json"),
               {**script_record("map_sessions.py", argv), **record})
    return 0


if __name__ == "__main__":
    sys.exit(main())
