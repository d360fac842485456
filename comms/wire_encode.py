"""Encoding side of the wire codec (``dran_edge.comms.codec``): a ``NeighbourMessage``'s entries
as id and value records (absolute or, with a ``DeltaEncoder``, delta), packed greedily into
datagrams with full headers (layout in docs/wire-format.md)."""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from dran_edge.comms import delta as dl
from dran_edge.comms.wire_header import (
    _FIXED,
    _FLAG_DELTA,
    _FLAG_DIM3,
    _FLAG_PAIRWISE,
    _FLAG_SIGNED,
    _FLAG_STATUS,
    _INIT_DELTA_BIT,
    DEFAULT_MAX_DATAGRAM_BYTES,
    DONE_COUNT_MAX,
    HARD_CAP_BYTES,
    KIND_HEADER,
    KIND_INIT,
    KIND_OBJECT,
    KIND_SEPARATOR,
    KINDS,
    MAGIC,
    MIN_DATAGRAM_BYTES,
    SCHEMA_VERSION,
    SIGNATURE_BYTES,
    TAG_BYTES,
)
from dran_edge.comms.wire_values import (
    _U16_MAX,
    _U32_MAX,
    EncodeError,
    _check_poses,
    _decode_poses,
    _encode_poses,
    _varint,
    _zigzag,
    pose_bytes,
)

from dran_edge.messages import InitStage, NeighbourMessage, ObjectEntry


def _support(e: ObjectEntry) -> int:
    support = int(e.support)
    if not 0 <= support <= _U16_MAX:
        raise EncodeError(
            f"object {e.object_id}: support must be in [0, {_U16_MAX}], got {support}"
        )
    return support


@dataclass(frozen=True)
class EncodedDatagram:
    """One datagram with its sequence number and byte accounting."""

    data: bytes
    sequence: int
    bytes_by_kind: dict


def _delta_bytes(e: int, q: np.ndarray) -> bytes:
    return struct.pack("<b", e) + q.astype(np.int8).tobytes()


class _EntryRecords:
    """Per entry: kind, id bytes, value bytes (separator and object poses encoded in one batch).
    With ``delta`` (the sending side of this link) the delta layout is used and ``delta`` is
    updated entry by entry."""

    def __init__(self, message: NeighbourMessage, dim: int, delta: dl.DeltaEncoder | None):
        self.dim = dim
        self.delta = delta
        self.stamp = message.stamp_ns
        self.rnd = int(message.round)
        self.kinds: list[str] = []
        self.ids: list[bytes] = []
        self.values: list[bytes] = []
        P = pose_bytes(dim)
        poses = [e.T_world_body for e in message.separators] + [
            e.T_world_object for e in message.objects
        ]
        if poses:
            T = np.asarray(poses, dtype=np.float64)
            _check_poses(T, dim, "separator/object")
            block = _encode_poses(T, dim)
            self.values.extend(block[i * P : (i + 1) * P] for i in range(len(poses)))
            if delta is not None:
                # what the receiver holds after absolute ones
                self.decoded = _decode_poses(block, dim)

    def as_delta(self, key: tuple, kind: str, value: np.ndarray, held_if_absolute: Callable):
        """Plan one entry on ``delta``: None (send it absolute; ``held_if_absolute()`` is what
        the receiver will hold) or (back, delta value bytes)."""
        assert self.delta is not None
        plan = self.delta.plan(key, kind, value, self.rnd)
        if plan is None:
            self.delta.sent_absolute(key, held_if_absolute(), self.rnd)
            return None
        base_round, ex, q, rebuilt = plan
        self.delta.sent_delta(key, rebuilt, self.rnd)
        return self.rnd - base_round, _delta_bytes(ex, q)

    def separator(self, k: int, e) -> None:
        if e.stamp_ns < 0:
            raise EncodeError(f"separator stamp_ns must be >= 0, got {e.stamp_ns}")
        self.kinds.append(KIND_SEPARATOR)
        if self.delta is None:
            self.ids.append(
                _varint(int(e.owner_robot))
                + _varint(int(e.keyframe_id))
                + _varint(_zigzag(int(e.stamp_ns) - self.stamp))
            )
            return
        key = ("s", int(e.owner_robot), int(e.keyframe_id))
        d = self.as_delta(
            key, dl.POSE, np.asarray(e.T_world_body, np.float64), lambda: self.decoded[k]
        )
        kf = _varint(int(e.keyframe_id))
        if d is None:
            self.ids.append(
                _varint(int(e.owner_robot) << 1)
                + kf
                + _varint(_zigzag(int(e.stamp_ns) - self.stamp))
            )
        else:
            self.ids.append(_varint((int(e.owner_robot) << 1) | 1) + kf + _varint(d[0]))
            self.values[k] = d[1]

    def object(self, k: int, e: ObjectEntry) -> None:
        self.kinds.append(KIND_OBJECT)
        if self.delta is None:
            self.ids.append(
                _varint(int(e.object_id))
                + _varint(int(e.origin_robot))
                + _varint(int(e.hop_count))
                + _varint(_support(e))
            )
            return
        d = self.as_delta(
            ("o", int(e.object_id)),
            dl.POSE,
            np.asarray(e.T_world_object, np.float64),
            lambda: self.decoded[k],
        )
        oid = _varint(int(e.object_id))
        hops_support = _varint(int(e.hop_count)) + _varint(_support(e))
        if d is None:
            self.ids.append(oid + _varint(int(e.origin_robot) << 1) + hops_support)
        else:
            self.ids.append(
                oid + _varint((int(e.origin_robot) << 1) | 1) + hops_support + _varint(d[0])
            )
            self.values[k] = d[1]

    def init(self, e) -> None:
        dim = self.dim
        stage = InitStage(e.stage)
        if stage.valueless:  # the id fields are the whole entry (never a delta)
            self.kinds.append(KIND_INIT)
            self.ids.append(
                bytes([int(stage)]) + _varint(int(e.owner_robot)) + _varint(int(e.keyframe_id))
            )
            self.values.append(b"")
            return
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
        self.kinds.append(KIND_INIT)
        who = _varint(int(e.owner_robot)) + _varint(int(e.keyframe_id))
        d = None
        if self.delta is not None and stage.delta_allowed:
            key = ("i", int(stage), int(e.owner_robot), int(e.keyframe_id))
            d = self.as_delta(
                key,
                dl.LINEAR if rotation else dl.POSE,
                v,
                lambda: (
                    np.frombuffer(value, "<f4").astype(np.float64).reshape(dim, dim)
                    if rotation
                    else _decode_poses(value, dim)[0]
                ),
            )
        if d is None:
            self.ids.append(bytes([int(stage)]) + who)
            self.values.append(value)
        else:
            self.ids.append(bytes([int(stage) | _INIT_DELTA_BIT]) + who + _varint(d[0]))
            self.values.append(d[1])


def _entry_records(message: NeighbourMessage, dim: int, delta: dl.DeltaEncoder | None = None):
    """Per entry: kind, id bytes, value bytes (values encoded in batches). With ``delta`` (the
    sending side of this link) the delta layout is used and ``delta`` is updated."""
    rec = _EntryRecords(message, dim, delta)
    n_sep = len(message.separators)
    for k, e in enumerate(message.separators):
        rec.separator(k, e)
    for k, e in enumerate(message.objects, start=n_sep):
        rec.object(k, e)
    assert len(rec.ids) == len(rec.values) and n_sep <= len(rec.ids)
    for e in message.init:
        rec.init(e)
    return rec.kinds, rec.ids, rec.values


def _message_dim(message: NeighbourMessage) -> int:
    dim = message.dim
    if dim is None:
        for e in message.init:
            if InitStage(e.stage).valueless:
                continue
            v = np.asarray(e.value)
            return v.shape[-1] if InitStage(e.stage).matrix_valued else v.shape[-1] - 1
        return 3
    if dim not in (2, 3):
        raise EncodeError(f"poses must be SE(2) or SE(3), got dimension {dim}")
    return dim


def _check_header_fields(
    message: NeighbourMessage, fleet_id: int, boot_epoch: int, max_datagram_bytes: int
) -> None:
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


def _groups(
    kinds: list[str], ids: list[bytes], values: list[bytes], budget: int
) -> list[tuple[int, int]]:
    """Entry ranges [a, b) filling datagrams greedily, each within ``budget`` bytes."""
    n = len(kinds)
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
    return groups


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
    _check_header_fields(message, fleet_id, boot_epoch, max_datagram_bytes)
    dim = _message_dim(message)
    kinds, ids, values = _entry_records(message, dim, delta)
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
    groups = _groups(kinds, ids, values, budget)
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
        message,
        fleet_id=0,
        boot_epoch=0,
        first_sequence=0,
        max_datagram_bytes=max_datagram_bytes,
        signed=signed,
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
