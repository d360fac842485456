"""Value encodings of the wire codec (``dran_edge.comms.codec``): LEB128 varints, zigzag, and
the packed SE(3)/SE(2) pose blocks (layout and precision in docs/wire-format.md)."""

from __future__ import annotations

import math

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import DecodeError, DranError

_U16_MAX = 0xFFFF
_U32_MAX = 0xFFFFFFFF
_VARINT_MAX_BYTES = 10  # a uint64 in LEB128

# Smallest-three quaternion: 2-bit index of the dropped (largest) component in [x, y, z, w]
# order, then three 23-bit fields u = s + 2^22 with s = round(c * sqrt2 * (2^22 - 1)) for a
# component c in [-1/sqrt2, 1/sqrt2] (zero is exact); 71 of 72 bits used, the top one is 0.
_Q_BITS = 23
_Q_MASK = np.uint64((1 << _Q_BITS) - 1)
_Q_OFFSET = 1 << (_Q_BITS - 1)
_Q_SCALE = float(_Q_OFFSET - 1)
_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_POSE3 = np.dtype([("t", "<f4", (3,)), ("q_lo", "<u8"), ("q_hi", "u1")])  # 21 bytes
# SE(2): theta quantised to 24 bits over [-pi, pi).
_POSE2 = np.dtype([("t", "<f4", (2,)), ("theta", "u1", (3,))])  # 11 bytes
_THETA_STEPS = 1 << 24

assert _POSE3.itemsize == 21 and _POSE2.itemsize == 11


class EncodeError(DranError):
    """A message cannot be encoded (non-finite pose, non-rotation, id out of range)."""


def pose_bytes(dim: int) -> int:
    """Bytes of one encoded pose: 21 (SE(3)) or 11 (SE(2))."""
    return _POSE3.itemsize if dim == 3 else _POSE2.itemsize


def _rotation_value_bytes(dim: int) -> int:
    return 4 * dim * dim


# --------------------------------------------------------------------------- varints
_SMALL_VARINTS = tuple(bytes([i]) for i in range(0x80))


def _varint(value: int) -> bytes:
    if 0 <= value < 0x80:
        return _SMALL_VARINTS[value]
    if value < 0:
        raise EncodeError(f"expected a non-negative integer for a varint, got {value}")
    if value >= 1 << 64:
        raise EncodeError(f"integer {value} does not fit in 64 bits")
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _zigzag(value: int) -> int:
    return (value << 1) if value >= 0 else ((-value << 1) - 1)


def _unzigzag(value: int) -> int:
    return (value >> 1) if not value & 1 else -((value + 1) >> 1)


def _read_varint(data: bytes, pos: int, end: int) -> tuple[int, int]:
    if pos < end and data[pos] < 0x80:
        return data[pos], pos + 1
    result = 0
    shift = 0
    for i in range(_VARINT_MAX_BYTES):
        if pos >= end:
            raise DecodeError(f"truncated varint at byte {pos}")
        b = data[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            if i and b == 0:
                raise DecodeError(f"non-minimal varint ending at byte {pos - 1}")
            if result >= 1 << 64:
                raise DecodeError(f"varint ending at byte {pos - 1} exceeds 64 bits")
            return result, pos
        shift += 7
    raise DecodeError(
        f"varint longer than {_VARINT_MAX_BYTES} bytes at byte {pos - _VARINT_MAX_BYTES}"
    )


# --------------------------------------------------------------------------- pose blocks
def _check_poses(T: np.ndarray, dim: int, what: str) -> None:
    n = dim + 1
    if T.shape[-2:] != (n, n):
        raise EncodeError(
            f"{what}: expected ({n}, {n}) poses for SE({dim}), got shape {T.shape[-2:]}"
        )
    if not np.all(np.isfinite(T)):
        raise EncodeError(f"{what}: pose contains NaN or inf")
    R = T[..., :dim, :dim]
    err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(dim)).max(initial=0.0)
    if err > 1e-3 or np.any(np.linalg.det(R) <= 0):
        raise EncodeError(f"{what}: rotation block is not a rotation (|RᵀR - I| = {err:.2e})")
    if np.abs(T[..., :dim, dim]).max(initial=0.0) > 3.0e38:
        raise EncodeError(f"{what}: translation exceeds the float32 range")


def _encode_poses3(T: np.ndarray) -> np.ndarray:
    """(N, 4, 4) -> (N,) records of ``_POSE3``."""
    out = np.zeros(T.shape[0], dtype=_POSE3)
    out["t"] = T[:, :3, 3].astype(np.float32)
    q = geo.quat_wxyz_from_rotmat(T[:, :3, :3])[:, [1, 2, 3, 0]]  # -> [x, y, z, w]
    idx = np.argmax(np.abs(q), axis=1)
    largest = np.take_along_axis(q, idx[:, None], axis=1)
    q = np.where(largest < 0, -q, q)  # dropped component positive
    keep = np.ones_like(q, dtype=bool)
    keep[np.arange(q.shape[0]), idx] = False
    small = q[keep].reshape(-1, 3)
    signed = np.rint(np.clip(small / _INV_SQRT2, -1.0, 1.0) * _Q_SCALE).astype(np.int64)
    u = (signed + _Q_OFFSET).astype(np.uint64)
    lo = (
        idx.astype(np.uint64)
        | (u[:, 0] << np.uint64(2))
        | (u[:, 1] << np.uint64(2 + _Q_BITS))
        | ((u[:, 2] & np.uint64(0xFFFF)) << np.uint64(2 + 2 * _Q_BITS))
    )
    out["q_lo"] = lo
    out["q_hi"] = (u[:, 2] >> np.uint64(16)).astype(np.uint8)
    return out


def _decode_poses3(rec: np.ndarray) -> np.ndarray:
    t = rec["t"].astype(np.float64)
    if not np.all(np.isfinite(t)):
        raise DecodeError("pose translation is NaN or inf")
    hi = rec["q_hi"]
    if np.any(hi & 0x80):
        raise DecodeError("quaternion padding bit is set")
    lo = rec["q_lo"]
    idx = (lo & np.uint64(3)).astype(np.intp)
    u = np.stack(
        [
            (lo >> np.uint64(2)) & _Q_MASK,
            (lo >> np.uint64(2 + _Q_BITS)) & _Q_MASK,
            (lo >> np.uint64(2 + 2 * _Q_BITS)) | (hi.astype(np.uint64) << np.uint64(16)),
        ],
        axis=1,
    )
    small = (u.astype(np.float64) - _Q_OFFSET) * (_INV_SQRT2 / _Q_SCALE)
    sq = np.sum(small * small, axis=1)
    if np.any(sq > 1.0 + 1e-6):
        raise DecodeError("quaternion is not unit (smallest three have squared norm > 1)")
    largest = np.sqrt(np.maximum(1.0 - sq, 0.0))
    q = np.empty((rec.shape[0], 4))
    cols = np.arange(4)[None, :]
    others = cols != idx[:, None]
    q[others] = small.reshape(-1)
    q[~others] = largest
    T = np.zeros((rec.shape[0], 4, 4))
    T[:, :3, :3] = geo.rotmat_from_quat_wxyz(q[:, [3, 0, 1, 2]])
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    return T


def _encode_poses2(T: np.ndarray) -> np.ndarray:
    out = np.zeros(T.shape[0], dtype=_POSE2)
    out["t"] = T[:, :2, 2].astype(np.float32)
    theta = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    steps = np.rint((theta + np.pi) * (_THETA_STEPS / (2 * np.pi))).astype(np.int64) % _THETA_STEPS
    out["theta"] = np.stack([(steps >> s) & 0xFF for s in (0, 8, 16)], axis=1).astype(np.uint8)
    return out


def _decode_poses2(rec: np.ndarray) -> np.ndarray:
    t = rec["t"].astype(np.float64)
    if not np.all(np.isfinite(t)):
        raise DecodeError("pose translation is NaN or inf")
    b = rec["theta"].astype(np.int64)
    steps = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)
    theta = steps * (2 * np.pi / _THETA_STEPS) - np.pi
    return geo.se2_from_rt(geo.so2_exp(theta), t)


def _encode_poses(T: np.ndarray, dim: int) -> bytes:
    if T.shape[0] == 0:
        return b""
    return (_encode_poses3(T) if dim == 3 else _encode_poses2(T)).tobytes()


def _decode_poses(buf: bytes, dim: int) -> np.ndarray:
    rec = np.frombuffer(buf, dtype=_POSE3 if dim == 3 else _POSE2)
    if rec.shape[0] == 0:
        return np.zeros((0, dim + 1, dim + 1))
    return _decode_poses3(rec) if dim == 3 else _decode_poses2(rec)
