"""What an operator sees of the neighbours: every configured one listed ("never heard" until it
is), heartbeats from a robot that has nothing else to send, counted."""

from __future__ import annotations

import time

import numpy as np

from dran_edge.cli.commands.status import format_status
from dran_edge.comms.auth import AuthPolicy
from dran_edge.comms.bus import Bus
from dran_edge.comms.link import NeighbourLink
from dran_edge.daemon.service import LinkTransport
from dran_edge.messages import NeighbourMessage, ObjectEntry

KEY = bytes(range(32))


def _transport(bus, me, others, heartbeat_s):
    policy = AuthPolicy(
        fleet_id=1, self_id=me, fleet_robots=frozenset({1, 2, 3}), neighbours=frozenset(others)
    )
    link = NeighbourLink(bus.endpoint(me), key=KEY, policy=policy, boot_epoch=1)
    return LinkTransport(link, {j: f"r{j}" for j in others}, heartbeat_period_s=heartbeat_s)


def _status(t):
    return {
        "state": "running",
        "robot": {"id": 1, "name": "r1", "fleet": "f"},
        "neighbours": t.stats()["neighbours"],
        "transport": t.stats(),
    }


def test_never_heard_then_heartbeats():
    bus = Bus([1, 2, 3], graph=[(1, 2), (1, 3)])
    a = _transport(bus, 1, [2, 3], heartbeat_s=0.0)
    b = _transport(bus, 2, [1], heartbeat_s=0.05)
    _transport(bus, 3, [1], heartbeat_s=0.05)  # robot 3 is silent: its daemon never ticks
    text = format_status(_status(a))
    assert "r2 (id 2): never heard" in text and "r3 (id 3): never heard" in text
    # robot 2 has nothing to send: its heartbeats make it visible, robot 3 stays unheard
    now = time.time_ns()
    assert b.heartbeat(now) == 1
    assert b.heartbeat(now + 10_000_000) == 0  # not due again before 0.05 s
    bus.advance()
    got = a.receive()
    assert len(got) == 1 and got[0].message.sender_id == 2
    assert not (got[0].message.separators or got[0].message.objects)
    st = _status(a)
    assert a.heartbeats_received == 1 and b.heartbeats_sent == 1
    text = format_status(st)
    assert "r2 (id 2): heard 0.0 s ago" in text and "r3 (id 3): never heard" in text
    assert st["neighbours"]["2"]["bytes_received"] > 0
    # a robot that sends real messages sends no heartbeats meanwhile
    b.send(NeighbourMessage(2, 3, now, objects=(ObjectEntry(5, np.eye(4), 2),)), (1,))
    assert b.heartbeat(time.time_ns()) == 0 and b.heartbeats_sent == 1
    a_off = _transport(Bus([1, 2]), 1, [2], heartbeat_s=0.0)
    assert a_off.heartbeat(now) == 0
