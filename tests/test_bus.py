"""In-process bus: graphs, loss, latency, partitions, determinism, byte accounting."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from dran_edge.comms import codec
from dran_edge.comms.auth import AuthPolicy
from dran_edge.comms.bus import (
    Bus,
    BusParams,
    Partition,
    random_connected_graph,
    scheduled_graph,
    static_graph,
)
from dran_edge.comms.link import NeighbourLink
from dran_edge.comms.transport import Transport
from dran_edge.errors import ConfigError
from dran_edge.messages import NeighbourMessage, ObjectEntry, SeparatorEntry


def _connected(ids, edges):
    seen, todo = {ids[0]}, [ids[0]]
    while todo:
        a = todo.pop()
        for x, y in edges:
            for u, v in ((x, y), (y, x)):
                if u == a and v not in seen:
                    seen.add(v)
                    todo.append(v)
    return seen == set(ids)


def _flood(bus, rounds, payload=lambda i, j, k: bytes([i, j, k % 256])):
    """Every robot sends to every up-neighbour each round; returns the deliveries in order."""
    log = []
    for k in range(rounds):
        for i in bus.robot_ids:
            ep = bus.endpoint(i)
            log.extend((k, i, s, d) for s, d in ep.receive())
            for j in bus.neighbours(i):
                ep.send(j, payload(i, j, k))
        bus.advance()
    return log


def test_endpoint_is_a_transport():
    assert isinstance(Bus([0, 1]).endpoint(0), Transport)


@pytest.mark.parametrize("rho", [0.0, 0.1, 0.3, 1.0])
def test_random_connected_graph_is_connected_and_seeded(rho):
    ids = list(range(21))
    for seed in range(20):
        edges = random_connected_graph(ids, rho, seed)(0)
        assert _connected(ids, edges)
        assert edges == random_connected_graph(ids, rho, seed)(5)
    if rho == 1.0:
        assert len(edges) == 21 * 20 // 2
    if rho == 0.0:
        assert len(edges) == 20  # a spanning tree
    dens = np.mean([len(random_connected_graph(ids, 0.5, s)(0)) for s in range(30)]) / 210
    assert 0.45 < dens < 0.55


def test_latency_and_determinism():
    bus = Bus([0, 1, 2], graph=[(0, 1), (1, 2)], params=BusParams(latency_rounds=2))
    log = _flood(bus, 6)
    # Sent in round k, received in round k + 2 exactly.
    assert all(k == d[2] + 2 for k, _, _, d in log)
    # 2 robots x 1 neighbour + 1 robot x 2 neighbours = 4 per round, rounds 0..3 arrive.
    assert len(log) == 4 * 4
    again = _flood(Bus([0, 1, 2], graph=[(0, 1), (1, 2)], params=BusParams(latency_rounds=2)), 6)
    assert again == log


def test_loss_rate_per_link_and_independence():
    p = BusParams(loss_probability=0.3, link_loss={(0, 1): 1.0, (1, 0): 0.0}, seed=5)
    bus = Bus([0, 1, 2], graph=[(0, 1), (0, 2)], params=p)
    log = _flood(bus, 2001)
    got = {(s, r): 0 for s, r in [(0, 1), (1, 0), (0, 2), (2, 0)]}
    for _, r, s, _ in log:
        got[(s, r)] += 1
    assert got[(0, 1)] == 0 and got[(1, 0)] == 2000
    assert 0.66 < got[(0, 2)] / 2000 < 0.74 and 0.66 < got[(2, 0)] / 2000 < 0.74
    st = bus.stats()
    assert st["datagrams_sent"] == 4 * 2001
    assert st["lost"]["loss"] + st["datagrams_delivered"] + bus.pending() == st["datagrams_sent"]
    assert st["datagrams_delivered"] == len(log)
    # Another link's traffic does not change link (0, 2)'s fate.
    bus2 = Bus([0, 1, 2], graph=[(0, 2)], params=p)
    log2 = _flood(bus2, 2001)
    assert [(k, d) for k, r, s, d in log if (s, r) == (0, 2)] == [
        (k, d) for k, r, s, d in log2 if (s, r) == (0, 2)
    ]
    # Different seed, different losses.
    log3 = _flood(
        Bus([0, 1, 2], graph=[(0, 2)], params=BusParams(loss_probability=0.3, seed=6)), 200
    )
    assert [d for *_, d in log3] != [d for *_, d in log2[: len(log3)]]


def test_partition_cuts_links_only_during_its_rounds():
    part = Partition(frozenset({2, 3}), start_round=3, end_round=6)
    bus = Bus(range(4), graph=None, partitions=[part])
    assert bus.neighbours(0, 2) == [1, 2, 3]
    assert bus.neighbours(0, 3) == [1] and bus.neighbours(2, 4) == [3]
    assert bus.neighbours(0, 6) == [1, 2, 3]
    # Sending across the cut anyway: counted as sent, lost as no_link.
    bus.advance(4)
    assert bus.endpoint(0).send(2, b"x")
    bus.advance()
    assert bus.endpoint(2).receive() == []
    assert bus.stats()["lost"] == {"no_link": 1}


def test_scheduled_graph_changes_over_time():
    g = scheduled_graph([(0, [(0, 1)]), (5, [(1, 2)]), (10, [(0, 1), (1, 2)])])
    bus = Bus([0, 1, 2], graph=g)
    assert bus.neighbours(1, 0) == [0] and bus.neighbours(1, 5) == [2]
    assert bus.neighbours(1, 12) == [0, 2] and bus.neighbours(2, 3) == []
    with pytest.raises(ConfigError):
        static_graph([(1, 1)])


def test_reordering_and_duplicates():
    bus = Bus(
        [0, 1], params=BusParams(max_extra_latency_rounds=3, duplicate_probability=0.5, seed=1)
    )
    for k in range(200):
        bus.endpoint(0).send(1, k.to_bytes(2, "little"))
        bus.advance()
    bus.advance(5)
    got = [int.from_bytes(d, "little") for _, d in bus.endpoint(1).receive()]
    assert sorted(set(got)) == list(range(200))
    assert got != sorted(got)  # reordered
    assert 60 < len(got) - 200 < 140  # ~50 % duplicated


def test_local_refusals_are_counted():
    bus = Bus([0, 1], params=BusParams(max_datagram_bytes=100))
    ep = bus.endpoint(0)
    assert not ep.send(1, bytes(101))
    assert not ep.send(7, b"x")
    assert not ep.send(0, b"x")
    assert ep.send(1, bytes(100))
    reasons = {k: dict(v.dropped_by_reason) for k, v in ep.counters.peers.items()}
    assert reasons == {1: {"over_cap": 1}, 7: {"unknown_peer": 1}, 0: {"unknown_peer": 1}}
    with pytest.raises(ConfigError):
        BusParams(loss_probability=1.5)
    with pytest.raises(ConfigError):
        bus.endpoint(5)


def test_links_over_the_bus_count_every_byte_by_kind():
    ids = [0, 1, 2]
    key = bytes(32)
    bus = Bus(ids, graph=[(0, 1), (1, 2)])
    links = {
        i: NeighbourLink(
            bus.endpoint(i),
            key=key,
            boot_epoch=1,
            policy=AuthPolicy(
                fleet_id=3,
                self_id=i,
                fleet_robots=frozenset(ids),
                neighbours=frozenset(bus.neighbours(i)),
            ),
        )
        for i in ids
    }
    sent_bytes = 0
    received = {i: [] for i in ids}
    for k in range(4):
        for i in ids:
            received[i] += links[i].poll(now_ns=k)
            msg = NeighbourMessage(
                sender_id=i,
                round=k,
                stamp_ns=k,
                separators=tuple(SeparatorEntry(i, j, k, np.eye(4)) for j in range(30)),
                objects=tuple(ObjectEntry(j, np.eye(4), i) for j in range(30)),
            )
            for d in links[i].send_message(msg, bus.neighbours(i)):
                sent_bytes += len(d) * len(bus.neighbours(i))
        bus.advance()
    st = bus.stats()
    assert st["bytes_total"] == sent_bytes
    assert sum(st["bytes_by_kind"].values()) == sent_bytes
    assert set(st["bytes_by_kind"]) == set(codec.KINDS) - {"init"} | {"init"}
    assert st["bytes_by_kind"]["init"] == 0 and st["bytes_by_kind"]["separator"] > 0
    # Robot 1 heard both neighbours in rounds 1..3; two datagrams per message.
    assert sorted({m.sender_id for m in received[1]}) == [0, 2]
    assert len(received[1]) == 2 * 2 * 3
    c1 = links[1].counters.snapshot()["peers"]
    assert c1["0"]["last_heard_ns"] == 3 and c1["0"]["received_bytes_by_kind"]["object"] > 0
    # 30 separators + 30 objects (24 B each) span two datagrams: all separators and 18
    # objects in the first, 12 objects in the second -> over rounds 1..3, 3 datagrams carry
    # separators and 6 carry objects.
    assert c1["0"]["received_datagrams_by_kind"] == {"separator": 3, "object": 6}
    assert sum(links[1].counters.totals()[k] for k in ("datagrams_rejected",)) == 0
    # Byte totals agree between the bus (what went on the wire) and the links' counters.
    assert sum(links[i].counters.totals()["bytes_sent"] for i in ids) == sent_bytes
    assert list(itertools.chain.from_iterable(m.separators for m in received[0]))


def test_per_datagram_latency_override_delivers_in_the_same_round():
    bus = Bus([0, 1, 2], graph=[(0, 1), (1, 2)], params=BusParams(latency_rounds=2, seed=3))
    e0, e1 = bus.endpoint(0), bus.endpoint(1)
    bus.advance()
    assert e0.send(1, b"now", latency_rounds=0)
    assert e0.send(1, b"later")
    assert e0.send(1, b"next", latency_rounds=1)
    assert e1.receive() == [(0, b"now")]
    bus.advance()
    assert e1.receive() == [(0, b"next")]
    bus.advance()
    assert e1.receive() == [(0, b"later")]
    # The override is still subject to the link model: no link, no delivery, bytes counted.
    assert e0.send(2, b"x", latency_rounds=0) and bus.endpoint(2).receive() == []
    assert bus.lost["no_link"] == 1 and bus.stats()["bytes_total"] == 3 + 5 + 4 + 1
    with pytest.raises(ConfigError):
        e0.send(1, b"y", latency_rounds=-1)


def test_links_with_delta_entries_rebuild_values_and_survive_replays_and_restarts():
    """NeighbourLink with delta_every: values arrive within the quantisation bound at a
    fraction of the bytes; a replayed datagram is rejected before it can touch the delta
    state; a restarted sender (new boot epoch, rounds starting over) is decoded afresh."""
    from dran_edge import geometry as geo

    ids = [0, 1]
    bus = Bus(ids, graph=[(0, 1)])

    def link(i, epoch=1, delta=5):
        return NeighbourLink(
            bus.endpoint(i),
            key=bytes(32),
            boot_epoch=epoch,
            delta_every=delta,
            policy=AuthPolicy(
                fleet_id=3, self_id=i, fleet_robots=frozenset(ids), neighbours=frozenset({1 - i})
            ),
        )

    a, b = link(0), link(1)
    rng = np.random.default_rng(1)
    T = geo.se3_exp(rng.normal(0, 1, (20, 6)))

    def message(k):
        return NeighbourMessage(0, k, k, tuple(SeparatorEntry(0, j, j, T[j]) for j in range(20)))

    sizes, got = [], []
    for k in range(1, 9):
        T = T @ geo.se3_exp(rng.normal(0, 1e-2, (20, 6)))
        sizes.append(sum(map(len, a.send_message(message(k), [1]))))
        bus.advance()
        (m,) = b.poll()
        got = {e.keyframe_id: e.T_world_body for e in m.separators}
        assert len(got) == 20 and max(np.abs(got[j] - T[j]).max() for j in range(20)) < 5e-4
    assert max(sizes[1:5]) < 0.5 * sizes[0] and sizes[5] == sizes[0]  # absolute every 5 rounds
    replay = b.accepted_datagrams = []
    a.send_message(message(9), [1])
    bus.advance()
    b.poll()
    state = {k: v[0].copy() for k, v in b._dec[0][1].held.items()}
    bus.endpoint(0).send(1, replay[0])  # the same datagram again
    bus.advance()
    assert b.poll() == [] and b.counters.totals()["datagrams_rejected"] == 1
    assert all(np.array_equal(v[0], state[k]) for k, v in b._dec[0][1].held.items())
    # robot 0 restarts: a larger boot epoch, its rounds start over at 1
    a2 = link(0, epoch=2)
    a2.send_message(message(1), [1])
    bus.advance()
    (m,) = b.poll()
    assert len(m.separators) == 20 and b.delta_unresolved == 0
    a2.send_message(message(2), [1])
    bus.advance()
    (m,) = b.poll()
    assert len(m.separators) == 20 and b.delta_unresolved == 0  # deltas on the new epoch's base
