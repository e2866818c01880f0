"""The one place that turns a ``Config`` (and learnt ``params.Params``) into the numbers the
solvers run on, and says once which of them are static (jit static arguments: they shape or
unroll the program) and which are traced (arrays: configurations that differ in them share
one compiled program).

Tracker (``align.track``, ``chunk``, ``batch``):
- static: ``SolveStructure`` (the number of pyramid levels);
- ``readout_time``: the rolling shutter's readout time (the config's, else the camera's);
- traced: ``SolveKnobs`` (per-level Huber radius and gate, iterations, eta, step tolerance,
  reject limit, the depth residual's weight; learnt Params override the Huber radii, eta
  and the weighting model).

Window (``window.refine.refine``, ``window.sliding``):
- ``window_config(config)``: the refinement's ``MappingConfig``, the same for
  ``refine.refine(problem, config)`` and for the tracker's local map;
- ``split_window`` / ``join_window``: its ``WINDOW_TRACED`` numbers (Huber radius, gate, eta)
  as arrays, the rest static.

Both: ``program_structure(config)``, everything of a config that reaches the programs
statically, and ``structural_fields(config)``, the settings that take a run off the
defaults' programs (named before a run compiles).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, NamedTuple

import jax.numpy as jnp
import numpy as np

from .config import Config

if TYPE_CHECKING:  # a type only: derive sits below the front end that defines it
    from .frontend.robust import EdgeWeighting


# --- the tracker ---------------------------------------------------------------------------
class SolveStructure(NamedTuple):
    """The static part of the tracker's solve (hashable; a jit static argument): the number
    of pyramid levels. Everything else reaches the solve as ``SolveKnobs`` arrays."""

    num_levels: int


class SolveKnobs(NamedTuple):
    """The numeric settings of the solve as arrays (a pytree, traced), so that one compiled
    program serves many configurations (``batch.py`` vmaps over them): per level huber_delta
    (L,) and max_residual (L,) in that level's pixels, iterations (L,) int32; eta (),
    step_tol () and max_rejects () int32; depth_weight (), the depth residual's share of the
    normal equations at level 0. ``weighting``: the learnable per-edge weighting
    model (``robust.EdgeWeighting``, from ``params.solve_knobs_of``), or None (the plain
    tracker; a None compiles without it)."""

    huber_delta: jnp.ndarray
    max_residual: jnp.ndarray
    eta: jnp.ndarray
    iterations: jnp.ndarray
    step_tol: jnp.ndarray
    max_rejects: jnp.ndarray
    depth_weight: jnp.ndarray
    weighting: EdgeWeighting | None = None


def solve_structure(config: Config) -> SolveStructure:
    """The static part of the tracker's solve for ``config``."""
    return SolveStructure(config.num_levels)


def solve_knobs(
    config: Config,
    *,
    huber_delta: np.ndarray | None = None,
    eta: np.ndarray | float | None = None,
    weighting: EdgeWeighting | None = None,
) -> SolveKnobs:
    """The ``SolveKnobs`` of ``config`` (numpy float32 and int32), with learnt values in
    place of the config's where given (``params.solve_knobs_of``): huber_delta (L,) pixels
    of each level, eta (), the weighting model."""
    return SolveKnobs(
        huber_delta=np.asarray(config.huber_delta if huber_delta is None else huber_delta,
                               np.float32),
        max_residual=np.asarray(config.max_residual, np.float32),
        eta=np.asarray(config.eta if eta is None else eta, np.float32),
        iterations=np.asarray(config.iterations, np.int32),
        step_tol=np.asarray(config.step_tol, np.float32),
        max_rejects=np.asarray(config.max_rejects, np.int32),
        depth_weight=np.asarray(config.depth_weight, np.float32),
        weighting=weighting,
    )


def basin_px(config: Config) -> float:
    """How far (level-0 px) the edge alignment reaches from its start: the residual gate of
    the coarsest level in level-0 pixels (max_residual[-1] x 2^(levels - 1)); an edge
    farther than that from its match is rejected at every level, so a solve that moved
    farther found its minimum beyond where it could see."""
    return float(config.max_residual[-1]) * 2.0 ** (config.num_levels - 1)


def readout_time(config: Config, camera_readout_s: float) -> float:
    """The rolling shutter's readout time (s) a run uses: ``Config.readout_s`` where set,
    else the camera's own (its source's ``readout_s``; 0: a global shutter)."""
    return float(camera_readout_s if config.readout_s is None else config.readout_s)


# --- the window ----------------------------------------------------------------------------
class MappingConfig(NamedTuple):
    """The numbers of the window refinement (hashable: a jit static argument, except for
    the ``WINDOW_TRACED`` fields, which ``split_window`` turns into arrays).

    iterations: joint Levenberg-Marquardt tries; huber_delta, max_residual: Huber radius and
    gate (level-0 pixels); lambda_init: initial lam of (H + lam diag H); gauge_index: the
    keyframe whose pose is held fixed; fix_scale: keep the geometric mean of the inverse
    depths; step_tol: stop once a step's norm is below it; min_rho: floor of updated inverse
    depths; refine_depths, refine_intrinsics: which variables move (poses always do);
    warmup_iterations: pose-only tries before the joint ones (see ``refine.refine``); eta:
    the gradient-consistency threshold (used when the problem carries gradients);
    depth_prior_sigma: standard deviation (1/m, against residuals in pixels) of a measured
    inverse depth, used when the problem carries ``rho_prior`` (0: none). An edge's
    distance residual constrains its depth only across the edge: where the epipolar line
    runs along the edge nothing else holds the depth.
    The defaults are a plain refinement for tests; a run's numbers come from
    ``window_config``.
    """

    iterations: int = 10
    huber_delta: float = 1.0
    max_residual: float = 5.0
    lambda_init: float = 1e-4
    gauge_index: int = 0
    fix_scale: bool = True
    step_tol: float = 1e-8
    min_rho: float = 1e-3
    refine_depths: bool = True
    refine_intrinsics: bool = True
    warmup_iterations: int = 0
    eta: float = 0.6
    depth_prior_sigma: float = 0.0


def window_config(config: Config) -> MappingConfig:
    """The window refinement's numbers of a run's Config, as the tracker's local map uses
    them: level-0 Huber radius and gate (huber_delta[0], max_residual[0]) and eta;
    ``mapping_iterations`` pose-only tries, then as many joint ones; ``mapping_intrinsics``;
    ``mapping_depth_sigma`` as the depth prior; the other fields MappingConfig's defaults."""
    return MappingConfig(
        huber_delta=float(config.huber_delta[0]), max_residual=float(config.max_residual[0]),
        eta=float(config.eta), iterations=config.mapping_iterations,
        warmup_iterations=config.mapping_iterations,
        refine_intrinsics=config.mapping_intrinsics,
        depth_prior_sigma=config.mapping_depth_sigma,
    )


#: MappingConfig's numbers that reach the window's programs as arrays, not as static
#: values: configurations that differ in them (a grid of Huber radii) share one compilation.
WINDOW_TRACED = ("huber_delta", "max_residual", "eta")


def split_window(cfg: MappingConfig) -> tuple[MappingConfig, tuple[np.ndarray, ...]]:
    """The static part of ``cfg`` (its WINDOW_TRACED fields set to None) and those numbers
    as float32 arrays (0-d), in WINDOW_TRACED's order."""
    return (cfg._replace(**dict.fromkeys(WINDOW_TRACED)),
            tuple(np.asarray(getattr(cfg, k), np.float32) for k in WINDOW_TRACED))


def join_window(structure: MappingConfig, numbers: tuple) -> MappingConfig:
    """The inverse of ``split_window``: the static part with the (possibly traced) numbers
    put back."""
    return structure._replace(**dict(zip(WINDOW_TRACED, numbers, strict=True)))


# --- what the compiled programs depend on -------------------------------------------------
def program_structure(config: Config) -> tuple:
    """What of ``config`` reaches the compiled programs statically (their shapes, unrolled
    loops and static arguments), hashable: two configurations with equal structures run the
    same programs (the traced numbers apart), so a process or the program cache that holds
    one's holds the other's. The tracker's levels and slot counts; the selection's static
    options; the depth points; a rolling shutter or none; the window's static part, its
    size, active slots and activation options. (The image size and the camera's own readout
    are the source's, not the configuration's.)"""
    selecting = config.selection != "all"
    return (
        solve_structure(config),
        config.selection, config.edge_slots if selecting else config.max_edges,
        (config.max_per_cell, config.logdet_lambda, config.canny_high, config.greedy_epsilon,
         config.max_edges) if selecting else None,
        config.depth_points if config.depth_residual else None,
        config.readout_s == 0.0,
        (split_window(window_config(config))[0], config.window_size,
         config.active_per_keyframe, config.activation_cell,
         config.activation_max_angle_deg) if config.mapping else None,
    )


def structural_fields(config: Config) -> list[str]:
    """The fields in which ``config`` differs from ``Config()`` and whose default, put back
    alone, changes ``program_structure(config)``: why a run with ``config`` compiles
    programs that a run with the defaults does not (``num_edges`` beside ``selection=all``
    is not one: it has no effect there)."""
    default, own = Config(), program_structure(config)

    def changes(name: str) -> bool:
        try:
            back = dataclasses.replace(config, **{name: getattr(default, name)})
        except ValueError:  # tied to other fields (one value per level): it goes with them
            return True
        return program_structure(back) != own

    return [f.name for f in dataclasses.fields(Config)
            if getattr(config, f.name) != getattr(default, f.name) and changes(f.name)]
