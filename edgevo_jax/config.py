"""The frozen configuration of a run: every static choice of the method in one place. The
numbers the solvers run on, and which of them are static or traced, are derived from it in
one place only: ``derive.py`` (tracker, window, learnt Params).

Defaults and where they come from (EdgeVO: Zhao, Shang, Liu, Chen, Gu; DSO for the keyframe
weights the paper adopts):
- Canny on a 5x5, sigma 1 Gaussian-blurred gray image with L2 Sobel magnitude, thresholds
  50 / 100 (Canny's 1:2 ratio). The magnitude used for culling and for the re-observation
  sigmoid is that same Sobel L2 magnitude, so ``canny_high`` is the paper's ``a``.
- 3 pyramid levels (paper); residual gate and Huber radius in pixels of each level.
- Gradient-consistency threshold eta = 0.6 (paper).
- Edge selection (paper, Algorithm 1): stochastic partition greedy, 512 edges per keyframe.
  512 keeps the solve well under the preprocessing time it overlaps on a 2-core CPU;
  ``scripts/ablation_selection.py`` sweeps it. The 4 px grid gives many more non-empty
  partitions than the budget even on weakly textured frames, so the edge count is the budget,
  not the texture, and the random partition order follows the edge density (coarser grids
  force one edge into every textureless cell: worse on fr3_teddy, see the ablation).
  lambda = 1 only regularises the first picks (one edge's information is ~ (f / Z)^2 ~ 1e5).
- Levenberg-Marquardt stops a level after 3 rejected tries in a row: each rejection keeps
  the pose and grows the damping tenfold, so the third asks for a step ~1000x shorter than
  Gauss-Newton's. On the non-smooth distance fields levels used to end on the iteration
  budget instead (fr3_teddy: 28.7 of 30 tries per frame, 17.8 of them rejected); stopping
  after 3 kept the accuracy (ATE over selection seeds 0-5: 8.3 against 9.1 mm).
- Keyframe rule w1 * t + w2 * t' > 1 with t, t' the RMS optical flow in pixels (with and
  without rotation) and w1 = 1/50, w2 = 1/25 px^-1: DSO's 0.02 / 0.04 weights, i.e. a new keyframe
  after ~50 px of general or ~25 px of translational flow; correspondences under 30 % of their
  running average; 1 s since the last keyframe (paper).
- Local mapping, on (the paper's method; on fr3_teddy_first200 it lowers the ATE from 8.6 to
  6.7 mm over selection seeds 0-8, on a 700-frame pingpong of it from 19.3 to 8.4 mm, and
  costs 60-95 ms per keyframe on a 2-core CPU, not the frames: README, local mapping):
  a window of 6 keyframes (paper: 5-7), activation per 20 px cell with
  gradients within 30 degrees (paper); 256 active edges per keyframe (half the tracked ones:
  n A = 1536 inverse depths keep one LM try at a few ms); 5 pose-only then 5 joint LM tries
  per keyframe; DSO's rule of dropping a keyframe with under 5 % of its points in view.
  The depth sensor's inverse depth is a measurement of each edge (sigma 0.01 / m: the
  Kinect's disparity noise, ~1.4e-3 / m by Khoshelham and Elberink 2012, is constant in
  inverse depth; an edge's depth pixel sits a pixel or two off the edge (the depth image's
  registration to the colour one), which on a slanted surface adds ~2e-3 / m per pixel,
  so it is inflated ~7x). On fr3_teddy, depths held fixed (sigma -> 0) give the same ATE
  as 0.01 (6.7 mm over seeds 0-3); 0.03 is worse (7.9 mm): the depths absorb pose errors.
  Only edges whose depth is continuous across them join the window (not in the paper):
  an edge at a depth step is an occluding contour, which slides over the object as the
  camera moves, or carries the other side's depth; its point is not fixed, and on fr3_teddy
  such edges alone shrink the window's translations by ~3 % (README, local mapping).
  The test: the sensor's inverse depth 1-5 px to either side along the edge's gradient is
  planar (second difference) within 0.0105 / m = 3 sqrt(6) 1.425e-3 / m, three standard
  deviations of the second difference of three samples with Khoshelham and Elberink's
  disparity noise (a plane of any slant passes: inverse depth is affine in the pixels).
  5 px: a PrimeSense sensor matches its pattern over 9 x 9 pixel windows (Konolige and
  Mihelich's technical notes on the Kinect), so a depth step spreads up to 4 px around
  where it is, plus a pixel of Canny localisation; around the shared clips' colour edges
  the depth steps pile up within 5 px (fr3_teddy), 4 px (fr1_desk), 9 px (fr1_xyz)
  (``scripts/depth_step_offsets.py``). On fr3_teddy 3 px left 0.8 % of the window's
  translations short (similarity scale 1.008; 5 px: 1.005); 8 px leaves too few edges
  (the 700-frame pingpong of fr3_teddy: 12.0 against 8.8 mm).
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
    max_covariance_condition: float = 1e6  # lost beyond (TUM frames: 40-400, see README)
    recovery_keyframes: int = 3  # earlier keyframes tried after a loss
    # --- keyframes (host) ---
    kf_flow_weight: float = 0.02  # w1, on RMS flow (px)
    kf_flow_t_weight: float = 0.04  # w2, on RMS flow without rotation (px)
    kf_min_inlier_ratio: float = 0.3
    kf_max_interval_s: float = 1.0
    # --- local mapping (local_map.py) ---
    mapping: bool = True  # the sliding window of keyframes (README, local mapping)
    window_size: int = 6  # keyframes (paper: 5-7)
    active_per_keyframe: int = 256  # active edge slots each keyframe brings to the window
    activation_cell: int = 20  # px (paper)
    activation_max_angle_deg: float = 30.0  # gradient agreement for activation (paper)
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
        for name in ("max_edges", "num_edges", "cell_size", "max_per_cell"):
            if getattr(self, name) < 1:
                raise ValueError(f"Config.{name} must be positive")
        if self.logdet_lambda <= 0 or not 0 < self.greedy_epsilon < 1:
            raise ValueError("Config needs logdet_lambda > 0 and 0 < greedy_epsilon < 1")
        if not 0.0 < self.min_depth < self.max_depth:
            raise ValueError("Config needs 0 < min_depth < max_depth")
        if self.window_size < 3:
            raise ValueError("Config.window_size must be at least 3 (the newest two stay)")
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
                changes[key] = _parse_like(current, raw)
            except ValueError as err:
                raise ValueError(f"--set {key}={raw}: {err}") from None
        return self.replace(**changes)


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
