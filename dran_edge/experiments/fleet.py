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

Size: over ~500 lines because the in-process fleet (its rounds, plain and reliable exchanges:
the ARQ driver, ``Fleet.reliable_exchange``, shares the fleet's encoder, endpoints and
counters) and its Table 1 driver; the driver (``run_g2o_dran`` and its helpers) could move to
a module of its own.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import defaultdict
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from dran_edge.dran.agent import Agent
from dran_edge.comms import arq, codec
from dran_edge.comms.bus import Bus, BusParams
from dran_edge.comms.delta import DeltaDecoder, DeltaEncoder
from dran_edge.dran.consensus import metropolis_hastings_matrix
from dran_edge.errors import DecodeError
from dran_edge.events import EstimateUpdate, NeighbourData, Outgoing, Tick
from dran_edge.messages import InitStage, NeighbourMessage

if TYPE_CHECKING:
    from dran_edge.config import AgentConfig
    from dran_edge.dran.partition import Partition
    from dran_edge.formats.g2o import G2oGraph

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


def stop_rounds_for(bus: Bus, config, round_: int = 0) -> int:
    """``config.stop_rounds``, raised to the communication graph's diameter + 3 where that is
    larger (the done counter reaches K only when every robot within K − 1 hops passes its test,
    docs/notes/stopping-rule.md; capped at 255). A disconnected graph keeps the configured K."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import shortest_path

    ids = bus.robot_ids
    index = {r: k for k, r in enumerate(ids)}
    A = np.zeros((len(ids), len(ids)))
    for a, b in bus.edges(round_):
        A[index[a], index[b]] = A[index[b], index[a]] = 1.0
    hops = shortest_path(csr_matrix(A), unweighted=True)
    if not np.all(np.isfinite(hops)):
        return int(config.stop_rounds)
    return int(min(255, max(config.stop_rounds, int(hops.max()) + 3)))


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

    def __init__(
        self,
        agents: list[Agent],
        bus: Bus,
        max_datagram_bytes: int = codec.DEFAULT_MAX_DATAGRAM_BYTES,
        fleet_id: int = 1,
        delta_every: int = 0,
        arq_params: arq.ArqParams = arq.ArqParams(),
    ):
        """``delta_every > 0``: delta layout on every link (``dran_edge.comms.delta``), each key
        sent absolute again after that many rounds; 0: absolute values only."""
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
        self.delta_every = int(delta_every)
        self._enc: dict = {}  # (sender index, receiver index) -> DeltaEncoder
        self._dec: dict = {}  # (receiver index, sender id) -> DeltaDecoder
        self.arq: list[arq.Arq] | None = None  # per robot, from the first reliable exchange
        self.arq_params = arq_params
        self.ack_bytes = 0
        """Bytes of the ARQ's ack datagrams (in ``traffic`` too)."""
        self.init_fallback = ""
        """Why the init fell back to block iterations (``split_and_init``), else empty."""

    @property
    def round(self) -> int:
        return self.bus.round

    @property
    def traffic(self) -> Traffic:
        st = self.bus.stats()
        return Traffic(
            st["datagrams_sent"],
            st["bytes_total"],
            int(sum(st["lost"].values())),
            self.decode_errors,
            st["bytes_by_kind"],
            st["bytes_by_sender"],
        )

    def send(
        self, sender: int, message: NeighbourMessage, to, latency_rounds: int | None = None
    ) -> None:
        """Encode (once, or once per link with deltas), then hand every datagram to the bus for
        every recipient in ``to`` whose link is up this round (agent indices)."""
        up = set(self.bus.neighbours(self.ids[sender]))
        ep = self.endpoints[sender]
        # with deltas, one encoding per link below
        grams: list[Any] = [] if self.delta_every else self._encode(sender, message)
        for q in to:
            if self.ids[q] not in up:
                continue
            if self.delta_every:  # one encoding per link: each link has its own delta state
                enc = self._enc.setdefault((sender, q), DeltaEncoder(self.delta_every))
                grams = self._encode(sender, message, enc)
            for g in grams:
                ep.send(self.ids[q], g.data, latency_rounds)

    def _receive(self) -> list[list[NeighbourMessage]]:
        inbox: list[list[NeighbourMessage]] = [[] for _ in self.ids]
        for i, ep in enumerate(self.endpoints):
            for sender, data in ep.receive():
                dec = (
                    self._dec.setdefault((i, sender), DeltaDecoder()) if self.delta_every else None
                )
                try:
                    inbox[i].append(codec.decode_datagram(data, dec))
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
            idle = agent.counters.idle_rounds
            t0 = time.perf_counter()
            outs = agent.handle(Tick(stamp))
            if agent.counters.idle_rounds == idle:  # not an idle turn of a schedule
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

    # ----------------------------------------------------------------- reliable exchanges
    def reliable_exchange(self, stage: InitStage, iteration: int, outgoing: dict) -> dict:
        """``init_exchange`` with every message delivered: selective-repeat ARQ
        (``dran_edge.comms.arq``) over as many bus rounds as it takes. Each round every robot
        (re)sends its unacknowledged datagrams (latency 0), the receivers decode what arrived
        and acknowledge it with an ``ARQ_ACK`` datagram per sender heard, sent
        ``ArqParams.ack_copies`` times (latency 0, lossy too), and the senders take the acks
        in; the exchange ends in the round in which the last datagram is acknowledged (every
        robot knows its own sends are done and has what it was sent). As ``send``, nothing
        goes over a link that is down in the round. Every datagram, retransmission and ack crosses the bus and is counted.
        Messages are encoded absolute (no delta layout: a retransmission must decode alone).
        Raises ``arq.LinkDown`` when a datagram stays unacknowledged for
        ``arq_params.max_rounds`` rounds (the outstanding datagrams are dropped)."""
        if self.arq is None:
            self.arq = [arq.Arq(r, self.arq_params) for r in self.ids]
        arqs = self.arq
        start = self.bus.round + 1  # the round every datagram of the exchange carries
        for r, sends in outgoing.items():
            for q, entries in sends:
                msg = NeighbourMessage(r, start, start * ROUND_PERIOD_NS, init=tuple(entries))
                for g in self._encode(r, msg):
                    arqs[r].offer(self.ids[q], g.sequence, g.data)
        incoming: dict[int, list] = defaultdict(list)
        while True:  # at least one round, as ``init_exchange``
            self.bus.advance()
            rnd = self.bus.round
            try:
                due = [a.due() for a in arqs]
            except arq.LinkDown:
                for a in arqs:
                    a.abandon()
                raise
            for r, sends in enumerate(due):
                for to, data in sends:
                    if self.bus.link_up(self.ids[r], to):
                        self.endpoints[r].send(to, data, 0)
            self._arq_receive(arqs, incoming)
            for q, a in enumerate(arqs):
                for peer, acked in a.acks().items():
                    ack = NeighbourMessage(
                        q, rnd, rnd * ROUND_PERIOD_NS, init=arq.ack_entries(acked)
                    )
                    if not self.bus.link_up(self.ids[q], peer):
                        continue
                    for g in self._encode(q, ack):
                        for _ in range(self.arq_params.ack_copies):
                            self.endpoints[q].send(peer, g.data, 0)
                            self.ack_bytes += len(g.data)
            self._arq_receive(arqs, incoming)
            if not any(a.pending for a in arqs):
                return incoming

    def _encode(
        self, sender: int, message: NeighbourMessage, delta: DeltaEncoder | None = None
    ) -> list:
        """The sender's next datagrams of ``message`` (its sequence numbers advance)."""
        grams = codec.encode_datagrams(
            message,
            fleet_id=self.fleet_id,
            boot_epoch=1,
            first_sequence=self.sequence[sender],
            max_datagram_bytes=self.max_datagram_bytes,
            delta=delta,
        )
        self.sequence[sender] += len(grams)
        return grams

    def _arq_receive(self, arqs: list[arq.Arq], incoming: dict) -> None:
        """Everything due: acks to their sender's ARQ state, new data into ``incoming``."""
        for i, ep in enumerate(self.endpoints):
            for sender, data in ep.receive():
                try:
                    msg = codec.decode_datagram(data)
                except DecodeError:
                    self.decode_errors += 1
                    continue
                acked = arq.ack_runs(msg.init)
                if acked:
                    arqs[i].acknowledged(sender, acked)
                elif arqs[i].received(sender, int(msg.sequence or 0)):
                    incoming[i].extend(msg.init)

    def run(self, max_rounds: int, min_rounds: int = 1, patience: int = 3, callback=None) -> int:
        """Rounds until every agent has reported convergence ``patience`` rounds in a row.
        ``callback(k, fleet)`` after each round; a true return value ends the run there
        (benchmarks whose question is decided before ``max_rounds``)."""
        streak = 0
        for k in range(max_rounds):
            done = self.step()
            streak = streak + 1 if done else 0
            if callback is not None and callback(k + 1, self):
                return k + 1
            if k + 1 >= min_rounds and streak >= patience:
                return k + 1
        return max_rounds


# --------------------------------------------------------------------------- Table 1 driver
#: Table 1 defaults (docs/dran.md, "Inter-robot schedule"): robots of one colour of a greedy
#: colouring update together (block Gauss–Seidel), block SOR ω on the trajectory, delta entries
#: on the wire (absolute again every 20 rounds), and the cost-decrease stop.
TABLE1_SOR_OMEGA = 1.9
TABLE1_EPS_COST_REL = 1e-4
TABLE1_DELTA_EVERY = 20


def default_init_params():
    """The init of the g2o runs: Gauss–Seidel block iterations, and the substructured exact
    stages where cheap (``InitParams.direct="auto"``; over lossy links through
    ``Fleet.reliable_exchange``, ``split_and_init``)."""
    from dran_edge.dran.dist_init import InitParams

    return InitParams(gauss_seidel=True, direct="auto")


def lossy_links(links: BusParams | None) -> bool:
    """Whether ``links`` lose datagrams (the tree protocols then go through the ARQ)."""
    return links is not None and (
        links.loss_probability > 0 or any(p > 0 for p in links.link_loss.values())
    )


def refine_over_fleet(fleet: Fleet, mode: str, run, reliable: bool, skip: str = "") -> dict:
    """An exact refinement over the fleet's bus: ``run(exchange) -> exact_gn.RefineResult``
    with ``exchange`` a ``dist_init.Exchange``: one bus round per call, or with ``reliable``
    (lossy links, partitions) ``Fleet.reliable_exchange``, as many rounds as the ARQ takes. A
    link down for longer than the ARQ allows (``arq.LinkDown``) ends it: no refined poses,
    ``refine_reason`` says which link (the caller runs plain DRAN from its start). ``skip``:
    do not run, for this reason. Returns ``poses_refined`` and the ``refine_*`` numbers,
    rounds and datagram bytes counted on the bus (``refine_curve``: (rounds, bytes since the
    start, F as the root summed it) at every accepted point; ``refine_arq``: the ARQ's
    transmissions, retransmissions, duplicates and ack bytes in it, when ``reliable``)."""
    from dran_edge.dran import exact_gn

    r0, b0 = fleet.round, fleet.traffic.bytes_total
    arq0 = arq_totals(fleet)
    sent, at = [b0], [r0]  # bytes and bus round after each exchange
    over = fleet.reliable_exchange if reliable else fleet.init_exchange

    def exchange(stage, iteration: int, outgoing: dict) -> dict:
        incoming = over(stage, iteration, outgoing)
        sent.append(fleet.traffic.bytes_total)
        at.append(fleet.round)
        return incoming

    if skip:
        res = exact_gn.RefineResult(np.zeros(0), False, reason=skip)
    else:
        try:
            res = run(exchange)
        except arq.LinkDown as exc:
            res = exact_gn.RefineResult(
                np.zeros(0), False, reason=f"{exc}: not refined, plain DRAN from the start"
            )
    out: dict[str, Any] = {
        "poses_refined": res.poses if res.poses.size else None,
        "refine_mode": mode,
        "refine_used": res.used,
        "refine_reason": res.reason,
        "refine_rounds": fleet.round - r0,
        "refine_bytes": fleet.traffic.bytes_total - b0,
        "refine_steps": res.steps,
        "refine_trials": res.trials,
        "refine_F_history": res.F_history,
        "refine_converged": res.converged,
        "refine_curve": [
            (at[k] - r0, sent[k] - b0, F) for k, F in zip(res.F_rounds, res.F_history)
        ],
        "refine_step_over_round_floats": res.ratio_floats,
    }
    if res.frozen_steps:  # RefineParams.frozen
        out["refine_frozen_steps"] = res.frozen_steps
    if res.pcg_iterations:  # RefineParams.interface "pcg"
        out["refine_pcg_iterations"] = res.pcg_iterations
    if reliable:
        out["refine_arq"] = {k: v - arq0[k] for k, v in arq_totals(fleet).items()}
    return out


def arq_totals(fleet: Fleet) -> dict:
    """The fleet's ARQ counters summed over robots (since the fleet started)."""
    arqs = fleet.arq or []
    return {
        "transmissions": sum(a.transmissions for a in arqs),
        "retransmissions": sum(a.retransmissions for a in arqs),
        "duplicates": sum(a.duplicates for a in arqs),
        "ack_bytes": fleet.ack_bytes,
    }


def _refine(
    g, part, poses, kappa, tau, fleet: Fleet, params, reliable: bool, skip: str = ""
) -> dict:
    """``run_g2o_dran``'s refinement (``exact_gn.refine`` over the fleet's bus): {} when
    ``params`` is None, else the ``refine_*`` numbers and ``poses_refined`` (``skip``: not run,
    for this reason)."""
    from dran_edge.dran import exact_gn

    if params is None:
        return {}
    out = refine_over_fleet(
        fleet,
        params.mode,
        lambda exchange: exact_gn.refine(
            g.dim,
            g.num_vertices,
            g.edges,
            g.measurements,
            kappa,
            tau,
            part,
            poses,
            exchange,
            params,
        ),
        reliable,
        skip,
    )
    if out["poses_refined"] is None:
        out["poses_refined"] = poses.copy()
    return out


def table1_setup(dim: int, residual: str = "chordal", plain: bool = False, stop: str = "steps"):
    """``(AgentConfig, run_g2o_dran keyword arguments)`` of the Table 1 runs. ``plain``: Alg. 1
    as printed — every robot every round, ω = 1, absolute values, the ε_u/ε_v stop alone.
    ``stop``: "steps" (Table 1: the ε_u/ε_v and relative-decrease tests) or "tail" (the rule
    that cannot fire far from F*, docs/notes/stopping-rule.md; replaces the stop only)."""
    import dataclasses

    from dran_edge.config import AgentConfig, Residual, RobustKernel

    if stop not in ("steps", "tail"):
        raise ValueError(f"stop must be 'steps' or 'tail', got {stop!r}")
    res, kernel = Residual.parse(residual, "residual"), RobustKernel.NONE
    if plain:
        cfg = AgentConfig(dim=dim, residual=res, robust_kernel=kernel)
        kw = {"schedule": "parallel", "delta_every": 0}
    else:
        cfg = AgentConfig(
            dim=dim,
            residual=res,
            robust_kernel=kernel,
            sor_omega=TABLE1_SOR_OMEGA,
            eps_cost_rel=TABLE1_EPS_COST_REL,
        )
        kw = {"schedule": "colour", "delta_every": TABLE1_DELTA_EVERY}
    if stop == "tail":
        cfg = dataclasses.replace(cfg, stop_rule="tail", eps_cost_rel=0.0)
    return cfg, kw


def _table1_agents(
    g: G2oGraph,
    part: Partition,
    init_poses: np.ndarray,
    W: list[dict[int, float]],
    config: AgentConfig,
    colour: np.ndarray,
    stop_rounds: int,
    kappa: np.ndarray,
    tau: np.ndarray,
) -> list[Agent]:
    """One agent per part of the split, started at ``init_poses`` and holding its neighbours'
    separators (the distributed init's last exchange left every robot with them)."""
    import dataclasses

    from dran_edge.dran.problem import LocalProblem

    agents = []
    for r in range(len(part.parts)):
        cfg = dataclasses.replace(
            config,
            robot_id=r,
            neighbours=tuple(sorted(W[r])),
            dim=g.dim,
            colour=int(colour[r]),
            colours=int(colour.max()) + 1,
            stop_rounds=stop_rounds,
        )
        prob = LocalProblem.from_partition(g, part, r, init_poses, kappa, tau, cfg.residual)
        agent = Agent(cfg, prob, weights=W[r])
        for p in part.parts:
            if p.robot_id == r:
                continue
            for v in p.vertices[np.isin(p.vertices, part.parts[r].anchors)].tolist():
                agent.anchors[(p.robot_id, v)] = init_poses[v].copy()
        agents.append(agent)
    return agents


def split_and_init(
    g: G2oGraph,
    num_robots: int,
    partition: Partition | None,
    links: BusParams | None,
    partitions: Any,
    delta_every: int,
    initial_poses: np.ndarray | None,
    init_params: Any,
) -> tuple[np.ndarray, np.ndarray, Partition, Fleet, np.ndarray]:
    """The set-up the g2o drivers share (DRAN here, DGS in ``experiments.dgs``): SE-Sync weights
    (κ, τ), the split (``partition`` or the contiguous one), a fleet on the split's neighbour
    graph, and the distributed chordal init over it (or ``initial_poses``, without init rounds
    or bytes). Returns (kappa, tau, partition, fleet, initial poses)."""
    from dran_edge.dran.dist_init import distributed_chordal_init
    from dran_edge.dran.partition import partition_contiguous
    from dran_edge.solver.objective import sesync_weights

    kappa, tau = sesync_weights(g.dim, g.information)
    part = (
        partition
        if partition is not None
        else partition_contiguous(g.edges, g.num_vertices, num_robots)
    )
    bus = Bus(
        range(num_robots),
        graph=part.neighbour_pairs(),
        params=links or BusParams(),
        partitions=partitions,
    )
    fleet = Fleet([], bus, delta_every=delta_every)
    if initial_poses is not None:
        return kappa, tau, part, fleet, np.asarray(initial_poses, np.float64).copy()
    params = init_params or default_init_params()
    reliable = bool(partitions) or lossy_links(links)

    def init(params, tree_exchange):
        return distributed_chordal_init(
            g.dim,
            g.num_vertices,
            g.edges,
            g.measurements,
            kappa,
            tau,
            part,
            fleet.init_exchange,
            params,
            tree_exchange=tree_exchange,
        )

    try:  # the substructured stages need every message: over lossy links through the ARQ
        res = init(params, fleet.reliable_exchange if reliable else None)
    except arq.LinkDown as exc:  # a link down too long: the block iterations alone, again
        fleet.init_fallback = f"{exc}: init by block iterations only"
        res = init(dataclasses.replace(params, direct="never"), None)
    return kappa, tau, part, fleet, res.poses


def run_g2o_dran(
    g,
    num_robots: int,
    config,
    init_params=None,
    max_rounds: int | None = None,
    links: BusParams | None = None,
    partitions=(),
    callback=None,
    schedule: str = "parallel",
    delta_every: int = 0,
    initial_poses: np.ndarray | None = None,
    partition=None,
    stop: bool = True,
    refine=None,
    on_start=None,
    polish=None,
) -> dict:
    """Table 1 protocol: contiguous split, distributed chordal init, DRAN until every robot has
    converged (or K_max of its own local steps), over a bus on the split's neighbour graph with
    network model ``links`` (default lossless) and ``partitions``. ``schedule``: "parallel"
    (every robot every round) or "colour" (the robots of one colour of a greedy colouring per
    round); ``delta_every``: see ``Fleet``. Returns the merged poses and the numbers the bench
    reports. ``initial_poses`` (diagnostics): start DRAN from these instead of running the
    distributed init (no init rounds or bytes). ``partition`` (a ``partition.Partition`` of
    ``num_robots`` robots): use this split instead of the contiguous one. ``stop=False``: run
    all ``max_rounds`` even after every robot has met its stopping rule (benchmarks that
    record where it fired, via ``callback``). The result also holds ``poses_init``.
    ``polish`` (an ``exact_gn.RefineParams``): after DRAN's rounds, exact distributed LM
    steps from DRAN's merged estimate over the same bus (its numbers as ``polish_*``, its end as
    ``objective_polished``; ``poses`` is then the polished estimate).
    ``refine`` (an ``exact_gn.RefineParams``): after the init, exact distributed LM steps over
    the same bus (``dran_edge.dran.exact_gn``; over lossy links and partitions through the
    ARQ, ``Fleet.reliable_exchange``); the result then also holds ``refine_*`` numbers (``refine_curve``: (rounds,
    bytes since the init, F as the root summed it) at every accepted point), ``objective_refined``
    and ``poses_refined``, where DRAN starts. A refinement that stopped on its relative-decrease
    test (``refine_converged``) ends the run there when ``stop``: DRAN runs no round
    (``stopped_by`` "refine"). ``on_start(numbers)``: called once before DRAN's first round
    with the refinement's ``refine_*`` numbers ({} without refinement), for callbacks that
    need to know whether the run would already have ended there."""
    # Long: the Table 1 protocol in order (split, init, refinement, agents, rounds, record).
    from dran_edge.dran.linear_stage import greedy_colouring
    from dran_edge.solver.objective import sesync_objective

    t_start = time.perf_counter()
    kappa, tau, part, fleet, init_poses = split_and_init(
        g, num_robots, partition, links, partitions, delta_every, initial_poses, init_params
    )
    bus = fleet.bus
    W = neighbour_weights(bus)
    init_rounds, init_bytes = fleet.round, fleet.traffic.bytes_total
    F = lambda T: sesync_objective(T, g.edges, g.measurements, kappa, tau)
    F_init = F(init_poses)
    lossy = bool(partitions) or lossy_links(links)  # tree protocols through the ARQ, no SOR
    start, refined = (
        init_poses,
        _refine(
            g,
            part,
            init_poses,
            kappa,
            tau,
            fleet,
            refine,
            reliable=lossy,
        ),
    )
    if refined:
        start = refined["poses_refined"]
        refined["objective_refined"] = F(start)
    colour = greedy_colouring(part) if schedule == "colour" else np.zeros(num_robots, np.int64)
    sor_off = config.sor_omega != 1.0 and lossy
    if sor_off:  # block SOR needs every neighbour's values each round (docs/config.md)
        config = dataclasses.replace(config, sor_omega=1.0)
    agents = _table1_agents(
        g, part, start, W, config, colour, stop_rounds_for(bus, config), kappa, tau
    )
    fleet.agents = agents
    fleet.estimates = [None] * num_robots
    cap = max_rounds or config.k_max * (int(colour.max()) + 1)
    if on_start is not None:
        on_start({k: v for k, v in refined.items() if k != "poses_refined"})
    if stop and refined.get("refine_converged"):  # the root's global test already held
        rounds, reasons = 0, ["refine"]
    else:
        rounds = fleet.run(cap, min_rounds=1 if stop else cap, callback=callback)
        reasons = sorted({a.stop_reason for a in agents if a.stop_reason})
    merged = start.copy()
    for r, p in enumerate(part.parts):
        merged[p.vertices] = agents[r].x
    polished: dict = {}
    if polish is not None:  # Newton steps from DRAN's estimate (bench g2o --polish)
        skip = "the refinement converged" if refined.get("refine_converged") else ""
        out = _refine(g, part, merged, kappa, tau, fleet, polish, lossy, skip)
        merged = out.pop("poses_refined")
        polished = {k.replace("refine_", "polish_", 1): v for k, v in out.items()}
        polished["objective_polished"] = F(merged)
    return (
        refined
        | polished
        | {
            "poses": merged,
            "poses_init": init_poses,
            "rounds": rounds,
            "stopped_by": "+".join(reasons) if rounds < cap else None,
            "init_rounds": init_rounds,
            "rounds_total": init_rounds
            + refined.get("refine_rounds", 0)
            + rounds
            + polished.get("polish_rounds", 0),
            "bytes_init": init_bytes,
            "bytes_total": fleet.traffic.bytes_total,
            "datagrams": fleet.traffic.datagrams,
            "objective_init": F_init,
            "objective_final": F(merged),
            "local_step_ms_median": float(np.median(fleet.step_ms)) if fleet.step_ms else 0.0,
            "schedule": schedule,
            "colours": int(colour.max()) + 1,
            "delta_every": delta_every,
            "wall_s": time.perf_counter() - t_start,
        }
        | ({"init_fallback": fleet.init_fallback} if fleet.init_fallback else {})
        | ({"sor_omega": "1 (lossy links)"} if sor_off else {})
        | ({"arq": arq_totals(fleet)} if fleet.arq is not None else {})
    )
