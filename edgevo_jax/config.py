"""The frozen configuration of a run: every static choice of the method in one place. The
numbers the solvers run on, and which of them are static or traced, are derived from it in
one place only: ``derive.py`` (tracker, window, learnt Params).

``Config`` is hashable (a jit static argument where it is one). Each field's meaning, unit
and default: the docstring under it, tabulated in ``docs/config.md``. The defaults follow the
EdgeVO paper (and DSO for the keyframe weights it adopts); where a default is this project's
own, the reason and the measurements behind it are in ``docs/decisions.md``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields

SELECTIONS = ("spg", "all", "random", "greedy")


@dataclass(frozen=True)
class Config:
    """Static configuration of a run: every choice of the method, frozen and hashable (it is a
    jit static argument where it is one).

    Each field's meaning, unit, default and, where known, the reason for the default is the
    docstring under it; ``docs/config.md`` tabulates them (written by
    ``scripts/config_docs.py``; a test fails when a field has no entry or the table is stale).
    The longer measurements behind the defaults are in ``docs/decisions.md``.

    Change fields when making one, ``Config(num_edges=1024, mapping=False)``, or from an
    existing one: ``config.replace(num_edges=1024)`` (``dataclasses.replace``). From the
    command line: ``edgevo run --set num_edges=1024 --set iterations=10,10,5``
    (:meth:`with_overrides`: each value parsed by the field's type; ``none`` for an optional
    field). Invalid values raise ValueError naming the field.
    """

    # --- preprocessing (host, OpenCV) ---
    blur_ksize: int = 5
    """[px] Side of the Gaussian blur applied to the gray image before Canny (odd). Why: the
    paper's 5 x 5."""
    blur_sigma: float = 1.0
    """[px] Standard deviation of that blur. Why: the paper's sigma 1."""
    canny_low: float = 50.0
    """[gradient] Canny's lower hysteresis threshold, on the L2 Sobel magnitude of the 0-255
    gray image. Why: Canny's 1:2 ratio to ``canny_high``."""
    canny_high: float = 100.0
    """[gradient] Canny's upper threshold; also the paper's ``a``, the magnitude that edge
    culling and the re-observation sigmoid use. Why: the paper's 100."""
    min_depth: float = 0.1
    """[m] Depths below this count as missing."""
    max_depth: float = 8.0
    """[m] Depths above this count as missing."""
    # --- edge selection (frontend/selection.py) ---
    selection: str = "spg"
    """[-] How keyframe edges are chosen: ``spg`` (stochastic partition greedy, the paper's
    Algorithm 1), ``all``, ``random`` or ``greedy`` (stochastic greedy over all edges)."""
    num_edges: int = 512
    """[edges] Edges tracked per keyframe with spg / random / greedy. Why: keeps the solve well
    under the preprocessing it overlaps on a 2-core CPU (``docs/ablation``)."""
    cell_size: int = 4
    """[px] Side of spg's partition grid. Why: many more non-empty partitions than the budget
    even on weakly textured frames; coarser grids were worse on fr3_teddy
    (``docs/ablation/``)."""
    max_per_cell: int = 16
    """[edges] Candidate slots per partition (a seeded subset beyond that)."""
    logdet_lambda: float = 1.0
    """[-] lambda in logdet(H(S) + lambda I), the selection's objective. Why: only regularises
    the first picks (one edge's information is ~ (f / Z)^2 ~ 1e5)."""
    greedy_epsilon: float = 0.1
    """[-] Stochastic greedy's epsilon: (N / k) log(1 / epsilon) samples per step."""
    max_edges: int = 16384
    """[edges] Edge slots with ``selection="all"``. Why: holds every culled edge of a 640 x 480
    frame."""
    # --- tracking (device) ---
    iterations: tuple[int, ...] = (10, 10, 10)
    """[iterations] Levenberg-Marquardt iterations at pyramid level 0, 1, 2, ...; its length is
    the number of levels. Why: the paper's 3 levels."""
    huber_delta: tuple[float, ...] = (1.0, 1.0, 1.0)
    """[px of each level] Huber radius of the edge residual, one per level."""
    max_residual: tuple[float, ...] = (5.0, 5.0, 5.0)
    """[px of each level] Residuals beyond this are outliers (the gate), one per level."""
    eta: float = 0.6
    """[-] Gradient consistency: a point is rejected when g(p) . g(p') < eta (unit gradients
    of keyframe and frame). Why: the paper's 0.6."""
    step_tol: float = 1e-5
    """[-] A level stops once the norm of its update twist is below this."""
    max_rejects: int = 3
    """[tries] A level stops after this many rejected LM tries in a row. Why: the third asks for
    a step ~1000x shorter than Gauss-Newton's; fr3_teddy ATE 8.3 against 9.1 mm with the
    iteration budget (``docs/decisions.md``)."""
    min_inliers: int = 30
    """[points] Fewer level-0 inliers than this: tracking is lost."""
    max_covariance_condition: float = 1e6
    """[-] Condition number of the pose covariance beyond which tracking is lost. Why: frames
    tracked well give 40-400 on TUM."""
    recovery_keyframes: int = 3
    """[keyframes] Earlier keyframes tried after a loss."""
    doubt_share_ratio: float = 0.8
    """[-] Inlier share (level-0 inliers per keyframe edge in view) below this fraction of the
    highest of the last 5 frames': recovery tries other starts and keeps the best (0: no
    check). Why: ``docs/decisions.md``, "Never silently wrong"."""
    lost_share_ratio: float = 0.5
    """[-] Inlier share below this fraction of the recent highest, with no better start found:
    the frame is LOST."""
    lost_extrapolate_s: float = 0.2
    """[s] A LOST frame (without a motion prior) takes the constant-velocity prediction up to
    this long after the last tracked frame, and holds the last pose beyond it. Why: the
    prediction's error grows as a t^2 / 2 (a: the camera's angular acceleration), holding's
    as w t; they cross at t = 2 w / a, 0.2 s for a hand-held camera turning at ~70 deg/s
    and accelerating at ~12 rad/s^2 (fr1_rpy); measured: docs/decisions.md, "A LOST frame
    holds the last pose"."""
    depth_check_share: float = 0.6
    """[-] The second opinion: a frame whose solve was searched for, confirmed from features
    or placed by the map, or that follows a LOST frame, is WEAK when under this share of
    the previous frame's depth points lie on the surfaces its depth image sees at the pose
    relative to the previous frame (``frontend.depth.depth_agreement``: two depth images,
    no edge); 0: no check. Why: ``docs/decisions.md``, "A second opinion from depth"."""
    depth_check_tol_m: float = 0.02
    """[m] A point agrees within this distance of the surface (growing with the square of
    depth beyond 1.5 m, as the sensor's noise does)."""
    recovery_features: bool = True
    """[-] Recovery also starts from image features (ORB, then SIFT, matched, PnP;
    ``frontend/features.py``)."""
    depth_residual: bool = True
    """[-] Point-to-plane ICP of keyframe depth points added to the edge residual at the finest
    level, once the edges have brought the pose into its basin (``frontend/depth.py``). Why:
    ``docs/decisions.md``, "The depth residual"."""
    depth_points: int = 256
    """[points] Keyframe depth points with ``depth_residual``."""
    depth_weight: float = 1.0
    """[-] Weight of the depth residual's normal equations against the edges' (both in
    pixels of the level, Huber-weighted alike). Why 1: a depth point counts as much as an
    edge; the weight learnt by gradients (``learn.depth_weight_gradient``) tracked worse over
    seeds and frame rates: ``docs/decisions.md``, "The depth residual's weight"."""
    readout_s: float | None = None
    """[s] Rolling shutter: the rgb camera's readout time, top row to bottom row; 0: a global
    shutter; None: the camera's own (the source's ``readout_s``; ``frontend/shutter.py``)."""
    # --- keyframes (host) ---
    kf_flow_weight: float = 0.02
    """[1/px] w1 of the keyframe rule w1 t + w2 t' > 1, on the RMS optical flow t. Why: DSO's
    weight, a new keyframe after ~50 px of flow."""
    kf_flow_t_weight: float = 0.04
    """[1/px] w2, on the RMS flow t' without rotation. Why: DSO's weight, ~25 px of
    translational flow."""
    kf_min_inlier_ratio: float = 0.3
    """[-] A new keyframe when a frame's correspondences (level-0 inliers) fall under this
    fraction of their running average (the paper's)."""
    kf_max_interval_s: float = 1.0
    """[s] A new keyframe at the latest this long after the last one (the paper's)."""
    # --- the sliding window (window/sliding.py) ---
    mapping: bool = True
    """[-] The sliding window of keyframes (the backend). Why: the paper's method; fr3_teddy
    ATE 8.6 -> 6.7 mm over seeds 0-8."""
    window_size: int = 6
    """[keyframes] Keyframes in the window. Why: the paper's 5-7."""
    active_per_keyframe: int = 256
    """[edges] Active edge slots each keyframe brings to the window. Why: half the tracked ones
    keeps one LM try at a few ms."""
    activation_cell: int = 20
    """[px] Cell of the window's activation grid (the paper's)."""
    activation_max_angle_deg: float = 30.0
    """[deg] Gradient agreement for activation (the paper's)."""
    mapping_lag: int = 4
    """[frames] Frames after a keyframe at which tracking takes its refined pose from the
    window, which runs beside tracking on a worker thread (``window/worker.py``); 0:
    inline. Why: the window step takes ~4-6 frames' time on 2 cores."""
    mapping_iterations: int = 5
    """[tries] Pose-only LM tries in the window, then as many joint ones."""
    mapping_intrinsics: bool = False
    """[-] Refine fx, fy, cx, cy in the window and track with them."""
    drop_visible_ratio: float = 0.05
    """[-] A keyframe with fewer than this fraction of its edges in view of the newest leaves
    the window. Why: DSO's rule."""
    mapping_depth_sigma: float = 0.01
    """[1/m] Standard deviation of the sensor's inverse depth as a prior in the window (0: no
    prior). Why: the Kinect's disparity noise inflated for registration; 0.03 was worse on
    fr3_teddy."""
    activation_depth_step: float = 0.0105
    """[1/m] Only edges on continuous depth join the window: the inverse depth beside an edge
    must be planar within this (0: no test). Why: three standard deviations of the second
    difference under the Kinect's disparity noise."""
    activation_depth_reach: int = 5
    """[px] How far to either side of an edge the depth test reads. Why: a depth step spreads
    up to 4 px (9 x 9 matching windows), plus a pixel of Canny localisation."""
    # --- the keyframe map (map/, tracking/places.py) ---
    map: bool = True
    """[-] Keep every keyframe in a map: a lost or doubted frame, and a frame tracked from a
    keyframe made at a guess, asks it where it is (place recognition, a feature start, the
    edge alignment, verified); an older keyframe that sees a frame takes over from a new
    keyframe. False: the paper's odometry, bit for bit. Why: ``docs/decisions.md``, "The
    keyframe map"."""
    map_max_keyframes: int = 5000
    """[keyframes] The map keeps at most this many (~80 kB each; later ones are not kept, and
    a warning says so). Why: 400 MB at most, ten minutes of a camera making a keyframe
    every ~4 frames (``docs/results.md``, "The keyframe map's memory")."""
    map_candidates: int = 3
    """[keyframes] Place recognition's candidates each query verifies (most alike first),
    besides the one a guessed pose would see best. Why: ``docs/decisions.md``, "The keyframe
    map"."""
    map_overlap: float = 0.7
    """[-] A keyframe of the map sees a frame when this share of its edges projects into the
    frame at the frame's pose (predicted overlap): the bar for an older keyframe to take
    over on a revisit, and for a keyframe to be tried at a guessed pose. Why:
    ``docs/decisions.md``, "The keyframe map"."""
    map_chain_query_s: float = 0.25
    """[s] A chain of keyframes made at a guess asks the map where it is at every frame in
    its first second, then at most this often (its frames are tracked, only their frame is
    not the map's): 4 queries a second find the place within 1 s of its coming into view, at
    a fraction of a query per frame. Frames lost or doubted by their own solve ask at every
    frame. Why: ``docs/decisions.md``, "Loops found by what the camera sees"."""
    map_query_lag: int = 5
    """[frames] A run started in a map loaded from a file asks it where it is beside
    tracking while its frames track in their own frame: one frame's query (recognition, a
    feature start, the edge alignment, verified) runs on a worker and is taken this many
    frames later (waiting for it if need be: runs stay deterministic), and the frame then
    is aligned to the keyframe found, from where the query put the chain. Why: a query
    costs ~3 frames of tracking here; on the tracker's thread it cost a run that never sees
    the map 1.9x the time per frame (``docs/map-file.md``)."""
    loops: bool = True
    """[-] Close loops (with ``map``): a new keyframe is looked for, beside tracking, among
    the older keyframes of the map that look like it (place recognition over the whole
    map, less the keyframes the pose graph ties to it within twice ``window_size`` edges),
    each placed by its landmarks matched to the frame (PnP, with no pose of the chain's),
    refined by the edge alignment, verified and confirmed by a keyframe beside the old
    one; the relation is a loop edge, and a pose graph over the map's keyframes
    (``map/pose_graph.py``) spreads the drift beside tracking: the keyframes, the window and
    the frames tracked from them move with it. False: the map's odometry, bit for bit.
    Why: ``docs/decisions.md``, "Loops closed" and "Loops found by what the camera sees"."""
    loop_lag: int = 45
    """[frames] Frames after a keyframe at which the tracker takes its loop search, and
    after a pose graph is submitted at which it takes the correction (waiting for the
    worker if need be): when they are taken never depends on the machine, so runs stay
    deterministic. Why: 1.5 s at 30 Hz, more than a cold solve of 1,000 keyframes here
    (``docs/results.md``, "Loops closed")."""
    # --- determinism ---
    seed: int = 0
    """[-] Seed of the edge selection's random choices (keyframe k draws with seed + k)."""

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
        if not self.depth_weight >= 0:
            raise ValueError("Config.depth_weight must be >= 0 (0: the edges alone)")
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
        if not 0.0 < self.map_overlap <= 1.0:
            raise ValueError("Config.map_overlap must be in (0, 1]")
        if not 0.0 <= self.depth_check_share <= 1.0:
            raise ValueError("Config.depth_check_share must be in [0, 1] (0: no check)")
        if not self.depth_check_tol_m > 0.0:
            raise ValueError("Config.depth_check_tol_m must be positive")
        if not self.map_chain_query_s >= 0.0:
            raise ValueError("Config.map_chain_query_s must be non-negative")
        for name in ("active_per_keyframe", "activation_cell", "mapping_iterations",
                     "activation_depth_reach", "map_max_keyframes", "map_candidates",
                     "loop_lag", "map_query_lag"):
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
