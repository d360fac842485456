"""Delta entries (comms/delta.py, codec flag 0x02): round trips, loss, strict decoding."""

import struct

import numpy as np
import pytest
from dran_edge.comms import codec
from dran_edge.comms import delta as dl

from dran_edge import geometry as geo
from dran_edge.errors import DecodeError
from dran_edge.messages import InitEntry, InitStage, NeighbourMessage, SeparatorEntry

N = 6


def _message(rnd, T, R):
    seps = tuple(SeparatorEntry(2, 40 + i, 1_000 + i, T[i]) for i in range(N))
    init = tuple(InitEntry(InitStage.ROTATION, 2, 40 + i, R[i]) for i in range(N))
    return NeighbourMessage(2, rnd, rnd * 500_000_000, seps, (), init)


def _walk(rounds, seed=0, step=1e-2):
    """Separator poses and relaxed rotations moving a little each round."""
    rng = np.random.default_rng(seed)
    T = geo.se3_exp(rng.normal(0, 1, (N, 6)))
    R = rng.normal(0, 1, (N, 3, 3))
    for _ in range(rounds):
        T = T @ geo.se3_exp(rng.normal(0, step, (N, 6)))
        R = R + rng.normal(0, step, (N, 3, 3))
        yield T, R


def _encode(msg, enc):
    return codec.encode_datagrams(
        msg, fleet_id=1, boot_epoch=1, first_sequence=msg.round, delta=enc
    )


def test_deltas_rebuild_the_values_within_the_quantisation_bound_in_under_half_the_bytes():
    enc, dec = dl.DeltaEncoder(absolute_every=1000), dl.DeltaDecoder()
    sizes = []
    for rnd, (T, R) in enumerate(_walk(30), start=1):
        grams = _encode(_message(rnd, T, R), enc)
        msg = codec.decode_datagram(grams[0].data, dec)
        assert len(grams) == 1 and msg.extra["delta_unresolved"] == 0
        got_T = np.stack([e.T_world_body for e in msg.separators])
        got_R = np.stack([e.value for e in msg.init])
        assert [e.stamp_ns for e in msg.separators] == [1_000 + i for i in range(N)]
        # each round's error is one quantisation step of that round's change (error feedback:
        # it does not grow over the 30 rounds); a change of ~3e-2 gives steps of ~1.2e-4
        assert np.abs(got_T - T).max() < 5e-4
        assert np.abs(got_R - R).max() < 5e-4
        assert np.allclose(geo.so3_project(got_T[:, :3, :3]), got_T[:, :3, :3], atol=1e-9)
        sizes.append(len(grams[0].data))
    plain = len(
        codec.encode_datagrams(_message(1, T, R), fleet_id=1, boot_epoch=1, first_sequence=1)[
            0
        ].data
    )
    assert sizes[0] == pytest.approx(plain, abs=N)  # first round: absolute values
    assert max(sizes[1:]) < 0.45 * plain  # header and tag included


def test_a_lost_datagram_is_counted_and_repaired_by_the_next_absolute_value():
    enc, dec = dl.DeltaEncoder(absolute_every=5), dl.DeltaDecoder()
    unresolved = []
    for rnd, (T, R) in enumerate(_walk(12), start=1):
        grams = _encode(_message(rnd, T, R), enc)
        if rnd == 3:
            continue  # lost on the link: the sender does not know
        msg = codec.decode_datagram(grams[0].data, dec)
        unresolved.append(msg.extra["delta_unresolved"])
        if msg.separators:
            got = {e.keyframe_id: e.T_world_body for e in msg.separators}
            assert all(np.abs(got[40 + i] - T[i]).max() < 5e-4 for i in range(N))
    # round 4 names round 3 as its base: all 2N entries dropped; round 5 names round 4 (also
    # not held); round 6 is absolute again (every 5 rounds per key) and repairs every key
    assert unresolved == [0, 0, 2 * N, 2 * N, 0, 0, 0, 0, 0, 0, 0]
    assert dec.unresolved == 4 * N


def test_delta_entries_without_link_state_are_left_out_and_counted():
    enc = dl.DeltaEncoder()
    walk = _walk(2)
    _encode(_message(1, *next(walk)), enc)
    data = _encode(_message(2, *next(walk)), enc)[0].data
    msg = codec.decode_datagram(data)  # e.g. a capture inspected offline
    assert msg.separators == () and msg.init == ()
    assert msg.extra["delta_unresolved"] == 2 * N
    assert sum(codec.bytes_by_kind(data).values()) == len(data)


def _delta_gram(owner=2, back=1, exponent=-8, q=(1, 2, 3, -4, 5, -6), rnd=7):
    """A hand-built one-separator delta datagram (layout of docs/wire-format.md)."""
    head = (
        struct.pack("<2sBB", b"DR", codec.SCHEMA_VERSION, 0x01 | 0x02)
        + bytes([1, 2, 1, 9, rnd])
        + bytes([0x80, 0x01])
        + bytes([1, 0, 0])
    )
    ids = bytes([(owner << 1) | 1, 40, back])
    value = struct.pack("<b", exponent) + struct.pack("<6b", *q)
    return head + ids + value + bytes(codec.TAG_BYTES)


def test_hand_built_delta_datagram_decodes_against_the_held_base():
    dec = dl.DeltaDecoder()
    base = geo.se3_exp(np.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.3]))
    dec.absolute(("s", 2, 40), base, 6, stamp_ns=123)
    msg = codec.decode_datagram(_delta_gram(), dec)
    (e,) = msg.separators
    xi = np.array([1, 2, 3, -4, 5, -6]) * 2.0**-8
    assert (e.owner_robot, e.keyframe_id, e.stamp_ns) == (2, 40, 123)
    assert np.allclose(e.T_world_body, base @ geo.se3_exp(xi), atol=1e-15)


@pytest.mark.parametrize(
    "kw, why",
    [
        ({"exponent": 1}, "exponent"),
        ({"q": (1, 2, 3, -128, 5, -6)}, "-128"),
        ({"back": 0}, "delta base"),
        ({"back": 8}, "delta base"),
    ],
)
def test_malformed_delta_fields_are_decode_errors(kw, why):
    dec = dl.DeltaDecoder()
    dec.absolute(("s", 2, 40), np.eye(4), 6, stamp_ns=0)
    with pytest.raises(DecodeError, match=why):
        codec.decode_datagram(_delta_gram(**kw), dec)


def test_truncated_delta_datagrams_are_decode_errors():
    data = _delta_gram()
    body = data[: -codec.TAG_BYTES]
    for cut in range(1, 8):
        with pytest.raises(DecodeError):
            codec.decode_datagram(body[:-cut] + bytes(codec.TAG_BYTES), dl.DeltaDecoder())


@pytest.mark.parametrize(
    "stage",
    [
        InitStage.REFINE_SCHUR,
        InitStage.REFINE_STEP,
        InitStage.REFINE_CONTROL,
        InitStage.REFINE_PCG_UP,
        InitStage.REFINE_PCG_DOWN,
    ],
)
def test_refinement_values_always_travel_absolute_in_float32(stage):
    """A condensed system needs every digit float32 keeps: no quantised deltas, even for a
    key whose value barely moved (a ROTATION entry in its place goes as a delta)."""
    enc, dec = dl.DeltaEncoder(absolute_every=1000), dl.DeltaDecoder()
    rng = np.random.default_rng(1)
    V = rng.normal(0, 1, (N, 3, 3))
    sizes = {}
    for kind in (stage, InitStage.ROTATION):
        for rnd in (1, 2):
            V = V + 1e-3 * rnd
            msg = NeighbourMessage(
                2,
                rnd,
                rnd * 500_000_000,
                (),
                (),
                tuple(InitEntry(kind, 2, 40 + i, V[i]) for i in range(N)),
            )
            grams = _encode(msg, enc)
            got = np.stack([e.value for e in codec.decode_datagram(grams[0].data, dec).init])
            sizes[kind, rnd] = len(grams[0].data)
        if kind == stage:
            assert np.array_equal(got, V.astype(np.float32).astype(np.float64))
    assert sizes[stage, 2] == sizes[stage, 1]
    assert sizes[InitStage.ROTATION, 2] < 0.6 * sizes[InitStage.ROTATION, 1]
