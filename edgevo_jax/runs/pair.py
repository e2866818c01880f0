"""One RGB-D frame pair aligned on its own (``align``): the tracker's edge alignment without
the tracker's state, as OpenCV's ``cv2.Odometry.compute`` and Open3D's
``compute_rgbd_odometry`` align a pair from an initial guess.

The source frame plays the keyframe: its edges with depth are selected
(``selection.keyframe_edges``, with the keyframe's depth points when ``Config.depth_residual``)
and aligned, coarse to fine, to the target frame's distance fields from the initial guess
(``frontend.align.track``, the program the tracker's recovery runs). The result is judged by
the tracker's own checks (``decision.lost_reason``, ``decision.weak_reason`` and the basin
check of ``Odometry``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..derive import basin_px, solve_knobs, solve_structure
from ..frontend.align import track
from ..frontend.depth import depth_points
from ..frontend.features import Detections
from ..frontend.selection import KeyframeEdges, keyframe_edges
from ..geometry import orthonormalise_np
from ..hostmem import to_host
from ..image.preprocess import Frame, preprocess
from ..programs import enable_cache, program, release_compiled
from ..tracking import recovery
from ..tracking.decision import inlier_share, lost_reason, weak_reason
from ..tracking.inputs import rigid_transform
from ..tracking.results import LOST, OK, WEAK

_track_jit = program(track, static_argnames="config")



class AlignResult(NamedTuple):
    """The alignment of one frame pair (``align``).

    success: whether the solve is usable (state OK or WEAK); transform (4, 4) float64:
    T_target_source in metres (p_target = T p_source), the initial guess when not a
    success; information (6, 6) float64: the inverse of the solve's covariance, J^T W J of
    the final level-0 solve (residuals in level-0 pixels, unit variance) over a left twist
    xi = [v, w] (translation first, then rotation; T <- exp(xi) T, in the target camera),
    zero when not a success; state: ``OK``, ``WEAK`` (usable but doubtful) or ``LOST``
    (not usable), with the reason when not OK; inliers: level-0 inlier edges; inlier_share:
    inliers per source edge in view of the target."""

    success: bool
    transform: np.ndarray
    information: np.ndarray
    state: str
    reason: str | None
    inliers: int
    inlier_share: float


@dataclass
class _Source:
    """The source frame as the keyframe of the solve (what ``recovery.confirm`` reads: its
    frame, edges and keypoints, ``features.Detections``; None without a gray image)."""

    frame: Frame
    edges: KeyframeEdges
    features: Detections | None = None




def _image(rgb, name: str) -> np.ndarray:
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or not (rgb.ndim == 2 or (rgb.ndim == 3 and rgb.shape[2] == 3)):
        raise ValueError(f"{name} must be uint8 (H, W, 3) or (H, W), got {rgb.dtype} "
                         f"{rgb.shape}")
    if rgb.size == 0:
        raise ValueError(f"{name} is empty ({rgb.shape})")
    return rgb


def _depth(depth, name: str, depth_scale: float | None) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.dtype.kind not in "uif":
        raise ValueError(f"{name} must be an (H, W) depth image, got {depth.dtype} "
                         f"{depth.shape}")
    if depth.size == 0:
        raise ValueError(f"{name} is empty ({depth.shape})")
    if depth_scale is None:
        if depth.dtype.kind != "f":
            raise ValueError(f"{name} is {depth.dtype}: pass depth_scale (raw units per "
                             "metre, 5000 for TUM PNGs, 1000 for millimetres), or metres "
                             "as floats")
        return depth
    if depth.dtype.kind != "f":
        return depth.astype(np.float32) / np.float32(depth_scale)
    return depth / depth.dtype.type(depth_scale)


def align(
    source_rgb: np.ndarray, source_depth: np.ndarray, target_rgb: np.ndarray,
    target_depth: np.ndarray, *, intrinsics: Intrinsics | tuple[float, float, float, float],
    init: np.ndarray | None = None, config: Config | None = None,
    depth_scale: float | None = None,
) -> AlignResult:
    """Align one RGB-D frame pair from an initial guess: the motion T_target_source.

    Contract:
    - The source frame is the keyframe (its edges with depth are aligned); the target
      needs edges only (its depth joins through the depth residual where it has some).
    - ``transform`` and ``init`` are T_target_source (4, 4), metres: they map a point in
      the source camera to the target camera, p_target = T p_source. This is OpenCV's
      ``Rt`` of ``cv2.Odometry.compute(src..., dst...)`` ("Rt * src = dst") and Open3D's
      ``compute_rgbd_odometry(source, target, ...)`` transform. In world poses
      T_world_cam: T_target_source = inv(T_world_target) @ T_world_source.
    - ``information`` is over a left twist [v, w], translation first (see ``AlignResult``).
    - rgb: uint8 (H, W, 3) RGB or (H, W) gray; depth (H, W): float metres (0 or NaN =
      missing), or raw integers (e.g. uint16 PNGs) with ``depth_scale`` (raw units per
      metre; it divides float depth too). Images rectified, all four of one size, taken
      by the pinhole camera ``intrinsics`` (fx, fy, cx, cy in pixels).
    - ``init``: T_target_source to start from (None: identity); the edge alignment reaches
      ``derive.basin_px`` level-0 pixels of image motion from it. ``config``: the
      tracker's (None: ``Config()``); its ``seed`` drives the edge selection, so a call is
      deterministic.
    - A global-shutter solve (``Config.readout_s`` is not used: a rolling shutter needs
      the frames' times and the camera's velocity, which the streaming ``Odometry`` has).

    Success (``AlignResult.success``) is the tracker's notion: LOST when the solve cannot be
    used (``decision.lost_reason``: too few inliers, a non-finite pose, an ill-conditioned
    covariance), or when the source has fewer than ``Config.min_inliers`` edges with depth;
    WEAK (usable, doubtful) for ``decision.weak_reason`` or a solve that no ORB / SIFT start
    converges to (``recovery.confirm``; with ``Config.recovery_features`` off, every solve
    is WEAK): OK rests on evidence beyond the distance fields, since the tracker's
    comparison with the recent frames' inlier shares has no history here.

    The solve compiles once per image size and configuration structure; later calls reuse
    it (and share it with ``Odometry``'s). ValueError naming the argument for images of the
    wrong kind or of different sizes, a source without any depth, an ``init`` that is no
    rigid transform (wrong shape, NaN, a rotation block off SO(3)) and bad intrinsics.
    """
    config = Config() if config is None else config
    intr, images = _checked_inputs(source_rgb, source_depth, target_rgb, target_depth,
                                   intrinsics, depth_scale, config)
    T_init = np.eye(4) if init is None else rigid_transform(init, name="init")

    enable_cache()  # as every tracker: programs kept on disk, the CLI's arithmetic
    release_compiled()  # a process that solved under many configurations: room first
    source = preprocess(images["source_rgb"], images["source_depth"], config)
    target = preprocess(images["target_rgb"], images["target_depth"], config)
    edges = keyframe_edges(source, config, seed=config.seed, T_prior=T_init, intr=intr)
    n = int(edges.valid.sum())
    if n < config.min_inliers:
        return _lost(T_init, f"too few source edges with depth ({n})")
    kf = _Source(source, jax.device_put(_with_depth_points(edges, source, intr, config)),
                 None if source.gray is None else Detections(source.gray))
    solve = _solver(intr, config)
    res = solve(kf, target, T_init)
    lost = lost_reason(target.num_edges, res, config)
    if lost is not None:
        return _lost(T_init, lost, int(res.inliers), inlier_share(res))
    return _usable(res, _doubt(target, kf, res, solve, intr, config))


def _checked_inputs(source_rgb, source_depth, target_rgb, target_depth, intrinsics,
                    depth_scale: float | None, config: Config
                    ) -> tuple[Intrinsics, dict[str, np.ndarray]]:
    """``align``'s arguments checked: the intrinsics (fx, fy, cx, cy in pixels, valid for the
    images' size) and the four images by name (rgb uint8 as given; depth (H, W) in metres,
    ``_depth``), all of one size (H, W), the source with some depth within the config's
    range. ValueError naming the argument otherwise."""
    try:
        intr = Intrinsics(*(float(x) for x in intrinsics))
    except (TypeError, ValueError) as err:
        raise ValueError(f"intrinsics must be (fx, fy, cx, cy), got {intrinsics!r}") from err
    if depth_scale is not None and not (np.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale must be positive and finite, got {depth_scale}")
    images = {"source_rgb": _image(source_rgb, "source_rgb"),
              "source_depth": _depth(source_depth, "source_depth", depth_scale),
              "target_rgb": _image(target_rgb, "target_rgb"),
              "target_depth": _depth(target_depth, "target_depth", depth_scale)}
    sizes = {name: a.shape[:2] for name, a in images.items()}
    if len(set(sizes.values())) > 1:
        raise ValueError("the four images must have one size (H, W): " + ", ".join(
            f"{name} {h}x{w}" for name, (h, w) in sizes.items()) + " (H x W)")
    h, w = sizes["source_rgb"]
    intr.validate(width=w, height=h)
    src_depth = images["source_depth"]
    if not np.any(np.isfinite(src_depth) & (src_depth >= config.min_depth)
                  & (src_depth <= config.max_depth)):
        raise ValueError(f"source_depth has no depth within [{config.min_depth:g}, "
                         f"{config.max_depth:g}] m (Config.min_depth, max_depth): nothing "
                         "to align; raw sensor units need depth_scale")
    return intr, images


def _with_depth_points(edges: KeyframeEdges, source: Frame, intr: Intrinsics,
                       config: Config) -> KeyframeEdges:
    """The source's edges with its depth points and normals (source camera, metres) added
    for the depth residual when ``Config.depth_residual``, else as they are."""
    if not config.depth_residual:
        return edges
    return edges._replace(**dict(zip(("depth_pts", "depth_normals"), depth_points(
        source.depth, intr, config.depth_points, min_depth=config.min_depth,
        max_depth=config.max_depth, seed=config.seed), strict=True)))


def _solver(intr: Intrinsics, config: Config):
    """The pair's solve as ``recovery.confirm`` calls it: (keyframe ``_Source``, target
    Frame, T_c_k (4, 4) T_target_source, metres) -> the host copy of ``align.track``'s
    TrackResult (a global-shutter solve, the program shared with ``Odometry``)."""
    structure, knobs = solve_structure(config), solve_knobs(config)

    def solve(k: _Source, frame: Frame, T_c_k: np.ndarray):
        return to_host(_track_jit(k.edges, frame.dist, frame.edge_map,
                                  np.asarray(T_c_k, np.float32), intr, config=structure,
                                  knobs=knobs, shutter=None))

    return solve


def _doubt(target: Frame, kf: _Source, res, solve, intr: Intrinsics, config: Config
           ) -> str | None:
    """Why a usable solve ``res`` of the pair is WEAK (``decision.weak_reason``, or no
    confirmation by matched features, ``recovery.confirm``), None when it is OK."""
    reason = weak_reason(bool(np.any(target.edge_depth > 0)), res, config)
    basin, moved = basin_px(config), float(res.moved)
    # OK needs evidence beyond the distance fields: a solve from matched image features
    # converging to the same pose (a lone pair has no recent frames to compare with)
    found = None if target.gray is None else Detections(target.gray)
    if reason is None and not recovery.confirm(
            target, kf, res, align=solve, intrinsics=intr, config=config, found=found,
            usable=lambda out: lost_reason(target.num_edges, out, config) is None):
        reason = (f"moved {moved:.0f} px from its start, past the {basin:.0f} px basin, not "
                  "confirmed by features" if moved > basin else
                  "not confirmed by features: a solve from matched ORB / SIFT keypoints did "
                  "not converge to this pose (or none could be made)")
    return reason


def _usable(res, reason: str | None) -> AlignResult:
    """The AlignResult of a usable solve ``res``: its pose (T_target_source, metres,
    float64, orthonormalised), its information (6, 6) over [v, w] (the symmetrised inverse
    of the symmetrised covariance), WEAK with ``reason``, else OK."""
    cov = np.asarray(res.covariance, np.float64)
    information = np.linalg.inv(0.5 * (cov + cov.T))
    return AlignResult(True, orthonormalise_np(np.asarray(res.T_c_k, np.float64)),
                       0.5 * (information + information.T), WEAK if reason else OK, reason,
                       int(res.inliers), inlier_share(res))


def _lost(T_init: np.ndarray, reason: str, inliers: int = 0, share: float = 0.0
          ) -> AlignResult:
    return AlignResult(False, T_init.copy(), np.zeros((6, 6)), LOST, reason, inliers, share)

