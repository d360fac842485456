"""Per-robot identity (the ed25519 key policy): key files, signed datagrams, forgery, rotation."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import assert_forgeries_rejected, flip_one_bit, mutate_datagram

pytest.importorskip("cryptography")

from dran_edge.comms import auth, codec
from dran_edge.comms.auth import (
    AuthPolicy,
    Ed25519Signer,
    Reject,
    RobotIdentity,
    Signer,
    Verifier,
)

from dran_edge.errors import ConfigError
from dran_edge.messages import NeighbourMessage, ObjectEntry, SeparatorEntry

FLEET = 7
SEEDS = {r: bytes([r]) * 32 for r in (1, 2, 3)}
PUBLIC = {r: (auth.public_key_of(s),) for r, s in SEEDS.items()}


def _policy(self_id, neighbours, window=64):
    return AuthPolicy(
        fleet_id=FLEET,
        self_id=self_id,
        fleet_robots=frozenset({1, 2, 3}),
        neighbours=frozenset(neighbours),
        replay_window=window,
    )


def _message(sender, rng, n_sep=3, n_obj=2):
    T = np.tile(np.eye(4), (n_sep + n_obj, 1, 1))
    T[:, :3, 3] = rng.normal(size=(n_sep + n_obj, 3)) * 10
    return NeighbourMessage(
        sender_id=sender,
        round=4,
        stamp_ns=1_000_000,
        separators=tuple(SeparatorEntry(sender, k, 1_000_000, T[k]) for k in range(n_sep)),
        objects=tuple(ObjectEntry(i, T[n_sep + i], sender, 0, 1) for i in range(n_obj)),
    )


def _signed(msg, seed, seq, epoch=5):
    (g,) = codec.encode_message(
        msg, fleet_id=FLEET, boot_epoch=epoch, first_sequence=seq, signed=True
    )
    return Ed25519Signer(seed).sign(g)


def test_key_pair_files(tmp_path):
    path = tmp_path / "dingo3.key"
    public = auth.write_robot_key(path, robot_id=3)
    assert oct(os.stat(path).st_mode & 0o777) == "0o600"
    assert auth.public_key_of(auth.load_robot_key(path)) == public
    assert auth.load_public_key_file(auth.public_key_path(path)) == (3, public)
    with pytest.raises(ConfigError, match="exists"):
        auth.write_robot_key(path, robot_id=3)
    os.chmod(path, 0o640)
    with pytest.raises(ConfigError, match="0640"):
        auth.load_robot_key(path)
    os.chmod(path, 0o600)
    # The two policies' key files are told apart, with a message that says what to set.
    with pytest.raises(ConfigError, match="comms.auth: ed25519"):
        auth.load_fleet_key(path)
    fleet = tmp_path / "fleet.key"
    auth.write_fleet_key(fleet)
    with pytest.raises(ConfigError, match="comms.auth: hmac"):
        auth.load_robot_key(fleet)
    keys_file = tmp_path / "fleet.pub"
    auth.write_fleet_public_keys(keys_file, "dingo6", {3: (public,), 1: PUBLIC[1] + PUBLIC[2]})
    assert auth.load_fleet_public_keys(keys_file) == (
        "dingo6",
        {1: PUBLIC[1] + PUBLIC[2], 3: (public,)},
    )
    bad = tmp_path / "bad.pub"
    bad.write_text("fleet: x\npublic_keys: {1: abcd}\n")
    with pytest.raises(ConfigError, match="public_keys.1"):
        auth.load_fleet_public_keys(bad)


def test_signed_datagram_layout_and_acceptance():
    rng = np.random.default_rng(0)
    msg = _message(1, rng)
    (plain,) = codec.encode_message(msg, fleet_id=FLEET, boot_epoch=5, first_sequence=0)
    data = _signed(msg, SEEDS[1], 0)
    assert len(data) == len(plain) + codec.SIGNATURE_BYTES - codec.TAG_BYTES
    assert data[3] == plain[3] | 0x04  # the signed flag
    assert data[:3] == plain[:3] and data[4:-64] == plain[4:-16]
    size = codec.encoded_size(msg, signed=True)
    assert size.total_bytes == len(data) and size.bytes_by_kind["header"] == (
        codec.encoded_size(msg).bytes_by_kind["header"] + 48
    )
    v = Verifier(RobotIdentity(SEEDS[2], PUBLIC), _policy(2, {1, 3}))
    got, reason = v.check(data)
    assert reason is None and got.sender_id == 1 and len(got.separators) == 3
    assert got.extra["bytes_by_kind"]["header"] == size.bytes_by_kind["header"]
    assert v.check(data) == (None, Reject.REPLAYED)


def test_policies_do_not_mix():
    rng = np.random.default_rng(1)
    msg = _message(1, rng)
    (g,) = codec.encode_message(msg, fleet_id=FLEET, boot_epoch=5, first_sequence=0)
    hmac_gram = Signer(bytes(32)).sign(g)
    ed = Verifier(PUBLIC, _policy(2, {1, 3}))
    assert ed.check(hmac_gram) == (None, Reject.WRONG_AUTH)
    hm = Verifier(bytes(32), _policy(2, {1, 3}))
    assert hm.check(_signed(msg, SEEDS[1], 1)) == (None, Reject.WRONG_AUTH)
    assert hm.check(hmac_gram)[1] is None


def test_missing_public_key_is_a_config_error():
    with pytest.raises(ConfigError, match=r"robot\(s\) \[3\]"):
        Verifier({1: PUBLIC[1]}, _policy(2, {1, 3}))


def test_compromised_robot_cannot_forge_another():
    """Robot 3's secret (what a thief of robot 3 holds, with every public key) never yields a
    datagram robot 2 accepts as robot 1's: 10 000 forgeries of four kinds, all rejected, while
    genuine datagrams of robots 1 and 3 are accepted."""
    rng = np.random.default_rng(2)
    v = Verifier(RobotIdentity(SEEDS[2], PUBLIC), _policy(2, {1, 3}, window=4096))
    genuine = _signed(_message(1, rng), SEEDS[1], 0)
    assert v.check(genuine)[1] is None
    own3 = _signed(_message(3, rng), SEEDS[3], 0)  # a valid datagram of robot 3
    assert v.check(own3)[1] is None
    thief = Ed25519Signer(SEEDS[3])
    # 32 robot-1 messages encoded once (signature slot empty); each forgery gets a fresh
    # sequence number spliced into the header (fleet, sender and epoch are one byte each here,
    # so the sequence varint starts at byte 7).
    templates = [
        codec.encode_message(
            _message(1, rng, n_sep=k % 4),
            fleet_id=FLEET,
            boot_epoch=5,
            first_sequence=0,
            signed=True,
        )[0]
        for k in range(32)
    ]

    def unsigned(seq):
        t = templates[seq % len(templates)]
        return t[:7] + codec._varint(seq) + t[8:]

    def forgeries(n):
        for i in range(n):
            seq = 10 + i  # fresh sequence numbers: only the signature can reject them
            kind = i % 4
            if kind == 0:  # a message claiming robot 1, signed with robot 3's secret
                yield kind, thief.sign(unsigned(seq))
            elif kind == 1:  # a valid signature of robot 3 (from its own datagram) transplanted
                yield kind, unsigned(seq)[:-64] + own3[-64:]
            elif kind == 2:  # random signature bytes
                yield kind, unsigned(seq)[:-64] + rng.bytes(64)
            else:  # genuine robot-1 bytes with one bit of the body or the signature flipped
                yield kind, flip_one_bit(rng, genuine)

    assert_forgeries_rejected(v, forgeries(10_000), 10_000)
    assert v.counts.accepted == 2


def test_rotation_two_keys_then_revocation():
    rng = np.random.default_rng(3)
    new_seed = bytes([9]) * 32
    both = {**PUBLIC, 1: PUBLIC[1] + (auth.public_key_of(new_seed),)}
    v = Verifier(both, _policy(2, {1, 3}))
    assert v.check(_signed(_message(1, rng), SEEDS[1], 0))[1] is None
    assert v.check(_signed(_message(1, rng), new_seed, 1))[1] is None
    revoked = Verifier({**PUBLIC, 1: both[1][1:]}, _policy(2, {1, 3}))
    assert revoked.check(_signed(_message(1, rng), SEEDS[1], 0)) == (None, Reject.BAD_TAG)
    assert revoked.check(_signed(_message(1, rng), new_seed, 1))[1] is None


def test_fleet_key_pair_export_check_commands(tmp_path, capsys):
    from dran_edge.cli.app import main

    for r in (1, 2):
        assert main(["fleet-key", "pair", str(tmp_path / f"r{r}.key"), "--robot-id", str(r)]) == 0
    pubs = [auth.load_public_key_file(tmp_path / f"r{r}.key.pub")[1] for r in (1, 2)]
    # rotation: a second key pair of robot 1 exported next to the first gives both keys
    (tmp_path / "new").mkdir()
    assert main(["fleet-key", "pair", str(tmp_path / "new" / "r1.key"), "--robot-id", "1"]) == 0
    new1 = auth.load_public_key_file(tmp_path / "new" / "r1.key.pub")[1]
    out = tmp_path / "fleet.pub"
    assert (
        main(
            [
                "fleet-key",
                "export",
                str(out),
                "--fleet",
                "f",
                str(tmp_path),
                str(tmp_path / "new" / "r1.key.pub"),
            ]
        )
        == 0
    )
    assert auth.load_fleet_public_keys(out) == ("f", {1: (pubs[0], new1), 2: (pubs[1],)})
    capsys.readouterr()
    assert main(["fleet-key", "check", str(tmp_path / "r2.key")]) == 0
    assert pubs[1].hex() in capsys.readouterr().out
    assert main(["fleet-key", "check", str(out)]) == 0
    assert "1: 2 keys, 2: 1 key" in capsys.readouterr().out
    os.chmod(tmp_path / "r2.key", 0o644)
    assert main(["fleet-key", "check", str(tmp_path / "r2.key")]) == 2
    assert "chmod 600" in capsys.readouterr().err


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_mutated_signed_datagrams_never_accepted_never_raise(data):
    genuine = _signed(_message(1, np.random.default_rng(5)), SEEDS[1], 0)
    v = Verifier(PUBLIC, _policy(2, {1, 3}))
    msg, reason = v.check(mutate_datagram(data, genuine))
    assert msg is None and reason is not None


def test_rfc8032_vector_and_signed_golden_bytes():
    """Ed25519Signer is RFC 8032 Ed25519 (test 1: empty message), and a signed heartbeat's bytes
    are pinned (Ed25519 is deterministic): header with flags 0x05 (SE(3) | signed), then the
    64-byte signature."""
    seed = bytes.fromhex("9d61b19deffd5a60ba844af492ec2cc44449c5697b326919703bac031cae7f60")
    assert auth.public_key_of(seed).hex() == (
        "d75a980182b10ab7d54bfed3c964073a0ee172f3daa62325af021a68f707511a"
    )
    assert Ed25519Signer(seed).sign(bytes(64)).hex() == (
        "e5564300c360ac729086e2cc806e828a84877f1eb8e5d974d873e06522490155"
        "5fb8821590a33bacc61e39701cf9b46bd25bf5f0595bbe24655141438e7a100b"
    )
    (g,) = codec.encode_message(
        NeighbourMessage(1, 3, 1000), fleet_id=7, boot_epoch=5, first_sequence=2, signed=True
    )
    assert Ed25519Signer(bytes([1]) * 32).sign(g).hex() == (
        "445202050701050203e807000000"
        "c9826bf6b3a2bcf91b1d1f70c526b529f008b37923d7b73cbd6c5e3779801d2b"
        "2f36386c566d0f4d6d3e15e94f764e9def316f8c9228419bbb95c48243bf3b03"
    )
