"""ONE Levenberg-Marquardt, with explicit state, for every least-squares loop of edgevo: the
tracker's per-level pose solve (``align.align_level``, a ``lax.while_loop``), the sliding
window's joint refinement (``refine.refine``, a ``lax.while_loop`` with a pose-only warm-up
and a fixed-inlier-set acceptance) and the differentiable tracker's unrolled tries
(``learn._align``, a ``lax.scan``).

In the spirit of optimistix: the solver is a small frozen object holding the damping policy,
and the loop state is a NamedTuple the caller carries. One try (``LevenbergMarquardt.step``)
is

    delta  = solve(x, system, lam)          # the damped system, the caller's
    x_new  = apply(x, delta)                # the retraction / update, the caller's
    new    = evaluate(x_new, system)        # the system at x_new (may read the old one)
    keep   = accept(system, new)            # e.g. lower_cost; new is also returned (aux)
    x, system = keep ? (x_new, new) : (x, system)    # one where-select over both pytrees
    lam    = clip(keep ? lam * shrink : lam * grow, lam_min, lam_max)
    rejects = keep ? 0 : rejects + 1;  step = norm(delta)

The loop (while_loop or scan), its iteration budget and any staging are the caller's: the
solver only says whether the last try asks for another (``continues``). Everything here is
traceable; the policy's numbers are Python floats (static, folded into the program).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp


class LMState(NamedTuple):
    """The state of a Levenberg-Marquardt loop (a pytree).

    x: the current point (any pytree: a ``geometry.Pose``, a tuple of arrays);
    system: what the caller evaluated at x (normal equations, cost; any pytree);
    lam: the damping () to use on the next try; step: the norm () of the last step tried
    (inf before the first); rejects: how many tries in a row were rejected () int32.
    """

    x: Any
    system: Any
    lam: jnp.ndarray
    step: jnp.ndarray
    rejects: jnp.ndarray


def lower_cost(old: Any, new: Any) -> jnp.ndarray:
    """The plain acceptance test: the try lowered ``.cost`` (systems with a ``cost`` field)."""
    return new.cost < old.cost


def euclidean_norm(delta: jnp.ndarray) -> jnp.ndarray:
    """sqrt(sum delta_i^2) of a vector (n,), added element by element in index order (a fixed
    order: the tracker's 6-vector gives the same bits alone and vmapped)."""
    return jnp.sqrt(sum(delta[i] * delta[i] for i in range(delta.shape[0])))


@dataclass(frozen=True)
class LevenbergMarquardt:
    """The damping policy of Levenberg-Marquardt (hashable, static).

    lam_init: damping of the first try; shrink / grow: factors applied to lam after a kept /
    rejected try (multiplications, in that order of operations: ``lam * shrink``);
    lam_min, lam_max: the one clip range of lam after every try; lam_retry: after a rejected
    try lam is max(lam, lam_retry) * grow (0: plain lam * grow), so a floor far below it
    still reaches a useful damping in a few rejects.
    """

    lam_init: float = 1e-4
    shrink: float = 0.1
    grow: float = 10.0
    lam_min: float = 1e-6
    lam_max: float = 1e4
    lam_retry: float = 0.0

    def init(self, x: Any, system: Any, dtype: jnp.dtype, lam: float | jnp.ndarray | None = None
             ) -> LMState:
        """The state before the first try from point x with its ``system``: lam = ``lam``
        (default ``lam_init``) of ``dtype``, step inf, no rejects."""
        lam = self.lam_init if lam is None else lam
        return LMState(x, system, jnp.asarray(lam, dtype), jnp.asarray(jnp.inf, dtype),
                       jnp.asarray(0, jnp.int32))

    def damping(self, lam: jnp.ndarray, accepted: jnp.ndarray) -> jnp.ndarray:
        """The next lam: lam * shrink after a kept try, lam * grow after a rejected one (from
        at least lam_retry), clipped to [lam_min, lam_max]."""
        up = (jnp.maximum(lam, self.lam_retry) if self.lam_retry else lam) * self.grow
        return jnp.clip(jnp.where(accepted, lam * self.shrink, up), self.lam_min, self.lam_max)

    def step(
        self,
        state: LMState,
        *,
        solve: Callable[[Any, Any, jnp.ndarray], Any],
        apply: Callable[[Any, Any], Any],
        evaluate: Callable[[Any, Any], Any],
        accept: Callable[[Any, Any], jnp.ndarray] = lower_cost,
        norm: Callable[[Any], jnp.ndarray] = euclidean_norm,
    ) -> tuple[LMState, Any]:
        """One try (module doc): ``solve(x, system, lam)`` gives the step delta,
        ``apply(x, delta)`` the candidate point, ``evaluate(x_new, system)`` its system
        (given the current one, e.g. to judge it with the current inlier set), and
        ``accept(system, new_system)`` () bool whether it is kept; ``norm(delta)`` () is
        recorded as ``step``. x and system are where-selected together, leaf by leaf.
        Returns the next state and the candidate's system, kept or not (an aux output:
        unused, it costs nothing under jit)."""
        delta = solve(state.x, state.system, state.lam)
        x_new = apply(state.x, delta)
        sys_new = evaluate(x_new, state.system)
        better = accept(state.system, sys_new)
        x, system = jax.tree.map(lambda a, b: jnp.where(better, a, b), (x_new, sys_new),
                                 (state.x, state.system))
        rejects = jnp.where(better, 0, state.rejects + 1)
        return LMState(x, system, self.damping(state.lam, better), norm(delta), rejects), sys_new

    @staticmethod
    def continues(state: LMState, step_tol: float | jnp.ndarray,
                  max_rejects: int | jnp.ndarray | None = None) -> jnp.ndarray:
        """Whether the loop tries again after ``state``: its step was at least ``step_tol``
        and (unless ``max_rejects`` is None) fewer than ``max_rejects`` tries in a row were
        rejected. The iteration budget is the caller's."""
        go = state.step >= step_tol
        return go if max_rejects is None else go & (state.rejects < max_rejects)


#: The damping policy of the tracker's pose solve (``align.pose_try``, and so of
#: ``learn.differentiable``'s unrolled tries): lam from 1e-4, x0.1 after a kept try, x10
#: after a rejected one, within [1e-6, 1e4].
DAMPING = LevenbergMarquardt()

#: The window's policy (``refine.refine``, from ``MappingConfig.lambda_init``): the same but
#: for a floor of 1e-7 (both lams do reach their floors, and one floor for both moves
#: trajectories: docs/decisions.md).
WINDOW_DAMPING = LevenbergMarquardt(lam_min=1e-7)

#: The pose graph's (``map.pose_graph``): floors >= 1e-4 leave a loop's drift half spread,
#: and 1e-6 (the floor before the direct solve) held a 2,500-pose sphere to a linear rate of
#: 0.68 a try (lam diag H outweighed its softest modes): at 1e-12 the kept tries are
#: Gauss-Newton's (quadratic), from the first (a first lam of 1e-4 cost 2-3 tries on long
#: chains, whose softest modes are ~N^-2 of the diagonal). A rejected try retries from at
#: least 1e-6 (1e-5, 1e-4, ...), so rejects climb as they did from the old floor.
POSE_GRAPH_DAMPING = LevenbergMarquardt(lam_init=1e-12, lam_min=1e-12, lam_retry=1e-6)
