"""In-process bus: N robots' transports in one process, with a network model.

What simulation, replay and the benchmarks use instead of UDP. It carries the same encoded,
authenticated bytes as ``radio.RadioTransport`` and counts every byte per sender, receiver
and kind. Time is counted in *rounds* (the 2 Hz DRAN tick); the bus owns no clock.

Usage::

    from dran_edge.comms.bus import Bus, BusParams, Partition, random_connected_graph

    ids = list(range(5))
    bus = Bus(ids, graph=random_connected_graph(ids, rho=0.3, seed=1),
              params=BusParams(loss_probability=0.1, latency_rounds=1, seed=7),
              partitions=[Partition(frozenset({3, 4}), start_round=10, end_round=20)])
    ep = {i: bus.endpoint(i) for i in ids}          # each is a transport.Transport
    for k in range(100):
        for i in ids:
            for sender, data in ep[i].receive():    # what arrived by round k
                ...                                 # verify, decode, feed the agent
            for j in bus.neighbours(i):             # links up in round k
                ep[i].send(j, datagram)
        bus.advance()                               # round k -> k + 1

Model (all deterministic for a fixed ``BusParams.seed`` and the same call sequence):

- Communication graph: any callable ``round -> iterable of undirected (a, b) edges``;
  helpers ``static_graph(edges)``, ``random_connected_graph(ids, rho, seed)`` (each edge with
  probability rho, then components joined by random edges so the graph is connected), and
  ``scheduled_graph([(start_round, edges), ...])`` (piecewise constant, time-varying).
- Partitions: ``Partition(robots, start_round, end_round)`` cuts every link between a robot in
  ``robots`` and one outside during rounds ``[start_round, end_round)``.
- A datagram sent in round k over a link that is up in round k is lost with probability
  ``link_loss.get((a, b), loss_probability)``, else delivered at round
  ``k + latency_rounds + U{0..max_extra_latency_rounds}`` (extra latency reorders), and
  duplicated with ``duplicate_probability``. Each directed link draws from its own seeded
  generator, so one robot's traffic never changes another link's fate.
  ``BusEndpoint.send(to, data, latency_rounds=0)`` overrides the base latency for one
  datagram (synchronous exchanges such as the distributed initialisation: receivable in the
  round it was sent).
- ``send`` returns False (and counts the reason) only for local refusals: a datagram over
  ``max_datagram_bytes``, an unknown robot, or itself. Link-down and random losses count as
  lost in ``Bus.stats()`` after the sender counted the bytes as sent — as on a real radio.
"""

from __future__ import annotations

import heapq
import itertools
import random
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable, Iterable, Mapping

from dran_edge.comms.codec import HARD_CAP_BYTES, bytes_by_kind
from dran_edge.comms.counters import CommCounters
from dran_edge.errors import ConfigError

Edge = tuple[int, int]
CommGraph = Callable[[int], Iterable[Edge]]


def _norm(edges: Iterable[Edge]) -> frozenset[Edge]:
    out = set()
    for a, b in edges:
        a, b = int(a), int(b)
        if a == b:
            raise ConfigError(f"communication graph has a self-loop on robot {a}")
        out.add((a, b) if a < b else (b, a))
    return frozenset(out)


def static_graph(edges: Iterable[Edge]) -> CommGraph:
    """The same undirected edges in every round."""
    fixed = _norm(edges)
    return lambda round_: fixed


def complete_graph(robot_ids: Iterable[int]) -> CommGraph:
    ids = sorted(int(i) for i in robot_ids)
    return static_graph(itertools.combinations(ids, 2))


def random_connected_graph(robot_ids: Iterable[int], rho: float, seed: int) -> CommGraph:
    """Static G(n, rho) made connected: each pair linked with probability rho, then each
    remaining component joined to the growing connected part by one random edge."""
    if not 0.0 <= rho <= 1.0:
        raise ConfigError(f"edge probability rho must be in [0, 1], got {rho}")
    ids = sorted(int(i) for i in robot_ids)
    rng = random.Random(f"dran-graph:{seed}")
    edges = {(a, b) for a, b in itertools.combinations(ids, 2) if rng.random() < rho}
    parent = {i: i for i in ids}

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in edges:
        parent[find(a)] = find(b)
    components: dict[int, list[int]] = defaultdict(list)
    for i in ids:
        components[find(i)].append(i)
    comps = sorted(components.values())
    joined = list(comps[0]) if comps else []
    for comp in comps[1:]:
        a, b = rng.choice(joined), rng.choice(comp)
        edges.add((min(a, b), max(a, b)))
        joined.extend(comp)
    return static_graph(edges)


def scheduled_graph(schedule: Iterable[tuple[int, Iterable[Edge]]]) -> CommGraph:
    """Piecewise-constant graph ``[(start_round, edges), ...]``; no edges before the first."""
    steps = sorted((int(r), _norm(e)) for r, e in schedule)

    def at(round_: int) -> frozenset[Edge]:
        current: frozenset[Edge] = frozenset()
        for start, edges in steps:
            if start > round_:
                break
            current = edges
        return current

    return at


@dataclass(frozen=True)
class Partition:
    """Robots cut off from all others during rounds [start_round, end_round)."""

    robots: frozenset[int]
    start_round: int
    end_round: int

    def cuts(self, a: int, b: int, round_: int) -> bool:
        return self.start_round <= round_ < self.end_round and (
            (a in self.robots) != (b in self.robots)
        )


@dataclass(frozen=True)
class BusParams:
    """Network model of the bus."""

    #: Probability that a datagram on a link is lost (each datagram independently).
    loss_probability: float = 0.0
    #: Per directed link (sender, receiver) loss probability overriding ``loss_probability``.
    link_loss: Mapping[Edge, float] = field(default_factory=dict)
    #: Rounds between sending and delivery (1: sent in round k, receivable from round k+1).
    latency_rounds: int = 1
    #: Extra latency drawn uniformly from {0..max_extra_latency_rounds} per datagram (reorders).
    max_extra_latency_rounds: int = 0
    #: Probability that a delivered datagram arrives twice.
    duplicate_probability: float = 0.0
    #: Datagrams above this many bytes are refused by ``send`` (like the radio's cap).
    max_datagram_bytes: int = HARD_CAP_BYTES
    #: Seed of every random choice of the bus.
    seed: int = 0

    def __post_init__(self):
        probs = [self.loss_probability, self.duplicate_probability, *self.link_loss.values()]
        if not all(0.0 <= p <= 1.0 for p in probs):
            raise ConfigError(f"bus probabilities must be in [0, 1], got {probs}")
        if self.latency_rounds < 0 or self.max_extra_latency_rounds < 0:
            raise ConfigError("latency_rounds and max_extra_latency_rounds must be >= 0")
        if not 1 <= self.max_datagram_bytes <= HARD_CAP_BYTES:
            raise ConfigError(f"max_datagram_bytes must be in [1, {HARD_CAP_BYTES}]")


class Bus:
    """The shared medium; see the module docstring."""

    def __init__(
        self,
        robot_ids: Iterable[int],
        graph: CommGraph | Iterable[Edge] | None = None,
        params: BusParams = BusParams(),
        partitions: Iterable[Partition] = (),
        classify: Callable[[bytes], dict] = bytes_by_kind,
    ):
        self.robot_ids = tuple(sorted(int(i) for i in robot_ids))
        if len(set(self.robot_ids)) != len(self.robot_ids):
            raise ConfigError(f"robot ids must be unique, got {self.robot_ids}")
        if graph is None:
            graph = complete_graph(self.robot_ids)
        elif not callable(graph):
            graph = static_graph(graph)
        self.graph: CommGraph = graph
        self.params = params
        self.partitions = tuple(partitions)
        self.classify = classify
        self.round = 0
        self._queues: dict[int, list] = {i: [] for i in self.robot_ids}
        self._order = itertools.count()
        self._rngs: dict[Edge, random.Random] = {}
        self._edges_cache: tuple[int, frozenset[Edge]] | None = None
        self._endpoints: dict[int, BusEndpoint] = {}
        #: bytes sent per (sender, receiver, kind), including datagrams later lost.
        self.bytes_sent: dict[tuple[int, int, str], int] = defaultdict(int)
        self.datagrams_sent = 0
        self.datagrams_delivered = 0
        self.lost: dict[str, int] = defaultdict(int)

    # ------------------------------------------------------------------ topology
    def edges(self, round_: int | None = None) -> frozenset[Edge]:
        r = self.round if round_ is None else round_
        if self._edges_cache is None or self._edges_cache[0] != r:
            self._edges_cache = (r, _norm(self.graph(r)))
        return self._edges_cache[1]

    def link_up(self, a: int, b: int, round_: int | None = None) -> bool:
        r = self.round if round_ is None else round_
        if (min(a, b), max(a, b)) not in self.edges(r):
            return False
        return not any(p.cuts(a, b, r) for p in self.partitions)

    def neighbours(self, robot: int, round_: int | None = None) -> list[int]:
        """Robots with a link to ``robot`` that is up in this round (partitions applied)."""
        r = self.round if round_ is None else round_
        out = []
        for a, b in self.edges(r):
            other = b if a == robot else a if b == robot else None
            if other is not None and self.link_up(robot, other, r):
                out.append(other)
        return sorted(out)

    # ------------------------------------------------------------------ traffic
    def endpoint(self, robot: int) -> BusEndpoint:
        robot = int(robot)
        if robot not in self._queues:
            raise ConfigError(f"robot {robot} is not on this bus (robots: {self.robot_ids})")
        if robot not in self._endpoints:
            self._endpoints[robot] = BusEndpoint(self, robot)
        return self._endpoints[robot]

    def advance(self, rounds: int = 1) -> None:
        """Move the bus clock forward; datagrams due by the new round become receivable."""
        self.round += int(rounds)

    def _rng(self, a: int, b: int) -> random.Random:
        rng = self._rngs.get((a, b))
        if rng is None:
            rng = self._rngs[(a, b)] = random.Random(f"dran-bus:{self.params.seed}:{a}:{b}")
        return rng

    def _transmit(self, a: int, b: int, data: bytes, latency_rounds: int | None = None) -> None:
        p = self.params
        self.datagrams_sent += 1
        for kind, n in self.classify(data).items():
            self.bytes_sent[(a, b, kind)] += n
        if not self.link_up(a, b):
            self.lost["no_link"] += 1
            return
        rng = self._rng(a, b)
        # Draw all per-datagram randomness every time so outcomes stay aligned per link.
        u_loss, u_dup = rng.random(), rng.random()
        extra = rng.randint(0, p.max_extra_latency_rounds) if p.max_extra_latency_rounds else 0
        if u_loss < p.link_loss.get((a, b), p.loss_probability):
            self.lost["loss"] += 1
            return
        base = p.latency_rounds if latency_rounds is None else latency_rounds
        due = self.round + base + extra
        copies = 2 if u_dup < p.duplicate_probability else 1
        for _ in range(copies):
            heapq.heappush(self._queues[b], (due, next(self._order), a, data))

    def _collect(self, robot: int, max_datagrams: int | None) -> list[tuple[int, bytes]]:
        q = self._queues[robot]
        out = []
        while q and q[0][0] <= self.round and (max_datagrams is None or len(out) < max_datagrams):
            _, _, sender, data = heapq.heappop(q)
            out.append((sender, data))
        self.datagrams_delivered += len(out)
        return out

    def pending(self) -> int:
        """Datagrams in flight (sent, not yet received)."""
        return sum(len(q) for q in self._queues.values())

    def stats(self) -> dict:
        """JSON-ready totals: bytes per sender / receiver / kind, losses by reason."""
        per_sender: dict[int, int] = defaultdict(int)
        per_receiver: dict[int, int] = defaultdict(int)
        per_kind: dict[str, int] = defaultdict(int)
        for (a, b, kind), n in self.bytes_sent.items():
            per_sender[a] += n
            per_receiver[b] += n
            per_kind[kind] += n
        return {
            "round": self.round,
            "datagrams_sent": self.datagrams_sent,
            "datagrams_delivered": self.datagrams_delivered,
            "bytes_total": sum(per_sender.values()),
            "bytes_by_sender": {str(k): v for k, v in sorted(per_sender.items())},
            "bytes_by_receiver": {str(k): v for k, v in sorted(per_receiver.items())},
            "bytes_by_kind": dict(sorted(per_kind.items())),
            "lost": dict(self.lost),
        }


class BusEndpoint:
    """One robot's ``transport.Transport`` on a ``Bus``."""

    def __init__(self, bus: Bus, robot: int):
        self.bus = bus
        self.robot = robot
        self.counters = CommCounters()
        self._closed = False

    def send(self, to: int, data: bytes, latency_rounds: int | None = None) -> bool:
        """``Transport.send``; ``latency_rounds`` overrides ``BusParams.latency_rounds`` for this
        datagram (loss, extra latency and duplication still apply). Synchronous exchanges in
        simulation use 0: sent in round k, receivable in round k (``multiagent.Fleet``'s
        initialisation rounds)."""
        if latency_rounds is not None and latency_rounds < 0:
            raise ConfigError(f"latency_rounds must be >= 0, got {latency_rounds}")
        data = bytes(data)
        n = len(data)
        if self._closed:
            self.counters.dropped(to, n, "closed")
            return False
        if n > self.bus.params.max_datagram_bytes:
            self.counters.dropped(to, n, "over_cap")
            return False
        if to not in self.bus._queues or to == self.robot:
            self.counters.dropped(to, n, "unknown_peer")
            return False
        self.counters.sent(to, n)
        self.bus._transmit(self.robot, to, data, latency_rounds)
        return True

    def receive(self, max_datagrams: int | None = None) -> list[tuple[int | None, bytes]]:
        if self._closed:
            return []
        got = self.bus._collect(self.robot, max_datagrams)
        for sender, data in got:
            self.counters.received(sender, len(data))
        return got

    def close(self) -> None:
        self._closed = True
