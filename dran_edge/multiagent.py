"""N DRAN agents in one process, talking through encoded datagrams over the in-process bus.

Every message an agent emits is encoded by the wire codec (``dran_edge.comms.codec``) into
self-contained datagrams and sent through the robot's endpoint of a ``dran_edge.comms.bus.Bus``
— the same bus replay uses — so the graph, partitions, loss, latency and the byte counters
(every byte of every datagram: header, entries and the 16-byte tag slot, per sender, receiver
and kind) are the bus's. Datagrams are decoded again before the receiving agent sees them, so
the agents face exactly what the radio would give them.

Rounds are synchronous and are the bus's rounds: in round k every agent first absorbs the
datagrams due by round k, then runs its round (``Tick``); its messages go to the neighbours
whose link is up in round k (``Bus.neighbours``) and, with ``BusParams.latency_rounds = 1``
(the default), are receivable in round k + 1. Initialisation rounds (``init_exchange``) are
synchronous exchanges: sent and received in the same round (per-datagram latency 0), loss
still applies. Everything random is the bus's (seeded per directed link by
``BusParams.seed``), so the same seed gives the same run.

This module is a shell around the pure core (it imports the codec and the bus); the agents stay
pure.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from dran_edge.agent import Agent
from dran_edge.comms import codec
from dran_edge.comms.bus import Bus, BusParams
from dran_edge.consensus import metropolis_hastings_matrix
from dran_edge.errors import DecodeError
from dran_edge.events import EstimateUpdate, NeighbourData, Outgoing, Tick
from dran_edge.messages import InitStage, NeighbourMessage

log = logging.getLogger(__name__)

ROUND_PERIOD_NS = 500_000_000  # 2 Hz, the robots' round rate (stamps only; nothing sleeps)


def neighbour_weights(bus: Bus, round_: int = 0) -> list[dict]:
    """Per robot (index into ``bus.robot_ids``): neighbour -> Metropolis–Hastings weight
    (``consensus.metropolis_hastings_matrix``) on the bus's graph in ``round_``."""
    ids = bus.robot_ids
    index = {r: k for k, r in enumerate(ids)}
    A = np.zeros((len(ids), len(ids)), dtype=bool)
    for a, b in bus.edges(round_):
        A[index[a], index[b]] = A[index[b], index[a]] = True
    W = metropolis_hastings_matrix(A)
    return [{ids[j]: W[i, j] for j in np.flatnonzero(A[i])} for i in range(len(ids))]


@dataclass(frozen=True)
class Traffic:
    """What crossed the bus so far (a view of ``Bus.stats()`` plus the decode failures)."""

    datagrams: int
    """Datagrams handed to the bus (each recipient counts once)."""
    bytes_total: int
    """Every byte of those datagrams, including the ones the link model then lost."""
    dropped: int
    """Datagrams the link model lost (all reasons of ``Bus.lost``)."""
    decode_errors: int
    """Delivered datagrams the codec rejected."""
    bytes_by_kind: dict
    bytes_by_robot: dict
    """Bytes sent per sender (string keys, as in ``Bus.stats()``)."""


class Fleet:
    """Agents (agent i is robot ``bus.robot_ids[i]``) and the datagram exchange between them."""

    def __init__(self, agents: list[Agent], bus: Bus,
                 max_datagram_bytes: int = codec.DEFAULT_MAX_DATAGRAM_BYTES, fleet_id: int = 1):
        self.agents = agents
        self.bus = bus
        self.ids = bus.robot_ids
        self.endpoints = [bus.endpoint(r) for r in self.ids]
        self.max_datagram_bytes = max_datagram_bytes
        self.fleet_id = fleet_id
        self.sequence = [0] * len(self.ids)
        self.decode_errors = 0
        self.estimates: list[EstimateUpdate | None] = [None] * len(agents)
        self.step_ms: list[float] = []

    @property
    def round(self) -> int:
        return self.bus.round

    @property
    def traffic(self) -> Traffic:
        st = self.bus.stats()
        return Traffic(st["datagrams_sent"], st["bytes_total"], int(sum(st["lost"].values())),
                       self.decode_errors, st["bytes_by_kind"], st["bytes_by_sender"])

    def send(self, sender: int, message: NeighbourMessage, to, latency_rounds: int | None = None
             ) -> None:
        """Encode once, then hand every datagram to the bus for every recipient in ``to`` whose
        link is up this round (agent indices)."""
        grams = codec.encode_datagrams(message, fleet_id=self.fleet_id, boot_epoch=1,
                                       first_sequence=self.sequence[sender],
                                       max_datagram_bytes=self.max_datagram_bytes)
        self.sequence[sender] += len(grams)
        up = set(self.bus.neighbours(self.ids[sender]))
        ep = self.endpoints[sender]
        for q in to:
            if self.ids[q] not in up:
                continue
            for g in grams:
                ep.send(self.ids[q], g.data, latency_rounds)

    def _receive(self) -> list[list[NeighbourMessage]]:
        inbox: list[list[NeighbourMessage]] = [[] for _ in self.ids]
        for i, ep in enumerate(self.endpoints):
            for _sender, data in ep.receive():
                try:
                    inbox[i].append(codec.decode_datagram(data))
                except DecodeError:
                    self.decode_errors += 1
        return inbox

    # ----------------------------------------------------------------- DRAN rounds
    def step(self) -> bool:
        """One synchronous round; returns True when every agent reports convergence."""
        self.bus.advance()
        rnd = self.bus.round
        inbox = self._receive()
        stamp = rnd * ROUND_PERIOD_NS
        outgoing = []
        for i, agent in enumerate(self.agents):
            for msg in inbox[i]:
                agent.handle(NeighbourData(stamp, msg))
            t0 = time.perf_counter()
            outs = agent.handle(Tick(stamp))
            self.step_ms.append(1e3 * (time.perf_counter() - t0))
            for o in outs:
                if isinstance(o, Outgoing):
                    outgoing.append((i, o))
                elif isinstance(o, EstimateUpdate):
                    self.estimates[i] = o
        for i, o in outgoing:
            self.send(i, o.message, o.to)
        return all(e is not None and e.converged for e in self.estimates)

    # ----------------------------------------------------------------- initialisation rounds
    def init_exchange(self, stage: InitStage, iteration: int, outgoing: dict) -> dict:
        """``dist_init.Exchange`` over encoded datagrams: one bus round, delivered in it."""
        self.bus.advance()
        rnd = self.bus.round
        for r, sends in outgoing.items():
            for q, entries in sends:
                msg = NeighbourMessage(r, rnd, rnd * ROUND_PERIOD_NS, init=tuple(entries))
                self.send(r, msg, (q,), latency_rounds=0)
        incoming: dict[int, list] = defaultdict(list)
        for q, msgs in enumerate(self._receive()):
            for m in msgs:
                incoming[q].extend(m.init)
        return incoming

    def run(self, max_rounds: int, min_rounds: int = 1, patience: int = 3, callback=None) -> int:
        """Rounds until every agent has reported convergence ``patience`` rounds in a row."""
        streak = 0
        for k in range(max_rounds):
            done = self.step()
            streak = streak + 1 if done else 0
            if callback is not None:
                callback(k + 1, self)
            if k + 1 >= min_rounds and streak >= patience:
                return k + 1
        return max_rounds


# --------------------------------------------------------------------------- Table 1 driver
def run_g2o_dran(g, num_robots: int, config, init_params=None, max_rounds: int | None = None,
                 links: BusParams | None = None, partitions=(), callback=None) -> dict:
    """Table 1 protocol: contiguous split, distributed chordal init, DRAN until every robot has
    converged (or K_max), over a bus on the split's neighbour graph with network model
    ``links`` (default lossless) and ``partitions``. Returns the merged poses and the numbers
    the bench reports."""
    import dataclasses

    from dran_edge.agent import LocalProblem
    from dran_edge.dist_init import InitParams, distributed_chordal_init
    from dran_edge.objective import sesync_objective, sesync_weights
    from dran_edge.partition import partition_contiguous

    t_start = time.perf_counter()
    kappa, tau = sesync_weights(g.dim, g.information)
    part = partition_contiguous(g.edges, g.num_vertices, num_robots)
    bus = Bus(range(num_robots), graph=part.neighbour_pairs(), params=links or BusParams(),
              partitions=partitions)
    W = neighbour_weights(bus)
    fleet = Fleet([], bus)
    init = distributed_chordal_init(g.dim, g.num_vertices, g.edges, g.measurements, kappa, tau,
                                    part, fleet.init_exchange, init_params or InitParams(gauss_seidel=True))
    init_rounds, init_bytes = fleet.round, fleet.traffic.bytes_total
    F = lambda T: sesync_objective(T, g.edges, g.measurements, kappa, tau)
    F_init = F(init.poses)
    agents = []
    for r in range(num_robots):
        cfg = dataclasses.replace(config, robot_id=r, neighbours=tuple(sorted(W[r])), dim=g.dim)
        prob = LocalProblem.from_partition(g, part, r, init.poses, kappa, tau, cfg.residual)
        agent = Agent(cfg, prob, weights=W[r])
        # the init's last exchange left every robot with its neighbours' separators
        for p in part.parts:
            if p.robot_id == r:
                continue
            for v in p.vertices[np.isin(p.vertices, part.parts[r].anchors)].tolist():
                agent.anchors[(p.robot_id, v)] = init.poses[v].copy()
        agents.append(agent)
    fleet.agents = agents
    fleet.estimates = [None] * num_robots
    rounds = fleet.run(max_rounds or config.k_max, callback=callback)
    merged = init.poses.copy()
    for r, p in enumerate(part.parts):
        merged[p.vertices] = agents[r].x
    return {
        "poses": merged,
        "rounds": rounds,
        "init_rounds": init_rounds,
        "rounds_total": init_rounds + rounds,
        "bytes_init": init_bytes,
        "bytes_total": fleet.traffic.bytes_total,
        "datagrams": fleet.traffic.datagrams,
        "objective_init": F_init,
        "objective_final": F(merged),
        "local_step_ms_median": float(np.median(fleet.step_ms)) if fleet.step_ms else 0.0,
        "wall_s": time.perf_counter() - t_start,
    }
