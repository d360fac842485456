"""N DRAN agents in one process, talking through encoded datagrams (simulation and benchmarks).

Every message an agent emits is encoded by the wire codec (``dran_edge.comms.codec``) into
self-contained datagrams; each datagram to each recipient is counted (every byte: header,
entries and the 16-byte tag slot), may be dropped (per-datagram loss probability), is delayed by
``latency_rounds`` and is decoded again before the receiving agent sees it, so the agents face
exactly what the radio would give them. Rounds are synchronous: in round k every agent first
absorbs the datagrams due, then runs its round (``Tick``).

Communication graphs: explicit pairs, random connected with edge probability ρ (the paper's
Sec. 6.2), time-varying (a per-round random subset of a base graph) and partitions (rounds during
which links between groups are cut). Everything random draws from one seeded generator, so the
same seed gives the same run.

This module is a shell around the pure core (it imports the codec); the agents stay pure.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from dran_edge.agent import Agent
from dran_edge.comms import codec
from dran_edge.errors import DecodeError
from dran_edge.events import EstimateUpdate, NeighbourData, Outgoing, Tick
from dran_edge.messages import InitStage, NeighbourMessage

log = logging.getLogger(__name__)

ROUND_PERIOD_NS = 500_000_000  # 2 Hz, the robots' round rate (stamps only; nothing sleeps)


# --------------------------------------------------------------------------- topologies
def adjacency_from_pairs(n: int, pairs) -> np.ndarray:
    A = np.zeros((n, n), dtype=bool)
    for i, j in pairs:
        if i != j:
            A[i, j] = A[j, i] = True
    return A


def is_connected(A: np.ndarray) -> bool:
    n = A.shape[0]
    seen = np.zeros(n, bool)
    seen[0] = True
    frontier = [0]
    while frontier:
        i = frontier.pop()
        for j in np.flatnonzero(A[i] & ~seen):
            seen[j] = True
            frontier.append(int(j))
    return bool(seen.all())


def random_connected(n: int, rho: float, rng: np.random.Generator, max_tries: int = 1000) -> np.ndarray:
    """Erdős–Rényi graph G(n, ρ) redrawn until connected; after ``max_tries`` a random spanning
    tree is added (so very small ρ still gives a connected, sparse graph)."""
    for _ in range(max_tries):
        U = np.triu(rng.random((n, n)) < rho, 1)
        A = U | U.T
        if is_connected(A):
            return A
    order = rng.permutation(n)
    for k in range(1, n):
        i, j = order[k], order[rng.integers(0, k)]
        A[i, j] = A[j, i] = True
    return A


def metropolis_weights(A: np.ndarray) -> list[dict]:
    """Per robot: neighbour -> MH weight 1 / (1 + max(deg_i, deg_j))."""
    deg = A.sum(axis=1)
    return [{int(j): 1.0 / (1.0 + max(deg[i], deg[j])) for j in np.flatnonzero(A[i])}
            for i in range(A.shape[0])]


@dataclass(frozen=True)
class LinkModel:
    """Per-datagram behaviour of every link."""

    loss: float = 0.0
    """Probability that one datagram to one recipient is lost."""
    latency_rounds: int = 0
    """Extra rounds before delivery (0: available at the start of the next round)."""
    keep_probability: float = 1.0
    """Time-varying graph: each round each link of the base graph is up with this probability."""
    partitions: tuple = ()
    """(first_round, last_round, groups): during those rounds only links within a group work."""


@dataclass
class Traffic:
    """What crossed the simulated radio."""

    datagrams: int = 0
    bytes_total: int = 0
    dropped: int = 0
    decode_errors: int = 0
    by_kind: dict = field(default_factory=lambda: defaultdict(int))
    by_robot: dict = field(default_factory=lambda: defaultdict(int))


class Fleet:
    """Agents, a communication graph and the encoded-datagram exchange between them."""

    def __init__(self, agents: list[Agent], adjacency: np.ndarray, links: LinkModel = LinkModel(),
                 seed: int = 0, max_datagram_bytes: int = codec.DEFAULT_MAX_DATAGRAM_BYTES,
                 fleet_id: int = 1):
        self.agents = agents
        self.A = np.asarray(adjacency, dtype=bool)
        self.links = links
        self.rng = np.random.default_rng(seed)
        self.max_datagram_bytes = max_datagram_bytes
        self.fleet_id = fleet_id
        self.sequence = [0] * self.A.shape[0]
        self.queue: dict[int, list] = defaultdict(list)  # round due -> (to, bytes)
        self.traffic = Traffic()
        self.round = 0
        self.estimates: list[EstimateUpdate | None] = [None] * len(agents)
        self.step_ms: list[float] = []

    # ----------------------------------------------------------------- links
    def link_up(self, i: int, j: int, rnd: int) -> bool:
        if not self.A[i, j]:
            return False
        for first, last, groups in self.links.partitions:
            if first <= rnd <= last and not any(i in g and j in g for g in groups):
                return False
        return True

    def _round_up(self, rnd: int) -> np.ndarray:
        """Links up this round (time-varying draw is symmetric and made once per round)."""
        up = self.A.copy()
        if self.links.keep_probability < 1.0:
            U = np.triu(self.rng.random(self.A.shape) < self.links.keep_probability, 1)
            up &= U | U.T
        return up

    def send(self, sender: int, message: NeighbourMessage, to, rnd: int, up: np.ndarray) -> None:
        """Encode once, then count, drop or queue every datagram for every recipient."""
        grams = codec.encode_datagrams(message, fleet_id=self.fleet_id, boot_epoch=1,
                                       first_sequence=self.sequence[sender],
                                       max_datagram_bytes=self.max_datagram_bytes)
        self.sequence[sender] += len(grams)
        for q in to:
            if not (up[sender, q] and self.link_up(sender, q, rnd)):
                continue
            for g in grams:
                self.traffic.datagrams += 1
                self.traffic.bytes_total += len(g.data)
                self.traffic.by_robot[sender] += len(g.data)
                for k, v in g.bytes_by_kind.items():
                    self.traffic.by_kind[k] += v
                if self.links.loss > 0.0 and self.rng.random() < self.links.loss:
                    self.traffic.dropped += 1
                    continue
                self.queue[rnd + 1 + self.links.latency_rounds].append((q, g.data))

    def _deliver(self, rnd: int) -> dict[int, list[NeighbourMessage]]:
        inbox: dict[int, list[NeighbourMessage]] = defaultdict(list)
        for q, data in self.queue.pop(rnd, []):
            try:
                inbox[q].append(codec.decode_datagram(data))
            except DecodeError:
                self.traffic.decode_errors += 1
        return inbox

    # ----------------------------------------------------------------- DRAN rounds
    def step(self) -> bool:
        """One synchronous round; returns True when every agent reports convergence."""
        self.round += 1
        rnd = self.round
        inbox = self._deliver(rnd)
        up = self._round_up(rnd)
        stamp = rnd * ROUND_PERIOD_NS
        outgoing = []
        for i, agent in enumerate(self.agents):
            for msg in inbox.get(i, []):
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
            self.send(i, o.message, o.to, rnd, up)
        return all(e is not None and e.converged for e in self.estimates)

    # ----------------------------------------------------------------- initialisation rounds
    def init_exchange(self, stage: InitStage, iteration: int, outgoing: dict) -> dict:
        """``dist_init.Exchange`` over encoded datagrams (same loss model, no latency)."""
        self.round += 1
        rnd = self.round
        up = self._round_up(rnd)
        for r, sends in outgoing.items():
            for q, entries in sends:
                msg = NeighbourMessage(r, rnd, rnd * ROUND_PERIOD_NS, init=tuple(entries))
                self.send(r, msg, (q,), rnd - 1 - self.links.latency_rounds, up)
        incoming: dict[int, list] = defaultdict(list)
        for q, msgs in self._deliver(rnd).items():
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
                 links: LinkModel = LinkModel(), seed: int = 0, callback=None) -> dict:
    """Table 1 protocol: contiguous split, distributed chordal init, DRAN until every robot has
    converged (or K_max). Returns the merged poses and the numbers the bench reports."""
    import dataclasses

    from dran_edge.agent import LocalProblem
    from dran_edge.dist_init import InitParams, distributed_chordal_init
    from dran_edge.objective import sesync_objective, sesync_weights
    from dran_edge.partition import partition_contiguous

    t_start = time.perf_counter()
    kappa, tau = sesync_weights(g.dim, g.information)
    part = partition_contiguous(g.edges, g.num_vertices, num_robots)
    A = adjacency_from_pairs(num_robots, part.neighbour_pairs())
    W = metropolis_weights(A)
    fleet = Fleet([], A, links, seed=seed)
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
