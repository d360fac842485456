"""Tests of dran_edge.dran.consensus: MH weights, φ, dual update and the eq. 6 factor."""

import numpy as np

from dran_edge import geometry as geo
from dran_edge.dran.consensus import (
    ConsensusFactors,
    dual_update,
    metropolis_hastings_matrix,
    phi,
)


def _poses(rng, n):
    return geo.se3_exp(rng.normal(0, 0.7, (n, 6)))


def test_mh_matrix_is_symmetric_doubly_stochastic():
    rng = np.random.default_rng(0)
    U = np.triu(rng.random((7, 7)) < 0.4, 1)
    W = metropolis_hastings_matrix(U | U.T)
    assert np.allclose(W, W.T)
    assert np.allclose(W.sum(axis=1), 1.0)
    assert np.all(W >= 0)


def test_geodesic_phi_is_antisymmetric_and_zero_at_consensus():
    rng = np.random.default_rng(1)
    a, b = _poses(rng, 5), _poses(rng, 5)
    assert np.allclose(phi(a, b), -phi(b, a), atol=1e-9)
    assert np.allclose(phi(a, a), 0.0, atol=1e-12)
    assert np.allclose(phi(a, a, "chordal"), 0.0)


def test_dual_update_is_eq_5b():
    lam = np.ones((2, 6))
    p = np.arange(12.0).reshape(2, 6)
    out = dual_update(lam, p, np.array([0.5, 0.25]), beta=2.0, eta=0.1)
    assert np.allclose(out, lam + 0.1 * 2.0 * np.array([0.5, 0.25])[:, None] * p)


def test_consensus_factor_jacobian_matches_finite_differences():
    rng = np.random.default_rng(2)
    for kind in ("geodesic", "chordal"):
        poses = _poses(rng, 4)
        lam = rng.normal(0, 0.3, (2, 6 if kind == "geodesic" else 12))
        f = ConsensusFactors(np.array([[0, 2], [1, 3]]), np.array([0.3, 0.5]), lam, 1.5, kind)
        r, J = f.linearize(poses)
        assert np.allclose(r, f.residuals(poses))
        h = 1e-6
        for k in range(6):
            d = np.zeros(6)
            d[k] = h
            P = poses.copy()
            P[[0, 1]] = geo.se3_retract(poses[[0, 1]], np.stack([d, d]))
            num = (f.residuals(P) - r) / h
            assert np.allclose(num, J[:, 0, :, k], atol=1e-4)
        # the anchor end (the neighbour's copy) is fixed: its Jacobian block is zero
        assert np.all(J[:, 1] == 0)
        # biased prior: at consensus the residual is √β λ/β
        same = poses.copy()
        same[2], same[3] = poses[0], poses[1]
        assert np.allclose(f.residuals(same), np.sqrt(1.5) * lam / 1.5, atol=1e-9)
