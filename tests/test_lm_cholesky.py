"""The supernodal Cholesky against dense solves, and LM with it against LM with SuperLU."""

from __future__ import annotations

import numpy as np
import pytest

from dran_edge.graph import kinds_array
from dran_edge.graphgen import synthetic_graph
from dran_edge.lm import LMParams, build_plan, cholesky_factorizer, linearize, schur_step, solve
from dran_edge.pgo import initial_poses, pose_graph
from dran_edge.sparse_cholesky import NotPositiveDefinite, SymbolicCholesky


@pytest.mark.parametrize("dim,side,layers", [(2, 7, 1), (3, 5, 3), (3, 2, 1)])
@pytest.mark.parametrize("residual", ["geodesic", "chordal"])
def test_factor_solves_like_dense(dim, side, layers, residual):
    g, truth = synthetic_graph(dim, side=min(side, 5), layers=min(layers, 2), seed=side)
    graph = pose_graph(g, residual, "sesync")
    plan = build_plan(graph)
    lin = linearize(graph, plan, truth)
    sym = SymbolicCholesky(plan.A_indptr, plan.A_indices, plan.n_u, plan.dof)
    for mu in (0.0, 1e-3, 10.0):
        num = sym.factorize(lin.A.data, mu)
        M = lin.A.toarray() + mu * np.eye(plan.n_u)
        rhs = np.random.default_rng(0).normal(size=(plan.n_u, 3))
        np.testing.assert_allclose(num.solve(rhs), np.linalg.solve(M, rhs), rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(
            num.solve(rhs[:, 0]), np.linalg.solve(M, rhs[:, 0]), rtol=1e-7, atol=1e-9
        )


def test_random_block_sparse_spd_matrices():
    rng = np.random.default_rng(4)
    for _ in range(12):
        nb, b = int(rng.integers(5, 120)), int(rng.choice([1, 3, 6]))
        # a path of blocks plus random chords, each edge a random PSD coupling
        edges = [(i, i + 1) for i in range(nb - 1)]
        edges += [tuple(rng.choice(nb, 2, replace=False)) for _ in range(int(rng.integers(0, nb)))]
        M = np.eye(nb * b) * 1e-3
        block_pattern = np.eye(nb, dtype=bool)
        for i, j in edges:
            X = rng.normal(size=(2 * b, 2 * b))
            idx = np.r_[i * b : (i + 1) * b, j * b : (j + 1) * b]
            M[np.ix_(idx, idx)] += X @ X.T
            block_pattern[i, j] = block_pattern[j, i] = True
        pattern = np.kron(block_pattern, np.ones((b, b), dtype=bool))
        cols, rows = np.nonzero(pattern.T)  # CSC order: by column, rows ascending
        indptr = np.searchsorted(cols, np.arange(nb * b + 1))
        sym = SymbolicCholesky(indptr, rows, nb * b, b)
        rhs = rng.normal(size=nb * b)
        x = sym.factorize(M[rows, cols]).solve(rhs)
        np.testing.assert_allclose(x, np.linalg.solve(M, rhs), rtol=1e-6, atol=1e-8)


def test_indefinite_matrix_is_reported():
    g, truth = synthetic_graph(2, side=3)
    plan = build_plan(pose_graph(g, "geodesic", "sesync"))
    lin = linearize(pose_graph(g, "geodesic", "sesync"), plan, truth)
    sym = SymbolicCholesky(plan.A_indptr, plan.A_indices, plan.n_u, plan.dof)
    with pytest.raises(NotPositiveDefinite):
        sym.factorize(lin.A.data, -1e6)


def test_schur_step_with_cholesky_matches_superlu():
    g, _ = synthetic_graph(3, side=4, layers=2, seed=8)
    graph = pose_graph(g, "chordal", "sesync").with_kinds(
        kinds_array(g.num_vertices, public=[3, 9, 20], fixed=[0])
    )
    plan = build_plan(graph)
    lin = linearize(graph, plan, initial_poses(g, "odometry"))
    u1, v1 = schur_step(lin.A, lin.B, lin.C, lin.g_x, lin.g_y, 1e-2, cholesky_factorizer(plan))
    u2, v2 = schur_step(lin.A, lin.B, lin.C, lin.g_x, lin.g_y, 1e-2)
    np.testing.assert_allclose(u1, u2, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(v1, v2, rtol=1e-8, atol=1e-12)


def test_lm_same_result_with_either_factorisation():
    g, _ = synthetic_graph(3, side=5, layers=2, seed=6)
    graph = pose_graph(g, "geodesic", "sesync")
    T0 = initial_poses(g, "chordal")
    a = solve(graph, T0, LMParams(linear_solver="cholesky"))
    b = solve(graph, T0, LMParams(linear_solver="superlu"))
    assert a.status == b.status
    np.testing.assert_allclose(a.cost, b.cost, rtol=1e-9)
    np.testing.assert_allclose(a.poses, b.poses, atol=1e-8)
