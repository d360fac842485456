r"""One damped Levenberg–Marquardt step: the trial/acceptance loop of :func:`dran_edge.solver.lm.solve`
and of the DRAN agent's local step (:class:`dran_edge.dran.agent.Agent`).

At a linearisation point with gradient ``g`` and model Hessian ``H`` (``JᵀJ``, or the exact
Hessian), the damped model of the paper (eqs. 13, 15)

    m(ξ) = L̂ + ⟨g, ξ⟩ + ½⟨ξ, M ξ⟩,     M = H + μI,   μ > 0,

has the minimiser ``ξ = −M⁻¹ g`` (eq. 17; computed by :func:`dran_edge.solver.schur.schur_step`
through the Schur complement, eqs. 8–11), applied by the retraction ``z ← Retr_z(ξ)`` (eq. 18).
Each *trial* solves for ξ at the current μ and evaluates the cost at the retracted point.

Predicted decrease (of the *undamped* model, as in Madsen, Nielsen & Tingleff, "Methods for
non-linear least squares problems", 2004, Sec. 3.2; from ``(H + μI) ξ = −g``)::

    L(0) − L(ξ) = −⟨g, ξ⟩ − ½⟨ξ, H ξ⟩ = ½ (μ ‖ξ‖² − ⟨g, ξ⟩)  > 0  for ξ ≠ 0.

Gain ratio ``ρ = (cost − cost_new) / (L(0) − L(ξ))`` (0 when the prediction is not positive).

A trial is *accepted* when the new cost is finite and not higher than the old one: a descent
step in the sense of eq. 23. Costs closer than ``COST_RESOLUTION`` (relative; ``COST_FLOOR``
absolute) count as equal (``costs_equal``): at that size a difference is the order in which
floating-point sums were taken (BLAS kernels, CPUs), not the step, so neither the decision nor
μ may depend on it; such a trial is accepted (it moves the cost by nothing measurable; the
callers' stopping rules then see a zero decrease) and keeps μ (its gain ratio would be noise).
Else (Nielsen's update)

    μ ← max(μ · max(f, 1 − (2ρ − 1)³), μ_min),   ν ← 2,

with the floor ``f`` (1/3 in Nielsen's rule) set by the policy. A rejected trial raises μ and
tries again, up to the policy's trial cap: by Nielsen's ``μ ← μν, ν ← 2ν`` or by a fixed factor.
A damped system that cannot be factorised (:class:`~dran_edge.solver.schur.LinearSolveError`)
counts as a trial and raises μ in the same way, unless the policy says it does not (the
exact-Hessian model: not being convex at μ_N is a property of the point, not of the step length).

The first μ is ``max(μ_init · s, μ_min)`` with ``s`` the largest (``MAX_DIAGONAL``) or the median
(``MEDIAN_DIAGONAL``) diagonal entry of the undamped ``JᵀJ``; 1 when there is none.

Two policies are in use, each keeping its caller's numbers (whether they should become one is a
separate, measured question): :data:`LM_DAMPING` (centralized LM; :data:`LM_NEWTON_DAMPING` for
its exact-Hessian trial) and :data:`AGENT_DAMPING` (DRAN's local step; relative to the median
curvature, so a stiff gauge prior does not inflate μ; a cheap ×4 growth; at most 6 trials, as
the agent re-linearises every round anyway).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

import numpy as np

from dran_edge.solver.schur import LinearSolveError

log = logging.getLogger(__name__)

COST_RESOLUTION = 1e-10
"""Relative cost difference below which two costs are equal for the damping loop. Poses that
differ in the last bit (another CPU's BLAS kernel: x86-64 against aarch64) move a cost by far
more than 1e-16 relative when the residuals are small against the poses (a 1e-15 m position
error on a 1e-4 m residual), and a trial decided on such a difference makes two machines' runs
part (docs/notes/arm64-check.md). 1e-10 is the centralized LM's own convergence tolerance
(``LMParams.cost_tol``): a decrease below it already ends that solver."""

COST_FLOOR = 1e-18
"""Absolute cost difference (χ² units: whitened squared residuals) below which two costs are
equal: a cost that is zero in exact arithmetic (a prior at its measurement) comes out as 0 on
one machine and 4e-26 on another, which no relative tolerance covers."""


def costs_equal(cost: float, new_cost: float) -> bool:
    """|cost − new_cost| ≤ COST_RESOLUTION · max(|cost|, |new_cost|) + COST_FLOOR: a difference
    roundoff can explain."""
    scale = max(abs(cost), abs(new_cost))
    return abs(cost - new_cost) <= COST_RESOLUTION * scale + COST_FLOOR


class MuStart(str, Enum):
    """Which statistic of diag(JᵀJ) scales the first μ."""

    MAX_DIAGONAL = "max_diagonal"
    MEDIAN_DIAGONAL = "median_diagonal"

    def __str__(self) -> str:
        return str(self.value)


@dataclass(frozen=True)
class DampingPolicy:
    """The rules of one damping loop (see the module docstring for the maths)."""

    mu_start: MuStart
    """First μ relative to the largest or the median diagonal entry of JᵀJ."""
    mu_init: float
    """First μ = mu_init × that entry."""
    mu_min: float
    """Lower bound of μ after a decrease."""
    growth: float | None
    """Factor on μ after a rejected trial; None for Nielsen's ``μ ← μν, ν ← 2ν``."""
    decrease_floor: float
    """Smallest factor of the decrease ``max(floor, 1 − (2ρ − 1)³)`` after an accepted trial."""
    max_trials: int
    """Cap on trials (damped solves, accepted or not) per step."""
    grow_on_solve_failure: bool = True
    """A damped system that could not be factorised raises μ like a rejected trial."""

    def initial_mu(self, diag: np.ndarray) -> float:
        """``max(μ_init · max-or-median(diag), μ_min)``; ``max(1, μ_min)`` without entries."""
        if diag.size == 0:
            return max(1.0, self.mu_min)
        scale = np.max(diag) if self.mu_start is MuStart.MAX_DIAGONAL else np.median(diag)
        return max(self.mu_init * float(scale), self.mu_min)

    def accepts(self, cost: float, new_cost: float) -> bool:
        """Whether a trial that moved the cost from ``cost`` to ``new_cost`` is a descent step."""
        if not math.isfinite(new_cost):
            return False
        equal = costs_equal(cost, new_cost)  # first: the same calls whichever side roundoff fell
        return equal or new_cost < cost

    def decreased(self, state: DampingState, rho: float) -> DampingState:
        """Nielsen's decrease after an accepted trial with gain ratio ``rho``."""
        factor = max(self.decrease_floor, 1.0 - (2.0 * rho - 1.0) ** 3)
        return DampingState(max(state.mu * factor, self.mu_min), 2.0)

    def grown(self, state: DampingState) -> DampingState:
        """μ after a rejected (or, by policy, unfactorisable) trial."""
        if self.growth is None:
            return DampingState(state.mu * state.nu, state.nu * 2.0)
        return DampingState(state.mu * self.growth, state.nu)


@dataclass(frozen=True)
class DampingState:
    """μ and Nielsen's ν of one model between steps."""

    mu: float
    nu: float = 2.0


LM_DAMPING = DampingPolicy(
    mu_start=MuStart.MAX_DIAGONAL,
    mu_init=1e-12,
    mu_min=1e-20,
    growth=None,
    decrease_floor=1.0 / 3.0,
    max_trials=30,
)
"""Centralized LM (Gauss–Newton model). ``lm.solve`` takes mu_init, mu_min and max_trials from
its ``LMParams`` (whose defaults these are)."""

NEWTON_MU_DECREASE = 0.1
"""Smallest factor by which an accepted Newton step lowers μ_N (Nielsen's rule uses 1/3): the
Newton model converges quadratically once it is convex, so a μ_N raised while it was not (far
from the optimum) must fall back quickly; with 1/3 parking-garage needed one iteration more than
with the shared μ."""

LM_NEWTON_DAMPING = DampingPolicy(
    mu_start=MuStart.MAX_DIAGONAL,
    mu_init=LM_DAMPING.mu_init,
    mu_min=LM_DAMPING.mu_min,
    growth=None,
    decrease_floor=NEWTON_MU_DECREASE,
    max_trials=1,
    grow_on_solve_failure=False,
)
"""Centralized LM, exact-Hessian model with its own μ_N: one trial per iteration (a failed one
hands the iteration to the Gauss–Newton model), μ_N kept where the model is not convex."""

LM_SHARED_NEWTON_DAMPING = DampingPolicy(
    mu_start=MuStart.MAX_DIAGONAL,
    mu_init=LM_DAMPING.mu_init,
    mu_min=LM_DAMPING.mu_min,
    growth=1.0,
    decrease_floor=1.0 / 3.0,
    max_trials=1,
    grow_on_solve_failure=False,
)
"""Centralized LM, exact-Hessian model sharing the Gauss–Newton μ (``newton_damping='shared'``,
the policy before μ_N, kept for benchmarks): a failed trial leaves μ to the Gauss–Newton ones."""

AGENT_DAMPING = DampingPolicy(
    mu_start=MuStart.MEDIAN_DIAGONAL,
    mu_init=1e-4,
    mu_min=1e-12,
    growth=4.0,
    decrease_floor=1.0 / 3.0,
    max_trials=6,
)
"""DRAN's local step (one per round); the agent takes mu_init from ``AgentConfig.mu_init``."""


@dataclass(frozen=True, eq=False)
class DampedStep:
    """The outcome of :func:`damped_step`."""

    accepted: bool
    state: DampingState
    """μ (and ν) after the trials: decreased after an accepted one, else grown."""
    trials: int
    """Damped solves, accepted or not (failed factorisations included)."""
    solve_failures: int
    """Trials whose damped system could not be factorised."""
    mu: float
    """μ of the last trial (the accepted one when ``accepted``); nan without trials."""
    rho: float
    """Gain ratio of the accepted trial; nan when none was accepted or its decrease was below
    ``COST_RESOLUTION``."""
    predicted: float
    """Predicted decrease ½(μ‖ξ‖² − ⟨g, ξ⟩) of the last solved trial; inf when none was solved."""
    u: np.ndarray | None = None
    """The accepted private step (as solved, before any scaling by ``evaluate``)."""
    v: np.ndarray | None = None
    """The accepted public step."""
    step: np.ndarray | None = None
    """ξ = (u, v) stacked."""
    candidate: np.ndarray | None = None
    """What ``evaluate`` returned with the accepted cost (the new poses)."""
    cost: float = math.nan
    """The cost at ``candidate``."""

    @property
    def solved(self) -> int:
        """Trials whose damped system was solved."""
        return self.trials - self.solve_failures


SolveModel = Callable[[float], tuple[np.ndarray, np.ndarray]]
"""μ → (u, v), the minimiser of the damped model; raises LinearSolveError."""
Evaluate = Callable[[np.ndarray, np.ndarray], tuple[float, np.ndarray]]
"""(u, v) → (cost, poses) at the retracted point."""


def damped_step(
    policy: DampingPolicy,
    state: DampingState,
    solve_model: SolveModel,
    evaluate: Evaluate,
    cost: float,
    g: np.ndarray,
    max_trials: int | None = None,
    label: str = "",
) -> DampedStep:
    """Trials at growing μ from ``state`` until one lowers ``cost`` (module docstring).

    ``g`` is the gradient ``[g_x; g_y]`` at the linearisation point (for the predicted
    decrease); ``max_trials`` overrides the policy's cap (a caller that spent trials on another
    model). Never raises on numerical trouble.
    """
    trials = failures = 0
    mu = math.nan
    predicted = math.inf
    for _ in range(policy.max_trials if max_trials is None else max_trials):
        trials += 1
        mu = state.mu
        try:
            u, v = solve_model(mu)
        except LinearSolveError as exc:
            log.debug("%s damped solve failed at mu=%g: %s", label, mu, exc)
            failures += 1
            if policy.grow_on_solve_failure:
                state = policy.grown(state)
            continue
        step = np.concatenate([u, v])
        predicted = 0.5 * float(mu * step @ step - g @ step)
        new_cost, candidate = evaluate(u, v)
        log.debug("%s mu=%.3g predicted %.6g actual %.6g", label, mu, predicted, cost - new_cost)
        if policy.accepts(cost, new_cost):
            actual = cost - new_cost
            if costs_equal(cost, new_cost):  # an unmeasurable decrease says nothing about μ
                rho, after = math.nan, DampingState(state.mu, 2.0)
            else:
                rho = actual / predicted if predicted > 0 else 0.0
                after = policy.decreased(state, rho)
            return DampedStep(
                True,
                after,
                trials,
                failures,
                mu,
                rho,
                predicted,
                u,
                v,
                step,
                candidate,
                new_cost,
            )
        state = policy.grown(state)
    return DampedStep(False, state, trials, failures, mu, math.nan, predicted)
