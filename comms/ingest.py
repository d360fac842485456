"""Ingest records: what the VIO bridge and the perception worker hand the daemon (docs/ingest.md).

One module owns this byte format. The same framed records travel over the daemon's
Unix-domain ingest socket, are appended to the crash-safe ingest journal, and are stored byte
for byte as ``robots/<name>/ingest.bin`` of a recorded run, so replay exercises these decoders.

Framing (all little-endian, no padding)::

    offset size  field
    0      4     magic  b"DRNI"
    4      1     version (1)
    5      1     kind   (1 odometry, 2 keyframe, 3 loop, 4 reset, 5 frame, 6 observations)
    6      2     flags  (bit 0: odometry carries a covariance; other bits must be 0)
    8      4     payload_len  (bytes after the header; checked against the kind's exact size)
    12     4     crc32  (zlib.crc32 of the payload)
    16     ...   payload

Poses are ``xyz`` (3 x f64, metres) + ``quat_xyzw`` (4 x f64, unit norm within 1e-3,
renormalised on decode); stamps are int64 nanoseconds > 0. Payloads per kind:

- ODOMETRY  ``stamp_ns q, xyz 3d, quat_xyzw 4d [, covariance 36d row-major, [t, r] order]``
  (T_odom_body, body = IMU frame, odom = the VIO world of the current segment)
- KEYFRAME  ``stamp_ns q, xyz 3d, quat_xyzw 4d`` (T_odom_body of a VIO keyframe)
- LOOP      ``stamp_old_ns q, stamp_cur_ns q, xyz 3d, quat_xyzw 4d, inliers I`` (T_old_cur)
- RESET     ``stamp_ns q, reason_code B, reason utf-8 (0..200 bytes)``
- FRAME     ``stamp_ns q, frame bytes`` (perception's ``frame_to_bytes`` layout, carried opaquely)
- OBSERVATIONS ``stamp_ns q, count I, count x (object_id I, xyz 3d, quat_xyzw 4d, covariance 36d)``
  (tag observations T_body_object of one camera frame, count <= 256)

A stream decoder never trusts a length: oversize or corrupt records are skipped by scanning
for the next magic, every problem is a :class:`IngestDecodeError` with a short ``reason``
(counted by the server), and the decoder keeps going.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import DecodeError
from dran_edge.events import (
    Keyframe,
    LoopClosure,
    ObjectObservation,
    ObservationBatch,
    OdometrySample,
    VioReset,
)

MAGIC = b"DRNI"
VERSION = 1
HEADER = struct.Struct("<4sBBHII")
HEADER_SIZE = HEADER.size  # 16

KIND_ODOMETRY = 1
KIND_KEYFRAME = 2
KIND_LOOP = 3
KIND_RESET = 4
KIND_FRAME = 5
KIND_OBSERVATIONS = 6
KIND_NAMES = {1: "odometry", 2: "keyframe", 3: "loop", 4: "reset", 5: "frame", 6: "observations"}

FLAG_COVARIANCE = 0x0001

_POSE = struct.Struct("<q3d4d")  # stamp, xyz, quat_xyzw: 64 bytes
_COV = struct.Struct("<36d")  # 288 bytes
_LOOP = struct.Struct("<qq3d4dI")  # 76 bytes
_RESET = struct.Struct("<qB")  # 9 bytes + text
_OBS_HEAD = struct.Struct("<qI")  # 12 bytes
_OBS = struct.Struct("<I3d4d36d")  # 348 bytes

MAX_RESET_TEXT = 200
MAX_OBSERVATIONS = 256
MAX_FRAME_BYTES = 32 * 1024 * 1024
#: Largest payload any kind may declare; a larger length is corrupt by definition.
MAX_PAYLOAD = {
    KIND_ODOMETRY: _POSE.size + _COV.size,
    KIND_KEYFRAME: _POSE.size,
    KIND_LOOP: _LOOP.size,
    KIND_RESET: _RESET.size + MAX_RESET_TEXT,
    KIND_FRAME: 8 + MAX_FRAME_BYTES,
    KIND_OBSERVATIONS: _OBS_HEAD.size + MAX_OBSERVATIONS * _OBS.size,
}
QUAT_NORM_TOL = 1e-3

#: Reset reason codes (docs/ingest.md).
RESET_UNKNOWN = 0
RESET_FEATURE_TRACKER_RESTART = 1
RESET_BRIDGE_START = 2
RESET_ESTIMATOR_FAILURE = 3
RESET_REASONS = {
    0: "unknown",
    1: "feature_tracker_restart",
    2: "bridge_start",
    3: "estimator_failure",
}


class IngestDecodeError(DecodeError):
    """An ingest record that does not decode; ``reason`` is a short counter key."""

    def __init__(self, reason: str, message: str):
        super().__init__(f"ingest record rejected ({reason}): {message}")
        self.reason = reason


@dataclass(frozen=True, eq=False)
class ForwardedFrame:
    """A camera frame forwarded over the ingest socket (payload in perception's byte layout)."""

    stamp_ns: int
    payload: bytes


@dataclass(frozen=True, eq=False)
class Record:
    """One decoded record and its exact bytes (header + payload), for the journal/recording."""

    kind: int
    event: object
    raw: bytes


# --------------------------------------------------------------------------- encoding
def _frame(kind: int, payload: bytes, flags: int = 0) -> bytes:
    return HEADER.pack(MAGIC, VERSION, kind, flags, len(payload), zlib.crc32(payload)) + payload


def _floats(values, n: int, what: str) -> list[float]:
    if isinstance(values, tuple):  # the bag importer's poses: no numpy round trip
        out = [float(v) for v in values]
    else:
        out = [float(v) for v in np.asarray(values, dtype=np.float64).reshape(-1)]
    if len(out) != n:
        raise ValueError(f"{what}: expected {n} numbers, got {len(out)}")
    return out


def pack_odometry(stamp_ns: int, xyz, quat_xyzw, covariance=None) -> bytes:
    """An ODOMETRY record from raw components (the bridge has the same function)."""
    payload = _POSE.pack(int(stamp_ns), *_floats(xyz, 3, "xyz"), *_floats(quat_xyzw, 4, "quat"))
    if covariance is None:
        return _frame(KIND_ODOMETRY, payload)
    return _frame(
        KIND_ODOMETRY, payload + _COV.pack(*_floats(covariance, 36, "covariance")), FLAG_COVARIANCE
    )


def pack_keyframe(stamp_ns: int, xyz, quat_xyzw) -> bytes:
    return _frame(
        KIND_KEYFRAME,
        _POSE.pack(int(stamp_ns), *_floats(xyz, 3, "xyz"), *_floats(quat_xyzw, 4, "quat")),
    )


def pack_loop(stamp_old_ns: int, stamp_cur_ns: int, xyz, quat_xyzw, inliers: int) -> bytes:
    return _frame(
        KIND_LOOP,
        _LOOP.pack(
            int(stamp_old_ns),
            int(stamp_cur_ns),
            *_floats(xyz, 3, "xyz"),
            *_floats(quat_xyzw, 4, "quat"),
            int(inliers),
        ),
    )


def pack_reset(stamp_ns: int, reason_code: int, reason: str = "") -> bytes:
    text = reason.encode("utf-8")[:MAX_RESET_TEXT]
    return _frame(KIND_RESET, _RESET.pack(int(stamp_ns), int(reason_code)) + text)


def pack_frame(stamp_ns: int, frame_bytes: bytes) -> bytes:
    if len(frame_bytes) > MAX_FRAME_BYTES:
        raise ValueError(f"frame: expected <= {MAX_FRAME_BYTES} bytes, got {len(frame_bytes)}")
    return _frame(KIND_FRAME, struct.pack("<q", int(stamp_ns)) + bytes(frame_bytes))


def _pose_parts(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = geo.se3_to_xyz_quat_xyzw(np.asarray(T, dtype=np.float64))
    return a[:3], a[3:]


def encode_event(event) -> bytes:
    """Framed record bytes of one ingest event (the inverse of :func:`decode_record`)."""
    if isinstance(event, OdometrySample):
        xyz, q = _pose_parts(event.T_odom_body)
        return pack_odometry(event.stamp_ns, xyz, q, event.covariance)
    if isinstance(event, Keyframe):
        return pack_keyframe(event.stamp_ns, *_pose_parts(event.T_odom_body))
    if isinstance(event, LoopClosure):
        return pack_loop(
            event.stamp_old_ns, event.stamp_cur_ns, *_pose_parts(event.T_old_cur), event.inliers
        )
    if isinstance(event, VioReset):
        code = {v: k for k, v in RESET_REASONS.items()}.get(event.reason, RESET_UNKNOWN)
        return pack_reset(event.stamp_ns, code, "" if code else event.reason)
    if isinstance(event, ForwardedFrame):
        return pack_frame(event.stamp_ns, event.payload)
    if isinstance(event, ObservationBatch):
        obs = event.observations
        if len(obs) > MAX_OBSERVATIONS:
            raise ValueError(f"observations: expected <= {MAX_OBSERVATIONS}, got {len(obs)}")
        parts = [_OBS_HEAD.pack(int(event.stamp_ns), len(obs))]
        for o in obs:
            xyz, q = _pose_parts(o.T_body_object)
            parts.append(
                _OBS.pack(int(o.object_id), *xyz, *q, *_floats(o.covariance, 36, "covariance"))
            )
        return _frame(KIND_OBSERVATIONS, b"".join(parts))
    raise TypeError(f"not an ingest event: {type(event).__name__}")


# --------------------------------------------------------------------------- decoding
def _stamp(value: int, what: str) -> int:
    if value <= 0:
        raise IngestDecodeError("bad_stamp", f"{what}: expected > 0 ns, got {value}")
    return value


def _pose(xyz: tuple, quat: tuple, what: str) -> np.ndarray:
    a = np.array(xyz + quat, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise IngestDecodeError("non_finite", f"{what}: expected finite pose values, got {a}")
    if np.any(np.abs(a[:3]) > 1e6):
        raise IngestDecodeError("out_of_range", f"{what}: expected |xyz| <= 1e6 m, got {a[:3]}")
    norm = float(np.linalg.norm(a[3:]))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise IngestDecodeError(
            "bad_quaternion", f"{what}: expected a unit quaternion, got norm {norm:.6g}"
        )
    return geo.se3_from_xyz_quat_xyzw(a)


def _covariance(values: tuple, what: str) -> np.ndarray:
    C = np.array(values, dtype=np.float64).reshape(6, 6)
    if not np.all(np.isfinite(C)):
        raise IngestDecodeError("non_finite", f"{what}: expected a finite covariance")
    scale = max(1.0, float(np.max(np.abs(C))))
    if np.max(np.abs(C - C.T)) > 1e-9 * scale or np.any(np.diag(C) < 0):
        raise IngestDecodeError(
            "bad_covariance", f"{what}: expected a symmetric covariance with diagonal >= 0"
        )
    return C


def _exact(payload: bytes, size: int, kind: int) -> None:
    if len(payload) != size:
        raise IngestDecodeError(
            "bad_size", f"{KIND_NAMES[kind]}: expected {size} payload bytes, got {len(payload)}"
        )


def decode_payload(kind: int, flags: int, payload: bytes):
    """The event of one record's payload; IngestDecodeError on anything malformed."""
    if kind == KIND_ODOMETRY:
        if flags & ~FLAG_COVARIANCE:
            raise IngestDecodeError("bad_flags", f"odometry: unknown flags {flags:#x}")
        has_cov = bool(flags & FLAG_COVARIANCE)
        _exact(payload, _POSE.size + (_COV.size if has_cov else 0), kind)
        v = _POSE.unpack_from(payload)
        cov = _covariance(_COV.unpack_from(payload, _POSE.size), "odometry") if has_cov else None
        return OdometrySample(_stamp(v[0], "odometry"), _pose(v[1:4], v[4:8], "odometry"), cov)
    if flags:
        raise IngestDecodeError("bad_flags", f"{KIND_NAMES.get(kind, kind)}: flags must be 0")
    if kind == KIND_KEYFRAME:
        _exact(payload, _POSE.size, kind)
        v = _POSE.unpack(payload)
        return Keyframe(_stamp(v[0], "keyframe"), _pose(v[1:4], v[4:8], "keyframe"))
    if kind == KIND_LOOP:
        _exact(payload, _LOOP.size, kind)
        v = _LOOP.unpack(payload)
        old, cur = _stamp(v[0], "loop.stamp_old_ns"), _stamp(v[1], "loop.stamp_cur_ns")
        if old == cur:
            raise IngestDecodeError("bad_stamp", f"loop: expected two keyframes, got {old} twice")
        return LoopClosure(old, cur, _pose(v[2:5], v[5:9], "loop"), int(v[9]))
    if kind == KIND_RESET:
        if not _RESET.size <= len(payload) <= _RESET.size + MAX_RESET_TEXT:
            raise IngestDecodeError(
                "bad_size",
                f"reset: expected {_RESET.size}.."
                f"{_RESET.size + MAX_RESET_TEXT} bytes, got {len(payload)}",
            )
        stamp, code = _RESET.unpack_from(payload)
        try:
            text = payload[_RESET.size :].decode("utf-8")
        except UnicodeDecodeError:
            raise IngestDecodeError("bad_text", "reset: reason is not UTF-8") from None
        reason = RESET_REASONS.get(code, f"code_{code}") if code or not text else text
        return VioReset(_stamp(stamp, "reset"), reason)
    if kind == KIND_FRAME:
        if len(payload) < 8:
            raise IngestDecodeError("bad_size", f"frame: expected >= 8 bytes, got {len(payload)}")
        (stamp,) = struct.unpack_from("<q", payload)
        return ForwardedFrame(_stamp(stamp, "frame"), bytes(payload[8:]))
    if kind == KIND_OBSERVATIONS:
        if len(payload) < _OBS_HEAD.size:
            raise IngestDecodeError("bad_size", f"observations: got {len(payload)} bytes")
        stamp, count = _OBS_HEAD.unpack_from(payload)
        if count > MAX_OBSERVATIONS:
            raise IngestDecodeError(
                "bad_count", f"observations: expected <= {MAX_OBSERVATIONS}, got {count}"
            )
        _exact(payload, _OBS_HEAD.size + count * _OBS.size, kind)
        stamp = _stamp(stamp, "observations")
        obs = []
        for i in range(count):
            v = _OBS.unpack_from(payload, _OBS_HEAD.size + i * _OBS.size)
            obs.append(
                ObjectObservation(
                    stamp,
                    int(v[0]),
                    _pose(v[1:4], v[4:8], f"observation {i}"),
                    _covariance(v[8:44], f"observation {i}"),
                )
            )
        return ObservationBatch(stamp, tuple(obs))
    raise IngestDecodeError("unknown_kind", f"expected a kind in 1..6, got {kind}")


def decode_record(data: bytes):
    """The event of exactly one framed record (header + payload)."""
    if len(data) < HEADER_SIZE:
        raise IngestDecodeError("truncated", f"expected >= {HEADER_SIZE} bytes, got {len(data)}")
    magic, version, kind, flags, length, crc = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise IngestDecodeError("bad_magic", f"expected {MAGIC!r}, got {magic!r}")
    if len(data) != HEADER_SIZE + length:
        raise IngestDecodeError(
            "bad_size", f"header says {length} payload bytes, got {len(data) - HEADER_SIZE}"
        )
    payload = bytes(data[HEADER_SIZE:])
    if zlib.crc32(payload) != crc:
        raise IngestDecodeError("bad_crc", "payload checksum mismatch")
    if version != VERSION:
        raise IngestDecodeError("bad_version", f"expected version {VERSION}, got {version}")
    return decode_payload(kind, flags, payload)


class StreamDecoder:
    """Incremental decoder of a byte stream of records (socket or file); never raises on input.

    ``feed(data)`` returns, in stream order, :class:`Record` for each good record and
    :class:`IngestDecodeError` for each rejected one. Garbage is skipped by searching for the
    next magic; a rejected record costs only itself.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.bytes_consumed = 0

    @property
    def pending_bytes(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes) -> list:
        self._buf += data
        out: list = []
        buf = self._buf
        pos = 0
        while pos < len(buf):
            head = bytes(buf[pos : pos + 4])
            if head != MAGIC[: len(head)]:
                out.append(IngestDecodeError("bad_magic", "bytes between records that are not one"))
                pos = _next_candidate(buf, pos + 1)
                continue
            if len(buf) - pos < HEADER_SIZE:
                break
            magic, version, kind, flags, length, crc = HEADER.unpack_from(buf, pos)
            problem = _length_problem(kind, length)
            if problem:
                out.append(IngestDecodeError("bad_size", problem))
                pos = _next_candidate(buf, pos + 1)
                continue
            end = pos + HEADER_SIZE + length
            if end > len(buf):
                break
            payload = bytes(buf[pos + HEADER_SIZE : end])
            if zlib.crc32(payload) != crc:
                out.append(IngestDecodeError("bad_crc", "payload checksum mismatch"))
                pos = _next_candidate(buf, pos + 1)  # the length may be what is corrupt
                continue
            raw = bytes(buf[pos:end])
            pos = end
            try:
                if version != VERSION:
                    raise IngestDecodeError(
                        "bad_version", f"expected version {VERSION}, got {version}"
                    )
                out.append(Record(kind, decode_payload(kind, flags, payload), raw))
            except IngestDecodeError as exc:
                out.append(exc)
        del buf[:pos]
        self.bytes_consumed += pos
        return out


def _next_candidate(buf: bytearray, start: int) -> int:
    """Index of the next full magic, or of a partial magic at the very end, or len(buf)."""
    i = buf.find(MAGIC, start)
    if i >= 0:
        return i
    for k in (3, 2, 1):
        if len(buf) - k >= start and buf[len(buf) - k :] == MAGIC[:k]:
            return len(buf) - k
    return len(buf)


def _length_problem(kind: int, length: int) -> str:
    """Why a declared payload length cannot be right for ``kind`` ("" if it can)."""
    name = KIND_NAMES.get(kind, f"kind {kind}")
    limit = MAX_PAYLOAD.get(kind, max(MAX_PAYLOAD.values()))
    if length > limit:
        return f"{name}: declared {length} payload bytes, at most {limit} allowed"
    fixed = {
        KIND_ODOMETRY: (_POSE.size, _POSE.size + _COV.size),
        KIND_KEYFRAME: (_POSE.size,),
        KIND_LOOP: (_LOOP.size,),
    }.get(kind)
    if fixed is not None and length not in fixed:
        return f"{name}: declared {length} payload bytes, expected one of {fixed}"
    if kind == KIND_OBSERVATIONS and (
        length < _OBS_HEAD.size or (length - _OBS_HEAD.size) % _OBS.size
    ):
        return f"{name}: declared {length} payload bytes, not 12 + n x {_OBS.size}"
    if kind == KIND_RESET and length < _RESET.size:
        return f"{name}: declared {length} payload bytes, expected >= {_RESET.size}"
    return ""


def iter_records(data: bytes) -> Iterator:
    """Records and errors of a complete byte string (an ``ingest.bin``); a torn tail is an error."""
    dec = StreamDecoder()
    yield from dec.feed(data)
    if dec.pending_bytes:
        yield IngestDecodeError(
            "truncated", f"{dec.pending_bytes} bytes of an incomplete record at the end"
        )
