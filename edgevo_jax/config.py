"""The frozen configuration of a run: every static choice of the method in one place. The
numbers the solvers run on, and which of them are static or traced, are derived from it in
one place only: ``derive.py`` (tracker, window, learnt Params).

``Config`` is hashable (a jit static argument where it is one). Units: pixels of each
pyramid level for the per-level tuples (``huber_delta``, ``max_residual``), metres for
depths, 1/m for inverse depths, seconds for time. The defaults follow the EdgeVO paper (and
DSO for the keyframe weights it adopts); where a default is this project's own, the reason
and the measurements behind it are in ``docs/decisions.md``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields

SELECTIONS = ("spg", "all", "random", "greedy")


@dataclass(frozen=True)
class Config:
    """Static configuration (hashable: it is a jit static argument)."""

    # --- preprocessing (host, OpenCV) ---
    blur_ksize: int = 5
    blur_sigma: float = 1.0
    canny_low: float = 50.0
    canny_high: float = 100.0
    min_depth: float = 0.1  # metres; depth outside [min_depth, max_depth] counts as missing
    max_depth: float = 8.0
    # --- edge selection (see selection.py) ---
    selection: str = "spg"  # spg | all | random | greedy
    num_edges: int = 512  # edges tracked per keyframe with spg / random / greedy
    cell_size: int = 4  # partition grid (pixels) for spg; see the module doc
    max_per_cell: int = 16  # candidate slots per partition (a seeded subset beyond that)
    logdet_lambda: float = 1.0  # lambda in logdet(H(S) + lambda I)
    greedy_epsilon: float = 0.1  # stochastic greedy: samples (N / k) log(1 / eps) per step
    max_edges: int = 16384  # edge slots with selection=all (holds every culled edge at 640x480)
    # --- tracking (device) ---
    iterations: tuple[int, ...] = (10, 10, 10)  # Gauss-Newton iterations at level 0, 1, 2
    huber_delta: tuple[float, ...] = (1.0, 1.0, 1.0)  # pixels of each level
    max_residual: tuple[float, ...] = (5.0, 5.0, 5.0)  # residual gate, pixels of each level
    eta: float = 0.6  # gradient consistency: reject g(p) . g(p') < eta
    step_tol: float = 1e-5  # stop a level once the update's norm is below this
    max_rejects: int = 3  # stop a level after this many rejected LM tries in a row
    min_inliers: int = 30  # fewer level-0 inliers than this: tracking lost
    max_covariance_condition: float = 1e6  # lost beyond this condition number
    recovery_keyframes: int = 3  # earlier keyframes tried after a loss
    # inlier share: level-0 inliers per keyframe edge in view, against the highest of the
    # last 5 frames' (what a correct alignment reaches here). Under doubt_share_ratio of it
    # recovery tries other starts (keeping the best); under lost_share_ratio with no better
    # start the frame is LOST (doubt_share_ratio 0: no check)
    doubt_share_ratio: float = 0.8
    lost_share_ratio: float = 0.5
    recovery_features: bool = True  # recovery also starts from SIFT + PnP (features.py)
    # point-to-plane ICP of keyframe depth points added to the edge residual (depth.py)
    # (at the finest level, where the edges have brought the pose into its basin)
    depth_residual: bool = True
    depth_points: int = 256  # keyframe depth points with depth_residual
    # rolling shutter: the rgb camera's readout time, top row to bottom row (s); 0: a global
    # shutter; None: the camera's own (the source's readout_s; frontend/shutter.py)
    readout_s: float | None = None
    # --- keyframes (host) ---
    kf_flow_weight: float = 0.02  # w1, on RMS flow (px)
    kf_flow_t_weight: float = 0.04  # w2, on RMS flow without rotation (px)
    kf_min_inlier_ratio: float = 0.3
    kf_max_interval_s: float = 1.0
    # --- local mapping (local_map.py) ---
    mapping: bool = True  # the sliding window of keyframes (backend)
    window_size: int = 6  # keyframes (paper: 5-7)
    active_per_keyframe: int = 256  # active edge slots each keyframe brings to the window
    activation_cell: int = 20  # px (paper)
    activation_max_angle_deg: float = 30.0  # gradient agreement for activation (paper)
    # frames after a keyframe at which tracking takes its refined pose from the window, which
    # runs beside tracking on a worker thread (pipeline/mapping.py); 0: inline
    mapping_lag: int = 4
    mapping_iterations: int = 5  # pose-only LM tries, then as many joint ones
    mapping_intrinsics: bool = False  # refine fx, fy, cx, cy in the window, track with them
    drop_visible_ratio: float = 0.05  # a keyframe with fewer edges in view of the newest goes
    mapping_depth_sigma: float = 0.01  # 1/m: the sensor's inverse depth as a prior (0: none)
    activation_depth_step: float = 0.0105  # 1/m: planarity of the depth across an edge (0: off)
    activation_depth_reach: int = 5  # px to either side of an edge that the depth test reads
    # --- determinism ---
    seed: int = 0

    def __post_init__(self) -> None:
        n = self.num_levels
        for name in ("huber_delta", "max_residual"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"Config.{name} needs one value per level ({n})")
        if self.canny_low > self.canny_high:
            raise ValueError("Config.canny_low must not exceed canny_high")
        if self.selection not in SELECTIONS:
            raise ValueError(
                f"Config.selection must be one of {', '.join(SELECTIONS)}, got {self.selection!r}"
            )
        for name in ("max_edges", "num_edges", "cell_size", "max_per_cell", "depth_points"):
            if getattr(self, name) < 1:
                raise ValueError(f"Config.{name} must be positive")
        if self.logdet_lambda <= 0 or not 0 < self.greedy_epsilon < 1:
            raise ValueError("Config needs logdet_lambda > 0 and 0 < greedy_epsilon < 1")
        if not 0.0 < self.min_depth < self.max_depth:
            raise ValueError("Config needs 0 < min_depth < max_depth")
        if self.window_size < 3:
            raise ValueError("Config.window_size must be at least 3 (the newest two stay)")
        if not 0.0 <= self.lost_share_ratio <= self.doubt_share_ratio < 1.0:
            raise ValueError("Config needs 0 <= lost_share_ratio <= doubt_share_ratio < 1")
        if self.readout_s is not None and not 0.0 <= self.readout_s < 1.0:
            raise ValueError("Config.readout_s must be in [0, 1) seconds, or None (the "
                             "camera's own)")
        if self.mapping_lag < 0:
            raise ValueError("Config.mapping_lag must be >= 0 (0: the window runs inline)")
        if not self.activation_depth_step >= 0:
            raise ValueError("Config.activation_depth_step must be >= 0 (0: no depth test)")
        for name in ("active_per_keyframe", "activation_cell", "mapping_iterations",
                     "activation_depth_reach"):
            if getattr(self, name) < 1:
                raise ValueError(f"Config.{name} must be positive")

    @property
    def edge_slots(self) -> int:
        """Most keyframe edges tracked (``all`` packs them into power-of-two slot counts)."""
        return self.max_edges if self.selection == "all" else self.num_edges

    @property
    def num_levels(self) -> int:
        """Number of pyramid levels (level 0 = full resolution)."""
        return len(self.iterations)

    def replace(self, **changes: object) -> Config:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)

    def with_overrides(self, items: list[str]) -> Config:
        """Apply ``key=value`` strings (the CLI's ``--set``), parsed by each field's type."""
        known = {f.name: f for f in fields(self)}
        changes: dict[str, object] = {}
        for item in items:
            if "=" not in item:
                raise ValueError(f"--set expects key=value, got {item!r}")
            key, raw = (s.strip() for s in item.split("=", 1))
            if key not in known:
                raise ValueError(f"unknown config key {key!r}; known: {', '.join(sorted(known))}")
            current = getattr(self, key)
            try:
                optional = "None" in str(known[key].type)
                changes[key] = (_parse_optional(str(known[key].type), raw)
                                if current is None or (optional and raw.strip().lower()
                                                       in ("none", "null"))
                                else _parse_like(current, raw))
            except ValueError as err:
                raise ValueError(f"--set {key}={raw}: {err}") from None
        return self.replace(**changes)


def _parse_optional(annotation: str, raw: str) -> object:
    """A value for a field that is None now, by its annotation (``float | None``): "none"
    keeps None."""
    if raw.strip().lower() in ("none", "null", ""):
        return None
    kind = annotation.split("|")[0].strip()
    return {"float": float, "int": int, "bool": lambda r: _parse_like(True, r)}.get(
        kind, str)(raw)


def _parse_like(current: object, raw: str) -> object:
    if isinstance(current, bool):
        low = raw.lower()
        if low in ("1", "true", "yes", "on"):
            return True
        if low in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"expected a boolean, got {raw!r}")
    if isinstance(current, tuple):
        parts = [p for p in raw.replace("(", "").replace(")", "").split(",") if p.strip()]
        kind = type(current[0]) if current else float
        return tuple(kind(p) for p in parts)
    if isinstance(current, int):
        return int(raw)
    if isinstance(current, float):
        return float(raw)
    return raw
