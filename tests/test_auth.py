"""Authentication: key files, tags, and the drop-and-count verifier (every attack class)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import mutate_datagram

from dran_edge.comms import auth, codec
from dran_edge.comms.auth import AuthPolicy, Reject, Signer, Verifier
from dran_edge.errors import ConfigError
from dran_edge.messages import NeighbourMessage, ObjectEntry

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
FLEET = 4
POLICY = AuthPolicy(
    fleet_id=FLEET,
    self_id=1,
    fleet_robots=frozenset({1, 2, 3, 4, 5}),
    neighbours=frozenset({2, 3}),
    relay_from=frozenset({4}),
    replay_window=8,
)


def _datagram(sender=2, seq=0, epoch=10, fleet=FLEET, key=KEY, n_obj=1):
    msg = NeighbourMessage(
        sender_id=sender,
        round=3,
        stamp_ns=99,
        objects=tuple(ObjectEntry(i, np.eye(4), sender) for i in range(n_obj)),
    )
    (g,) = codec.encode_message(msg, fleet_id=fleet, boot_epoch=epoch, first_sequence=seq)
    return Signer(key).sign(g)


def test_key_file_permissions_and_format(tmp_path):
    path = tmp_path / "fleet.key"
    key = auth.write_fleet_key(path)
    assert oct(os.stat(path).st_mode & 0o777) == "0o600"
    assert auth.load_fleet_key(path) == key
    with pytest.raises(ConfigError, match="exists"):
        auth.write_fleet_key(path)
    for mode in (0o644, 0o640, 0o604, 0o660):
        os.chmod(path, mode)
        with pytest.raises(ConfigError, match=f"{mode:04o}") as exc:
            auth.load_fleet_key(path)
        assert str(path) in str(exc.value) and "chmod 600" in str(exc.value)
    os.chmod(path, 0o400)
    assert auth.load_fleet_key(path) == key
    short = tmp_path / "short.key"
    short.write_text("abcd\n")
    os.chmod(short, 0o600)
    with pytest.raises(ConfigError, match="32..64 bytes"):
        auth.load_fleet_key(short)
    junk = tmp_path / "junk.key"
    junk.write_text("zz" * 32)
    os.chmod(junk, 0o600)
    with pytest.raises(ConfigError, match="hexadecimal"):
        auth.load_fleet_key(junk)
    with pytest.raises(ConfigError, match="cannot read"):
        auth.load_fleet_key(tmp_path / "missing.key")


def test_boot_epoch_increases_even_if_clock_goes_back(tmp_path):
    p = tmp_path / "epoch"
    e1 = auth.next_boot_epoch(p, now_s=1000)
    e2 = auth.next_boot_epoch(p, now_s=500)  # clock went back (no RTC)
    e3 = auth.next_boot_epoch(p, now_s=5000)
    assert e1 == 1000 and e2 == 1001 and e3 == 5000


def test_accepts_valid_and_relay_allowed():
    v = Verifier(KEY, POLICY)
    msg, reason = v.check(_datagram(sender=2, seq=0))
    assert reason is None and msg.sender_id == 2 and msg.sequence == 0
    msg, reason = v.check(_datagram(sender=4, seq=0))  # not a neighbour, relaying allowed
    assert reason is None and msg.sender_id == 4
    assert v.counts.accepted == 2


@pytest.mark.parametrize(
    "datagram, reason",
    [
        (_datagram(fleet=FLEET + 1), Reject.WRONG_FLEET),
        (_datagram(sender=9), Reject.UNKNOWN_SENDER),
        (_datagram(sender=1), Reject.UNKNOWN_SENDER),  # claims to be us
        (_datagram(sender=5), Reject.NOT_NEIGHBOUR),
        (_datagram(key=OTHER_KEY), Reject.BAD_TAG),
        (_datagram()[:-16] + bytes(16), Reject.BAD_TAG),
        (b"\x00" * 50, Reject.MALFORMED),
        (
            _datagram()[:2] + bytes([codec.SCHEMA_VERSION - 1]) + _datagram()[3:],
            Reject.WRONG_VERSION,
        ),
        (b"", Reject.MALFORMED),
    ],
)
def test_each_attack_class_is_rejected_and_counted(datagram, reason):
    v = Verifier(KEY, POLICY)
    assert v.check(datagram) == (None, reason)
    assert v.counts.rejected[reason.value] == 1 and v.counts.accepted == 0


def test_replay_window_and_restarted_neighbour():
    v = Verifier(KEY, POLICY)
    ok = lambda d: v.check(d)[1] is None  # noqa: E731
    assert ok(_datagram(seq=5))
    assert v.check(_datagram(seq=5)) == (None, Reject.REPLAYED)
    assert ok(_datagram(seq=3))  # reordered, inside the window
    assert v.check(_datagram(seq=3)) == (None, Reject.REPLAYED)
    assert ok(_datagram(seq=12))
    assert v.check(_datagram(seq=4)) == (None, Reject.STALE)  # 12 - 4 >= window 8
    assert ok(_datagram(seq=6))
    assert ok(_datagram(seq=2**32 - 1))  # huge jump resets the bitmap, no big-int blowup
    assert v.check(_datagram(seq=2**32 - 1)) == (None, Reject.REPLAYED)
    # A restarted neighbour: larger boot epoch, sequence from 0 again -> accepted.
    assert ok(_datagram(seq=0, epoch=11))
    assert v.check(_datagram(seq=0, epoch=11)) == (None, Reject.REPLAYED)
    # Datagrams of the old epoch are now stale, even new sequence numbers.
    assert v.check(_datagram(seq=2**32 - 2, epoch=10)) == (None, Reject.STALE)
    assert v.peer_state() == {2: (11, 0)}
    assert v.counts.rejected == {
        "malformed": 0,
        "wrong_version": 0,
        "wrong_fleet": 0,
        "unknown_sender": 0,
        "not_neighbour": 0,
        "wrong_auth": 0,
        "bad_tag": 0,
        "replayed": 4,
        "stale": 2,
    }


def test_rejected_datagrams_do_not_advance_the_window():
    v = Verifier(KEY, POLICY)
    assert v.check(_datagram(seq=100, key=OTHER_KEY))[1] == Reject.BAD_TAG
    assert v.check(_datagram(seq=1))[1] is None  # a forged high sequence did not stale us


@settings(max_examples=500, deadline=None)
@given(st.data())
def test_forgeries_never_accepted(data):
    """Any modification of a valid datagram (bytes flipped, cut, extended) is rejected."""
    good = bytearray(_datagram(seq=data.draw(st.integers(0, 1000)), n_obj=3))
    v = Verifier(KEY, POLICY)
    msg, reason = v.check(mutate_datagram(data, bytes(good)))
    assert msg is None and reason is not None


def test_fleet_key_command(tmp_path, capsys):
    from dran_edge.cli.app import main

    path = tmp_path / "fleet.key"
    assert main(["fleet-key", "new", str(path)]) == 0
    fp = capsys.readouterr().out.split("fingerprint ")[1].strip()
    assert main(["fleet-key", "check", str(path)]) == 0
    assert capsys.readouterr().out.strip().endswith(fp)
    os.chmod(path, 0o644)
    assert main(["fleet-key", "check", str(path)]) == 2
    assert "0644" in capsys.readouterr().err
