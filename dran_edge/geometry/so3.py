"""SO(3): rotation matrices ``(..., 3, 3)`` and rotation vectors ``(..., 3)``.

Conventions (Solà, Deray, Atchuthan, "A micro Lie theory for state estimation in
robotics", arXiv:1812.01537 — equation numbers below refer to it):

- ``Exp(φ) = I + sin θ/θ Φ + (1 − cos θ)/θ² Φ²`` with Φ = hat(φ), θ = ‖φ‖ (eq. 77).
- ``Log`` goes through the unit quaternion, ``θ = 2 atan2(‖q_v‖, q_w)``, which is well
  conditioned near 0 and near π (unlike ``arccos((tr R − 1)/2)``).
- Right Jacobian ``J_r(φ) = d Log(Exp(φ)⁻¹ Exp(φ + δ)) / dδ`` (eq. 143);
  ``J_l(φ) = J_r(−φ) = J_r(φ)ᵀ`` (eq. 145).

All functions are batched over leading axes and broadcast like numpy.
"""

from __future__ import annotations

import numpy as np

from dran_edge.geometry import _series as s


def hat3(w: np.ndarray) -> np.ndarray:
    """The skew matrix ``[w]×`` with ``hat3(w) @ v == cross(w, v)``; ``(..., 3) -> (..., 3, 3)``."""
    w = np.asarray(w, dtype=np.float64)
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


def vee3(W: np.ndarray) -> np.ndarray:
    """Inverse of ``hat3`` (takes the skew part of W); ``(..., 3, 3) -> (..., 3)``."""
    W = np.asarray(W, dtype=np.float64)
    return 0.5 * np.stack(
        [W[..., 2, 1] - W[..., 1, 2], W[..., 0, 2] - W[..., 2, 0], W[..., 1, 0] - W[..., 0, 1]],
        axis=-1,
    )


def so3_exp(phi: np.ndarray) -> np.ndarray:
    """Exp: rotation vector ``(..., 3)`` -> rotation matrix ``(..., 3, 3)`` (Solà eq. 77)."""
    phi = np.asarray(phi, dtype=np.float64)
    theta_sq = np.sum(phi * phi, axis=-1)
    P = hat3(phi)
    a = s.sinc(theta_sq)[..., None, None]
    b = s.one_minus_cos_over_sq(theta_sq)[..., None, None]
    return np.eye(3) + a * P + b * (P @ P)


def quat_wxyz_from_rotmat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(..., 4)`` [w, x, y, z] with w ≥ 0 from ``(..., 3, 3)`` (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = r00 + r11 + r22
    # Four candidate formulas; each is well conditioned when its pivot is the largest.
    piv = np.stack([tr, r00, r11, r22], axis=-1)
    choice = np.argmax(piv, axis=-1)
    d21, d12 = R[..., 2, 1], R[..., 1, 2]
    d02, d20 = R[..., 0, 2], R[..., 2, 0]
    d10, d01 = R[..., 1, 0], R[..., 0, 1]
    cand_list = []
    for k, diag in enumerate(
        (1 + tr, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22)
    ):
        big = 0.5 * np.sqrt(np.maximum(diag, 1e-300))
        f = 0.25 / big
        if k == 0:
            q = (big, (d21 - d12) * f, (d02 - d20) * f, (d10 - d01) * f)
        elif k == 1:
            q = ((d21 - d12) * f, big, (d01 + d10) * f, (d02 + d20) * f)
        elif k == 2:
            q = ((d02 - d20) * f, (d01 + d10) * f, big, (d12 + d21) * f)
        else:
            q = ((d10 - d01) * f, (d02 + d20) * f, (d12 + d21) * f, big)
        cand_list.append(np.stack(q, axis=-1))
    cands = np.stack(cand_list, axis=-2)  # (..., 4 candidates, 4)
    quat = np.take_along_axis(cands, choice[..., None, None], axis=-2)[..., 0, :]
    quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    return np.where(quat[..., :1] < 0, -quat, quat)


def rotmat_from_quat_wxyz(q: np.ndarray) -> np.ndarray:
    """Rotation matrix from a quaternion [w, x, y, z] (normalised here); ``(..., 4) -> (..., 3, 3)``."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def so3_log(R: np.ndarray) -> np.ndarray:
    """Log: rotation matrix ``(..., 3, 3)`` -> rotation vector ``(..., 3)`` with ‖φ‖ ≤ π."""
    R = np.asarray(R, dtype=np.float64)
    one_plus_tr = 1.0 + R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]  # 4 w²
    if np.all(one_plus_tr > 0.2):
        # Fast path (every θ below ~2.6 rad, the usual case in a solver): Shepperd's first
        # candidate alone, well conditioned there since w ≥ 0.22.
        w = 0.5 * np.sqrt(one_plus_tr)
        f = (0.25 / w)[..., None]
        v = (
            np.stack(
                [
                    R[..., 2, 1] - R[..., 1, 2],
                    R[..., 0, 2] - R[..., 2, 0],
                    R[..., 1, 0] - R[..., 0, 1],
                ],
                axis=-1,
            )
            * f
        )
        norm = np.sqrt(w * w + np.sum(v * v, axis=-1))
        w, v = w / norm, v / norm[..., None]
    else:
        q = quat_wxyz_from_rotmat(R)
        w, v = q[..., 0], q[..., 1:]
    n_sq = np.sum(v * v, axis=-1)
    small = n_sq < 1e-12
    n = np.sqrt(np.where(small, 1.0, n_sq))
    # θ/‖v‖ with θ = 2 atan2(‖v‖, w); for tiny ‖v‖: 2/w (1 − ‖v‖²/(3 w²)).
    w_safe = np.where(small, w, 1.0)
    k = np.where(small, 2.0 / w_safe * (1 - n_sq / (3 * w_safe**2)), 2 * np.arctan2(n, w) / n)
    return k[..., None] * v


def so3_angle(R: np.ndarray) -> np.ndarray:
    """θ = ‖Log(R)‖ in [0, π] from the trace (tr R = 1 + 2 cos θ), arccos((tr R − 1) / 2):
    ``(..., 3, 3) -> (...)``. Cheaper than ``so3_log`` and what thresholds and noise models
    need; near θ = 0 and π the arccos loses precision (≈ 1e-8 rad), use ``so3_log`` there."""
    R = np.asarray(R, dtype=np.float64)
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) * 0.5, -1.0, 1.0))


def so3_left_jacobian(phi: np.ndarray) -> np.ndarray:
    """J_l(φ) = I + (1 − cos θ)/θ² Φ + (θ − sin θ)/θ³ Φ² (Solà eq. 145); also SE(3)'s V(φ)."""
    phi = np.asarray(phi, dtype=np.float64)
    theta_sq = np.sum(phi * phi, axis=-1)
    P = hat3(phi)
    b = s.one_minus_cos_over_sq(theta_sq)[..., None, None]
    c = s.theta_minus_sin_over_cube(theta_sq)[..., None, None]
    return np.eye(3) + b * P + c * (P @ P)


def so3_left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """J_l⁻¹(φ) = I − ½ Φ + (1/θ² − cot(θ/2)/(2θ)) Φ² (Solà eq. 146)."""
    phi = np.asarray(phi, dtype=np.float64)
    theta_sq = np.sum(phi * phi, axis=-1)
    P = hat3(phi)
    c = s.so3_jinv_coeff(theta_sq)[..., None, None]
    return np.eye(3) - 0.5 * P + c * (P @ P)


def so3_right_jacobian(phi: np.ndarray) -> np.ndarray:
    """J_r(φ) = d/dδ Log(Exp(φ)⁻¹ Exp(φ + δ)) at δ = 0, equal to J_l(−φ) (Solà eqs. 143–145)."""
    return so3_left_jacobian(-np.asarray(phi, dtype=np.float64))


def so3_right_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """J_r⁻¹(φ) = d/dδ Log(Exp(φ) Exp(δ)) at δ = 0, equal to J_l⁻¹(−φ)."""
    return so3_left_jacobian_inv(-np.asarray(phi, dtype=np.float64))


def so3_project(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to M in Frobenius norm: U diag(1, …, det(U Vᵀ)) Vᵀ (any d × d)."""
    M = np.asarray(M, dtype=np.float64)
    U, _, Vt = np.linalg.svd(M)
    det = np.linalg.det(U @ Vt)
    D = np.ones(M.shape[:-1])
    D[..., -1] = det
    return (U * D[..., None, :]) @ Vt
