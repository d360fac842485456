"""Wire codec for neighbour datagrams: ``NeighbourMessage`` <-> self-contained datagrams.

Layout, precision and CHANGELOG in ``docs/wire-format.md`` (schema version 1).
One round's message may span several datagrams; each carries a full header and a share of the
entries, decodes alone, and is at most ``max_datagram_bytes`` long (default 1200, hard cap
``HARD_CAP_BYTES`` = 4096, far below libzmq's 8192-byte UDP buffer). Bytes are the paper's
headline metric (Table 1), so the layout is built for size:

- header: magic ``DR``, version, flags (4 bytes), then LEB128 varints: fleet id (u16),
  sender id (u16), boot epoch (u32), sequence (u32), round, stamp_ns, three entry counts;
- an id section (varints) for all entries, then one packed value block, then the
  authentication trailer: a 16-byte HMAC tag slot (fleet key, or with flag bit 4,
  ``pairwise=True``, a pair key), or with flag bit 2 (``signed=True``) a 64-byte Ed25519
  signature slot (zeros here; ``dran_edge.comms.auth`` fills and checks it);
- SE(3) pose = float32 translation (12 bytes) + "smallest three" unit quaternion with 23-bit
  components (9 bytes): 21 bytes. SE(2) pose = float32 x, y + 24-bit angle: 11 bytes.
  Worst-case round-trip error: ~3.8e-6 m at 100 m, ~4.4e-7 rad (``tests/test_codec.py``
  measures it; far below the solver's tolerances ε_u = 1e-2, ε_v = 1e-1).

Decoding is strict: anything malformed (truncated, oversized, counts that do not match the
length, NaN/inf, a non-unit quaternion, unknown magic/version/flags/stage, over-long varints)
raises ``DecodeError`` and nothing else.

This module is the codec's public face; the work is split by job: ``wire_values`` (varints and
pose blocks), ``wire_header`` (constants, flags, ``Header``), ``wire_decode`` and
``wire_encode``. Every name callers import from here is re-exported below.
"""

from __future__ import annotations

from dran_edge.comms.wire_decode import bytes_by_kind, decode_datagram
from dran_edge.comms.wire_encode import (
    ByteCount,
    EncodedDatagram,
    encode_datagrams,
    encode_message,
    encoded_size,
    sum_kinds,
)
from dran_edge.comms.wire_header import (
    DEFAULT_MAX_DATAGRAM_BYTES,
    DONE_COUNT_MAX,
    HARD_CAP_BYTES,
    HEADER_FIXED_BYTES,
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
    Header,
    decode_header,
    trailer_bytes,
)

# Varint and pose-block helpers, re-exported for the codec's own tests.
from dran_edge.comms.wire_values import (
    EncodeError,
    _encode_poses,
    _read_varint,
    _varint,
    pose_bytes,
)

__all__ = [
    "DEFAULT_MAX_DATAGRAM_BYTES",
    "DONE_COUNT_MAX",
    "HARD_CAP_BYTES",
    "HEADER_FIXED_BYTES",
    "KIND_HEADER",
    "KIND_INIT",
    "KIND_OBJECT",
    "KIND_SEPARATOR",
    "KINDS",
    "MAGIC",
    "MIN_DATAGRAM_BYTES",
    "SCHEMA_VERSION",
    "SIGNATURE_BYTES",
    "TAG_BYTES",
    "ByteCount",
    "EncodeError",
    "EncodedDatagram",
    "Header",
    "_encode_poses",
    "_read_varint",
    "_varint",
    "bytes_by_kind",
    "decode_datagram",
    "decode_header",
    "encode_datagrams",
    "encode_message",
    "encoded_size",
    "pose_bytes",
    "sum_kinds",
    "trailer_bytes",
]
