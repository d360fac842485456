"""Property tests of dran_edge.geometry against scipy's Rotation and finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dran_edge import geometry as g

BATCHES = [(), (1,), (3, 1, 2)]
SAMPLERS = ["uniform", "near_identity", "near_pi"]


def rotvecs(rng: np.random.Generator, batch: tuple[int, ...], sampler: str) -> np.ndarray:
    axis = rng.normal(size=batch + (3,))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    if sampler == "uniform":
        angle = rng.uniform(0, np.pi, size=batch)
    elif sampler == "near_identity":
        angle = rng.uniform(0, 1e-7, size=batch)
    else:
        angle = np.pi - rng.uniform(0, 1e-7, size=batch)
    return axis * angle[..., None]


def tangents(rng, batch, sampler, dim):
    if dim == 3:
        rho = rng.normal(size=batch + (3,)) * (1e-7 if sampler == "near_identity" else 2.0)
        return np.concatenate([rho, rotvecs(rng, batch, sampler)], axis=-1)
    theta = np.linalg.norm(rotvecs(rng, batch, sampler), axis=-1) * rng.choice([-1, 1], size=batch)
    rho = rng.normal(size=batch + (2,)) * (1e-7 if sampler == "near_identity" else 2.0)
    return np.concatenate([rho, theta[..., None]], axis=-1)


def numeric_jacobian(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Central differences of f: R^n -> R^m at x (unbatched)."""
    cols = []
    for k in range(x.shape[-1]):
        dx = np.zeros_like(x)
        dx[k] = eps
        cols.append((f(x + dx) - f(x - dx)) / (2 * eps))
    return np.stack(cols, axis=-1)


seeds = st.integers(min_value=0, max_value=2**32 - 1)


@pytest.mark.parametrize("batch", BATCHES)
@pytest.mark.parametrize("sampler", SAMPLERS)
@settings(max_examples=25, deadline=None)
@given(seed=seeds)
def test_so3_exp_matches_scipy(batch, sampler, seed):
    phi = rotvecs(np.random.default_rng(seed), batch, sampler)
    R = g.so3_exp(phi)
    ref = Rotation.from_rotvec(phi.reshape(-1, 3)).as_matrix().reshape(batch + (3, 3))
    np.testing.assert_allclose(R, ref, atol=1e-12)


@pytest.mark.parametrize("batch", BATCHES)
@pytest.mark.parametrize("sampler", SAMPLERS)
@settings(max_examples=25, deadline=None)
@given(seed=seeds)
def test_so3_log_inverts_exp(batch, sampler, seed):
    phi = rotvecs(np.random.default_rng(seed), batch, sampler)
    R = g.so3_exp(phi)
    back = g.so3_log(R)
    # At θ = π, φ and −φ are the same rotation: compare rotations, and angles.
    np.testing.assert_allclose(g.so3_exp(back), R, atol=1e-12)
    np.testing.assert_allclose(
        np.linalg.norm(back, axis=-1), np.linalg.norm(phi, axis=-1), atol=1e-9
    )
    ref = Rotation.from_matrix(R.reshape(-1, 3, 3)).magnitude().reshape(batch)
    np.testing.assert_allclose(np.linalg.norm(back, axis=-1), ref, atol=1e-9)


@pytest.mark.parametrize("batch", BATCHES)
@settings(max_examples=25, deadline=None)
@given(seed=seeds)
def test_quaternion_layouts_match_scipy(batch, seed):
    phi = rotvecs(np.random.default_rng(seed), batch, "uniform")
    R = g.so3_exp(phi)
    q_xyzw = g.quat_xyzw_from_rotmat(R)
    ref = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(batch + (4,))
    ref = np.where(ref[..., 3:] < 0, -ref, ref)
    np.testing.assert_allclose(q_xyzw, ref, atol=1e-12)
    np.testing.assert_allclose(g.rotmat_from_quat_xyzw(q_xyzw), R, atol=1e-12)
    T = g.se3_from_rt(R, phi)
    np.testing.assert_allclose(g.se3_from_xyz_quat_wxyz(g.se3_to_xyz_quat_wxyz(T)), T, atol=1e-12)
    np.testing.assert_allclose(g.se3_from_xyz_quat_xyzw(g.se3_to_xyz_quat_xyzw(T)), T, atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("batch", BATCHES)
@pytest.mark.parametrize("sampler", SAMPLERS)
@settings(max_examples=20, deadline=None)
@given(seed=seeds)
def test_exp_log_round_trip_and_group_axioms(dim, batch, sampler, seed):
    rng = np.random.default_rng(seed)
    xi = tangents(rng, batch, sampler, dim)
    T = g.exp(xi)
    assert T.shape == batch + (dim + 1, dim + 1)
    np.testing.assert_allclose(g.exp(g.log(T)), T, atol=1e-10)
    if sampler != "near_pi":
        np.testing.assert_allclose(g.log(T), xi, atol=1e-9)
    np.testing.assert_allclose(g.compose(T, g.inverse(T)), g.identity(dim, batch), atol=1e-12)
    U = g.exp(tangents(rng, batch, "uniform", dim))
    np.testing.assert_allclose(g.compose(T, g.between(T, U)), U, atol=1e-10)
    # Adjoint: T Exp(η) T⁻¹ = Exp(Adj(T) η).
    eta = tangents(rng, batch, "uniform", dim) * 0.3
    lhs = T @ g.exp(eta) @ g.inverse(T)
    rhs = g.exp((g.adjoint(T) @ eta[..., None])[..., 0])
    np.testing.assert_allclose(lhs, rhs, atol=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("sampler", SAMPLERS)
@settings(max_examples=20, deadline=None)
@given(seed=seeds)
def test_right_jacobian_is_its_defining_derivative(dim, sampler, seed):
    """J_r(ξ) = d/dδ Log(Exp(ξ)⁻¹ Exp(ξ + δ)); J_r⁻¹(ξ) = d/dδ Log(Exp(ξ) Exp(δ))."""
    rng = np.random.default_rng(seed)
    xi = tangents(rng, (), sampler, dim)
    if sampler == "near_pi":
        xi = xi * (1 - 1e-4)  # keep the FD stencil inside the principal branch
    X = g.exp(xi)
    num_jr = numeric_jacobian(lambda d: g.log(g.inverse(X) @ g.exp(xi + d)), np.zeros_like(xi))
    np.testing.assert_allclose(g.right_jacobian(xi), num_jr, atol=1e-6)
    num_jri = numeric_jacobian(lambda d: g.log(X @ g.exp(d)), np.zeros_like(xi))
    np.testing.assert_allclose(g.right_jacobian_inv(xi), num_jri, atol=1e-5)
    np.testing.assert_allclose(
        g.right_jacobian(xi) @ g.right_jacobian_inv(xi), np.eye(len(xi)), atol=1e-9
    )


@pytest.mark.parametrize("sampler", SAMPLERS)
@settings(max_examples=20, deadline=None)
@given(seed=seeds)
def test_se3_left_jacobian_is_its_defining_derivative(sampler, seed):
    """J_l(ξ) = d/dδ Log(Exp(ξ + δ) Exp(ξ)⁻¹)."""
    xi = tangents(np.random.default_rng(seed), (), sampler, 3)
    if sampler == "near_pi":
        xi = xi * (1 - 1e-4)
    Xi = g.se3_inverse(g.se3_exp(xi))
    num = numeric_jacobian(lambda d: g.se3_log(g.se3_exp(xi + d) @ Xi), np.zeros(6))
    np.testing.assert_allclose(g.se3_left_jacobian(xi), num, atol=1e-6)
    np.testing.assert_allclose(
        g.se3_left_jacobian(xi) @ g.se3_left_jacobian_inv(xi), np.eye(6), atol=1e-9
    )


def test_so3_jacobians_match_definition_and_project():
    rng = np.random.default_rng(3)
    phi = rotvecs(rng, (), "uniform")
    Rm = g.so3_exp(phi)
    num = numeric_jacobian(lambda d: g.so3_log(Rm.T @ g.so3_exp(phi + d)), np.zeros(3))
    np.testing.assert_allclose(g.so3_right_jacobian(phi), num, atol=1e-6)
    np.testing.assert_allclose(g.so3_right_jacobian_inv(phi) @ num, np.eye(3), atol=1e-6)
    M = Rm + 0.05 * rng.normal(size=(3, 3))
    P = g.so3_project(M)
    np.testing.assert_allclose(P @ P.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(P) == pytest.approx(1.0)
    np.testing.assert_allclose(
        g.so3_project(-np.eye(3)) @ g.so3_project(-np.eye(3)).T, np.eye(3), atol=1e-12
    )
    np.testing.assert_allclose(g.vee3(g.hat3(phi)), phi)


def test_distances_and_embeddings():
    rng = np.random.default_rng(5)
    xi = tangents(rng, (4,), "uniform", 3)
    A, B = g.exp(xi), g.exp(tangents(rng, (4,), "uniform", 3))
    np.testing.assert_allclose(
        g.geodesic_distance(A, A @ g.exp(xi)), np.linalg.norm(xi, axis=-1), atol=1e-9
    )
    np.testing.assert_allclose(
        g.chordal_distance(A, B), np.linalg.norm((A - B)[:, :3, :], axis=(1, 2))
    )
    T2 = g.se2_from_xy_theta(np.array([1.0, -2.0, 0.7]))
    T3 = g.se3_from_se2(T2)
    np.testing.assert_allclose(g.se3_log(T3)[[0, 1, 5]], g.se2_log(T2), atol=1e-12)
    np.testing.assert_allclose(g.se2_to_xy_theta(T2), [1.0, -2.0, 0.7])


def test_tum_rows_and_interpolation():
    rng = np.random.default_rng(7)
    T = g.exp(tangents(rng, (3,), "uniform", 3))
    stamps_ns = np.array([0, 1_000_000_000, 3_000_000_000])
    rows = g.se3_to_tum_rows(stamps_ns * 1e-9, T)
    s_back, T_back = g.se3_from_tum_rows(rows)
    np.testing.assert_allclose(T_back, T, atol=1e-12)
    np.testing.assert_allclose(s_back, [0.0, 1.0, 3.0])
    Tq, valid = g.se3_interpolate(
        stamps_ns, T, np.array([0, 500_000_000, 3_000_000_000, 4_000_000_000])
    )
    assert valid.tolist() == [True, True, True, False]
    np.testing.assert_allclose(Tq[0], T[0], atol=1e-12)
    np.testing.assert_allclose(Tq[2], T[2], atol=1e-12)
    mid = Tq[1]
    np.testing.assert_allclose(mid[:3, 3], 0.5 * (T[0, :3, 3] + T[1, :3, 3]), atol=1e-12)
    half = g.so3_log(T[0, :3, :3].T @ mid[:3, :3])
    full = g.so3_log(T[0, :3, :3].T @ T[1, :3, :3])
    np.testing.assert_allclose(half, 0.5 * full, atol=1e-12)


def test_dispatch_rejects_bad_shapes():
    with pytest.raises(ValueError, match="shape"):
        g.exp(np.zeros(5))
    with pytest.raises(ValueError, match="shape"):
        g.log(np.eye(5))


@pytest.mark.parametrize("batch", BATCHES)
@settings(max_examples=25, deadline=None)
@given(seed=seeds)
def test_so3_angle_is_the_norm_of_log(batch, seed):
    """The trace form agrees with ‖Log(R)‖ (scipy's magnitude) away from θ = 0 and π, and one
    rotation gives the same number as the same rotation inside a batch."""
    rng = np.random.default_rng(seed)
    phi = rotvecs(rng, batch, "uniform")
    theta = np.linalg.norm(phi, axis=-1)
    phi = phi * (np.clip(theta, 1e-3, np.pi - 1e-3) / np.maximum(theta, 1e-300))[..., None]
    R = g.so3_exp(phi)
    angle = g.so3_angle(R)
    assert angle.shape == batch
    want = Rotation.from_matrix(R.reshape(-1, 3, 3)).magnitude().reshape(batch)
    np.testing.assert_allclose(angle, want, atol=1e-7)
    flat = R.reshape(-1, 3, 3)
    assert all(float(g.so3_angle(r)) == a for r, a in zip(flat, angle.reshape(-1)))


@pytest.mark.parametrize("batch", BATCHES)
@settings(max_examples=25, deadline=None)
@given(seed=seeds)
def test_se3_inverse_and_adjoint_one_pose_equals_batch(batch, seed):
    """T T⁻¹ = I (numpy's general inverse as oracle); Adj(T⁻¹) = Adj(T)⁻¹; a pose alone gives
    the bits it gives inside a batch (callers use the same function for both)."""
    rng = np.random.default_rng(seed)
    T = g.se3_exp(tangents(rng, batch, "uniform", 3))
    Ti = g.se3_inverse(T)
    np.testing.assert_allclose(Ti, np.linalg.inv(T), atol=1e-10)
    np.testing.assert_allclose(g.se3_adjoint(Ti), np.linalg.inv(g.se3_adjoint(T)), atol=1e-9)
    for one, inv in zip(T.reshape(-1, 4, 4), Ti.reshape(-1, 4, 4)):
        assert np.array_equal(g.se3_inverse(one), inv)


@pytest.mark.parametrize("batch", BATCHES)
def test_se3_transform_points_is_the_homogeneous_product(batch):
    rng = np.random.default_rng(7)
    T = g.se3_exp(tangents(rng, batch, "uniform", 3))
    P = rng.normal(size=batch + (5, 3))
    want = T[..., None, :, :] @ np.concatenate([P, np.ones(batch + (5, 1))], -1)[..., None]
    np.testing.assert_allclose(g.se3_transform_points(T, P), want[..., :3, 0], atol=1e-12)
