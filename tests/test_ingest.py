"""Ingest record codec: golden bytes, round trips, and every malformed input is a counted error."""

from __future__ import annotations

import random
import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dran_edge import geometry as geo
from dran_edge.comms import ingest as I
from dran_edge.events import (
    Keyframe,
    LoopClosure,
    ObjectObservation,
    ObservationBatch,
    OdometrySample,
    VioReset,
)


def random_pose(rng: np.random.Generator) -> np.ndarray:
    xi = np.concatenate([rng.normal(0, 5, 3), rng.normal(0, 1, 3)])
    return geo.se3_exp(xi)


def random_cov(rng: np.random.Generator) -> np.ndarray:
    A = rng.normal(size=(6, 6))
    return A @ A.T + 1e-3 * np.eye(6)


def sample_events(seed: int = 0) -> list:
    rng = np.random.default_rng(seed)
    obs = tuple(ObjectObservation(5_000, k, random_pose(rng), random_cov(rng)) for k in (3, 9))
    return [
        OdometrySample(1_000, random_pose(rng)),
        OdometrySample(1_050, random_pose(rng), random_cov(rng)),
        Keyframe(1_100, random_pose(rng)),
        LoopClosure(1_100, 9_900, random_pose(rng), 41),
        VioReset(2_000, "feature_tracker_restart"),
        VioReset(2_001, "jump of 4.2 m"),
        I.ForwardedFrame(3_000, bytes(range(256)) * 10),
        ObservationBatch(5_000, obs),
        ObservationBatch(5_001, ()),
    ]


def assert_same_event(a, b) -> None:
    assert type(a) is type(b)
    for name, va in vars(a).items():
        vb = getattr(b, name)
        if isinstance(va, np.ndarray):
            np.testing.assert_allclose(vb, va, atol=1e-12)
        elif isinstance(va, tuple):
            assert len(va) == len(vb)
            for x, y in zip(va, vb):
                assert_same_event(x, y)
        else:
            assert va == vb, name


# --------------------------------------------------------------------------- golden bytes
def test_golden_bytes_keyframe_reset_loop():
    kf = I.pack_keyframe(1_700_000_000_123_456_789, [1.0, -2.0, 0.5], [0, 0, 0.6, 0.8])
    assert kf.hex() == (
        "44524e4901020000400000005856f25515cd853dfe9c9717000000000000f03f00000000000000c0"
        "000000000000e03f00000000000000000000000000000000333333333333e33f9a9999999999e93f"
    )
    assert I.pack_reset(42, 1).hex() == "44524e490104000009000000052cd1862a0000000000000001"
    loop = I.pack_loop(10, 20, [0.1, 0.2, 0.3], [0, 0, 0, 1], 37)
    assert loop[:16] == I.HEADER.pack(b"DRNI", 1, 3, 0, 76, zlib.crc32(loop[16:]))
    assert struct.unpack("<qq", loop[16:32]) == (10, 20)
    assert loop[-4:] == (37).to_bytes(4, "little")


# --------------------------------------------------------------------------- round trips
def test_every_kind_round_trips():
    for ev in sample_events():
        raw = I.encode_event(ev)
        assert_same_event(ev, I.decode_record(raw))
        (rec,) = I.StreamDecoder().feed(raw)
        assert isinstance(rec, I.Record) and rec.raw == raw
        assert_same_event(ev, rec.event)


def test_decoded_pose_is_a_valid_rotation():
    q = np.array([0.1, 0.2, 0.3, 0.9])
    q = q / np.linalg.norm(q) * (1 + 5e-4)  # slightly off unit: accepted, renormalised
    ev = I.decode_record(I.pack_keyframe(7, [0, 0, 0], q))
    R = ev.T_odom_body[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    stamp=st.integers(1, 2**63 - 1),
    xyz=st.lists(st.floats(-1e5, 1e5), min_size=3, max_size=3),
    rot=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    with_cov=st.booleans(),
)
def test_odometry_round_trip_property(stamp, xyz, rot, with_cov):
    T = geo.se3_from_rt(geo.so3_exp(np.array(rot)), np.array(xyz))
    cov = np.diag(np.arange(1.0, 7.0)) if with_cov else None
    ev = I.decode_record(I.encode_event(OdometrySample(stamp, T, cov)))
    assert ev.stamp_ns == stamp
    np.testing.assert_allclose(ev.T_odom_body, T, atol=1e-9 * max(1.0, np.abs(xyz).max()))
    assert (ev.covariance is None) == (cov is None)


@settings(max_examples=40, deadline=None)
@given(cuts=st.lists(st.integers(0, 4000), max_size=12), seed=st.integers(0, 2**16))
def test_stream_split_anywhere_decodes_the_same(cuts, seed):
    events = sample_events(seed % 7)
    stream = b"".join(I.encode_event(e) for e in events)
    points = sorted({c % (len(stream) + 1) for c in cuts} | {0, len(stream)})
    dec = I.StreamDecoder()
    got = []
    for a, b in zip(points, points[1:]):
        got += dec.feed(stream[a:b])
    assert all(isinstance(r, I.Record) for r in got)
    assert len(got) == len(events)
    for e, r in zip(events, got):
        assert_same_event(e, r.event)
    assert dec.pending_bytes == 0 and dec.bytes_consumed == len(stream)


# --------------------------------------------------------------------------- malformed input
def reframe(kind: int, payload: bytes, flags: int = 0, version: int = 1) -> bytes:
    return I.HEADER.pack(I.MAGIC, version, kind, flags, len(payload), zlib.crc32(payload)) + payload


POSE_OK = struct.pack("<q3d4d", 5, 0, 0, 0, 0, 0, 0, 1)


@pytest.mark.parametrize(
    "raw, reason",
    [
        (reframe(2, struct.pack("<q3d4d", 5, float("nan"), 0, 0, 0, 0, 0, 1)), "non_finite"),
        (reframe(2, struct.pack("<q3d4d", 5, 0, 0, 0, 0, 0, 0, 2)), "bad_quaternion"),
        (reframe(2, struct.pack("<q3d4d", 0, 0, 0, 0, 0, 0, 0, 1)), "bad_stamp"),
        (reframe(2, struct.pack("<q3d4d", -5, 0, 0, 0, 0, 0, 0, 1)), "bad_stamp"),
        (reframe(2, struct.pack("<q3d4d", 5, 1e9, 0, 0, 0, 0, 0, 1)), "out_of_range"),
        (reframe(2, POSE_OK[:-1]), "bad_size"),
        (reframe(2, POSE_OK, flags=1), "bad_flags"),
        (
            reframe(1, POSE_OK + struct.pack("<36d", *np.triu(np.ones((6, 6))).ravel()), flags=1),
            "bad_covariance",
        ),
        (
            reframe(1, POSE_OK + struct.pack("<36d", *(-np.eye(6)).ravel()), flags=1),
            "bad_covariance",
        ),
        (reframe(3, struct.pack("<qq3d4dI", 7, 7, 0, 0, 0, 0, 0, 0, 1, 30)), "bad_stamp"),
        (reframe(4, struct.pack("<qB", 5, 0) + b"\xff\xfe"), "bad_text"),
        (reframe(6, struct.pack("<qI", 5, 1000)), "bad_count"),
        (reframe(6, struct.pack("<qI", 5, 2) + b"\0" * 348), "bad_size"),
        (reframe(9, b"abc"), "unknown_kind"),
        (reframe(2, POSE_OK, version=2), "bad_version"),
        (reframe(2, POSE_OK)[:20], "bad_size"),
        (reframe(2, POSE_OK)[:-1] + b"\x00", "bad_crc"),
        (b"XXXX" + reframe(2, POSE_OK)[4:], "bad_magic"),
        (b"short", "truncated"),
    ],
)
def test_malformed_record_is_a_decode_error_with_reason(raw, reason):
    with pytest.raises(I.IngestDecodeError) as info:
        I.decode_record(raw)
    assert info.value.reason == reason


def test_stream_survives_garbage_and_keeps_good_records():
    rng = random.Random(3)
    events = sample_events(1)
    good = [I.encode_event(e) for e in events]
    bad = [
        bytes(rng.getrandbits(8) for _ in range(37)),
        reframe(2, struct.pack("<q3d4d", 5, float("inf"), 0, 0, 0, 0, 0, 1)),
        I.HEADER.pack(I.MAGIC, 1, 5, 0, 0xFFFFFFFF, 0),  # absurd length: never trusted
        I.HEADER.pack(I.MAGIC, 1, 2, 0, 63, 0) + b"\0" * 63,  # wrong fixed size
        good[2][:-3] + b"zzz",  # corrupted payload: crc
        b"DRN",  # partial magic followed by a real record
    ]
    stream = b""
    for g, b in zip(good, bad + [b""] * (len(good) - len(bad))):
        stream += b + g
    dec = I.StreamDecoder()
    out = []
    for i in range(0, len(stream), 97):
        out += dec.feed(stream[i : i + 97])
    records = [r for r in out if isinstance(r, I.Record)]
    errors = [r for r in out if isinstance(r, I.IngestDecodeError)]
    assert [r.raw for r in records] == good
    assert len(errors) >= len(bad) - 1
    assert {e.reason for e in errors} >= {"bad_magic", "non_finite", "bad_size", "bad_crc"}


@settings(max_examples=80, deadline=None)
@given(junk=st.binary(max_size=600), seed=st.integers(0, 5))
def test_random_bytes_never_raise(junk, seed):
    good = I.encode_event(sample_events(seed)[2])
    dec = I.StreamDecoder()
    out = dec.feed(junk) + dec.feed(good)
    assert all(isinstance(r, (I.Record, I.IngestDecodeError)) for r in out)
    for r in I.iter_records(junk):
        assert isinstance(r, (I.Record, I.IngestDecodeError))


def test_truncated_file_tail_reported():
    data = I.encode_event(sample_events()[2])
    out = list(I.iter_records(data + data[:30]))
    assert isinstance(out[0], I.Record)
    assert isinstance(out[-1], I.IngestDecodeError) and out[-1].reason == "truncated"
