"""Pose from image points, and its covariance by first-order propagation of corner noise.

Model (batched over poses, m poses of N points each, padded with a mask):

    u_ij = pi(K, T_i P_ij) + e_ij,   e_ij ~ N(0, sigma_i^2 I_2)   (pixels, OpenCV convention)

with ``T_i`` the pose of the points' frame in the camera, right perturbation
``T_i <- T_i Exp(delta)``, ``delta = [rho, phi]`` (translation first, as ``dran_edge.geometry``).
The Jacobian of one projection w.r.t. delta is

    d pi / d delta = D(p) [R, -R [P]x],   D(p) = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]

(p = R P + t; Sola et al. arXiv:1812.01537, eqs. 166-168 for the point action). Stacking the
2N rows gives J (2N x 6), and the Gauss-Newton / first-order covariance is

    Sigma_delta = sigma^2 (J^T J)^-1

(Hartley & Zisserman, Multiple View Geometry, 2nd ed., Result 5.10: backward propagation of
a covariance through a function of full rank). It grows with distance, shrinks with tag size,
and becomes elongated with viewing angle, all through J, with no extra tuning.

``sigma`` is the corner noise: the library default is a configured constant; the pooled residual
estimate ``corner_sigma_from_residuals`` (sum r^2 / (2N - 6) over detections) calibrates it from
the data itself, without ground truth (validated by NEES in tests/test_perception_covariance.py).
"""

from __future__ import annotations

import numpy as np

from dran_edge import geometry as geo


def project(K: np.ndarray, T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Pixels ``(..., N, 2)`` of points ``P (..., N, 3)`` seen by poses ``T (..., 4, 4)``."""
    p = np.einsum("...ij,...nj->...ni", T[..., :3, :3], P) + T[..., None, :3, 3]
    z = p[..., 2:3]
    return np.stack(
        [K[0, 0] * p[..., 0] / z[..., 0] + K[0, 2], K[1, 1] * p[..., 1] / z[..., 0] + K[1, 2]],
        axis=-1,
    )


def projection_jacobian(K: np.ndarray, T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """d pi(K, T Exp(delta) P) / d delta at delta = 0: ``(..., N, 2, 6)`` (module docstring)."""
    R = T[..., :3, :3]
    p = np.einsum("...ij,...nj->...ni", R, P) + T[..., None, :3, 3]
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    fx, fy = K[0, 0], K[1, 1]
    D = np.zeros(p.shape[:-1] + (2, 3))
    D[..., 0, 0] = fx / z
    D[..., 0, 2] = -fx * x / (z * z)
    D[..., 1, 1] = fy / z
    D[..., 1, 2] = -fy * y / (z * z)
    dp = np.empty(p.shape[:-1] + (3, 6))
    dp[..., :3] = R[..., None, :, :]
    dp[..., 3:] = -R[..., None, :, :] @ geo.hat3(P)
    return D @ dp


def gauss_newton(
    K: np.ndarray,
    T: np.ndarray,
    P: np.ndarray,
    uv: np.ndarray,
    mask: np.ndarray | None = None,
    iterations: int = 2,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refine poses ``T (m, 4, 4)`` on points ``P (m, N, 3)`` observed at ``uv (m, N, 2)``.

    Minimises the sum of squared reprojection errors over the valid points (``mask (m, N)``)
    with ``iterations`` Gauss-Newton steps, all poses at once. Returns ``(T, JtJ (m, 6, 6),
    residual (m, N, 2))`` at the final pose, residuals zero where masked.
    """
    w = np.ones(P.shape[:-1]) if mask is None else mask.astype(np.float64)
    for it in range(iterations + 1):
        r = (project(K, T, P) - uv) * w[..., None]
        J = projection_jacobian(K, T, P) * w[..., None, None]
        Jf = J.reshape(J.shape[:-3] + (-1, 6))
        JtJ = np.swapaxes(Jf, -1, -2) @ Jf
        if it == iterations:
            return T, JtJ, r
        g = np.swapaxes(Jf, -1, -2) @ r.reshape(r.shape[:-2] + (-1, 1))
        step = -np.linalg.solve(JtJ + 1e-12 * np.eye(6), g)[..., 0]
        T = geo.se3_retract(T, step)
    raise AssertionError("unreachable")


def pose_covariance(JtJ: np.ndarray, corner_sigma_px: np.ndarray | float) -> np.ndarray:
    """``sigma^2 (J^T J)^-1`` ``(..., 6, 6)`` over [rho, phi] of the right perturbation."""
    s2 = np.asarray(corner_sigma_px, dtype=np.float64) ** 2
    cov = np.linalg.inv(JtJ) * np.reshape(s2, np.shape(s2) + (1, 1))
    return 0.5 * (cov + np.swapaxes(cov, -1, -2))


def transform_covariance(cov: np.ndarray, T_a_b: np.ndarray) -> np.ndarray:
    """Covariance of the right perturbation of ``X @ T_a_b`` given that of X.

    ``X Exp(d) T_a_b = (X T_a_b) Exp(Adj(T_a_b^-1) d)`` (Sola eq. 169 with Adj), so the new
    covariance is ``Adj(T_b_a) cov Adj(T_b_a)^T``. Left factors (``T_body_camera @ X``) leave a
    right-perturbation covariance unchanged.
    """
    A = geo.se3_adjoint(geo.se3_inverse(T_a_b))
    return A @ cov @ np.swapaxes(A, -1, -2)


def corner_sigma_from_residuals(residual_sq_sum: np.ndarray, n_points: np.ndarray) -> float:
    """Pooled corner-noise estimate sqrt(sum r^2 / sum(2N - 6)) over detections (pixels).

    ``residual_sq_sum`` per detection is the summed squared reprojection residual at the
    least-squares pose of its N points; 2N - 6 are its degrees of freedom.
    """
    dof = np.sum(2 * np.asarray(n_points) - 6)
    if dof <= 0:
        return float("nan")
    return float(np.sqrt(np.sum(residual_sq_sum) / dof))
