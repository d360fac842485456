"""Decoding side of the wire codec (``dran_edge.comms.codec``): the id section walk, the value
block (absolute poses, rotations and deltas) and the ``NeighbourMessage`` it becomes."""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from dran_edge.comms import delta as dl
from dran_edge.comms.wire_header import (
    _INIT_DELTA_BIT,
    _STAGES,
    KIND_HEADER,
    KIND_INIT,
    KIND_OBJECT,
    KIND_SEPARATOR,
    Header,
    decode_header,
)
from dran_edge.comms.wire_values import (
    _U16_MAX,
    _decode_poses,
    _read_varint,
    _rotation_value_bytes,
    _unzigzag,
    pose_bytes,
)

from dran_edge import geometry as geo
from dran_edge.errors import DecodeError
from dran_edge.messages import InitEntry, InitStage, NeighbourMessage, ObjectEntry, SeparatorEntry


def _read_base_round(
    data: bytes, pos: int, end: int, h: Header, is_delta: bool
) -> tuple[int | None, int]:
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
    # Long: the id section of docs/wire-format.md, one entry kind after the other.
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
        if stage.valueless:
            if base is not None:
                raise DecodeError(f"init stage {stage.name} cannot be a delta")
        elif base is not None:
            init_bytes += dl.value_bytes(h.dim * h.dim if stage.matrix_valued else geo.dof(h.dim))
        else:
            init_bytes += _rotation_value_bytes(h.dim) if stage.matrix_valued else P
    sep_obj_bytes = sep_bytes + obj_bytes
    if end - pos != sep_obj_bytes + init_bytes:
        raise DecodeError(
            f"value block is {end - pos} bytes, counts "
            f"{h.n_separators}/{h.n_objects}/{h.n_init} need {sep_obj_bytes + init_bytes}"
        )
    return _Ids(
        sep_ids,
        obj_ids,
        init_ids,
        sep_id_end,
        obj_id_end,
        pos,
        init_bytes,
        sep_bytes,
        obj_bytes,
        tuple(sep_base),
        tuple(obj_base),
        tuple(init_base),
    )


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


class _ValueReader:
    """Reads one datagram's value block in entry order; with ``delta`` (the receiving side of
    this link) delta entries are rebuilt and absolute ones recorded as future bases."""

    def __init__(self, data: bytes, h: Header, pos: int, delta: dl.DeltaDecoder | None):
        self.data = data
        self.h = h
        self.pos = pos
        self.delta = delta
        self.P = pose_bytes(h.dim)
        self.dof = geo.dof(h.dim)
        #: delta entries left out (base not held, or no ``delta``)
        self.unresolved = 0

    def delta_value(self, key, kind, base_round, n):
        e, q = _read_delta(self.data, self.pos, n)
        self.pos += dl.value_bytes(n)
        if self.delta is None:
            self.unresolved += 1
            return None
        before = self.delta.unresolved
        value = self.delta.resolve(key, kind, base_round, e, q, self.h.round)
        self.unresolved += self.delta.unresolved - before
        return value

    def poses(self, keys: list, bases: tuple, stamps: list) -> list:
        """Separator or object poses: one batch without deltas, else entry by entry."""
        data, P, dim = self.data, self.P, self.h.dim
        if not self.h.delta:
            out = list(_decode_poses(data[self.pos : self.pos + len(keys) * P], dim))
            self.pos += len(keys) * P
            return out
        out = []
        for key, base, stamp in zip(keys, bases, stamps):
            if base is None:
                T = _decode_poses(data[self.pos : self.pos + P], dim)[0]
                self.pos += P
                if self.delta is not None:
                    self.delta.absolute(key, T, self.h.round, stamp)
            else:
                T = self.delta_value(key, dl.POSE, base, self.dof)
            out.append(T)
        return out

    def init_value(self, stage: InitStage, owner: int, kf: int, base: int | None):
        """One init entry's value: a rotation (``stage.matrix_valued``) or a pose."""
        if stage.valueless:
            return np.zeros(0)
        key = ("i", int(stage), owner, kf)
        dim = self.h.dim
        rotation = stage.matrix_valued
        if base is not None:
            kind, n = (dl.LINEAR, dim * dim) if rotation else (dl.POSE, self.dof)
            return self.delta_value(key, kind, base, n)
        if rotation:
            nb = _rotation_value_bytes(dim)
            v = np.frombuffer(self.data, dtype="<f4", count=dim * dim, offset=self.pos).astype(
                np.float64
            )
            if not np.all(np.isfinite(v)):
                raise DecodeError("init rotation value is NaN or inf")
            v = v.reshape(dim, dim)
        else:
            nb = self.P
            v = _decode_poses(self.data[self.pos : self.pos + self.P], dim)[0]
        self.pos += nb
        if self.h.delta and self.delta is not None:
            self.delta.absolute(key, v, self.h.round)
        return v


def decode_datagram(data: bytes, delta: dl.DeltaDecoder | None = None) -> NeighbourMessage:
    """Decode one datagram alone into a ``NeighbourMessage`` carrying its entries.

    ``fleet_id``, ``boot_epoch`` and ``sequence`` are filled; ``extra`` holds
    ``datagram_bytes``, ``bytes_by_kind`` and ``delta_unresolved``. The tag is not checked here
    (see auth). Delta entries (flag 0x02) are rebuilt with ``delta``, the receiving side of
    this link; one whose base is not held (or any, without ``delta``) is left out and counted.
    """
    h = decode_header(data)
    data = bytes(data)
    ids = _walk_ids(data, h)
    reader = _ValueReader(data, h, ids.end, delta)
    sep_keys = [("s", owner, kf) for owner, kf, _ in ids.sep]
    sep_T = reader.poses(sep_keys, ids.sep_base, [stamp for *_, stamp in ids.sep])
    for k, base in enumerate(ids.sep_base if h.delta else ()):
        if base is not None and sep_T[k] is not None:  # a delta entry's stamp: its key's
            ids.sep[k] = (*ids.sep[k][:2], delta.stamp(sep_keys[k]))
    obj_T = reader.poses([("o", oid) for oid, *_ in ids.obj], ids.obj_base, [None] * len(ids.obj))
    bases = ids.init_base if h.delta else (None,) * len(ids.init)
    init_values = [
        reader.init_value(stage, owner, kf, base)
        for (stage, owner, kf), base in zip(ids.init, bases)
    ]
    return _message(h, ids, sep_T, obj_T, init_values, len(data), reader.unresolved)


def _message(
    h: Header, ids: _Ids, sep_T: list, obj_T: list, init_values: list, n_bytes: int, unresolved: int
) -> NeighbourMessage:
    """The decoded entries (those with a value) as a ``NeighbourMessage``."""
    separators = tuple(
        SeparatorEntry(owner, kf, stamp, sep_T[i])
        for i, (owner, kf, stamp) in enumerate(ids.sep)
        if sep_T[i] is not None
    )
    objects = tuple(
        ObjectEntry(oid, obj_T[i], origin, hops, support)
        for i, (oid, origin, hops, support) in enumerate(ids.obj)
        if obj_T[i] is not None
    )
    init = tuple(
        InitEntry(stage, owner, kf, init_values[i])
        for i, (stage, owner, kf) in enumerate(ids.init)
        if init_values[i] is not None
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
        extra={
            "datagram_bytes": n_bytes,
            "bytes_by_kind": by_kind,
            "dim": h.dim,
            "delta_unresolved": unresolved,
        },
    )


def bytes_by_kind(data: bytes) -> dict[str, int]:
    """Split a datagram's length over ``KINDS`` (header and ids parsed, values not decoded);
    a malformed one counts as ``{"malformed": n}``."""
    try:
        h = decode_header(data)
        return _kind_split(h, _walk_ids(bytes(data), h))
    except DecodeError:
        return {"malformed": len(data)}
