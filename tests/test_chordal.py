"""Chordal initialisation is exact on noiseless graphs and close on noisy ones."""

from __future__ import annotations

import numpy as np
import pytest

from dran_edge import geometry as geo
from dran_edge.solver.chordal import chordal_initialization
from dran_edge.errors import InputError
from dran_edge.sim.graphgen import synthetic_graph
from dran_edge.solver.objective import sesync_objective, sesync_weights
from dran_edge.solver.centralized import initial_poses


@pytest.mark.parametrize("dim", [2, 3])
def test_chordal_is_exact_on_noiseless_graphs(dim):
    g, truth = synthetic_graph(dim, side=6, layers=2, sigma_t_m=0.0, sigma_r_rad=0.0)
    kappa, tau = sesync_weights(dim, g.information)
    T = chordal_initialization(g.num_vertices, g.edges, g.measurements, kappa, tau, anchor=0)
    np.testing.assert_allclose(T[0], np.eye(dim + 1), atol=1e-12)
    # truth expressed relative to vertex 0
    np.testing.assert_allclose(T, geo.inverse(truth[0]) @ truth, atol=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
def test_chordal_anchor_and_noisy_quality(dim):
    g, truth = synthetic_graph(dim, side=6, layers=2, seed=4)
    T = initial_poses(g, "chordal")
    np.testing.assert_allclose(T[0], truth[0], atol=1e-12)  # gauge: first vertex keeps its pose
    d = T.shape[-1] - 1
    np.testing.assert_allclose(
        np.swapaxes(T[:, :d, :d], 1, 2) @ T[:, :d, :d],
        np.broadcast_to(np.eye(d), (T.shape[0], d, d)),
        atol=1e-12,
    )
    kappa, tau = sesync_weights(dim, g.information)
    F_init = sesync_objective(T, g.edges, g.measurements, kappa, tau)
    F_odo = sesync_objective(initial_poses(g, "odometry"), g.edges, g.measurements, kappa, tau)
    assert F_init < F_odo
    assert np.max(np.linalg.norm(T[:, :d, d] - truth[:, :d, d], axis=1)) < 0.2


def test_odometry_initialization_composes_the_chain():
    g, truth = synthetic_graph(2, side=4, sigma_t_m=0.0, sigma_r_rad=0.0)
    np.testing.assert_allclose(initial_poses(g, "odometry"), truth, atol=1e-9)


def test_disconnected_graph_is_an_input_error():
    g, _ = synthetic_graph(2, side=3, sigma_t_m=0.0, sigma_r_rad=0.0)
    keep = ~(
        (g.edges[:, 0] <= 3) & (g.edges[:, 1] >= 4) | (g.edges[:, 1] <= 3) & (g.edges[:, 0] >= 4)
    )
    with pytest.raises(InputError, match="connected"):
        chordal_initialization(
            g.num_vertices,
            g.edges[keep],
            g.measurements[keep],
            np.ones(keep.sum()),
            np.ones(keep.sum()),
        )
