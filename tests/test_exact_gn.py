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
    res = exact_gn.refine(
        g.dim,
        g.num_vertices,
        g.edges,
        g.measurements,
        kappa,
        tau,
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
        wire_dtype=None,
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
    res = exact_gn.refine(
        g.dim,
        g.num_vertices,
        g.edges,
        g.measurements,
        kappa,
        tau,
        part,
        T0,
        direct_exchange,
        exact_gn.RefineParams(mode="always", max_steps=12, mu_init=1e-6, rel_tol=0.0),
        wire_dtype=None,
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
