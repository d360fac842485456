r"""Levenberg–Marquardt with the Schur complement of the paper (Sec. 4, eqs. 7–11): :func:`solve`.

The solver is split by job, each tier a pure function:

- :mod:`dran_edge.solver.plan` — :func:`build_plan`: variable ordering (private ``u`` first, then
  public ``v``) and the sparsity/scatter plan, once per topology;
- :mod:`dran_edge.solver.linearize` — :func:`linearize`: ``A, B, C, g_x, g_y`` of eq. 7, once per
  iteration; :func:`evaluate_cost`, :func:`retract`;
- :mod:`dran_edge.solver.schur` — :func:`schur_step`: the damped solve of eqs. 8–11, once per μ trial;
- :mod:`dran_edge.solver.damping` — :func:`damped_step`: the trials at growing μ and the
  acceptance test (gain ratio, Nielsen's update), shared with the DRAN agent's local step.

This module runs the LM loop: one linearisation per iteration, then damped trials until one
lowers the cost; a rejected trial never counts toward convergence. With the exact Hessian
(``LMParams.hessian='exact'``) an iteration first tries the Newton model at its own μ_N, and
hands the iteration to the Gauss–Newton model when that trial fails. The names of the tiers are
re-exported here (``from dran_edge.solver.lm import build_plan, schur_step, ...``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np

from dran_edge.solver.choices import Hessian, LinearSolver, NewtonDamping
from dran_edge.solver.damping import (
    LM_DAMPING,
    LM_NEWTON_DAMPING,
    LM_SHARED_NEWTON_DAMPING,
    NEWTON_MU_DECREASE,
    DampedStep,
    DampingPolicy,
    DampingState,
    damped_step,
)
from dran_edge.solver.graph import PoseGraph
from dran_edge.solver.linearize import Linearization, evaluate_cost, linearize, retract
from dran_edge.solver.plan import StructurePlan, build_plan
from dran_edge.solver.schur import (
    Factorize,
    LinearSolveError,
    cholesky_factorizer,
    schur_step,
    superlu_factorize,
)

__all__ = [
    "AUTO_CHOLESKY_MIN_POSES",
    "Hessian",
    "LinearSolver",
    "NewtonDamping",
    "NEWTON_MU_DECREASE",
    "LMParams",
    "LMResult",
    "LMStatus",
    "LinearSolveError",
    "Linearization",
    "StructurePlan",
    "build_plan",
    "cholesky_factorizer",
    "evaluate_cost",
    "linearize",
    "retract",
    "schur_step",
    "solve",
    "superlu_factorize",
]

log = logging.getLogger(__name__)


AUTO_CHOLESKY_MIN_POSES = 1000
"""linear_solver='auto' uses the supernodal Cholesky from this many private SE(3) poses on."""


class LMStatus(str, Enum):
    CONVERGED = "converged"
    MAX_ITERATIONS = "max_iterations"
    LINEAR_SOLVE_FAILED = "linear_solve_failed"
    NON_FINITE = "non_finite"
    STALLED = "stalled"
    """No damping up to ``mu_max`` decreased the cost, yet the model predicted a decrease above
    ``cost_tol``: the Jacobian disagrees with the cost (a bug or an extreme kernel)."""


@dataclass(frozen=True)
class LMParams:
    """Levenberg–Marquardt parameters. Costs are Σ ½ρ(‖W r‖²)."""

    max_iterations: int = 100
    """Cap on accepted steps (linearisations)."""
    max_trials: int = LM_DAMPING.max_trials
    """Cap on damped solves per iteration before giving up."""
    mu_init: float = LM_DAMPING.mu_init
    """Initial μ relative to the largest diagonal entry of JᵀJ: near-Gauss–Newton first steps
    (rejected steps raise μ). On the six benchmark graphs 1e-12 needs 3–6 iterations from the
    chordal initialisation where 1e-8 needed up to 13, and no more from odometry/file values."""
    mu_min: float = LM_DAMPING.mu_min
    """Absolute lower bound of μ."""
    cost_tol: float = 1e-10
    """Converged when an accepted step's (cost_old − cost_new) / cost_old < cost_tol, or when no
    step is accepted and the model predicted less than that."""
    step_tol: float = 1e-10
    """Converged when an accepted step's ‖(u, v)‖₂ < step_tol (metres/radians mixed)."""
    gradient_tol: float = 0.0
    """Converged when ‖g‖_∞ ≤ gradient_tol at a linearisation point (whitened units)."""
    hessian: Hessian = Hessian.GAUSS_NEWTON
    """'gauss_newton' (M = JᵀJ + μI, the paper's LM) or 'exact' (adds the chordal residual's
    second-order terms — damped Newton). The exact model keeps its own damping μ_N, separate
    from the Gauss–Newton μ: in an iteration where ``A + μ_N I`` or ``Ĥ`` is not positive
    definite, or the Newton step does not lower the cost (then μ_N grows, Nielsen), the iteration
    continues with the Gauss–Newton model at its own μ. (With one shared μ, Gauss–Newton
    steps kept shrinking μ while the Newton model, indefinite or overshooting at that μ, failed
    every iteration: linear convergence at two solves per iteration. See
    docs/notes/solve-and-bounded-graph.md.)"""
    newton_damping: NewtonDamping = NewtonDamping.SEPARATE
    """'separate' (the μ_N above, with the definiteness check) or 'shared' (one μ for both models
    and no definiteness check on SuperLU factors: the policy before, kept for benchmarks)."""
    linear_solver: LinearSolver = LinearSolver.SUPERLU
    """Factorisation of A + μI: 'superlu', 'cholesky' (supernodal, dran_edge.solver.sparse_cholesky) or
    'auto' (cholesky for SE(3) graphs with ≥ AUTO_CHOLESKY_MIN_POSES private poses, else superlu;
    from tools/bench/bench_cholesky.py: 2–7× faster factorisations on the 3D benchmark graphs,
    no gain on the small 2D ones once its analysis is paid). The Cholesky makes many small BLAS
    calls, which a multi-threaded OpenBLAS on an oversubscribed machine slows down badly: shells
    that use it set OPENBLAS_NUM_THREADS=1 before numpy loads."""

    def __post_init__(self) -> None:
        # the choices may be given by their strings (CLI, YAML): checked and converted here, once
        for name, choice in (
            ("hessian", Hessian),
            ("newton_damping", NewtonDamping),
            ("linear_solver", LinearSolver),
        ):
            object.__setattr__(self, name, choice.parse(getattr(self, name), name))


@dataclass(frozen=True, eq=False)
class LMResult:
    status: LMStatus
    poses: np.ndarray
    """Best iterate (lowest cost seen); (n, D, D)."""
    cost: float
    """Cost at ``poses``."""
    iterations: int
    """Accepted steps."""
    trials: int
    """Damped solves, accepted or not."""
    cost_history: tuple[float, ...]
    """Cost at the start and after every accepted step."""
    reason: str
    """One line on why the loop stopped."""


@dataclass
class _LMDamping:
    """The damping state of :func:`solve`: μ of the Gauss–Newton model and μ_N of the exact one
    (the same μ with ``newton_damping='shared'``), with their policies."""

    gauss_newton: DampingPolicy
    newton: DampingPolicy
    shared: bool
    mu_gn: DampingState | None = None
    mu_newton: DampingState = field(default_factory=lambda: DampingState(0.0))

    @classmethod
    def for_params(cls, params: LMParams) -> _LMDamping:
        shared = params.newton_damping is NewtonDamping.SHARED
        newton = LM_SHARED_NEWTON_DAMPING if shared else LM_NEWTON_DAMPING
        mu_init, mu_min = params.mu_init, params.mu_min
        return cls(
            gauss_newton=replace(
                LM_DAMPING, mu_init=mu_init, mu_min=mu_min, max_trials=params.max_trials
            ),
            newton=replace(newton, mu_init=mu_init, mu_min=mu_min),
            shared=shared,
        )

    def start(self, lin: Linearization) -> None:
        """μ = μ_N = the policy's first μ, at the first linearisation."""
        if self.mu_gn is None:
            diag = np.concatenate([lin.A.diagonal(), np.diag(lin.B)])
            self.mu_gn = self.mu_newton = DampingState(self.gauss_newton.initial_mu(diag))


@dataclass(frozen=True, eq=False)
class _Iteration:
    """The damped trials of one LM iteration."""

    step: DampedStep
    """The accepted trial's outcome, or the Gauss–Newton model's when none was accepted."""
    trials: int
    solved_any: bool
    predicted: float
    """Predicted decrease of the last solved trial (inf when none)."""


def _damped_iteration(
    graph: PoseGraph,
    plan: StructurePlan,
    poses: np.ndarray,
    cost: float,
    lin: Linearization,
    exact: bool,
    damping: _LMDamping,
    factorize: Factorize | None,
    label: str,
) -> _Iteration:
    """One Newton trial at μ_N when ``exact``, then Gauss–Newton trials at μ (the rest of the
    trial cap) until one lowers the cost."""
    g = np.concatenate([lin.g_x, lin.g_y])

    def evaluate(u: np.ndarray, v: np.ndarray) -> tuple[float, np.ndarray]:
        new_poses = retract(plan, poses, u, v)
        return evaluate_cost(graph, new_poses), new_poses

    def model(
        lin: Linearization, require_pd: bool
    ) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
        return lambda mu: schur_step(
            lin.A, lin.B, lin.C, lin.g_x, lin.g_y, mu, factorize, require_pd
        )

    assert damping.mu_gn is not None
    trials_left = damping.gauss_newton.max_trials
    newton: DampedStep | None = None
    if exact and trials_left > 0:
        state = damping.mu_gn if damping.shared else damping.mu_newton
        newton = damped_step(
            damping.newton,
            state,
            model(lin, not damping.shared),
            evaluate,
            cost,
            g,
            label=label + " newton",
        )
        if damping.shared:
            damping.mu_gn = newton.state
        else:
            damping.mu_newton = newton.state
        if newton.accepted:
            return _Iteration(newton, newton.trials, True, newton.predicted)
        trials_left -= newton.trials
        # the Newton model failed (not convex at μ_N, or no decrease): Gauss–Newton takes over
        lin = linearize(graph, plan, poses, False)
    gn = damped_step(
        damping.gauss_newton,
        damping.mu_gn,
        model(lin, False),
        evaluate,
        cost,
        g,
        trials_left,
        label=label + " gauss-newton",
    )
    damping.mu_gn = gn.state
    if newton is None:
        return _Iteration(gn, gn.trials, gn.solved > 0, gn.predicted)
    predicted = gn.predicted if gn.solved else newton.predicted
    return _Iteration(gn, gn.trials + newton.trials, gn.solved + newton.solved > 0, predicted)


def _factorizer(plan: StructurePlan, params: LMParams) -> Factorize | None:
    """The supernodal Cholesky where ``linear_solver`` asks for it, else None (SuperLU)."""
    use_cholesky = params.linear_solver is LinearSolver.CHOLESKY or (
        params.linear_solver is LinearSolver.AUTO
        and plan.dof == 6
        and plan.private_vars.shape[0] >= AUTO_CHOLESKY_MIN_POSES
    )
    return cholesky_factorizer(plan) if use_cholesky else None


def solve(
    graph: PoseGraph,
    poses: np.ndarray,
    params: LMParams = LMParams(),
    plan: StructurePlan | None = None,
    callback: Callable[[int, float, float], None] | None = None,
) -> LMResult:
    """Minimise the graph's cost from ``poses`` by Schur–LM; never raises on numerical trouble.

    ``callback(iteration, cost, mu)`` is called after every accepted step (progress reports).
    """
    plan = build_plan(graph) if plan is None else plan
    factorize = _factorizer(plan, params)
    poses = np.asarray(poses, dtype=np.float64)
    cost = evaluate_cost(graph, poses)
    history = [cost]
    trials = 0

    def stop(status: LMStatus, iterations: int, reason: str) -> LMResult:
        """The result at the current (best) iterate."""
        return LMResult(status, poses, cost, iterations, trials, tuple(history), reason)

    if not math.isfinite(cost):
        return stop(LMStatus.NON_FINITE, 0, "cost at the initial values is not finite")
    damping = _LMDamping.for_params(params)
    for iteration in range(params.max_iterations):
        # The first iteration uses Gauss–Newton even in 'exact' mode: far from a minimum the
        # Gauss–Newton model of the chordal cost predicts better (sphere2500 from the chordal
        # initialisation: F 1687.86 after a Gauss–Newton step, 1707.8 after an exact one).
        exact = params.hessian is Hessian.EXACT and iteration > 0
        lin = linearize(graph, plan, poses, exact)
        g = np.concatenate([lin.g_x, lin.g_y])
        if not np.all(np.isfinite(g)) or not np.all(np.isfinite(lin.A.data)):
            return stop(LMStatus.NON_FINITE, iteration, "non-finite gradient or Hessian")
        if g.size == 0 or np.max(np.abs(g)) <= params.gradient_tol:
            return stop(LMStatus.CONVERGED, iteration, "gradient below gradient_tol")
        damping.start(lin)
        it = _damped_iteration(
            graph, plan, poses, cost, lin, exact, damping, factorize, f"iteration {iteration}"
        )
        trials += it.trials
        out = it.step
        if not out.accepted:
            if not it.solved_any:
                reason = "every damped system failed to factorise"
                return stop(LMStatus.LINEAR_SOLVE_FAILED, iteration, reason)
            if it.predicted <= params.cost_tol * cost:
                reason = "no decreasing step; predicted decrease below cost_tol"
                return stop(LMStatus.CONVERGED, iteration, reason)
            reason = f"no decreasing step after {params.max_trials} damping trials"
            return stop(LMStatus.STALLED, iteration, reason)
        assert out.candidate is not None and out.step is not None
        rel = (cost - out.cost) / cost
        poses, cost = out.candidate, out.cost
        history.append(cost)
        if callback is not None:
            callback(iteration + 1, cost, out.state.mu)
        if rel < params.cost_tol:
            return stop(LMStatus.CONVERGED, iteration + 1, "relative cost decrease below cost_tol")
        if float(np.linalg.norm(out.step)) < params.step_tol:
            return stop(LMStatus.CONVERGED, iteration + 1, "step norm below step_tol")
    return stop(LMStatus.MAX_ITERATIONS, params.max_iterations, "reached max_iterations")
