"""SE(3): poses ``(..., 4, 4)`` and tangents ``(..., 6)``.

Conventions (fixed for the whole project):

- Tangent order ``ξ = [ρ, φ]``: translation part first, rotation second — the order of
  g2o's 6×6 information matrices, so an edge's information applies to our residual as is.
- Right perturbation and right retraction: ``T ⊕ ξ = T Exp(ξ)``, ``T_b ⊖ T_a = Log(T_a⁻¹ T_b)``.
- ``Exp(ξ) = [[Exp(φ), J_l(φ) ρ], [0, 1]]`` (Solà eq. 172); ``Adj(T) = [[R, [t]× R], [0, R]]``
  so that ``T Exp(ξ) T⁻¹ = Exp(Adj(T) ξ)`` (eq. 176 for our order).
- Right Jacobian ``J_r(ξ) = d/dδ Log(Exp(ξ)⁻¹ Exp(ξ + δ))`` = ``J_l(−ξ)``; the left Jacobian has
  the block form ``[[J_l(φ), Q(ρ, φ)], [0, J_l(φ)]]`` with Barfoot's Q (Barfoot, "State
  Estimation for Robotics", eq. 7.86; Solà eq. 180).

Batched over leading axes; no per-pose Python loops.
"""

from __future__ import annotations

import numpy as np

from dran_edge.geometry import _series as s
from dran_edge.geometry.so3 import (
    hat3,
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
)


def se3_from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Pose ``(..., 4, 4)`` from rotation ``(..., 3, 3)`` and translation ``(..., 3)``."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    shape = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros(shape + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """T⁻¹ = [[Rᵀ, −Rᵀ t], [0, 1]] (one pose or a batch; built in place, so that one pose costs
    little more than the three assignments: the bounded graph calls it per factor)."""
    T = np.asarray(T, dtype=np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros(T.shape[:-2] + (4, 4))
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ T[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def se3_transform_points(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Points ``P (..., N, 3)`` in frame b -> frame a by ``T_a_b (..., 4, 4)``: R p + t."""
    return np.einsum("...ij,...nj->...ni", T[..., :3, :3], P) + T[..., None, :3, 3]


def se3_compose(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A B (``T_a_c = se3_compose(T_a_b, T_b_c)``)."""
    return np.asarray(A, dtype=np.float64) @ np.asarray(B, dtype=np.float64)


def se3_between(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A⁻¹ B: the pose of B in A's frame (``T_a_b = se3_between(T_w_a, T_w_b)``)."""
    return se3_inverse(A) @ np.asarray(B, dtype=np.float64)


def _q_matrix(rho: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Barfoot's Q(ρ, φ), the upper-right block of the SE(3) left Jacobian."""
    theta_sq = np.sum(phi * phi, axis=-1)[..., None, None]
    P, Rh = hat3(phi), hat3(rho)
    PR, RP = P @ Rh, Rh @ P
    PRP = PR @ P
    c1 = s.theta_minus_sin_over_cube(theta_sq)
    c2 = s.se3_q_c2(theta_sq)
    c3 = s.se3_q_c3(theta_sq)
    return (
        0.5 * Rh
        + c1 * (PR + RP + PRP)
        + c2 * (P @ PR + RP @ P - 3 * PRP)
        + c3 * (PRP @ P + P @ PRP)
    )


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Exp: ``(..., 6)`` [ρ, φ] -> ``(..., 4, 4)``."""
    xi = np.asarray(xi, dtype=np.float64)
    rho, phi = xi[..., :3], xi[..., 3:]
    t = (so3_left_jacobian(phi) @ rho[..., None])[..., 0]
    return se3_from_rt(so3_exp(phi), t)


def se3_log(T: np.ndarray) -> np.ndarray:
    """Log: ``(..., 4, 4)`` -> ``(..., 6)`` [ρ, φ] with ‖φ‖ ≤ π."""
    T = np.asarray(T, dtype=np.float64)
    phi = so3_log(T[..., :3, :3])
    rho = (so3_left_jacobian_inv(phi) @ T[..., :3, 3:4])[..., 0]
    return np.concatenate([rho, phi], axis=-1)


def se3_adjoint(T: np.ndarray) -> np.ndarray:
    """Adj(T) ``(..., 6, 6)`` = [[R, [t]× R], [0, R]], so that T Exp(ξ) T⁻¹ = Exp(Adj(T) ξ)."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[..., :3, :3], T[..., :3, 3]
    out = np.zeros(T.shape[:-2] + (6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = hat3(t) @ R
    return out


def se3_left_jacobian(xi: np.ndarray) -> np.ndarray:
    """J_l(ξ) = d/dδ Log(Exp(ξ + δ) Exp(ξ)⁻¹) at δ = 0: [[J_l(φ), Q(ρ, φ)], [0, J_l(φ)]]."""
    xi = np.asarray(xi, dtype=np.float64)
    rho, phi = xi[..., :3], xi[..., 3:]
    J = so3_left_jacobian(phi)
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = J
    out[..., 3:, 3:] = J
    out[..., :3, 3:] = _q_matrix(rho, phi)
    return out


def se3_left_jacobian_inv(xi: np.ndarray) -> np.ndarray:
    """J_l(ξ)⁻¹ = [[J_l⁻¹, −J_l⁻¹ Q J_l⁻¹], [0, J_l⁻¹]] (closed form, no matrix inverse)."""
    xi = np.asarray(xi, dtype=np.float64)
    rho, phi = xi[..., :3], xi[..., 3:]
    Ji = so3_left_jacobian_inv(phi)
    out = np.zeros(xi.shape[:-1] + (6, 6))
    out[..., :3, :3] = Ji
    out[..., 3:, 3:] = Ji
    out[..., :3, 3:] = -Ji @ _q_matrix(rho, phi) @ Ji
    return out


def se3_right_jacobian(xi: np.ndarray) -> np.ndarray:
    """J_r(ξ) = d/dδ Log(Exp(ξ)⁻¹ Exp(ξ + δ)) at δ = 0, equal to J_l(−ξ)."""
    return se3_left_jacobian(-np.asarray(xi, dtype=np.float64))


def se3_right_jacobian_inv(xi: np.ndarray) -> np.ndarray:
    """J_r⁻¹(ξ) = d/dδ Log(Exp(ξ) Exp(δ)) at δ = 0, equal to J_l⁻¹(−ξ)."""
    return se3_left_jacobian_inv(-np.asarray(xi, dtype=np.float64))


def se3_retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """The project's retraction: T ⊕ ξ = T Exp(ξ)."""
    return np.asarray(T, dtype=np.float64) @ se3_exp(xi)


def se3_geodesic_distance(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """‖Log(A⁻¹ B)‖ over the whole tangent [ρ, φ] (metres and radians mixed, as the paper's ATE)."""
    return np.linalg.norm(se3_log(se3_between(A, B)), axis=-1)


def se3_chordal_distance(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """‖A − B‖_F over the 3×4 upper part (paper eq. 2, chordal)."""
    D = np.asarray(A, dtype=np.float64)[..., :3, :] - np.asarray(B, dtype=np.float64)[..., :3, :]
    return np.sqrt(np.sum(D * D, axis=(-1, -2)))
