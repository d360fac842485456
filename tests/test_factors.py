"""Factor Jacobians against central finite differences of the expression each one defines."""

from __future__ import annotations

import numpy as np
import pytest

from dran_edge import geometry as geo
from dran_edge.solver.factors import (
    BetweenFactors,
    Cauchy,
    Huber,
    PriorFactors,
    chordal_jacobians,
    chordal_residual,
    geodesic_jacobians,
    geodesic_residual,
    isotropic_whitening,
    whitening_from_information,
)

EPS = 1e-6


def _random_poses(rng, m, dof, scale=1.0):
    return geo.exp(rng.normal(size=(m, dof)) * scale)


def _numeric(fn, T_p, T_q, T_m, which):
    dof = 6 if T_p.shape[-1] == 4 else 3
    cols = []
    for k in range(dof):
        d = np.zeros((T_p.shape[0], dof))
        d[:, k] = EPS
        if which == "p":
            plus, minus = fn(geo.retract(T_p, d), T_q, T_m), fn(geo.retract(T_p, -d), T_q, T_m)
        else:
            plus, minus = fn(T_p, geo.retract(T_q, d), T_m), fn(T_p, geo.retract(T_q, -d), T_m)
        cols.append((plus - minus) / (2 * EPS))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("dof", [6, 3])
@pytest.mark.parametrize(
    "res,jac", [(geodesic_residual, geodesic_jacobians), (chordal_residual, chordal_jacobians)]
)
@pytest.mark.parametrize("scale", [1.0, 1e-3])
def test_between_jacobians_match_finite_differences(dof, res, jac, scale):
    rng = np.random.default_rng(dof)
    T_p, T_q = _random_poses(rng, 5, dof), _random_poses(rng, 5, dof)
    # scale ≈ 0: T_q ≈ T_p T̃, the small-residual regime of a converged graph
    T_m = geo.between(T_p, T_q) @ geo.exp(rng.normal(size=(5, dof)) * scale)
    r, J_p, J_q = jac(T_p, T_q, T_m)
    np.testing.assert_allclose(r, res(T_p, T_q, T_m), atol=1e-12)
    np.testing.assert_allclose(J_p, _numeric(res, T_p, T_q, T_m, "p"), atol=1e-7)
    np.testing.assert_allclose(J_q, _numeric(res, T_p, T_q, T_m, "q"), atol=1e-7)


@pytest.mark.parametrize("dof", [6, 3])
@pytest.mark.parametrize("residual", ["geodesic", "chordal"])
def test_prior_block_jacobian_and_whitening(dof, residual):
    rng = np.random.default_rng(7)
    dim = 3 if dof == 6 else 2
    poses = _random_poses(rng, 4, dof)
    prior = _random_poses(rng, 2, dof)
    r_dim = {"geodesic": dof, "chordal": dim * dim + dim}[residual]
    info = rng.normal(size=(2, r_dim, r_dim))
    info = info @ np.swapaxes(info, 1, 2) + np.eye(r_dim)
    W = whitening_from_information(info)
    np.testing.assert_allclose(np.swapaxes(W, 1, 2) @ W, info, rtol=1e-10, atol=1e-10)
    block = PriorFactors(np.array([[1], [3]]), prior, W, residual)
    _, J = block.linearize(poses)
    assert J.shape == (2, 1, r_dim, dof)
    for k in range(dof):
        d = np.zeros((4, dof))
        d[:, k] = EPS
        num = (block.residuals(geo.retract(poses, d)) - block.residuals(geo.retract(poses, -d))) / (
            2 * EPS
        )
        np.testing.assert_allclose(J[:, 0, :, k], num, atol=1e-6)
    # the residual is zero exactly at the prior
    at_prior = poses.copy()
    at_prior[[1, 3]] = prior
    np.testing.assert_allclose(block.residuals(at_prior), 0.0, atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_between_block_stacks_whitened_jacobians(dim):
    rng = np.random.default_rng(3)
    dof = 6 if dim == 3 else 3
    poses = _random_poses(rng, 3, dof)
    Z = _random_poses(rng, 2, dof, 0.3)
    W = isotropic_whitening(np.array([2.0, 3.0]), np.array([5.0, 7.0]), "chordal", dim)
    block = BetweenFactors(np.array([[0, 1], [2, 1]]), Z, W, "chordal")
    r, J = block.linearize(poses)
    raw, Jp, Jq = chordal_jacobians(poses[[0, 2]], poses[[1, 1]], Z)
    np.testing.assert_allclose(r, W * raw)
    np.testing.assert_allclose(J[:, 0], W[:, :, None] * Jp)
    np.testing.assert_allclose(J[:, 1], W[:, :, None] * Jq)


def test_isotropic_geodesic_weights_match_chordal_cost_near_zero():
    """½‖W_geo r_geo‖² ≈ ½‖W_chordal r_chordal‖² for small residuals (SE-Sync weights)."""
    rng = np.random.default_rng(11)
    for dim, dof in ((3, 6), (2, 3)):
        T_p = _random_poses(rng, 6, dof)
        T_m = _random_poses(rng, 6, dof)
        T_q = T_p @ T_m @ geo.exp(rng.normal(size=(6, dof)) * 1e-4)
        kappa, tau = rng.uniform(1, 10, 6), rng.uniform(1, 10, 6)
        c_geo = np.sum(
            (isotropic_whitening(kappa, tau, "geodesic", dim) * geodesic_residual(T_p, T_q, T_m))
            ** 2,
            1,
        )
        c_cho = np.sum(
            (isotropic_whitening(kappa, tau, "chordal", dim) * chordal_residual(T_p, T_q, T_m))
            ** 2,
            1,
        )
        np.testing.assert_allclose(c_geo, c_cho, rtol=1e-3)


@pytest.mark.parametrize("kernel", [Huber(1.5), Cauchy(2.0)])
def test_kernel_weight_is_derivative_of_rho(kernel):
    s = np.array([0.01, 0.5, 2.0, 9.0, 100.0])
    h = 1e-6
    numeric = (kernel.rho(s + h) - kernel.rho(s - h)) / (2 * h)
    np.testing.assert_allclose(kernel.weight(s), numeric, rtol=1e-5)
    assert np.all(kernel.rho(s) <= s + 1e-12)  # robust kernels never exceed the quadratic


def test_cauchy_takes_one_scale_per_factor_and_infinity_is_least_squares():
    s = np.array([0.5, 4.0, 4.0, 100.0])
    per_factor = Cauchy(np.array([1.0, 2.0, np.inf, np.inf]))
    rho, w = per_factor.rho(s), per_factor.weight(s)
    np.testing.assert_allclose(rho[:2], [Cauchy(1.0).rho(s[0]), Cauchy(2.0).rho(s[1])])
    np.testing.assert_allclose(w[:2], [Cauchy(1.0).weight(s[0]), Cauchy(2.0).weight(s[1])])
    np.testing.assert_array_equal(rho[2:], s[2:])  # no nan from inf · log1p(0)
    np.testing.assert_array_equal(w[2:], 1.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_chordal_second_order_gives_the_exact_hessian(dim):
    """JᵀJ + Σ S_i ∂²r_i equals the finite-difference Hessian of ½‖W r‖² on the pullback."""
    rng = np.random.default_rng(dim)
    dof = 6 if dim == 3 else 3
    T = geo.exp(rng.normal(size=(2, dof)))
    Z = geo.exp(rng.normal(size=(1, dof)))
    W = isotropic_whitening(np.array([3.0]), np.array([2.0]), "chordal", dim)
    block = BetweenFactors(np.array([[0, 1]]), Z, W, "chordal")
    prior = PriorFactors(np.array([[1]]), geo.exp(rng.normal(size=(1, dof))), W, "chordal")

    def cost(x):
        P = geo.retract(T, x.reshape(2, dof))
        return 0.5 * np.sum(block.residuals(P) ** 2) + 0.5 * np.sum(prior.residuals(P) ** 2)

    n, h = 2 * dof, 1e-4
    Hn = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            ei, ej = np.eye(n)[i] * h, np.eye(n)[j] * h
            Hn[i, j] = (cost(ei + ej) - cost(ei - ej) - cost(ej - ei) + cost(-ei - ej)) / (
                4 * h * h
            )
    _, J = block.linearize(T)
    Jf = np.concatenate([J[0, 0], J[0, 1]], axis=1)
    H = Jf.T @ Jf + block.second_order(T)[0]
    _, Jp = prior.linearize(T)
    H[dof:, dof:] += Jp[0, 0].T @ Jp[0, 0] + prior.second_order(T)[0]
    np.testing.assert_allclose(H, Hn, atol=1e-5 * np.abs(Hn).max())
    assert (
        BetweenFactors(
            np.array([[0, 1]]),
            Z,
            isotropic_whitening(np.array([3.0]), np.array([2.0]), "geodesic", dim),
            "geodesic",
        ).second_order(T)
        is None
    )
