"""The supernodal Cholesky against dense solves, and LM with it against LM with SuperLU."""

from __future__ import annotations

import numpy as np
import pytest

from dran_edge.solver.graph import kinds_array
from dran_edge.sim.graphgen import synthetic_graph
from dran_edge.solver.lm import (
    LMParams,
    build_plan,
    cholesky_factorizer,
    linearize,
    schur_step,
    solve,
)
from dran_edge.solver.centralized import initial_poses, pose_graph
from dran_edge.solver.sparse_cholesky import (
    NotPositiveDefinite,
    SymbolicCholesky,
    _front_pos,
    _tril_flat,
    _update_positions,
)


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


def _block_spd(rng, nb, b, edges):
    """A random SPD matrix with the given block edges, and its CSC pattern."""
    M = np.eye(nb * b) * 1e-3
    block_pattern = np.eye(nb, dtype=bool)
    for i, j in edges:
        X = rng.normal(size=(2 * b, 2 * b))
        idx = np.r_[i * b : (i + 1) * b, j * b : (j + 1) * b]
        M[np.ix_(idx, idx)] += X @ X.T
        block_pattern[i, j] = block_pattern[j, i] = True
    cols, rows = np.nonzero(np.kron(block_pattern, np.ones((b, b), dtype=bool)).T)
    return M, np.searchsorted(cols, np.arange(nb * b + 1)), rows, cols


@pytest.mark.parametrize("max_cols,small_cols", [(64, 8), (2, 1), (3, 8), (64, 64)])
def test_trees_with_many_leaf_siblings(max_cols, small_cols):
    """Stars and caterpillars: many elimination-tree leaves under one parent, gathered into
    their parent's supernode, or split again when the parent cannot join them (max_cols)."""
    rng = np.random.default_rng(7)
    b = 3
    shapes = {
        "star": [(0, j) for j in range(1, 15)],
        "caterpillar": [(i, i + 1) for i in range(9)]
        + [(i, 10 + 3 * i + t) for i in range(10) for t in range(3)],
        # siblings with different structures ({hub, outer j}): gathered ones must be split
        # again (their front would miss rows) unless their parent joins them
        "fan": [(0, j) for j in range(1, 11)]
        + [(j, 11 + j % 5) for j in range(1, 11)]
        + [(0, 11 + t) for t in range(5)],
        "two stars and a chord": [(0, j) for j in range(1, 8)]
        + [(8, j) for j in range(9, 16)]
        + [(3, 12)],
    }
    for edges in shapes.values():
        nb = 1 + max(max(e) for e in edges)
        M, indptr, rows, cols = _block_spd(rng, nb, b, edges)
        sym = SymbolicCholesky(indptr, rows, nb * b, b, max_cols=max_cols, small_cols=small_cols)
        rhs = rng.normal(size=(nb * b, 2))
        for mu in (0.0, 0.5):
            x = sym.factorize(M[rows, cols], mu).solve(rhs)
            np.testing.assert_allclose(
                x, np.linalg.solve(M + mu * np.eye(nb * b), rhs), rtol=1e-6, atol=1e-8
            )


def test_gathered_leaf_siblings_are_split_when_their_parent_cannot_join(monkeypatch):
    """Natural order on 0–2, 0–3, 1–2, 1–4, 2–3, 3–4: leaves 0 and 1 are siblings under 2 with
    different structures ({2, 3} and {2, 4}). With max_cols=2 they gather but 2 cannot join
    them, so they must become two supernodes again (one front would miss row 3 or 4)."""
    import dran_edge.solver.sparse_cholesky as sc

    monkeypatch.setattr(sc, "_block_order", lambda nb, rows, cols: np.arange(nb))
    rng = np.random.default_rng(11)
    b = 2
    M, indptr, rows, cols = _block_spd(rng, 5, b, [(0, 2), (0, 3), (1, 2), (1, 4), (2, 3), (3, 4)])
    rhs = rng.normal(size=5 * b)
    for max_cols, want_supernodes in ((2, 4), (64, 1)):
        sym = sc.SymbolicCholesky(indptr, rows, 5 * b, b, max_cols=max_cols)
        assert sym.num_supernodes == want_supernodes
        x = sym.factorize(M[rows, cols]).solve(rhs)
        np.testing.assert_allclose(x, np.linalg.solve(M, rhs), rtol=1e-6, atol=1e-8)


def test_extend_add_fallback_for_old_numpy_gives_the_same_solution(monkeypatch):
    import dran_edge.solver.sparse_cholesky as sc

    g, truth = synthetic_graph(3, side=4, layers=2, seed=5)
    plan = build_plan(pose_graph(g, "chordal", "sesync"))
    lin = linearize(pose_graph(g, "chordal", "sesync"), plan, truth)
    sym = SymbolicCholesky(plan.A_indptr, plan.A_indices, plan.n_u, plan.dof)
    rhs = np.random.default_rng(1).normal(size=plan.n_u)
    x_at = sym.factorize(lin.A.data, 1e-3).solve(rhs)
    monkeypatch.setattr(sc, "_scatter_add", sc._add_at_fancy)
    x_fancy = sym.factorize(lin.A.data, 1e-3).solve(rhs)
    np.testing.assert_allclose(x_fancy, x_at, rtol=1e-10, atol=1e-12)
    M = lin.A.toarray() + 1e-3 * np.eye(plan.n_u)
    np.testing.assert_allclose(x_fancy, np.linalg.solve(M, rhs), rtol=1e-7, atol=1e-9)


def test_update_positions_are_the_front_layout():
    rng = np.random.default_rng(3)
    for _ in range(20):
        f = int(rng.integers(2, 40))
        k = int(rng.integers(1, f))
        m = int(rng.integers(1, f + 1))
        locs = np.sort(np.stack([rng.choice(f, m, replace=False) for _ in range(4)]), axis=1)
        got = _update_positions(locs, np.full((4, 1), k), np.full((4, 1), f))
        i, j = np.divmod(_tril_flat(m), m)
        want = np.stack([_front_pos(loc[i], loc[j], k, f) for loc in locs])
        np.testing.assert_array_equal(got, want)
        # the layout is a bijection of the lower triangle onto the segments' positions
        r, c = np.tril_indices(f)
        pos = _front_pos(r, c, k, f)
        assert np.unique(pos).size == pos.size and pos.max() < k * k + (f - k) * f


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
