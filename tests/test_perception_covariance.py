"""Covariance: the projection Jacobian against finite differences, and NEES over rendered frames."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from dran_edge.perception.covariance import (
    gauss_newton,
    linearise,
    pose_covariance,
    project,
    transform_covariance,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from dran_edge import geometry as geo

K = np.array([[615.0, 0, 320.0], [0, 610.0, 240.0], [0, 0, 1]])


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_jacobian_matches_finite_differences(seed):
    """J = d/d delta pi(K, T Exp(delta) P) at delta = 0 (the definition in the docstring)."""
    rng = np.random.default_rng(seed)
    T = geo.se3_exp(rng.normal(0, 0.3, 6))
    T[2, 3] += 2.0
    P = rng.normal(0, 0.1, (3, 5, 3))
    Ts = np.broadcast_to(T, (3, 4, 4)).copy()
    uv, J = linearise(K, Ts, P)
    assert np.allclose(uv, project(K, Ts, P))
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        num = project(K, geo.se3_retract(Ts, d), P) - project(K, geo.se3_retract(Ts, -d), P)
        assert np.allclose(J[..., k], num / (2 * eps), atol=1e-5)


def test_gauss_newton_recovers_pose_and_weights_mask():
    rng = np.random.default_rng(1)
    T_true = geo.se3_from_rt(geo.so3_exp(np.array([0.2, -0.3, 0.1])), [0.1, -0.05, 1.5])
    P = rng.uniform(-0.2, 0.2, (1, 8, 3))
    uv = project(K, T_true[None], P)
    uv[0, 7] += [50.0, -40.0]  # an outlier point, masked out below
    mask = np.ones((1, 8))
    mask[0, 7] = 0.0
    T0 = geo.se3_retract(T_true[None], np.array([0.01, -0.01, 0.02, 0.02, -0.01, 0.01]))
    T, JtJ, r = gauss_newton(K, T0, P, uv, mask, iterations=4)
    assert np.allclose(T[0], T_true, atol=1e-8)
    assert np.abs(r[0, :7]).max() < 1e-6 and np.all(r[0, 7] == 0)
    cov = pose_covariance(JtJ, 0.5)
    assert np.all(np.linalg.eigvalsh(cov[0]) > 0)


def test_transform_covariance_matches_sampling():
    """Sigma of X @ T_a_b's right perturbation, by Monte Carlo through the group operations."""
    rng = np.random.default_rng(2)
    X = geo.se3_exp(rng.normal(0, 0.5, 6))
    T_ab = geo.se3_exp(rng.normal(0, 0.5, 6))
    A = rng.normal(0, 1, (6, 6))
    cov = 1e-6 * (A @ A.T + np.eye(6))
    d = rng.multivariate_normal(np.zeros(6), cov, size=20000)
    Y = X @ T_ab
    e = geo.se3_log(geo.se3_between(Y, geo.se3_retract(X, d) @ T_ab))
    emp = np.cov(e.T)
    pred = transform_covariance(cov, T_ab)
    assert np.allclose(emp, pred, atol=0.05 * np.abs(pred).max())


@pytest.fixture(scope="module")
def nees_tool():
    pytest.importorskip("pupil_apriltags")
    path = Path(__file__).resolve().parents[1] / "tools" / "bench" / "nees_perception.py"
    spec = importlib.util.spec_from_file_location("nees_perception", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_nees_consistent_with_six_dof(nees_tool):
    """Over ~200 rendered frames (noise 3, blur 0.8 px, 0.5-3 m, +-60 deg), with the corner
    noise set from reprojection residuals only (no ground truth), the NEES of T_camera_tag is of
    chi2(6) order and not over-confident: mean in [2, 9], at most 10 % above the chi2(6) 95 %
    quantile (5 % expected), no range band above 8; the residual inflation lowers the tail.
    (Numbers per condition: tools/bench/nees_perception.py, docs/benchmarks.md.)"""
    r = nees_tool.run(frames=220, noise=3.0, blur=0.8, seed=5)
    x, plain = r["residual+birge"], r["residual"]
    assert r["n_test"] > 180
    assert 2.0 <= x["mean"] <= 9.0, x
    assert x["above_95"] <= 0.10, x
    assert all(m <= 8.0 for _, _, m in x["bands"]), x
    assert x["above_95"] <= plain["above_95"]
