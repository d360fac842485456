"""The refinement's iterative interface solve (dran_edge.dran.interface_pcg): conjugate gradients
over the robot tree with a two-level Neumann–Neumann preconditioner instead of gathering every
robot's dense condensed system."""

import numpy as np
import pytest

from dran_edge.dran import exact_gn, interface_pcg, substructure
from dran_edge.dran.dist_init import direct_exchange
from dran_edge.experiments.suite import Case, make_graph, make_partition
from dran_edge.messages import InitStage
from dran_edge.solver.chordal import chordal_initialization
from dran_edge.solver.objective import sesync_objective, sesync_weights

INTERLEAVED = Case("car3d", 200, 2, robots=3, split="interleaved")


def _run(case, exchange=direct_exchange, **params):
    """The refinement (``RefineParams(mode="always", **params)``) of ``case`` from its
    centralized chordal init, values exchanged as float64 (``test_exact_gn._refine``)."""
    from test_exact_gn import _refine

    g, _ = make_graph(case)
    part = make_partition(case, g)
    kappa, tau = sesync_weights(g.dim, g.information)
    T0 = chordal_initialization(g.num_vertices, g.edges, g.measurements, kappa, tau)
    res = _refine(g, part, T0, exchange, exact_gn.RefineParams(mode="always", **params))
    return g, part, kappa, tau, res


def test_a_tight_pcg_step_is_the_dense_step():
    """Solved to a relative residual of 1e-12 the interface step is the factorised one: the
    same accepted points, F to 1e-10."""
    _, _, _, _, dense = _run(INTERLEAVED, rel_tol=1e-12, max_steps=3)
    _, _, _, _, pcg = _run(INTERLEAVED, rel_tol=1e-12, max_steps=3, interface="pcg", pcg_eta=1e-12)
    assert len(pcg.F_history) == len(dense.F_history) >= 3
    np.testing.assert_allclose(pcg.F_history, dense.F_history, rtol=1e-10)
    assert all(1 <= k <= 60 for k in pcg.pcg_iterations)


@pytest.mark.parametrize(
    "case", [INTERLEAVED, Case("car2d", 240, 1, robots=3), Case("car3d", 200, 2, robots=3)]
)
def test_pcg_refinement_reaches_the_centralized_optimum_in_few_iterations(case):
    """Inexact Newton (CG to 0.01) still lands on F*; the coarse space of each robot's soft
    modes keeps CG short on contiguous and interleaved splits (without it, 76–122 iterations
    on the interleaved split)."""
    from dran_edge.solver.centralized import solve_g2o
    from dran_edge.solver.lm import Hessian, LMParams

    g, _, kappa, tau, res = _run(case, rel_tol=1e-10, hessian="exact", interface="pcg")
    central = solve_g2o(g, params=LMParams(hessian=Hessian.EXACT, cost_tol=1e-14))
    F = sesync_objective(res.poses, g.edges, g.measurements, kappa, tau)
    assert res.converged
    assert np.all(np.diff(res.F_history) <= 0)
    assert F == pytest.approx(central.objective_final, rel=1e-8)
    assert max(res.pcg_iterations) <= 15


def test_pcg_sends_no_condensed_matrix():
    """Every REFINE_SCHUR gather carries only condensed gradients and scalars; the PCG vectors
    are boundary-sized (no |B_r|² system crosses a link)."""
    from dran_edge import geometry as geo

    biggest: dict[InitStage, int] = {}

    def counting(kind, rounds, outgoing):
        for lst in outgoing.values():
            for _, es in lst:
                floats = sum(np.size(e.value) for e in es)
                biggest[kind] = max(biggest.get(kind, 0), floats)
        return direct_exchange(kind, rounds, outgoing)

    g, part, _, _, res = _run(INTERLEAVED, counting, rel_tol=1e-8, interface="pcg")
    b, d = geo.dof(g.dim), g.dim
    tree = substructure.robot_tree(part)
    sizes = [substructure.boundary(p, 0).size * b for p in part.parts]
    # one link carries at most the subtree's vectors: its gradients + 5 scalars + the length
    subtree = max(len(tree.subtree(r)) for r in range(len(sizes)) if r != tree.root)
    bound = subtree * (max(sizes) + 6 + d * d)
    assert res.converged and res.pcg_iterations
    assert biggest[InitStage.REFINE_SCHUR] <= bound
    assert InitStage.REFINE_PCG_UP in biggest and InitStage.REFINE_PCG_DOWN in biggest
    # the dense refinement sends far more in one gather
    dense_floats: list[int] = []

    def counting_dense(kind, rounds, outgoing):
        if kind == InitStage.REFINE_SCHUR:
            for lst in outgoing.values():
                for _, es in lst:
                    dense_floats.append(sum(np.size(e.value) for e in es))
        return direct_exchange(kind, rounds, outgoing)

    _run(INTERLEAVED, counting_dense, rel_tol=1e-8, max_steps=1)
    assert max(dense_floats) > 3 * bound


def test_soft_modes_count_the_floating_pieces():
    """A block-diagonal S made of two weakly anchored chains has 2 × dof soft modes."""
    b = 3
    rng = np.random.default_rng(0)

    def chain(n):  # a path Laplacian ⊗ I_b plus a tiny anchor: dof near-zero modes
        L = np.diag(np.r_[1.0, 2 * np.ones(n - 2), 1.0]) - np.eye(n, k=1) - np.eye(n, k=-1)
        return np.kron(L + 1e-7 * np.eye(n), np.eye(b))

    S = np.zeros((2 * 5 * b, 2 * 5 * b))
    S[: 5 * b, : 5 * b] = chain(5)
    S[5 * b :, 5 * b :] = chain(5)
    Q, _ = np.linalg.qr(rng.normal(size=(b, b)))  # a rotation inside every block: same spectrum
    R = np.kron(np.eye(10), Q)
    modes = interface_pcg.soft_modes(R @ S @ R.T, b, 1e-3, 20)
    assert modes.shape == (30, 2 * b)


def test_an_iteration_moves_one_value_per_vertex_and_link():
    """Down, a link carries its subtree's boundary vertices once (not one copy per robot); up,
    their sums: every CG exchange is Σ_links (1 + |∪ B_subtree|·dof) floats, in d×d chunks."""
    from dran_edge import geometry as geo

    per_exchange: dict[InitStage, list[int]] = {}

    def counting(kind, rounds, outgoing):
        floats = sum(np.size(e.value) for lst in outgoing.values() for _, es in lst for e in es)
        per_exchange.setdefault(InitStage(kind), []).append(floats)
        return direct_exchange(kind, rounds, outgoing)

    g, part, _, _, res = _run(INTERLEAVED, counting, rel_tol=1e-8, interface="pcg")
    b, d = geo.dof(g.dim), g.dim
    tree = substructure.robot_tree(part)
    B = [substructure.boundary(p, 0) for p in part.parts]
    expected = {  # per tree level, the links into it
        level: sum(
            -(-(1 + np.unique(np.concatenate([B[q] for q in tree.subtree(c)])).size * b) // d**2)
            * d**2
            for c in np.flatnonzero(tree.depth == level).tolist()
        )
        for level in range(1, tree.height + 1)
    }
    iterations = sum(res.pcg_iterations)
    for kind in (InitStage.REFINE_PCG_DOWN, InitStage.REFINE_PCG_UP):
        sizes = per_exchange[kind]
        # a solve of k iterations: the preconditioner at the start, then S p and (but after the
        # last) the preconditioner per iteration: 2k round trips, one such exchange per level
        for level, floats in expected.items():
            assert sizes.count(floats) == 2 * iterations
