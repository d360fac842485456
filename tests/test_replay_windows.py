"""Replay windows survive a receiver's restart: a datagram captured before it is not accepted
again, whether the receiver stopped cleanly (checkpoint) or was killed between checkpoints
(``replay_windows.json``, written after every tick that accepted something)."""

from __future__ import annotations

import numpy as np
import pytest
from daemon_helpers import write_config
from dran_edge.comms import codec
from dran_edge.comms.auth import AuthPolicy, Reject, Signer, Verifier
from dran_edge.comms.bus import Bus, BusEndpoint
from dran_edge.comms.link import NeighbourLink

from dran_edge.config import load_config
from dran_edge.daemon.service import Daemon, LinkTransport, fleet_id
from dran_edge.messages import NeighbourMessage, ObjectEntry
from dran_edge.daemon.notify import Notifier

KEY = bytes(range(32))


def _gram(sender, seq, epoch, fleet=3):
    msg = NeighbourMessage(sender, 1, 5, objects=(ObjectEntry(7, np.eye(4), sender),))
    (g,) = codec.encode_message(msg, fleet_id=fleet, boot_epoch=epoch, first_sequence=seq)
    return Signer(KEY).sign(g)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_verifier_windows_round_trip(seed):
    rng = np.random.default_rng(seed)
    policy = AuthPolicy(
        fleet_id=3,
        self_id=1,
        fleet_robots=frozenset({1, 2, 3}),
        neighbours=frozenset({2, 3}),
        replay_window=32,
    )
    v = Verifier(KEY, policy)
    seen = {2: set(), 3: set()}
    for _ in range(60):
        s = int(rng.integers(2, 4))
        seq = int(rng.integers(0, 80))
        if v.check(_gram(s, seq, 9))[1] is None:
            seen[s].add(seq)
    restarted = Verifier(KEY, policy)
    assert restarted.restore_windows(v.windows_state()) == 2
    assert restarted.windows_state() == v.windows_state()
    for s, seqs in seen.items():
        for seq in seqs:  # every accepted datagram is refused after the restart
            assert restarted.check(_gram(s, seq, 9))[1] in (Reject.REPLAYED, Reject.STALE)
        assert restarted.check(_gram(s, 0, 8)) == (None, Reject.STALE)  # an older epoch
        assert restarted.check(_gram(s, 0, 10))[1] is None  # the sender restarted
    # a saved window never lowers the one held
    assert restarted.restore_windows(v.windows_state()) == 0
    with pytest.raises(ValueError):
        restarted.restore_windows([[2, 1, "x", "0"]])


class _Quiet(Notifier):
    def __init__(self):
        super().__init__({})
        self.backend = "test"

    def notify(self, message: str) -> bool:
        return True


def _daemon(tmp_path, bus):
    cfg = load_config(
        write_config(
            tmp_path,
            robot={"id": 1, "name": "r1"},
            ingest={"enabled": False},
            comms={"period_s": 0.05},
            daemon={"checkpoint_period_s": 3600.0},
        )
    )  # only the first tick checkpoints

    def transport(cfg, epoch):
        policy = AuthPolicy(
            fleet_id=fleet_id(cfg.robot.fleet),
            self_id=1,
            fleet_robots=frozenset({1, 2}),
            neighbours=frozenset({2}),
        )
        # a fresh endpoint per life: the previous life's was closed by its shutdown
        link = NeighbourLink(BusEndpoint(bus, 1), key=KEY, policy=policy, boot_epoch=epoch)
        return LinkTransport(link, {2: "r2"})

    return cfg, Daemon(cfg, notifier=_Quiet(), environ={}, transport_factory=transport)


def _crash(d):
    """What a kill -9 leaves: no shutdown, so no final checkpoint."""
    d.status_server.stop()
    d.journal.close()


@pytest.mark.parametrize("clean_stop", [False, True])
def test_daemon_refuses_a_replay_after_restart(tmp_path, clean_stop):
    bus = Bus([1, 2], graph=[(1, 2)])
    cfg, d = _daemon(tmp_path, bus)
    sender = NeighbourLink(
        bus.endpoint(2),
        key=KEY,
        boot_epoch=77,
        policy=AuthPolicy(
            fleet_id=fleet_id(cfg.robot.fleet),
            self_id=2,
            fleet_robots=frozenset({1, 2}),
            neighbours=frozenset({1}),
        ),
    )
    d.start()
    d.tick()  # the first tick checkpoints (nothing received yet)
    captured = sender.send_message(
        NeighbourMessage(2, 1, 10, objects=(ObjectEntry(4, np.eye(4), 2),)), [1]
    )
    bus.advance()
    d.tick()
    assert d.transport.link.verifier.counts.accepted == 1
    assert d.counters.window_saves == 1
    if clean_stop:
        d.shutdown()
        # the final checkpoint alone must carry the windows
        (tmp_path / "state" / "replay_windows.json").unlink()
    else:
        _crash(d)

    def replay_into_fresh_daemon():
        _, d2 = _daemon(tmp_path, bus)
        d2.start()
        for data in captured:
            bus.endpoint(2).send(1, data)
        bus.advance()
        d2.tick()
        counts = d2.transport.link.verifier.counts
        d2.shutdown()
        return counts

    counts = replay_into_fresh_daemon()
    assert counts.accepted == 0 and counts.rejected["replayed"] == len(captured)
    # Control: without the saved windows the same replay is accepted (what happened before).
    for f in ("replay_windows.json", "checkpoint.npz", "checkpoint.prev.npz"):
        (tmp_path / "state" / f).unlink(missing_ok=True)
    assert replay_into_fresh_daemon().accepted == len(captured)
