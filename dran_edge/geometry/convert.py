"""Converters between our pose arrays and external layouts, each named by its layout.

- ``xyz_quat_xyzw``: [x, y, z, qx, qy, qz, qw] (g2o VERTEX_SE3:QUAT, TUM, ROS, Motive order).
- ``xyz_quat_wxyz``: [x, y, z, qw, qx, qy, qz] (VINS-Mono CSVs, Eigen's coefficient order w first).
- ``tum_rows``: [stamp_s, x, y, z, qx, qy, qz, qw] (the TUM trajectory format read by evo).
Quaternions are normalised on the way in and returned with w ≥ 0.
"""

from __future__ import annotations

import numpy as np

from dran_edge.geometry.se3 import se3_from_rt
from dran_edge.geometry.so3 import (
    quat_wxyz_from_rotmat,
    rotmat_from_quat_wxyz,
    so3_exp,
    so3_log,
)


def quat_xyzw_from_rotmat(R: np.ndarray) -> np.ndarray:
    return np.roll(quat_wxyz_from_rotmat(R), -1, axis=-1)


def rotmat_from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    return rotmat_from_quat_wxyz(np.roll(np.asarray(q, dtype=np.float64), 1, axis=-1))


def se3_from_xyz_quat_xyzw(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return se3_from_rt(rotmat_from_quat_xyzw(a[..., 3:7]), a[..., :3])


def se3_to_xyz_quat_xyzw(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[..., :3, 3], quat_xyzw_from_rotmat(T[..., :3, :3])], axis=-1)


def se3_from_xyz_quat_wxyz(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return se3_from_rt(rotmat_from_quat_wxyz(a[..., 3:7]), a[..., :3])


def se3_to_xyz_quat_wxyz(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[..., :3, 3], quat_wxyz_from_rotmat(T[..., :3, :3])], axis=-1)


def se3_from_se2(T2: np.ndarray) -> np.ndarray:
    """Embed planar poses ``(..., 3, 3)`` as SE(3) ``(..., 4, 4)`` (z = 0, rotation about z)."""
    T2 = np.asarray(T2, dtype=np.float64)
    T = np.zeros(T2.shape[:-2] + (4, 4))
    T[..., :2, :2] = T2[..., :2, :2]
    T[..., 2, 2] = 1.0
    T[..., :2, 3] = T2[..., :2, 2]
    T[..., 3, 3] = 1.0
    return T


def se3_to_tum_rows(stamps_s: np.ndarray, T: np.ndarray) -> np.ndarray:
    """TUM rows ``(N, 8)`` [stamp_s, x, y, z, qx, qy, qz, qw] from stamps ``(N,)`` and poses ``(N, 4, 4)``."""
    stamps_s = np.asarray(stamps_s, dtype=np.float64).reshape(-1, 1)
    return np.concatenate([stamps_s, se3_to_xyz_quat_xyzw(T).reshape(-1, 7)], axis=-1)


def se3_from_tum_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_s ``(N,)``, poses ``(N, 4, 4)``) from TUM rows ``(N, 8)``."""
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    return rows[:, 0].copy(), se3_from_xyz_quat_xyzw(rows[:, 1:])


def se3_interpolate(
    stamps_ns: np.ndarray, T: np.ndarray, query_ns: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``query_ns`` by lerp of translation and slerp of rotation between neighbours.

    ``stamps_ns`` must be strictly increasing. Returns ``(T_query (M, 4, 4), valid (M,))``;
    queries outside [stamps_ns[0], stamps_ns[-1]] are not extrapolated: ``valid`` is False
    there and the nearest end pose is returned.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    query = np.asarray(query_ns, dtype=np.int64).reshape(-1)
    T = np.asarray(T, dtype=np.float64)
    valid = (query >= stamps[0]) & (query <= stamps[-1])
    if len(stamps) == 1:
        return np.broadcast_to(T[0], (len(query), 4, 4)).copy(), valid
    hi = np.clip(np.searchsorted(stamps, query, side="right"), 1, len(stamps) - 1)
    lo = hi - 1
    span = (stamps[hi] - stamps[lo]).astype(np.float64)
    s = np.clip((query - stamps[lo]).astype(np.float64) / span, 0.0, 1.0)
    R0, R1 = T[lo, :3, :3], T[hi, :3, :3]
    dphi = so3_log(np.swapaxes(R0, -1, -2) @ R1)
    R = R0 @ so3_exp(s[:, None] * dphi)
    t = (1 - s)[:, None] * T[lo, :3, 3] + s[:, None] * T[hi, :3, 3]
    return se3_from_rt(R, t), valid
