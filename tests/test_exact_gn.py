"""Exact distributed LM refinement (dran_edge.dran.exact_gn): the condensed step is the
centralized one, and the root's rule rejects a step that raises the cost."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from dran_edge import geometry as geo
from dran_edge.dran import exact_gn
from dran_edge.dran.dist_init import direct_exchange
from dran_edge.experiments.suite import Case, make_graph, make_partition
from dran_edge.solver.centralized import initial_poses, pose_graph
from dran_edge.solver.lm import build_plan, linearize
from dran_edge.solver.objective import sesync_objective, sesync_weights


def _refine(g, part, T0, exchange, params):
    """``exact_gn.refine`` on graph ``g`` (SE-Sync weights), values exchanged as float64."""
    kappa, tau = sesync_weights(g.dim, g.information)
    return exact_gn.refine(
        g.dim,
        g.num_vertices,
        g.edges,
        g.measurements,
        kappa,
        tau,
        part,
        T0,
        exchange,
        params,
        wire_dtype=None,
    )


def _central_step(g, poses, mu, exact=False):
    """One centralized damped step (A + μ diag A_GN) u = −g_x, every vertex but the gauge
    private (``solver.lm``'s own linearisation; A the Gauss–Newton or the exact Hessian)."""
    graph = pose_graph(g, "chordal", "sesync")
    plan = build_plan(graph)
    lin = linearize(graph, plan, poses, exact_hessian=exact)
    A_gn = linearize(graph, plan, poses).A
    A = lin.A + mu * sp.diags(A_gn.diagonal())
    u = spla.spsolve(sp.csc_matrix(A), -lin.g_x)
    out = poses.copy()
    out[plan.private_vars] = geo.retract(poses[plan.private_vars], u.reshape(-1, plan.dof))
    return out


@pytest.mark.parametrize(
    "case,hessian",
    [
        (Case("car2d", 240, 1, robots=3), "gauss_newton"),
        (Case("car3d", 200, 2, robots=3, split="interleaved"), "gauss_newton"),
        (Case("car3d", 200, 2, robots=3, split="interleaved"), "exact"),
    ],
)
def test_condensed_step_equals_the_centralized_step(case, hessian):
    g, _ = make_graph(case)
    part = make_partition(case, g)
    assert case.split == "contiguous" or len(part.parts[0].neighbours) == 2  # loops across
    kappa, tau = sesync_weights(g.dim, g.information)
    T0 = initial_poses(g, "chordal" if hessian == "exact" else "odometry")
    mu = 1e-3
    res = _refine(
        g,
        part,
        T0,
        direct_exchange,
        exact_gn.RefineParams(
            mode="always",
            max_steps=1,
            mu_init=mu,
            rel_tol=0.0,
            hessian=hessian,
            newton_switch=np.inf,
        ),
    )
    assert res.used and res.steps == 1 and res.rounds > 0 and res.indefinite == 0
    T1 = _central_step(g, T0, mu, exact=hessian == "exact")
    np.testing.assert_allclose(res.poses, T1, atol=1e-9)
    F = lambda T: sesync_objective(T, g.edges, g.measurements, kappa, tau)
    assert res.F_history[0] == pytest.approx(F(T0), rel=1e-12)
    assert res.F_history[1] == pytest.approx(F(T1), rel=1e-12)


def test_the_root_rejects_a_step_that_raises_the_cost_and_damps_more():
    rule = exact_gn.LMRule(exact_gn.RefineParams(mu_init=1e-3), wire_dtype=None)
    assert rule.decide(100.0, 0.0, 0) == (True, False, "")  # the start point
    assert rule.decide(101.0, 5.0, 1)[0] is False  # a trial above: rejected
    assert rule.mu == pytest.approx(2e-3)
    assert rule.decide(100.0, 0.0, 2)[0] is True  # the accepted point again
    accepted, stop, _ = rule.decide(90.0, 10.0, 3)  # a good step: μ falls
    assert accepted and not stop and rule.mu < 2e-3


def test_refinement_never_raises_the_cost_from_a_bad_start():
    case = Case("car2d", 240, 1, robots=3)
    g, _ = make_graph(case)
    part = make_partition(case, g)
    kappa, tau = sesync_weights(g.dim, g.information)
    rng = np.random.default_rng(0)
    T0 = initial_poses(g, "odometry")
    T0[1:] = geo.retract(T0[1:], rng.normal(0, 2.0, (g.num_vertices - 1, 3)))
    res = _refine(
        g,
        part,
        T0,
        direct_exchange,
        exact_gn.RefineParams(mode="always", max_steps=12, mu_init=1e-6, rel_tol=0.0),
    )
    F = lambda T: sesync_objective(T, g.edges, g.measurements, kappa, tau)
    assert res.trials > res.steps  # some trial raised F and was rejected
    assert np.all(np.diff(res.F_history) < 0)
    assert F(res.poses) == pytest.approx(res.F_history[-1], rel=1e-12)
    assert res.F_history[-1] < F(T0)


def test_run_g2o_dran_refines_over_the_bus_and_counts_its_rounds_and_bytes():
    from dran_edge.experiments.fleet import run_g2o_dran, table1_setup

    case = Case("car2d", 240, 1, robots=3)
    g, _ = make_graph(case)
    part = make_partition(case, g)
    cfg, kw = table1_setup(g.dim)
    off = run_g2o_dran(g, 3, cfg, max_rounds=3, partition=part, **kw)
    on = run_g2o_dran(
        g, 3, cfg, max_rounds=3, partition=part, refine=exact_gn.RefineParams(mode="auto"), **kw
    )
    assert not any(k.startswith("refine") for k in off)
    assert on["refine_used"] and on["refine_rounds"] > 0 and on["refine_bytes"] > 0
    assert on["objective_init"] == off["objective_init"]
    assert on["objective_refined"] < 0.9 * on["objective_init"]
    # converged on the root's relative-decrease test: DRAN does not run
    assert on["refine_converged"] and on["rounds"] == 0 and on["stopped_by"] == "refine"
    assert on["rounds_total"] == on["init_rounds"] + on["refine_rounds"]
    assert on["bytes_total"] == on["bytes_init"] + on["refine_bytes"]
    assert [k for k, _, _ in on["refine_curve"]] == sorted(k for k, _, _ in on["refine_curve"])


def _frozen_run(case, hessian, exchange=direct_exchange):
    g, _ = make_graph(case)
    part = make_partition(case, g)
    kappa, tau = sesync_weights(g.dim, g.information)
    params = exact_gn.RefineParams(mode="always", rel_tol=1e-12, hessian=hessian, frozen=True)
    T0 = initial_poses(g, "chordal")
    res = _refine(
        g,
        part,
        T0,
        exchange,
        params,
    )
    return g, part, kappa, tau, res


@pytest.mark.parametrize("hessian", ["gauss_newton", "exact"])
def test_frozen_steps_reach_the_centralized_optimum(hessian):
    from dran_edge.solver.centralized import solve_g2o
    from dran_edge.solver.lm import Hessian, LMParams

    case = Case("car3d", 200, 2, robots=3, split="interleaved")
    g, _, kappa, tau, res = _frozen_run(case, hessian)
    central = solve_g2o(g, params=LMParams(hessian=Hessian.EXACT, cost_tol=1e-14))
    F = sesync_objective(res.poses, g.edges, g.measurements, kappa, tau)
    assert res.converged and res.frozen_steps >= 2
    assert np.all(np.diff(res.F_history) <= 0)
    assert F == pytest.approx(central.objective_final, rel=1e-9)
    assert F == pytest.approx(res.F_history[-1], rel=1e-12)


def test_a_frozen_gather_sends_only_the_condensed_gradient():
    """Per robot and tree link a frozen gather carries its boundary vector (|B_r|·dof floats),
    its 5 scalars and the chunk length, padded to d×d chunks; a full gather far more."""
    from dran_edge import geometry as geo
    from dran_edge.dran import substructure
    from dran_edge.messages import InitStage

    sent: list[tuple[int, int]] = []  # (rounds, floats) of every REFINE_SCHUR exchange

    def counting(kind, rounds, outgoing):
        if kind == InitStage.REFINE_SCHUR:
            floats = sum(np.size(e.value) for lst in outgoing.values() for _, es in lst for e in es)
            sent.append((rounds, floats))
        return direct_exchange(kind, rounds, outgoing)

    case = Case("car3d", 200, 2, robots=3, split="interleaved")
    g, part, _, _, res = _frozen_run(case, "exact", counting)
    tree = substructure.robot_tree(part)
    d, b = g.dim, geo.dof(g.dim)
    gathers: list[int] = []  # floats per gather (one exchange per tree level, consecutive rounds)
    for k, (r, f) in enumerate(sent):
        if k and r == sent[k - 1][0] + 1 and len(gathers) and tree.height > 1:
            gathers[-1] += f
        else:
            gathers.append(f)

    def chunked(floats: int) -> int:  # entries carry d × d values: round up to whole entries
        return -(-floats // (d * d)) * d * d

    # each robot's frozen gather: 1 + |B_r|·dof gradient values + 5 scalars, relayed depth times
    frozen_floats = sum(
        int(tree.depth[p.robot_id]) * chunked(1 + substructure.boundary(p, 0).size * b + 5)
        for p in part.parts
    )
    frozen = [f for f in gathers if f == frozen_floats]
    assert len(frozen) >= res.frozen_steps >= 2
    assert all(f == frozen_floats or f > 10 * frozen_floats for f in gathers)


def test_the_root_treats_a_rejected_or_slow_frozen_step_as_a_stale_factor():
    rule = exact_gn.LMRule(exact_gn.RefineParams(mu_init=1e-3, rel_tol=1e-2), wire_dtype=None)
    rule.decide(100.0, 0.0, 0)  # the start point
    assert rule.decide(80.0, 20.0, 1) == (True, False, "")  # the full step: −20
    mu = rule.mu
    assert rule.decide(81.0, 1.0, 2, frozen=True)[0] is False  # a frozen step raised F
    assert rule.mu == mu  # the factor was stale, not the damping too weak
    rule.decide(80.0, 0.0, 3)  # the accepted point again
    assert rule.decide(70.0, 10.0, 4) == (True, False, "")  # a full step: −10
    mu = rule.mu
    assert rule.decide(66.0, 4.0, 5, frozen=True) == (True, False, "")  # −4 ≤ ½ · 10: fast
    assert not rule.slow and rule.mu == mu  # damped with the frozen factor's μ
    assert rule.decide(63.0, 3.0, 6, frozen=True) == (True, False, "")  # −3 > ½ · 4: slow
    assert rule.slow  # a full gather follows
    rule.decide(62.9, 0.1, 7)  # a full step: −0.1
    accepted, stop, _ = rule.decide(62.88, 0.02, 8, frozen=True)  # fast, < rel_tol: no stop
    assert accepted and not stop and rule.slow
    accepted, stop, reason = rule.decide(62.87, 0.01, 9)  # a full step < rel_tol: stop
    assert accepted and stop and reason.startswith("relative decrease")
    rule.decide(62.86, 0.01, 10, frozen=True)  # a frozen step < rel_tol again
    accepted, stop, reason = rule.decide(62.87, 0.01, 11)  # the full step after it: rejected
    assert not accepted and stop and reason.startswith("relative decrease")


def test_newton_first_falls_back_to_gauss_newton_after_a_rejection():
    """``newton_first``: the exact Hessian from the start point on, while trials are accepted;
    after a rejected trial (or an indefinite system) Gauss–Newton until a step gains < 1 %."""
    p = exact_gn.RefineParams(hessian="exact", newton_first=True, mu_init=1e-10)
    rule = exact_gn.LMRule(p, wire_dtype=None)
    assert rule.exact
    rule.decide(100.0, 0.0, 0)  # the start point
    assert rule.exact
    rule.decide(90.0, 10.0, 1)  # accepted, gained 10 %: still Newton
    assert rule.exact
    rule.decide(95.0, 1.0, 2)  # rejected
    assert not rule.exact
    rule.decide(80.0, 10.0, 3)  # accepted, gained 11 %: Gauss–Newton goes on
    assert not rule.exact
    rule.decide(79.9, 0.1, 4)  # gained < 1 %: the usual switch
    assert rule.exact
    other = exact_gn.LMRule(p, wire_dtype=None)
    other.decide(100.0, 0.0, 0)
    other.indefinite()
    assert not other.exact
    plain = exact_gn.LMRule(exact_gn.RefineParams(hessian="exact"), wire_dtype=None)
    assert not plain.exact  # without it, Gauss–Newton first
