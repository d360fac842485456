"""Datagram header of the wire codec (``dran_edge.comms.codec``): constants, flags, the
``Header`` record and its strict parser (layout in docs/wire-format.md)."""

from __future__ import annotations

import struct
from dataclasses import dataclass

from dran_edge.comms import delta as dl
from dran_edge.comms.wire_values import _U16_MAX, _U32_MAX, _read_varint, pose_bytes

from dran_edge import geometry as geo
from dran_edge.errors import DecodeError
from dran_edge.messages import InitStage

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
    # Every separator or object entry takes at least 2 id bytes and a pose (a delta value in
    # the delta layout), every init entry at least 3 id bytes (a valueless ARQ_ACK nothing
    # more); counts beyond that are lies.
    least = dl.value_bytes(geo.dof(dim)) if flags & _FLAG_DELTA else pose_bytes(dim)
    if (n_sep + n_obj) * (2 + least) + 3 * n_init > end - pos:
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
