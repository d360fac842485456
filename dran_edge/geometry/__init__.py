"""SE(2) and SE(3) on plain numpy arrays, batched over leading axes.

Project conventions (docs/architecture.md, "Conventions"), fixed here once:

- Poses are ``(..., 4, 4)`` (SE(3)) or ``(..., 3, 3)`` (SE(2)) float64 arrays; ``T_a_b`` maps
  frame-b points into frame a, so ``T_a_c = T_a_b @ T_b_c``.
- Tangents are ``(..., 6)`` = [ρ, φ] or ``(..., 3)`` = [x, y, θ]: translation first.
- Right perturbation, one retraction: ``T ⊕ ξ = T Exp(ξ)``.
- Reference: Solà, Deray, Atchuthan, "A micro Lie theory for state estimation in robotics"
  (arXiv:1812.01537); equation numbers in the docstrings of ``so3``, ``se3``, ``se2``.

The unprefixed functions (``exp``, ``log``, ``inverse`` …) dispatch on the array's trailing
shape: a 6-vector or 4×4 matrix is SE(3), a 3-vector or 3×3 matrix SE(2).
"""

from __future__ import annotations

import numpy as np

from dran_edge.geometry.convert import (
    quat_xyzw_from_rotmat,
    rotmat_from_quat_xyzw,
    se3_from_se2,
    se3_from_tum_rows,
    se3_from_xyz_quat_wxyz,
    se3_from_xyz_quat_xyzw,
    se3_interpolate,
    se3_to_tum_rows,
    se3_to_xyz_quat_wxyz,
    se3_to_xyz_quat_xyzw,
)
from dran_edge.geometry.se2 import (
    se2_adjoint,
    se2_exp,
    se2_from_rt,
    se2_from_xy_theta,
    se2_inverse,
    se2_log,
    se2_retract,
    se2_right_jacobian,
    se2_right_jacobian_inv,
    se2_to_xy_theta,
    so2_exp,
    so2_log,
)
from dran_edge.geometry.se3 import (
    se3_adjoint,
    se3_between,
    se3_chordal_distance,
    se3_compose,
    se3_exp,
    se3_from_rt,
    se3_geodesic_distance,
    se3_inverse,
    se3_left_jacobian,
    se3_left_jacobian_inv,
    se3_log,
    se3_retract,
    se3_right_jacobian,
    se3_right_jacobian_inv,
    se3_transform_points,
)
from dran_edge.geometry.so3 import (
    hat3,
    quat_wxyz_from_rotmat,
    rotmat_from_quat_wxyz,
    so3_angle,
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inv,
    so3_log,
    so3_project,
    so3_right_jacobian,
    so3_right_jacobian_inv,
    vee3,
)


def dof(dim: int) -> int:
    """Tangent dimension of SE(dim): 3 for SE(2), 6 for SE(3)."""
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim}")
    return 3 if dim == 2 else 6


def _is_se3_matrix(T: np.ndarray) -> bool:
    n = np.shape(T)[-1]
    if n not in (3, 4) or np.shape(T)[-2] != n:
        raise ValueError(f"expected (..., 3, 3) or (..., 4, 4) poses, got shape {np.shape(T)}")
    return n == 4


def _is_se3_tangent(xi: np.ndarray) -> bool:
    n = np.shape(xi)[-1]
    if n not in (3, 6):
        raise ValueError(f"expected (..., 3) or (..., 6) tangents, got shape {np.shape(xi)}")
    return n == 6


def exp(xi: np.ndarray) -> np.ndarray:
    return se3_exp(xi) if _is_se3_tangent(xi) else se2_exp(xi)


def log(T: np.ndarray) -> np.ndarray:
    return se3_log(T) if _is_se3_matrix(T) else se2_log(T)


def inverse(T: np.ndarray) -> np.ndarray:
    return se3_inverse(T) if _is_se3_matrix(T) else se2_inverse(T)


def compose(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    _is_se3_matrix(A)
    return np.asarray(A, dtype=np.float64) @ np.asarray(B, dtype=np.float64)


def between(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    return inverse(A) @ np.asarray(B, dtype=np.float64)


def adjoint(T: np.ndarray) -> np.ndarray:
    return se3_adjoint(T) if _is_se3_matrix(T) else se2_adjoint(T)


def right_jacobian(xi: np.ndarray) -> np.ndarray:
    return se3_right_jacobian(xi) if _is_se3_tangent(xi) else se2_right_jacobian(xi)


def right_jacobian_inv(xi: np.ndarray) -> np.ndarray:
    return se3_right_jacobian_inv(xi) if _is_se3_tangent(xi) else se2_right_jacobian_inv(xi)


def retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    return np.asarray(T, dtype=np.float64) @ exp(xi)


def geodesic_distance(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """‖Log(A⁻¹ B)‖ over the whole tangent."""
    return np.linalg.norm(log(between(A, B)), axis=-1)


def chordal_distance(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """‖A − B‖_F over the upper d × (d+1) block."""
    A = np.asarray(A, dtype=np.float64)
    d = A.shape[-1] - 1
    D = A[..., :d, :] - np.asarray(B, dtype=np.float64)[..., :d, :]
    return np.sqrt(np.sum(D * D, axis=(-1, -2)))


def identity(dim: int, batch: tuple[int, ...] = ()) -> np.ndarray:
    """Identity poses of SE(dim) with leading shape ``batch``."""
    return np.broadcast_to(np.eye(dim + 1), batch + (dim + 1, dim + 1)).copy()
