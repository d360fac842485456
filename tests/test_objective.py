"""The SE-Sync objective and weights against hand-computed values."""

from __future__ import annotations

import numpy as np

from dran_edge import geometry as geo
from dran_edge.sim.graphgen import synthetic_graph
from dran_edge.solver.lm import evaluate_cost
from dran_edge.solver.objective import edge_factors, sesync_objective, sesync_weights
from dran_edge.solver.centralized import pose_graph


def test_two_edge_example_by_hand_2d():
    # three poses on a line; two edges with measurement "1 m forward, no turn"
    poses = geo.se2_from_xy_theta(
        np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.5, np.pi / 2]])
    )
    edges = np.array([[0, 1], [1, 2]])
    Z = geo.se2_from_xy_theta(np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    kappa, tau = np.array([2.0, 3.0]), np.array([5.0, 7.0])
    # edge 0 is satisfied exactly: 0. Edge 1: R_2 − R_1 R̃ = R(π/2) − I, ‖·‖²_F = 4(1 − cos π/2) = 4;
    # t_2 − t_1 − R_1 t̃ = (2, .5) − (1, 0) − (1, 0) = (0, .5): 0.25.  F = 3·4 + 7·0.25 = 13.75
    assert abs(sesync_objective(poses, edges, Z, kappa, tau) - 13.75) < 1e-12


def test_two_edge_example_by_hand_3d():
    poses = np.broadcast_to(np.eye(4), (3, 4, 4)).copy()
    poses[1, :3, 3] = [1.0, 2.0, 3.0]
    poses[2, :3, :3] = geo.so3_exp(np.array([0.0, 0.0, np.pi]))
    edges = np.array([[0, 1], [0, 2]])
    Z = np.broadcast_to(np.eye(4), (2, 4, 4))
    kappa, tau = np.array([1.0, 0.5]), np.array([2.0, 1.0])
    # edge 0: rotation 0, translation ‖(1,2,3)‖² = 14 -> 2·14 = 28
    # edge 1: ‖Rz(π) − I‖²_F = 2·(2² ) = 8 -> 0.5·8 = 4, translation 0.  F = 32
    assert abs(sesync_objective(poses, edges, Z, kappa, tau) - 32.0) < 1e-12


def test_sesync_weights_from_information():
    I3 = np.zeros((1, 6, 6))
    I3[0, :3, :3] = np.diag([1.0, 2.0, 4.0])
    I3[0, 3:, 3:] = np.diag([10.0, 20.0, 40.0])
    kappa, tau = sesync_weights(3, I3)
    assert np.isclose(tau[0], 3.0 / (1 + 0.5 + 0.25))
    assert np.isclose(kappa[0], 3.0 / (2 * (0.1 + 0.05 + 0.025)))
    I2 = np.array([[[4.0, 1.0, 0.0], [1.0, 4.0, 0.0], [0.0, 0.0, 9.0]]])
    kappa, tau = sesync_weights(2, I2)
    assert np.isclose(tau[0], 2.0 / np.trace(np.linalg.inv(I2[0, :2, :2])))
    assert kappa[0] == 9.0


def test_chordal_sesync_cost_is_exactly_half_of_F():
    for dim in (2, 3):
        g, truth = synthetic_graph(dim, side=4, seed=1, sigma_t_m=0.1, sigma_r_rad=0.2)
        T = truth @ geo.exp(
            np.random.default_rng(0).normal(size=(truth.shape[0], 3 * dim - 3)) * 0.3
        )
        kappa, tau = sesync_weights(dim, g.information)
        F = sesync_objective(T, g.edges, g.measurements, kappa, tau)
        assert np.isclose(2 * evaluate_cost(pose_graph(g, "chordal", "sesync"), T), F, rtol=1e-12)


def test_information_weights_need_the_geodesic_residual():
    g, _ = synthetic_graph(2, side=3)
    block = edge_factors(2, g.edges, g.measurements, g.information, "geodesic", "information")
    assert block.whitening.shape == (g.num_edges, 3, 3)
    try:
        edge_factors(2, g.edges, g.measurements, g.information, "chordal", "information")
    except ValueError as exc:
        assert "geodesic" in str(exc)
    else:
        raise AssertionError("chordal + information accepted")
