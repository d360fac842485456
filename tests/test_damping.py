"""The damped LM step (dran_edge.solver.damping): gain ratio, Nielsen's update, acceptance, trial cap,
for both policies in use (centralized LM and the DRAN agent)."""

import math
from dataclasses import replace

import numpy as np
import pytest

from dran_edge.config import AgentConfig
from dran_edge.solver.damping import (
    AGENT_DAMPING,
    COST_FLOOR,
    COST_RESOLUTION,
    LM_DAMPING,
    LM_NEWTON_DAMPING,
    DampingState,
    MuStart,
    costs_equal,
    damped_step,
)

from dran_edge.solver.lm import LinearSolveError, LMParams

# A quadratic cost c(ξ) = c0 + ⟨g, ξ⟩ + ½⟨ξ, H ξ⟩ in (u, v) = (ξ[:2], ξ[2:]).
H = np.diag([4.0, 1.0, 2.0])
G = np.array([1.0, -2.0, 0.5])
C0 = 10.0


def quadratic_cost(xi: np.ndarray) -> float:
    return float(C0 + G @ xi + 0.5 * xi @ H @ xi)


def lm_model(mu: float) -> tuple[np.ndarray, np.ndarray]:
    """The minimiser of the damped model: (H + μI) ξ = −g."""
    xi = np.linalg.solve(H + mu * np.eye(3), -G)
    return xi[:2], xi[2:]


def evaluate_quadratic(u: np.ndarray, v: np.ndarray) -> tuple[float, np.ndarray]:
    xi = np.concatenate([u, v])
    return quadratic_cost(xi), xi


def constant_cost(value: float):
    return lambda u, v: (value, np.concatenate([u, v]))


POLICIES = [LM_DAMPING, AGENT_DAMPING]


@pytest.mark.parametrize("policy", POLICIES, ids=["lm", "agent"])
def test_quadratic_model_gain_ratio_one_and_nielsen_decrease(policy):
    mu = 0.5
    out = damped_step(policy, DampingState(mu, 8.0), lm_model, evaluate_quadratic, C0, G)
    assert out.accepted and out.trials == 1 and out.solve_failures == 0
    xi = np.linalg.solve(H + mu * np.eye(3), -G)
    np.testing.assert_allclose(out.step, xi)
    # the undamped model is the cost itself: predicted = actual decrease, ρ = 1
    assert out.predicted == pytest.approx(C0 - quadratic_cost(xi), rel=1e-12)
    assert out.rho == pytest.approx(1.0, rel=1e-12)
    assert out.cost == pytest.approx(quadratic_cost(xi), rel=1e-15)
    # Nielsen: μ · max(1/3, 1 − (2ρ − 1)³) = μ/3, and ν back to 2
    assert out.state.mu == pytest.approx(mu / 3.0, rel=1e-12)
    assert out.state.nu == 2.0
    assert out.mu == mu


def test_gain_ratio_sets_the_decrease_factor():
    # half the predicted decrease realised: ρ = ½, factor 1 − 0³ = 1 (μ kept)
    mu = 0.25
    u, v = lm_model(mu)
    xi = np.concatenate([u, v])
    predicted = 0.5 * float(mu * xi @ xi - G @ xi)
    out = damped_step(
        LM_DAMPING, DampingState(mu), lm_model, constant_cost(C0 - 0.5 * predicted), C0, G
    )
    assert out.accepted and out.rho == pytest.approx(0.5)
    assert out.state.mu == pytest.approx(mu)


@pytest.mark.parametrize("policy", POLICIES)
def test_a_cost_equal_up_to_roundoff_is_accepted_and_keeps_mu(policy):
    """Costs within COST_RESOLUTION (relative) or COST_FLOOR are equal: accepted by every
    policy, with μ kept and no gain ratio (a decision on roundoff would part two CPUs' runs)."""
    for new_cost in (C0, C0 * (1 + 0.5 * COST_RESOLUTION), C0 * (1 - 0.5 * COST_RESOLUTION)):
        out = damped_step(
            replace(policy, max_trials=1),
            DampingState(1.0),
            lm_model,
            constant_cost(new_cost),
            C0,
            G,
        )
        assert out.accepted and out.cost == new_cost
        assert math.isnan(out.rho)
        assert out.state == DampingState(1.0, 2.0)
    # a cost that is zero in exact arithmetic, as 0 on one machine and 4e-26 on another
    out = damped_step(
        replace(policy, max_trials=1), DampingState(1.0), lm_model, constant_cost(4e-26), 0.0, G
    )
    assert out.accepted and out.state.mu == 1.0
    assert costs_equal(0.0, 0.5 * COST_FLOOR) and not costs_equal(0.0, 2.0 * COST_FLOOR)


@pytest.mark.parametrize("policy", POLICIES)
def test_a_cost_measurably_above_is_rejected(policy):
    out = damped_step(
        replace(policy, max_trials=1),
        DampingState(1.0),
        lm_model,
        constant_cost(C0 * (1 + 2 * COST_RESOLUTION)),
        C0,
        G,
    )
    assert not out.accepted
    assert out.candidate is None and math.isnan(out.rho)


def test_acceptance_needs_a_finite_cost():
    for policy in POLICIES:
        out = damped_step(
            replace(policy, max_trials=2),
            DampingState(1.0),
            lm_model,
            constant_cost(math.nan),
            C0,
            G,
        )
        assert not out.accepted and out.trials == 2


def test_trial_cap_reached_grows_mu_per_policy():
    mu = 1e-3
    worse = constant_cost(C0 + 1.0)
    agent = damped_step(AGENT_DAMPING, DampingState(mu), lm_model, worse, C0, G)
    assert not agent.accepted and agent.trials == AGENT_DAMPING.max_trials
    assert agent.state.mu == pytest.approx(mu * AGENT_DAMPING.growth**AGENT_DAMPING.max_trials)
    assert agent.predicted > 0.0  # the last solved trial's prediction, kept for the caller
    lm = damped_step(LM_DAMPING, DampingState(mu), lm_model, worse, C0, G, max_trials=5)
    assert not lm.accepted and lm.trials == 5
    # Nielsen: μ ← μν, ν ← 2ν from ν = 2: factors 2, 4, 8, 16, 32
    assert lm.state.mu == pytest.approx(mu * 2.0 ** (1 + 2 + 3 + 4 + 5))
    assert lm.state.nu == 2.0**6


def test_overshooting_step_is_rejected_until_mu_is_large_enough():
    # a quartic cost: a small μ overshoots (non-descent), larger μ shortens the step until it pays
    def quartic(u, v):
        xi = np.concatenate([u, v])
        return C0 + float(G @ xi) + 50.0 * float(xi @ xi) ** 2, xi

    out = damped_step(LM_DAMPING, DampingState(1e-6), lm_model, quartic, C0, G)
    assert out.accepted and out.trials > 1
    assert quartic(*lm_model(out.mu))[0] < C0
    # every earlier μ gave a step that did not lower the cost
    mu = 1e-6
    for k in range(out.trials - 1):
        assert not quartic(*lm_model(mu))[0] < C0
        mu *= 2.0 ** (k + 1)
    assert out.mu == pytest.approx(mu)


def test_non_descent_direction_accepted_by_luck_gets_zero_gain():
    # a step against the gradient's descent (⟨g, ξ⟩ > 0): the predicted decrease is not positive,
    # so ρ = 0 and μ doubles (1 − (−1)³ = 2) even though the cost happened to drop
    def uphill(mu):
        return G[:2] / (1.0 + mu), G[2:] / (1.0 + mu)

    out = damped_step(LM_DAMPING, DampingState(1.0), uphill, constant_cost(C0 - 1.0), C0, G)
    assert out.accepted and out.predicted <= 0.0 and out.rho == 0.0
    assert out.state.mu == pytest.approx(2.0)


def test_unfactorisable_trials_raise_mu_or_not_by_policy():
    def fails_below_one(mu):
        if mu < 1.0:
            raise LinearSolveError("not positive definite")
        return lm_model(mu)

    out = damped_step(AGENT_DAMPING, DampingState(0.1), fails_below_one, evaluate_quadratic, C0, G)
    assert out.accepted and out.solve_failures == 2 and out.trials == 3  # 0.1, 0.4, 1.6
    assert out.mu == pytest.approx(1.6)
    newton = damped_step(
        LM_NEWTON_DAMPING, DampingState(0.1, 4.0), fails_below_one, evaluate_quadratic, C0, G
    )
    assert not newton.accepted and newton.trials == 1 and newton.solved == 0
    assert newton.state == DampingState(0.1, 4.0)  # μ_N kept: the model is not convex here
    assert newton.predicted == math.inf


def test_newton_policy_lowers_mu_faster():
    lm = damped_step(LM_DAMPING, DampingState(1.0), lm_model, evaluate_quadratic, C0, G)
    newton = damped_step(LM_NEWTON_DAMPING, DampingState(1.0), lm_model, evaluate_quadratic, C0, G)
    assert lm.rho == pytest.approx(1.0) and newton.rho == pytest.approx(1.0)
    assert newton.state.mu == pytest.approx(LM_NEWTON_DAMPING.decrease_floor)
    assert lm.state.mu == pytest.approx(1.0 / 3.0)


def test_initial_mu_rules():
    diag = np.array([1.0, 2.0, 3.0, 1e9])  # a stiff gauge prior
    assert LM_DAMPING.mu_start is MuStart.MAX_DIAGONAL
    assert LM_DAMPING.initial_mu(diag) == pytest.approx(LM_DAMPING.mu_init * 1e9)
    agent = replace(AGENT_DAMPING, mu_init=0.1)
    assert agent.initial_mu(diag) == pytest.approx(0.1 * 2.5)  # the median ignores the prior
    assert agent.initial_mu(np.zeros(0)) == 1.0
    assert replace(agent, mu_init=1e-30).initial_mu(diag) == agent.mu_min


def test_policy_defaults_are_the_callers_defaults():
    params = LMParams()
    assert (params.mu_init, params.mu_min, params.max_trials) == (
        LM_DAMPING.mu_init,
        LM_DAMPING.mu_min,
        LM_DAMPING.max_trials,
    )
    assert AgentConfig().mu_init == AGENT_DAMPING.mu_init


def test_no_trials():
    out = damped_step(
        LM_DAMPING, DampingState(1.0), lm_model, evaluate_quadratic, C0, G, max_trials=0
    )
    assert not out.accepted and out.trials == 0 and out.state == DampingState(1.0)
