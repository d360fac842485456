"""The pairwise key policy: pair keys agreed from the robots' Ed25519 key pairs (X25519 + HKDF),
one HMAC tag per receiver; forgery with another robot's secret, policies, rotation; links over
the bus with either per-robot policy (ed25519 or pairwise)."""

from __future__ import annotations

import hashlib
import hmac

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import assert_forgeries_rejected, flip_one_bit, mutate_datagram

pytest.importorskip("cryptography")

from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric import x25519
from cryptography.hazmat.primitives.kdf.hkdf import HKDF
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

from dran_edge.comms import auth, codec
from dran_edge.comms.auth import (
    AuthPolicy,
    Ed25519Signer,
    PairwiseSigner,
    Reject,
    RobotIdentity,
    Signer,
    Verifier,
)
from dran_edge.comms.pairwise import PairwiseIdentity, PairwiseKeys, montgomery_u, x25519_private
from dran_edge.errors import ConfigError
from dran_edge.messages import NeighbourMessage, SeparatorEntry

FLEET = 7
SEEDS = {r: bytes([r]) * 32 for r in (1, 2, 3)}
PUBLIC = {r: (auth.public_key_of(s),) for r, s in SEEDS.items()}


def _policy(self_id, neighbours=None, window=64):
    neighbours = {1, 2, 3} - {self_id} if neighbours is None else neighbours
    return AuthPolicy(
        fleet_id=FLEET,
        self_id=self_id,
        fleet_robots=frozenset({1, 2, 3}),
        neighbours=frozenset(neighbours),
        replay_window=window,
    )


def _keys(robot, seed=None, public=PUBLIC):
    return PairwiseKeys(PairwiseIdentity(seed or SEEDS[robot], public), robot, FLEET)


def _message(sender, rng, n_sep=3):
    T = np.tile(np.eye(4), (n_sep, 1, 1))
    T[:, :3, 3] = rng.normal(size=(n_sep, 3)) * 10
    return NeighbourMessage(
        sender_id=sender,
        round=4,
        stamp_ns=1_000_000,
        separators=tuple(SeparatorEntry(sender, k, 1_000_000, T[k]) for k in range(n_sep)),
    )


def _unsigned(msg, seq, epoch=5):
    (g,) = codec.encode_message(
        msg, fleet_id=FLEET, boot_epoch=epoch, first_sequence=seq, pairwise=True
    )
    return g


def _raw(public_key) -> bytes:
    return public_key.public_bytes(Encoding.Raw, PublicFormat.Raw)


@pytest.mark.parametrize(
    "seed",
    [bytes([r]) * 32 for r in (1, 2, 77, 255)]
    + [hashlib.sha256(b"%d" % k).digest() for k in range(4)],
)
def test_x25519_half_of_an_ed25519_key_pair(seed):
    """The Montgomery u of the Ed25519 public key is the X25519 public key of the secret's
    scalar (RFC 7748 §4.1 against cryptography's own X25519)."""
    expected = _raw(x25519.X25519PrivateKey.from_private_bytes(x25519_private(seed)).public_key())
    assert montgomery_u(auth.public_key_of(seed)) == expected


def test_unusable_public_keys_are_config_errors():
    with pytest.raises(ConfigError, match="not a usable point"):
        montgomery_u((1).to_bytes(32, "little"))  # y = 1, the neutral point
    with pytest.raises(ConfigError, match="32-byte"):
        montgomery_u(bytes(31))
    with pytest.raises(ConfigError, match="robot 3"):  # y = 0: u = 1, a low-order point
        _keys(1, public={**PUBLIC, 3: (bytes(32),)})


def test_pair_keys_follow_the_documented_derivation():
    """K_{1→2} re-derived from the module docstring's formula with cryptography's X25519 and
    HKDF: robot 1's tag for robot 2 is HMAC-SHA256-128 with it; robot 2 verifies it; the
    reverse direction has another key."""
    shared = x25519.X25519PrivateKey.from_private_bytes(x25519_private(SEEDS[1])).exchange(
        x25519.X25519PublicKey.from_public_bytes(montgomery_u(PUBLIC[2][0]))
    )
    info = FLEET.to_bytes(2, "big") + (1).to_bytes(2, "big") + (2).to_bytes(2, "big")
    k12 = HKDF(
        hashes.SHA256(), 32, b"dran-edge pairwise v1", info + PUBLIC[1][0] + PUBLIC[2][0]
    ).derive(shared)
    body = b"some datagram body"
    tag = _keys(1).tag_for(2, body)
    assert tag == hmac.digest(k12, body, "sha256")[:16]
    assert _keys(2).verify(1, body, tag) == 0
    assert _keys(2).tag_for(1, body) != tag  # directional keys
    assert _keys(3).verify(1, body, tag) is None


def test_pairwise_datagram_layout_and_acceptance():
    rng = np.random.default_rng(0)
    msg = _message(1, rng)
    (plain,) = codec.encode_message(msg, fleet_id=FLEET, boot_epoch=5, first_sequence=0)
    data = PairwiseSigner(_keys(1)).sign_for(_unsigned(msg, 0), 2)
    assert len(data) == len(plain) and data[3] == plain[3] | 0x10  # same size, flag bit 4
    v = Verifier(_keys(2), _policy(2))
    got, reason = v.check(data)
    assert reason is None and got.sender_id == 1 and len(got.separators) == 3
    assert v.check(data) == (None, Reject.REPLAYED)
    with pytest.raises(codec.EncodeError, match="not both"):
        codec.encode_message(
            msg, fleet_id=FLEET, boot_epoch=5, first_sequence=0, pairwise=True, signed=True
        )


def test_policies_do_not_mix():
    rng = np.random.default_rng(1)
    msg = _message(1, rng)
    (g,) = codec.encode_message(msg, fleet_id=FLEET, boot_epoch=5, first_sequence=0)
    hmac_gram = Signer(bytes(32)).sign(g)
    (s,) = codec.encode_message(msg, fleet_id=FLEET, boot_epoch=5, first_sequence=1, signed=True)
    signed_gram = Ed25519Signer(SEEDS[1]).sign(s)
    pair_gram = PairwiseSigner(_keys(1)).sign_for(_unsigned(msg, 2), 2)
    pw = Verifier(_keys(2), _policy(2))
    assert pw.check(hmac_gram) == (None, Reject.WRONG_AUTH)
    assert pw.check(signed_gram) == (None, Reject.WRONG_AUTH)
    assert Verifier(bytes(32), _policy(2)).check(pair_gram) == (None, Reject.WRONG_AUTH)
    assert Verifier(PUBLIC, _policy(2)).check(pair_gram) == (None, Reject.WRONG_AUTH)
    assert pw.check(pair_gram)[1] is None


def test_missing_public_key_is_a_config_error():
    with pytest.raises(ConfigError, match=r"robot\(s\) \[3\]"):
        Verifier(_keys(2, public={1: PUBLIC[1], 2: PUBLIC[2]}), _policy(2))


def test_compromised_robot_cannot_forge_another():
    """Robot 3's secret with every public key (what a thief of robot 3 holds) never yields a
    datagram robot 2 accepts as robot 1's: 10 000 forgeries of five kinds, all rejected, while
    genuine datagrams of robots 1 and 3 are accepted."""
    rng = np.random.default_rng(2)
    v = Verifier(_keys(2), _policy(2, window=4096))
    genuine = PairwiseSigner(_keys(1)).sign_for(_unsigned(_message(1, rng), 0), 2)
    assert v.check(genuine)[1] is None
    assert v.check(PairwiseSigner(_keys(3)).sign_for(_unsigned(_message(3, rng), 0), 2))[1] is None
    # What robot 3 can compute: its own keys, its keys "as robot 1" (its secret, robot 1's id),
    # and K_{1→3} (robot 1's key towards it), re-derived as in the docstring.
    as_self = _keys(3)
    as_one = PairwiseKeys(PairwiseIdentity(SEEDS[3], PUBLIC), 1, FLEET)
    shared13 = x25519.X25519PrivateKey.from_private_bytes(x25519_private(SEEDS[3])).exchange(
        x25519.X25519PublicKey.from_public_bytes(montgomery_u(PUBLIC[1][0]))
    )
    k13 = HKDF(
        hashes.SHA256(),
        32,
        b"dran-edge pairwise v1",
        FLEET.to_bytes(2, "big")
        + (1).to_bytes(2, "big")
        + (3).to_bytes(2, "big")
        + PUBLIC[1][0]
        + PUBLIC[3][0],
    ).derive(shared13)
    genuine_to_3 = [
        PairwiseSigner(_keys(1)).sign_for(_unsigned(_message(1, rng), 1 + k), 3) for k in range(8)
    ]  # robot 1's real datagrams to robot 3, sent on to 2
    templates = [_unsigned(_message(1, rng, n_sep=k % 4), 0) for k in range(32)]

    def unsigned(seq):  # fresh sequence numbers: only the tag can reject them
        t = templates[seq % len(templates)]
        return t[:7] + codec._varint(seq) + t[8:]

    def forgeries(n):
        for i in range(n):
            kind, body = i % 5, unsigned(10 + i)[:-16]
            if kind == 0:  # claims robot 1, tagged with robot 3's own key to robot 2
                yield kind, body + as_self.tag_for(2, body)
            elif kind == 1:  # robot 3's secret running as robot 1
                yield kind, body + as_one.tag_for(2, body)
            elif kind == 2:  # robot 1's key towards robot 3 (which robot 3 holds)
                yield kind, body + hmac.digest(k13, body, "sha256")[:16]
            elif kind == 3:  # a genuine datagram of robot 1 to robot 3, or random tag bytes
                yield kind, genuine_to_3[i % 8] if i % 2 else body + rng.bytes(16)
            else:  # genuine robot-1 bytes with one bit flipped
                yield kind, flip_one_bit(rng, genuine)

    assert_forgeries_rejected(v, forgeries(10_000), 10_000)
    assert v.counts.accepted == 2


def test_rotation_follows_the_receivers_key():
    """Robot 2 rotates its key pair: with both of its public keys listed, robot 1 answers it
    with the key robot 2 was last heard with; only datagrams sent before robot 2 is heard at all
    are lost (tagged for the newest key while robot 2 still holds the old one)."""
    rng = np.random.default_rng(3)
    new2 = bytes([9]) * 32
    both = {**PUBLIC, 2: PUBLIC[2] + (auth.public_key_of(new2),)}
    k1 = _keys(1, public=both)
    s1, v1 = PairwiseSigner(k1), Verifier(k1, _policy(1))
    old = _keys(2, public=both)
    s2, v2 = PairwiseSigner(old), Verifier(old, _policy(2))
    seq = iter(range(100))
    assert v2.check(s1.sign_for(_unsigned(_message(1, rng), next(seq)), 2))[1] == Reject.BAD_TAG
    assert v1.check(s2.sign_for(_unsigned(_message(2, rng), next(seq)), 1))[1] is None
    assert v2.check(s1.sign_for(_unsigned(_message(1, rng), next(seq)), 2))[1] is None
    new = _keys(2, seed=new2, public=both)  # robot 2 restarts with its new secret
    s2, v2 = PairwiseSigner(new), Verifier(new, _policy(2))
    assert v1.check(s2.sign_for(_unsigned(_message(2, rng), next(seq), epoch=6), 1))[1] is None
    assert v2.check(s1.sign_for(_unsigned(_message(1, rng), next(seq)), 2))[1] is None
    revoked = _keys(1, public=PUBLIC)  # robot 2's new key not listed: its datagrams rejected
    got = Verifier(revoked, _policy(1)).check(
        s2.sign_for(_unsigned(_message(2, rng), next(seq), epoch=6), 1)
    )
    assert got == (None, Reject.BAD_TAG)


@pytest.mark.parametrize("delta_every", [0, 5])
@pytest.mark.parametrize("identity", [RobotIdentity, PairwiseIdentity])
def test_links_over_the_bus_with_identities(identity, delta_every):
    """Three robots' links over the in-process bus, each with its own key pair: signed
    (ed25519) or pair-keyed (pairwise), absolute or delta layout; nothing rejected."""
    from dran_edge.comms.bus import Bus
    from dran_edge.comms.link import NeighbourLink

    bus = Bus([1, 2, 3], graph=[(1, 2), (2, 3), (1, 3)])
    rng = np.random.default_rng(4)
    links = {
        r: NeighbourLink(
            bus.endpoint(r),
            key=identity(SEEDS[r], PUBLIC),
            policy=_policy(r),
            boot_epoch=3,
            delta_every=delta_every,
        )
        for r in (1, 2, 3)
    }
    for _ in range(3):
        for r, link in links.items():
            sent = link.send_message(_message(r, rng), to=[j for j in links if j != r])
            if identity is PairwiseIdentity:  # one tag per receiver
                assert len(sent) == 2 and sent[0] != sent[1]
        bus.advance()
        for r, link in links.items():
            assert sorted(m.sender_id for m in link.poll()) == sorted({1, 2, 3} - {r})
    assert all(sum(link.verifier.counts.rejected.values()) == 0 for link in links.values())


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_mutated_pairwise_datagrams_never_accepted_never_raise(data):
    genuine = PairwiseSigner(_keys(1)).sign_for(
        _unsigned(_message(1, np.random.default_rng(5)), 0), 2
    )
    msg, reason = Verifier(_keys(2), _policy(2)).check(mutate_datagram(data, genuine))
    assert msg is None and reason is not None
