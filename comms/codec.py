"""Wire codec for neighbour datagrams: ``NeighbourMessage`` <-> self-contained datagrams.

Layout, precision and CHANGELOG in ``docs/wire-format.md`` (schema version 1).
One round's message may span several datagrams; each carries a full header and a share of the
entries, decodes alone, and is at most ``max_datagram_bytes`` long (default 1200, hard cap
``HARD_CAP_BYTES`` = 4096, far below libzmq's 8192-byte UDP buffer). Bytes are the paper's
headline metric (Table 1), so the layout is built for size:

- header: magic ``DR``, version, flags (4 bytes), then LEB128 varints: fleet id (u16),
  sender id (u16), boot epoch (u32), sequence (u32), round, stamp_ns, three entry counts;
- an id section (varints) for all entries, then one packed value block, then the
  authentication trailer: a 16-byte HMAC tag slot, or with flag bit 2 (``signed=True``) a
  64-byte Ed25519 signature slot (zeros here; ``dran_edge.comms.auth`` fills and checks it);
- SE(3) pose = float32 translation (12 bytes) + "smallest three" unit quaternion with 23-bit
  components (9 bytes): 21 bytes. SE(2) pose = float32 x, y + 24-bit angle: 11 bytes.
  Worst-case round-trip error: ~3.8e-6 m at 100 m, ~4.4e-7 rad (``tests/test_codec.py``
  measures it; far below the solver's tolerances ε_u = 1e-2, ε_v = 1e-1).

Decoding is strict: anything malformed (truncated, oversized, counts that do not match the
length, NaN/inf, a non-unit quaternion, unknown magic/version/flags/stage, over-long varints)
raises ``DecodeError`` and nothing else.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from dran_edge.comms import delta as dl

from dran_edge import geometry as geo
from dran_edge.errors import DecodeError, DranError
from dran_edge.messages import InitEntry, InitStage, NeighbourMessage, ObjectEntry, SeparatorEntry

MAGIC = b"DR"
SCHEMA_VERSION = 2
TAG_BYTES = 16
#: Trailer of a datagram with the signed flag: an Ed25519 signature (RFC 8032).
SIGNATURE_BYTES = 64
HARD_CAP_BYTES = 4096
DEFAULT_MAX_DATAGRAM_BYTES = 1200
#: Smallest allowed ``max_datagram_bytes``: header + tag + the largest single entry with room.
MIN_DATAGRAM_BYTES = 160

_FIXED = struct.Struct("<2sBB")
#: Magic, version, flags; then varints fleet, sender, boot epoch, sequence, round, stamp_ns
#: and the three entry counts.
HEADER_FIXED_BYTES = _FIXED.size  # 4
_HEADER_MIN_BYTES = HEADER_FIXED_BYTES + 9
_FLAG_DIM3 = 0x01
#: Delta layout (docs/wire-format.md, ``dran_edge.comms.delta``): separator and init entries may
#: carry a quantised change instead of a value; separator stamps chain from entry to entry.
_FLAG_DELTA = 0x02
#: Per-robot identity (docs/wire-format.md, "Authentication"): the trailer is the sender's
#: 64-byte Ed25519 signature instead of the fleet's 16-byte HMAC tag.
_FLAG_SIGNED = 0x04
#: Stop status (docs/wire-format.md): one varint after the entry counts, the sender's done
#: counter (``NeighbourMessage.done_count``, docs/notes/stopping-rule.md). Without the flag the
#: header is byte for byte the one before the flag existed.
_FLAG_STATUS = 0x08
#: Pairwise key policy (docs/wire-format.md, "Authentication", ``dran_edge.comms.pairwise``): the
#: 16-byte tag is an HMAC with the key of this sender-receiver pair, not the fleet key.
_FLAG_PAIRWISE = 0x10
_FLAGS_KNOWN = _FLAG_DIM3 | _FLAG_DELTA | _FLAG_SIGNED | _FLAG_STATUS | _FLAG_PAIRWISE
#: Largest done counter on the wire (a robot's counter saturates there; 2 varint bytes at most).
DONE_COUNT_MAX = 255
_INIT_DELTA_BIT = 0x80
_STAGES = frozenset(int(s) for s in InitStage)

#: Byte-accounting kinds (``bytes_by_kind``): header + tag, and one per entry type.
KIND_HEADER = "header"
KIND_SEPARATOR = "separator"
KIND_OBJECT = "object"
KIND_INIT = "init"
KINDS = (KIND_HEADER, KIND_SEPARATOR, KIND_OBJECT, KIND_INIT)

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


def _support(e: ObjectEntry) -> int:
    support = int(e.support)
    if not 0 <= support <= _U16_MAX:
        raise EncodeError(f"object {e.object_id}: support must be in [0, {_U16_MAX}], got {support}")
    return support


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


# --------------------------------------------------------------------------- header
@dataclass(frozen=True)
class Header:
    """The decoded header of one datagram (no entries decoded, tag not checked)."""

    version: int
    dim: int
    fleet_id: int
    sender_id: int
    boot_epoch: int
    sequence: int
    round: int
    stamp_ns: int
    n_separators: int
    n_objects: int
    n_init: int
    #: Offset of the id section (= header length in bytes).
    body_offset: int
    #: Delta layout (flag 0x02).
    delta: bool = False
    #: Ed25519-signed (flag 0x04): the trailer is ``SIGNATURE_BYTES`` long, else ``TAG_BYTES``.
    signed: bool = False
    #: The sender's done counter (flag 0x08), None without the flag.
    done_count: int | None = None
    #: Pairwise-keyed tag (flag 0x10, ``comms.pairwise``): a 16-byte tag like the fleet's.
    pairwise: bool = False

    @property
    def trailer_bytes(self) -> int:
        """Length of the authentication trailer (HMAC tag or Ed25519 signature)."""
        return SIGNATURE_BYTES if self.signed else TAG_BYTES


def trailer_bytes(data: bytes) -> int:
    """Length of ``data``'s authentication trailer from its flags byte (16 if unreadable)."""
    return SIGNATURE_BYTES if len(data) > 3 and data[3] & _FLAG_SIGNED else TAG_BYTES


def decode_header(data: bytes) -> Header:
    """Parse and check the header of ``data``; ``DecodeError`` on anything malformed."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise DecodeError(f"expected bytes, got {type(data).__name__}")
    data = bytes(data)
    size = len(data)
    if size > HARD_CAP_BYTES:
        raise DecodeError(f"datagram of {size} bytes exceeds the {HARD_CAP_BYTES}-byte cap")
    if size < _HEADER_MIN_BYTES + TAG_BYTES:
        raise DecodeError(
            f"truncated datagram: {size} bytes, header and tag need at least "
            f"{_HEADER_MIN_BYTES + TAG_BYTES}"
        )
    magic, version, flags = _FIXED.unpack_from(data)
    if magic != MAGIC:
        raise DecodeError(f"bad magic {magic!r}, expected {MAGIC!r}")
    if version != SCHEMA_VERSION:
        raise DecodeError(f"unknown schema version {version}, this build reads {SCHEMA_VERSION}")
    if flags & ~_FLAGS_KNOWN:
        raise DecodeError(f"unknown flag bits 0x{flags & ~_FLAGS_KNOWN:02x}")
    if flags & _FLAG_SIGNED and flags & _FLAG_PAIRWISE:
        raise DecodeError("flags 0x04 (signed) and 0x10 (pairwise) together")
    trailer = SIGNATURE_BYTES if flags & _FLAG_SIGNED else TAG_BYTES
    if size < _HEADER_MIN_BYTES + trailer:
        raise DecodeError(
            f"truncated datagram: {size} bytes, header and signature need at least "
            f"{_HEADER_MIN_BYTES + trailer}"
        )
    end = size - trailer
    pos = HEADER_FIXED_BYTES
    fleet_id, pos = _read_varint(data, pos, end)
    sender_id, pos = _read_varint(data, pos, end)
    boot_epoch, pos = _read_varint(data, pos, end)
    sequence, pos = _read_varint(data, pos, end)
    for name, value, top in (
        ("fleet id", fleet_id, _U16_MAX),
        ("sender id", sender_id, _U16_MAX),
        ("boot epoch", boot_epoch, _U32_MAX),
        ("sequence", sequence, _U32_MAX),
    ):
        if value > top:
            raise DecodeError(f"{name} {value} exceeds {top}")
    round_, pos = _read_varint(data, pos, end)
    stamp_ns, pos = _read_varint(data, pos, end)
    n_sep, pos = _read_varint(data, pos, end)
    n_obj, pos = _read_varint(data, pos, end)
    n_init, pos = _read_varint(data, pos, end)
    done_count = None
    if flags & _FLAG_STATUS:
        done_count, pos = _read_varint(data, pos, end)
        if done_count > DONE_COUNT_MAX:
            raise DecodeError(f"done count {done_count} exceeds {DONE_COUNT_MAX}")
    dim = 3 if flags & _FLAG_DIM3 else 2
    # Every entry takes at least 2 id bytes and a pose (a delta value in the delta layout);
    # counts beyond that are lies.
    least = dl.value_bytes(geo.dof(dim)) if flags & _FLAG_DELTA else pose_bytes(dim)
    if (n_sep + n_obj + n_init) * (2 + least) > end - pos:
        raise DecodeError(
            f"entry counts {n_sep}/{n_obj}/{n_init} do not fit in the {end - pos} bytes left"
        )
    return Header(
        version,
        dim,
        fleet_id,
        sender_id,
        boot_epoch,
        sequence,
        round_,
        stamp_ns,
        n_sep,
        n_obj,
        n_init,
        pos,
        bool(flags & _FLAG_DELTA),
        bool(flags & _FLAG_SIGNED),
        done_count,
        bool(flags & _FLAG_PAIRWISE),
    )


# --------------------------------------------------------------------------- decode
def _read_base_round(data: bytes, pos: int, end: int, h: Header,
                     is_delta: bool) -> tuple[int | None, int]:
    """A delta entry's ``back`` varint as the round of its base; (base round, new pos).
    An absolute entry has none: (None, pos)."""
    if not is_delta:
        return None, pos
    back, pos = _read_varint(data, pos, end)
    if back == 0 or back > h.round:
        raise DecodeError(f"delta base {back} rounds back from round {h.round}")
    return h.round - back, pos


@dataclass(frozen=True)
class _Ids:
    sep: list
    obj: list
    init: list
    sep_end: int
    obj_end: int
    end: int
    init_value_bytes: int
    sep_value_bytes: int = -1
    obj_value_bytes: int = -1
    #: per separator / object / init entry: round of the delta's base (None: absolute value)
    sep_base: tuple = ()
    obj_base: tuple = ()
    init_base: tuple = ()


def _walk_ids(data: bytes, h: Header) -> _Ids:
    """Parse the id section and check the value block's length against the counts."""
    end = len(data) - h.trailer_bytes
    pos = h.body_offset
    P = pose_bytes(h.dim)
    DP = dl.value_bytes(geo.dof(h.dim))
    sep_ids = []
    sep_base: list = []
    sep_bytes = 0
    for _ in range(h.n_separators):
        owner, pos = _read_varint(data, pos, end)
        kf, pos = _read_varint(data, pos, end)
        is_delta = False
        if h.delta:
            owner, is_delta = owner >> 1, bool(owner & 1)
        stamp = -1  # a delta entry's stamp is the one its key was first sent with
        if not is_delta:
            dstamp, pos = _read_varint(data, pos, end)
            stamp = h.stamp_ns + _unzigzag(dstamp)
            if stamp < 0:
                raise DecodeError(f"separator stamp {stamp} ns is negative")
        base, pos = _read_base_round(data, pos, end, h, is_delta)
        sep_base.append(base)
        sep_bytes += P if base is None else DP
        sep_ids.append((owner, kf, stamp))
    sep_id_end = pos
    obj_ids = []
    obj_base: list = []
    obj_bytes = 0
    for _ in range(h.n_objects):
        oid, pos = _read_varint(data, pos, end)
        origin, pos = _read_varint(data, pos, end)
        hops, pos = _read_varint(data, pos, end)
        support, pos = _read_varint(data, pos, end)
        if support > _U16_MAX:
            raise DecodeError(f"object support {support} exceeds {_U16_MAX}")
        is_delta = False
        if h.delta:
            origin, is_delta = origin >> 1, bool(origin & 1)
        base, pos = _read_base_round(data, pos, end, h, is_delta)
        obj_base.append(base)
        obj_bytes += P if base is None else DP
        obj_ids.append((oid, origin, hops, support))
    obj_id_end = pos
    init_ids = []
    init_base: list = []
    init_bytes = 0
    for _ in range(h.n_init):
        if pos >= end:
            raise DecodeError(f"truncated init entry at byte {pos}")
        stage = data[pos]
        pos += 1
        is_delta = h.delta and bool(stage & _INIT_DELTA_BIT)
        if h.delta:
            stage &= ~_INIT_DELTA_BIT
        if stage not in _STAGES:
            raise DecodeError(f"unknown init stage {stage}")
        stage = InitStage(stage)
        owner, pos = _read_varint(data, pos, end)
        kf, pos = _read_varint(data, pos, end)
        init_ids.append((InitStage(stage), owner, kf))
        base, pos = _read_base_round(data, pos, end, h, is_delta)
        init_base.append(base)
        if base is not None:
            init_bytes += dl.value_bytes(h.dim * h.dim if stage.matrix_valued else geo.dof(h.dim))
        else:
            init_bytes += _rotation_value_bytes(h.dim) if stage.matrix_valued else P
    sep_obj_bytes = sep_bytes + obj_bytes
    if end - pos != sep_obj_bytes + init_bytes:
        raise DecodeError(
            f"value block is {end - pos} bytes, counts "
            f"{h.n_separators}/{h.n_objects}/{h.n_init} need {sep_obj_bytes + init_bytes}"
        )
    return _Ids(sep_ids, obj_ids, init_ids, sep_id_end, obj_id_end, pos, init_bytes, sep_bytes,
                obj_bytes, tuple(sep_base), tuple(obj_base), tuple(init_base))


def _kind_split(h: Header, ids: _Ids) -> dict[str, int]:
    return {
        KIND_HEADER: h.body_offset + h.trailer_bytes,
        KIND_SEPARATOR: ids.sep_end - h.body_offset + ids.sep_value_bytes,
        KIND_OBJECT: ids.obj_end - ids.sep_end + ids.obj_value_bytes,
        KIND_INIT: ids.end - ids.obj_end + ids.init_value_bytes,
    }


def _read_delta(data: bytes, pos: int, n: int) -> tuple[int, np.ndarray]:
    e = struct.unpack_from("<b", data, pos)[0]
    q = np.frombuffer(data, dtype=np.int8, count=n, offset=pos + 1)
    if e > 0:  # an encoder sends changes up to dl.MAX_DELTA = 1, so e <= -6
        raise DecodeError(f"delta exponent {e} is out of range")
    if np.any(q == -128):
        raise DecodeError("delta component -128 is outside the symmetric int8 range")
    return e, q


def decode_datagram(data: bytes, delta: dl.DeltaDecoder | None = None) -> NeighbourMessage:
    """Decode one datagram alone into a ``NeighbourMessage`` carrying its entries.

    ``fleet_id``, ``boot_epoch`` and ``sequence`` are filled; ``extra`` holds
    ``datagram_bytes``, ``bytes_by_kind`` and ``delta_unresolved``. The tag is not checked here
    (see auth). Delta entries (flag 0x02) are rebuilt with ``delta``, the receiving side of
    this link; one whose base is not held (or any, without ``delta``) is left out and counted.
    """
    h = decode_header(data)
    data = bytes(data)
    dim = h.dim
    P = pose_bytes(dim)
    dof = geo.dof(dim)
    ids = _walk_ids(data, h)
    pos = ids.end
    unresolved = 0

    def delta_value(key, kind, base_round, n):
        nonlocal pos, unresolved
        e, q = _read_delta(data, pos, n)
        pos += dl.value_bytes(n)
        if delta is None:
            unresolved += 1
            return None
        before = delta.unresolved
        value = delta.resolve(key, kind, base_round, e, q, h.round)
        unresolved += delta.unresolved - before
        return value

    def poses(keys: list, bases: tuple, stamps: list) -> list:
        """Separator or object poses: one batch without deltas, else entry by entry."""
        nonlocal pos
        if not h.delta:
            out = list(_decode_poses(data[pos : pos + len(keys) * P], dim))
            pos += len(keys) * P
            return out
        out = []
        for key, base, stamp in zip(keys, bases, stamps):
            if base is None:
                T = _decode_poses(data[pos : pos + P], dim)[0]
                pos += P
                if delta is not None:
                    delta.absolute(key, T, h.round, stamp)
            else:
                T = delta_value(key, dl.POSE, base, dof)
            out.append(T)
        return out

    sep_keys = [("s", owner, kf) for owner, kf, _ in ids.sep]
    sep_T = poses(sep_keys, ids.sep_base, [stamp for *_, stamp in ids.sep])
    for k, base in enumerate(ids.sep_base if h.delta else ()):
        if base is not None and sep_T[k] is not None:  # a delta entry's stamp: its key's
            ids.sep[k] = (*ids.sep[k][:2], delta.stamp(sep_keys[k]))
    obj_T = poses([("o", oid) for oid, *_ in ids.obj], ids.obj_base,
                  [None] * len(ids.obj))
    init_values: list = []
    bases = ids.init_base if h.delta else (None,) * len(ids.init)
    for (stage, owner, kf), base in zip(ids.init, bases):
        key = ("i", int(stage), owner, kf)
        rotation = stage.matrix_valued
        if base is not None:
            kind, n = (dl.LINEAR, dim * dim) if rotation else (dl.POSE, dof)
            init_values.append(delta_value(key, kind, base, n))
            continue
        if rotation:
            nb = _rotation_value_bytes(dim)
            v = np.frombuffer(data, dtype="<f4", count=dim * dim, offset=pos).astype(np.float64)
            if not np.all(np.isfinite(v)):
                raise DecodeError("init rotation value is NaN or inf")
            v = v.reshape(dim, dim)
        else:
            nb = P
            v = _decode_poses(data[pos : pos + P], dim)[0]
        pos += nb
        if h.delta and delta is not None:
            delta.absolute(key, v, h.round)
        init_values.append(v)
    separators = tuple(
        SeparatorEntry(owner, kf, stamp, sep_T[i])
        for i, (owner, kf, stamp) in enumerate(ids.sep) if sep_T[i] is not None
    )
    objects = tuple(
        ObjectEntry(oid, obj_T[i], origin, hops, support)
        for i, (oid, origin, hops, support) in enumerate(ids.obj) if obj_T[i] is not None
    )
    init = tuple(
        InitEntry(stage, owner, kf, init_values[i])
        for i, (stage, owner, kf) in enumerate(ids.init) if init_values[i] is not None
    )
    by_kind = _kind_split(h, ids)
    return NeighbourMessage(
        sender_id=h.sender_id,
        round=h.round,
        stamp_ns=h.stamp_ns,
        separators=separators,
        objects=objects,
        init=init,
        fleet_id=h.fleet_id,
        boot_epoch=h.boot_epoch,
        sequence=h.sequence,
        done_count=h.done_count,
        extra={"datagram_bytes": len(data), "bytes_by_kind": by_kind, "dim": dim,
               "delta_unresolved": unresolved},
    )


def bytes_by_kind(data: bytes) -> dict[str, int]:
    """Split a datagram's length over ``KINDS`` (header and ids parsed, values not decoded);
    a malformed one counts as ``{"malformed": n}``."""
    try:
        h = decode_header(data)
        return _kind_split(h, _walk_ids(bytes(data), h))
    except DecodeError:
        return {"malformed": len(data)}


# --------------------------------------------------------------------------- encode
@dataclass(frozen=True)
class EncodedDatagram:
    """One datagram with its sequence number and byte accounting."""

    data: bytes
    sequence: int
    bytes_by_kind: dict


def _delta_bytes(e: int, q: np.ndarray) -> bytes:
    return struct.pack("<b", e) + q.astype(np.int8).tobytes()


def _entry_records(message: NeighbourMessage, dim: int, delta: dl.DeltaEncoder | None = None):
    """Per entry: kind, id bytes, value bytes (values encoded in batches). With ``delta`` (the
    sending side of this link) the delta layout is used and ``delta`` is updated."""
    kinds: list[str] = []
    ids: list[bytes] = []
    P = pose_bytes(dim)
    values: list[bytes] = []
    stamp = message.stamp_ns
    rnd = int(message.round)
    n_sep = len(message.separators)
    poses = [e.T_world_body for e in message.separators] + [
        e.T_world_object for e in message.objects
    ]
    if poses:
        T = np.asarray(poses, dtype=np.float64)
        _check_poses(T, dim, "separator/object")
        block = _encode_poses(T, dim)
        values.extend(block[i * P : (i + 1) * P] for i in range(len(poses)))
        if delta is not None:
            decoded = _decode_poses(block, dim)  # what the receiver holds after absolute ones

    def as_delta(key: tuple, kind: str, value: np.ndarray, held_if_absolute: Callable):
        """Plan one entry on ``delta``: None (send it absolute; ``held_if_absolute()`` is what
        the receiver will hold) or (back, delta value bytes)."""
        plan = delta.plan(key, kind, value, rnd)
        if plan is None:
            delta.sent_absolute(key, held_if_absolute(), rnd)
            return None
        base_round, ex, q, rebuilt = plan
        delta.sent_delta(key, rebuilt, rnd)
        return rnd - base_round, _delta_bytes(ex, q)

    for k, e in enumerate(message.separators):
        if e.stamp_ns < 0:
            raise EncodeError(f"separator stamp_ns must be >= 0, got {e.stamp_ns}")
        kinds.append(KIND_SEPARATOR)
        if delta is None:
            ids.append(
                _varint(int(e.owner_robot))
                + _varint(int(e.keyframe_id))
                + _varint(_zigzag(int(e.stamp_ns) - stamp))
            )
            continue
        key = ("s", int(e.owner_robot), int(e.keyframe_id))
        d = as_delta(key, dl.POSE, np.asarray(e.T_world_body, np.float64), lambda k=k: decoded[k])
        kf = _varint(int(e.keyframe_id))
        if d is None:
            ids.append(_varint(int(e.owner_robot) << 1) + kf
                       + _varint(_zigzag(int(e.stamp_ns) - stamp)))
        else:
            ids.append(_varint((int(e.owner_robot) << 1) | 1) + kf + _varint(d[0]))
            values[k] = d[1]
    for k, e in enumerate(message.objects, start=n_sep):
        kinds.append(KIND_OBJECT)
        if delta is None:
            ids.append(
                _varint(int(e.object_id)) + _varint(int(e.origin_robot)) + _varint(int(e.hop_count))
                + _varint(_support(e))
            )
            continue
        d = as_delta(("o", int(e.object_id)), dl.POSE, np.asarray(e.T_world_object, np.float64),
                     lambda k=k: decoded[k])
        oid = _varint(int(e.object_id))
        hops_support = _varint(int(e.hop_count)) + _varint(_support(e))
        if d is None:
            ids.append(oid + _varint(int(e.origin_robot) << 1) + hops_support)
        else:
            ids.append(oid + _varint((int(e.origin_robot) << 1) | 1) + hops_support + _varint(d[0]))
            values[k] = d[1]
    assert len(ids) == len(values) and n_sep <= len(ids)
    for e in message.init:
        stage = InitStage(e.stage)
        v = np.asarray(e.value, dtype=np.float64)
        rotation = stage.matrix_valued
        if rotation:
            if v.shape != (dim, dim):
                raise EncodeError(f"init rotation value: expected ({dim}, {dim}), got {v.shape}")
            if not np.all(np.isfinite(v)) or np.abs(v).max(initial=0.0) > 3.0e38:
                raise EncodeError("init rotation value is NaN, inf or beyond float32")
            value = v.astype("<f4").tobytes()
        else:
            _check_poses(v[None], dim, "init translation")
            value = _encode_poses(v[None], dim)
        kinds.append(KIND_INIT)
        who = _varint(int(e.owner_robot)) + _varint(int(e.keyframe_id))
        if delta is None:
            ids.append(bytes([int(stage)]) + who)
            values.append(value)
            continue
        key = ("i", int(stage), int(e.owner_robot), int(e.keyframe_id))
        d = as_delta(key, dl.LINEAR if rotation else dl.POSE, v,
                     lambda value=value, rotation=rotation: (
                         np.frombuffer(value, "<f4").astype(np.float64).reshape(dim, dim)
                         if rotation else _decode_poses(value, dim)[0]))
        if d is None:
            ids.append(bytes([int(stage)]) + who)
            values.append(value)
        else:
            ids.append(bytes([int(stage) | _INIT_DELTA_BIT]) + who + _varint(d[0]))
            values.append(d[1])
    return kinds, ids, values


def _message_dim(message: NeighbourMessage) -> int:
    dim = message.dim
    if dim is None:
        for e in message.init:
            v = np.asarray(e.value)
            return v.shape[-1] if InitStage(e.stage).matrix_valued else v.shape[-1] - 1
        return 3
    if dim not in (2, 3):
        raise EncodeError(f"poses must be SE(2) or SE(3), got dimension {dim}")
    return dim


def encode_datagrams(
    message: NeighbourMessage,
    *,
    fleet_id: int,
    boot_epoch: int,
    first_sequence: int,
    max_datagram_bytes: int = DEFAULT_MAX_DATAGRAM_BYTES,
    delta: dl.DeltaEncoder | None = None,
    signed: bool = False,
    pairwise: bool = False,
) -> list[EncodedDatagram]:
    """Encode ``message`` into datagrams of at most ``max_datagram_bytes`` each.

    Entries keep their order (separators, objects, init) and fill datagrams greedily; datagram
    k gets sequence ``first_sequence + k``. An entry-less message gives one header-only
    datagram (a heartbeat). The tag slot is zero; sign with ``auth.Signer``. With ``delta``
    (the sending side of the one link this message goes over) the delta layout (flag 0x02) is
    used: separator and init entries become quantised changes where ``delta`` allows.
    ``signed``: flag 0x04 and a ``SIGNATURE_BYTES`` slot for ``auth.Ed25519Signer`` instead of
    the ``TAG_BYTES`` HMAC slot (docs/wire-format.md). ``pairwise``: flag 0x10, the tag slot is
    for ``comms.pairwise`` (one datagram per receiver).
    """
    if signed and pairwise:
        raise EncodeError("a datagram is either signed or pairwise-tagged, not both")
    if not MIN_DATAGRAM_BYTES <= max_datagram_bytes <= HARD_CAP_BYTES:
        raise EncodeError(
            f"max_datagram_bytes must be in [{MIN_DATAGRAM_BYTES}, "
            f"{HARD_CAP_BYTES}], got {max_datagram_bytes}"
        )
    for name, value, top in (
        ("fleet_id", fleet_id, _U16_MAX),
        ("sender_id", message.sender_id, _U16_MAX),
        ("boot_epoch", boot_epoch, _U32_MAX),
    ):
        if not 0 <= int(value) <= top:
            raise EncodeError(f"{name} must be in [0, {top}], got {value}")
    if message.round < 0 or message.stamp_ns < 0:
        raise EncodeError(
            f"round and stamp_ns must be >= 0, got {message.round}, {message.stamp_ns}"
        )
    dim = _message_dim(message)
    kinds, ids, values = _entry_records(message, dim, delta)
    n = len(kinds)
    done = message.done_count
    if done is not None and not 0 <= int(done) <= DONE_COUNT_MAX:
        raise EncodeError(f"done_count must be in [0, {DONE_COUNT_MAX}], got {done}")
    status = b"" if done is None else _varint(int(done))
    flags = (
        (_FLAG_DIM3 if dim == 3 else 0)
        | (_FLAG_DELTA if delta is not None else 0)
        | (_FLAG_SIGNED if signed else 0)
        | (_FLAG_STATUS if done is not None else 0)
        | (_FLAG_PAIRWISE if pairwise else 0)
    )
    trailer = SIGNATURE_BYTES if signed else TAG_BYTES
    ident = (
        _FIXED.pack(MAGIC, SCHEMA_VERSION, flags)
        + _varint(fleet_id)
        + _varint(int(message.sender_id))
        + _varint(boot_epoch)
    )
    when = _varint(int(message.round)) + _varint(int(message.stamp_ns))
    # The sequence is reserved at 5 varint bytes (u32) and the counts at 2 each (< 16384
    # entries per datagram, guaranteed by the size cap), so packing never overshoots.
    budget = max_datagram_bytes - len(ident) - 5 - len(when) - 6 - len(status) - trailer
    groups: list[tuple[int, int]] = []
    start = 0
    used = 0
    for i in range(n):
        size = len(ids[i]) + len(values[i])
        if size > budget:
            raise EncodeError(f"one {kinds[i]} entry of {size} bytes exceeds the datagram budget")
        if used + size > budget:
            groups.append((start, i))
            start, used = i, 0
        used += size
    groups.append((start, n))
    last_sequence = first_sequence + len(groups) - 1
    if first_sequence < 0 or last_sequence > _U32_MAX:
        raise EncodeError(f"sequence numbers {first_sequence}..{last_sequence} leave [0, 2^32)")
    out = []
    for k, (a, b) in enumerate(groups):
        n_sep = sum(1 for x in kinds[a:b] if x == KIND_SEPARATOR)
        n_obj = sum(1 for x in kinds[a:b] if x == KIND_OBJECT)
        n_init = (b - a) - n_sep - n_obj
        head = (
            ident
            + _varint(first_sequence + k)
            + when
            + _varint(n_sep)
            + _varint(n_obj)
            + _varint(n_init)
            + status
        )
        data = b"".join([head, *ids[a:b], *values[a:b], bytes(trailer)])
        by_kind = dict.fromkeys(KINDS, 0)
        by_kind[KIND_HEADER] = len(head) + trailer
        for i in range(a, b):
            by_kind[kinds[i]] += len(ids[i]) + len(values[i])
        assert len(data) <= max_datagram_bytes
        out.append(EncodedDatagram(data, first_sequence + k, by_kind))
    return out


def encode_message(message: NeighbourMessage, **kwargs) -> list[bytes]:
    """``encode_datagrams`` returning only the bytes (same keyword arguments)."""
    return [d.data for d in encode_datagrams(message, **kwargs)]


@dataclass(frozen=True)
class ByteCount:
    """What a message costs on the wire."""

    datagrams: int
    total_bytes: int
    bytes_by_kind: dict


def encoded_size(
    message: NeighbourMessage,
    *,
    max_datagram_bytes: int = DEFAULT_MAX_DATAGRAM_BYTES,
    signed: bool = False,
) -> ByteCount:
    """Datagrams and bytes ``message`` takes (sequence/epoch values do not change the size)."""
    grams = encode_datagrams(
        message, fleet_id=0, boot_epoch=0, first_sequence=0,
        max_datagram_bytes=max_datagram_bytes, signed=signed,
    )
    return ByteCount(
        len(grams), sum(len(g.data) for g in grams), sum_kinds(g.bytes_by_kind for g in grams)
    )


def sum_kinds(parts: Iterable[dict]) -> dict:
    """Add up ``bytes_by_kind`` dictionaries."""
    total: dict = {}
    for p in parts:
        for k, v in p.items():
            total[k] = total.get(k, 0) + v
    return total
