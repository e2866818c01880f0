"""The recovery search (a doubted or lost frame aligned again from other starts) and the
confirmation of a solve by an independent start (``confirm``): host effects the decision
(``decision``) asks for.

A frame's solve is judged by its inlier share (``decision.inlier_share``). When the share is
far under the recent frames' (or the solve is unusable), ``search`` aligns the frame again,
against the current keyframe, in order of cost: from the keyframe's own pose, the last frame's
(no motion), constant velocity scaled by the frames' time steps, doubled and halved
(``motion_starts``); then from the pose of matched ORB, then SIFT keypoints
(``feature_start``: motions far beyond the edge alignment's basin; ORB is ~10x cheaper, SIFT
finds poses across wider motions); then against the earlier keyframes kept, from the
prediction and the same starts. The highest share wins. The search stops once the best is good
enough, or when the ORB start, independent evidence, converges to the first solve's pose
(``agree``): the doubt came from the scene, not the basin.

A solve is *confirmed* when an alignment from a start made of image features (ORB, then
SIFT keypoints matched, and PnP) and one from another start converge to the same pose: two
routes agree, one of which does not rest on the distance fields at all (``Found.confirmed``,
``confirm``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..frontend import features
from ..frontend.features import Detections
from ..geometry import inverse_np, scale_motion_np
from ..image.preprocess import Frame
from . import verify
from .decision import inlier_share


class Found(NamedTuple):
    """What the recovery search settles on: the keyframe and the solve, and whether a
    feature start and another start converged to that solve's pose (``agree``)."""

    keyframe: Any
    result: Any
    confirmed: bool


def agree(a, b) -> bool:
    """Whether two TrackResults' poses T_cur_kf agree (``verify.agree``: within
    ``verify.AGREE_M``, ``AGREE_DEG``)."""
    return verify.agree(a.T_c_k, b.T_c_k)


def motion_starts(poses: Sequence[np.ndarray], times: Sequence[float], timestamp: float
                  ) -> list[np.ndarray]:
    """World poses T_w_c to start from, given the last (at most two) frames' poses and
    timestamps: the last pose (no motion); with two, the last motion scaled by the time step
    to ``timestamp`` (a gap in the stream; at most 8x, left out when within 25 % of 1), 2x
    and 0.5x."""
    last = poses[-1]
    if len(poses) < 2:
        return [last]
    step = inverse_np(poses[0]) @ last  # the last frame's motion
    t_prev, t_last = times
    scale = (timestamp - t_last) / max(t_last - t_prev, 1e-6)
    scales = [min(scale, 8.0)] if abs(scale - 1.0) > 0.25 else []
    return [last, *(last @ scale_motion_np(step, s) for s in [*scales, 2.0, 0.5])]


def feature_start(kf: Any, found: Detections | None, kind: str, intrinsics: Intrinsics,
                  config: Config) -> np.ndarray | None:
    """T_cur_kf from keypoints of ``kind`` matched between a keyframe (its ``.features``, a
    ``features.Detections``, and its ``.frame``'s depth) and the frame (``found``: its
    ``Detections``), or None without gray images, depth or a pose."""
    if found is None or kf.features is None or kf.frame is None or kf.frame.depth is None:
        return None
    return features.relative_pose(
        kf.features.get(kind), kf.frame.depth, found.get(kind), intrinsics,
        min_depth=config.min_depth, max_depth=config.max_depth)


def search(
    frame: Frame, keyframes: Sequence[Any], *, first, predicted: np.ndarray,
    starts: Sequence[np.ndarray], align: Callable[[Any, Frame, np.ndarray], Any],
    usable: Callable[[Any], bool], good_enough: Callable[[Any], bool] | None,
    intrinsics: Intrinsics, config: Config, basin: float | None = None,
    found: Detections | None = None,
) -> Found | None:
    """The recovery search (module doc). ``keyframes``: the current one first, then the
    earlier ones to try (each with ``.pose`` T_w_kf); ``first``: the solve from the
    prediction, None when it was unusable; ``predicted`` and ``starts`` (``motion_starts``)
    world poses; ``align(kf, frame, T_cur_kf)`` a solve; ``usable(res)`` whether a solve can
    be used; ``good_enough(res)`` whether it ends the search (None: nothing does, as before
    any share was seen); ``found``: the frame's keypoints (``features.Detections``; None:
    no feature start); ``basin`` (level-0 px; None: none): a solve that moved farther from
    its start (``moved``) found a minimum it could not see from there and is no candidate.
    Returns the keyframe and solve with the highest inlier share (the first's when none beats
    it) and whether it is confirmed; None when nothing is usable."""
    current = keyframes[0]
    best = (current, first) if first is not None else None
    # every usable solve: (keyframe, solve, whether its start came from features)
    tried: list[tuple[Any, Any, bool]] = [] if first is None else [(current, first, False)]

    def better(kf, out, features: bool) -> None:
        nonlocal best
        if not usable(out) or (basin is not None and float(out.moved) > basin):
            return
        tried.append((kf, out, features))
        if best is None or inlier_share(out) > inlier_share(best[1]):
            best = (kf, out)

    def settled() -> bool:
        return best is not None and best[1] is not first and good_enough is not None \
            and good_enough(best[1])

    agreed = False  # the ORB start converged to the first solve: the scene, not the basin
    for kf in keyframes:
        guesses = [kf.pose, *starts] if kf is current else [predicted, *starts]
        for T_w_c in guesses:
            better(kf, align(kf, frame, inverse_np(T_w_c) @ kf.pose), False)
        if kf is current and not settled() and config.recovery_features:
            for kind in ("orb", "sift"):
                T_c_k = feature_start(kf, found, kind, intrinsics, config)
                if T_c_k is None:
                    continue
                out = align(kf, frame, T_c_k)
                better(kf, out, True)
                agreed = kind == "orb" and first is not None and usable(out) \
                    and agree(out, first)
                break  # SIFT (~40 ms an image) only where ORB finds no pose
        if agreed or settled():
            break
    if best is None:
        return None
    kf, res = best
    return Found(kf, res, confirmed(res, [(out, f) for k, out, f in tried if k is kf]))


def confirmed(res, solves: Sequence[tuple[Any, bool]]) -> bool:
    """Whether ``res`` is among ``solves`` (each a solve and whether its start came from
    image features) and another of them converged to its pose (``agree``), one of the two
    from features."""
    mine = [f for out, f in solves if out is res]
    return bool(mine) and any(out is not res and (f or mine[0]) and agree(out, res)
                              for out, f in solves)


def confirm(frame: Frame, kf: Any, res, *, align: Callable[[Any, Frame, np.ndarray], Any],
            usable: Callable[[Any], bool], intrinsics: Intrinsics, config: Config,
            found: Detections | None) -> bool:
    """Whether an alignment of ``frame`` to ``kf`` from a feature start (ORB, then SIFT,
    ``feature_start``; ``found``: the frame's keypoints) converges to the pose of the solve
    ``res`` (``agree``): independent confirmation of a solve that went far from its start.
    False when no feature start gives a usable solve there, or with
    ``Config.recovery_features`` off."""
    if not config.recovery_features:
        return False
    for kind in ("orb", "sift"):  # SIFT only where ORB finds no pose
        T_c_k = feature_start(kf, found, kind, intrinsics, config)
        if T_c_k is not None:
            out = align(kf, frame, T_c_k)
            return bool(usable(out) and agree(out, res))
    return False
