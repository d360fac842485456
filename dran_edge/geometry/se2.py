"""SE(2): poses ``(..., 3, 3)`` and tangents ``(..., 3)`` = [x, y, θ] (translation first).

Same conventions as SE(3): right perturbation, ``T ⊕ ξ = T Exp(ξ)``, Solà et al. Sec. IV-B:
``Exp(ξ) = [[R(θ), V(θ) ρ], [0, 1]]`` with ``V = [[sin θ/θ, −(1−cos θ)/θ], [(1−cos θ)/θ, sin θ/θ]]``
(eq. 156), ``Adj(T) = [[R, [t_y, −t_x]ᵀ], [0, 1]]`` (eq. 159), right Jacobian eq. 163.
"""

from __future__ import annotations

import numpy as np

from dran_edge.geometry import _series as s


def so2_exp(theta: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(..., 2, 2)`` of angle θ ``(...)``."""
    theta = np.asarray(theta, dtype=np.float64)
    c, sn = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([c, -sn], -1), np.stack([sn, c], -1)], -2)


def so2_log(R: np.ndarray) -> np.ndarray:
    """Angle in (−π, π] of a rotation matrix ``(..., 2, 2)``."""
    R = np.asarray(R, dtype=np.float64)
    return np.arctan2(R[..., 1, 0], R[..., 0, 0])


def se2_from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (3, 3))
    T[..., :2, :2] = R
    T[..., :2, 2] = t
    T[..., 2, 2] = 1.0
    return T


def _v_matrix(theta: np.ndarray) -> np.ndarray:
    theta_sq = theta * theta
    a = s.sinc(theta_sq)
    b = theta * s.one_minus_cos_over_sq(theta_sq)
    return np.stack([np.stack([a, -b], -1), np.stack([b, a], -1)], -2)


def se2_exp(xi: np.ndarray) -> np.ndarray:
    """Exp: ``(..., 3)`` [x, y, θ] -> ``(..., 3, 3)``."""
    xi = np.asarray(xi, dtype=np.float64)
    theta = xi[..., 2]
    t = (_v_matrix(theta) @ xi[..., :2, None])[..., 0]
    return se2_from_rt(so2_exp(theta), t)


def se2_log(T: np.ndarray) -> np.ndarray:
    """Log: ``(..., 3, 3)`` -> ``(..., 3)`` with θ in (−π, π]."""
    T = np.asarray(T, dtype=np.float64)
    theta = so2_log(T[..., :2, :2])
    V = _v_matrix(theta)
    rho = np.linalg.solve(V, T[..., :2, 2:3])[..., 0]
    return np.concatenate([rho, theta[..., None]], axis=-1)


def se2_inverse(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :2, :2], -1, -2)
    return se2_from_rt(Rt, -(Rt @ T[..., :2, 2:3])[..., 0])


def se2_adjoint(T: np.ndarray) -> np.ndarray:
    """Adj(T) ``(..., 3, 3)`` with T Exp(ξ) T⁻¹ = Exp(Adj(T) ξ)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros(T.shape[:-2] + (3, 3))
    out[..., :2, :2] = T[..., :2, :2]
    out[..., 0, 2] = T[..., 1, 2]
    out[..., 1, 2] = -T[..., 0, 2]
    out[..., 2, 2] = 1.0
    return out


def se2_right_jacobian(xi: np.ndarray) -> np.ndarray:
    """J_r(ξ) = d/dδ Log(Exp(ξ)⁻¹ Exp(ξ + δ)) at δ = 0 (Solà eq. 163)."""
    xi = np.asarray(xi, dtype=np.float64)
    r1, r2, th = xi[..., 0], xi[..., 1], xi[..., 2]
    x = th * th
    a = s.sinc(x)
    b = s.one_minus_cos_over_sq(x)
    c = s.theta_minus_sin_over_cube(x)
    out = np.zeros(xi.shape[:-1] + (3, 3))
    out[..., 0, 0] = a
    out[..., 0, 1] = th * b
    out[..., 1, 0] = -th * b
    out[..., 1, 1] = a
    # (θρ1 − ρ2 + ρ2 cos θ − ρ1 sin θ)/θ² and (ρ1 + θρ2 − ρ1 cos θ − ρ2 sin θ)/θ², small-θ safe.
    out[..., 0, 2] = r1 * th * c - r2 * b
    out[..., 1, 2] = r1 * b + r2 * th * c
    out[..., 2, 2] = 1.0
    return out


def se2_right_jacobian_inv(xi: np.ndarray) -> np.ndarray:
    """J_r⁻¹(ξ) = d/dδ Log(Exp(ξ) Exp(δ)) at δ = 0 (inverse of a well-conditioned 3×3 for |θ| ≤ π)."""
    return np.linalg.inv(se2_right_jacobian(xi))


def se2_retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """T ⊕ ξ = T Exp(ξ)."""
    return np.asarray(T, dtype=np.float64) @ se2_exp(xi)


def se2_from_xy_theta(a: np.ndarray) -> np.ndarray:
    """Pose from rows [x, y, θ] ``(..., 3)`` (g2o's VERTEX_SE2 layout)."""
    a = np.asarray(a, dtype=np.float64)
    return se2_from_rt(so2_exp(a[..., 2]), a[..., :2])


def se2_to_xy_theta(T: np.ndarray) -> np.ndarray:
    """Rows [x, y, θ] ``(..., 3)`` from poses ``(..., 3, 3)``."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[..., :2, 2], so2_log(T[..., :2, :2])[..., None]], axis=-1)
