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
    p = geo.se3_transform_points(T, P)
    return p[..., :2] / p[..., 2:3] * K[[0, 1], [0, 1]] + K[:2, 2]


def linearise(K: np.ndarray, T: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(..., N, 2)`` and d pi(K, T Exp(delta) P) / d delta at delta = 0 ``(..., N, 2, 6)``.

    Row i of the rotation block is ``-a_i^T R [P]x = cross(P, a_i)`` with ``a_i^T`` the
    translation row ``D_i R`` (module docstring), which saves forming the 3x6 point Jacobian.
    """
    R = T[..., :3, :3]
    p = geo.se3_transform_points(T, P)
    inv_z = 1.0 / p[..., 2:3]
    xy = p[..., :2] * inv_z  # normalised coordinates (..., N, 2)
    f = K[[0, 1], [0, 1]]
    # a_i = (f_i / z) (R_i - xy_i R_2): translation rows, (..., N, 2, 3)
    a = (R[..., None, :2, :] - xy[..., :, None] * R[..., None, 2:3, :]) * (
        f[:, None] * inv_z[..., None]
    )
    J = np.empty(a.shape[:-1] + (6,))
    J[..., :3] = a
    Pb = P[..., None, :]
    J[..., 3] = Pb[..., 1] * a[..., 2] - Pb[..., 2] * a[..., 1]
    J[..., 4] = Pb[..., 2] * a[..., 0] - Pb[..., 0] * a[..., 2]
    J[..., 5] = Pb[..., 0] * a[..., 1] - Pb[..., 1] * a[..., 0]
    return xy * f + K[:2, 2], J


def projection_jacobian(K: np.ndarray, T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """d pi(K, T Exp(delta) P) / d delta at delta = 0: ``(..., N, 2, 6)`` (module docstring)."""
    return linearise(K, T, P)[1]


def gauss_newton(
    K: np.ndarray,
    T: np.ndarray,
    P: np.ndarray,
    uv: np.ndarray,
    mask: np.ndarray | None = None,
    iterations: int = 2,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refine poses ``T (m, 4, 4)`` on points ``P (m, N, 3)`` observed at ``uv (m, N, 2)``.

    Minimises the sum of squared reprojection errors over the valid points (``mask (m, N)``,
    boolean or float weights multiplying each residual and Jacobian row: 1/sigma whitens)
    with ``iterations`` Gauss-Newton steps, all poses at once. Returns ``(T, JtJ (m, 6, 6),
    residual (m, N, 2))``: the final pose and its residuals (zero where masked), and J^T J of
    the last linearisation (at the input pose when ``iterations == 0``; one step before the
    final pose otherwise, which changes the covariance by O(step)).
    """
    w = None if mask is None else mask.astype(np.float64)[..., None]
    pred, J = linearise(K, T, P)
    r = pred - uv
    for it in range(iterations + 1):
        if w is not None:
            r = r * w
            J = J * w[..., None]
        Jf = J.reshape(J.shape[:-3] + (-1, 6))
        Jt = np.swapaxes(Jf, -1, -2)
        JtJ = Jt @ Jf
        if it == iterations:
            return T, JtJ, r
        step = -np.linalg.solve(JtJ + 1e-12 * np.eye(6), Jt @ r.reshape(r.shape[:-2] + (-1, 1)))
        T = _retract_fast(T, step[..., 0])
        if it + 1 == iterations:  # last step: residuals only, keep this JtJ
            r = project(K, T, P) - uv
            return T, JtJ, (r * w if w is not None else r)
        pred, J = linearise(K, T, P)
        r = pred - uv
    raise AssertionError("unreachable")


def _retract_fast(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """GN update ``R <- R Exp(phi)``, ``t <- t + R rho``: equal to ``T Exp(xi)`` to first order
    (the Jacobian above is its derivative too), so the fixed point and the covariance do not
    change; it avoids the full SE(3) exponential in the per-frame path. ``Exp(phi)`` is
    OpenCV's Rodrigues formula, one call per pose (a handful per frame)."""
    import cv2

    out = T.copy()
    R = T[..., :3, :3]
    out[..., :3, 3] += np.einsum("...ij,...j->...i", R, xi[..., :3])
    flat_xi = xi.reshape(-1, 6)
    dR = np.stack([cv2.Rodrigues(v[3:].reshape(3, 1))[0] for v in flat_xi])
    out[..., :3, :3] = R @ dR.reshape(xi.shape[:-1] + (3, 3))
    return out


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
    least-squares pose of its N points (scaled by ``edge / ref_edge`` to estimate the noise at
    the reference edge length of ``tagpose.corner_sigma``); 2N - 6 are its degrees of freedom.
    """
    dof = np.sum(2 * np.asarray(n_points) - 6)
    if dof <= 0:
        return float("nan")
    return float(np.sqrt(np.sum(residual_sq_sum) / dof))
