"""Host-side keyframe decision (EdgeVO, after DSO).

A new keyframe is made when any of these holds:
- w1 * t + w2 * t' > 1, with t the RMS optical flow of the keyframe's edges under the tracked
  motion and t' the same flow without rotation (pixels);
- the correspondences (level-0 inliers) fall under ``kf_min_inlier_ratio`` of their running
  average over the frames tracked against the current keyframe;
- ``kf_max_interval_s`` seconds have passed since the keyframe.
"""

from __future__ import annotations

from ..config import Config


def keyframe_reason(
    *, flow: float, flow_t: float, inliers: int, inlier_mean: float | None, dt: float,
    config: Config,
) -> str | None:
    """Why the current frame must become a keyframe, or None to keep the current one."""
    if config.kf_flow_weight * flow + config.kf_flow_t_weight * flow_t > 1.0:
        return "flow"
    if inlier_mean is not None and inliers < config.kf_min_inlier_ratio * inlier_mean:
        return "correspondences"
    if dt >= config.kf_max_interval_s:
        return "interval"
    return None
