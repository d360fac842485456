"""The robot side of a replay: each robot's core, link and recorded inputs, stepped round by round.

:class:`RobotRunner` holds some robots of a run. ``step(t_k, inboxes)`` runs one round for
each of them in id order — every recorded input with a stamp ≤ ``t_k`` (ingest records in file
order, then perception's observation records by stamp), the datagrams that arrived (verified
and decoded by :class:`~dran_edge.comms.link.NeighbourLink`), ``Tick(t_k)`` — and returns the
signed datagrams each robot sent. The replay's main loop routes them through the bus.

A robot's round depends only on its own state and its inbox, so the robots of a run can be
spread over worker processes (:class:`WorkerPool`); the results are the same with any number of
workers. With ``transport="udp"`` the runner's links own real loopback RADIO/DISH sockets and
the runner lives in the main process.
"""

from __future__ import annotations

import bisect
import logging
import math
import multiprocessing as mp
import traceback
import zlib
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from dran_edge.blas import set_blas_threads
from dran_edge.formats import run_dir as rd
from dran_edge.errors import DranError, InputError
from dran_edge.events import EstimateUpdate, Health, NeighbourData, ObservationBatch, Outgoing, Tick

if TYPE_CHECKING:
    from dran_edge.robot.core import RobotCore

log = logging.getLogger(__name__)

#: HMAC key of replayed links. A run never stores the fleet's secret; replay signs and verifies
#: with this fixed key so the authentication code path runs as on the robot.
REPLAY_KEY = bytes(range(32))


def fleet_id(fleet: str) -> int:
    """The 16-bit fleet id of the datagram header for a fleet name (CRC-32, low 16 bits)."""
    return zlib.crc32(fleet.encode("utf-8")) & 0xFFFF


def make_core(cfg: Any, robot: rd.RunRobot) -> RobotCore:
    """The robot's agent as the daemon builds it (ingest events in, outputs out).

    The run's ``T_world_odom`` (the paper's protocol: the robot's initial frame in the world,
    from mocap) is handed to the core.
    """
    from dran_edge.daemon.service import default_agent_factory

    # a RobotCore: bounded local graph + agent
    core = cast("RobotCore", default_agent_factory(cfg, None))
    if robot.T_world_odom is not None:
        core.set_world_frame(robot.T_world_odom)
    return core


def decode_ingest(data: bytes, what: str) -> tuple[list[Any], Counter[str]]:
    """Events of ingest bytes through the daemon's stream decoder; rejects counted by reason."""
    from dran_edge.comms.ingest import IngestDecodeError, iter_records

    events: list[Any] = []
    rejected: Counter[str] = Counter()
    for item in iter_records(data):
        if isinstance(item, IngestDecodeError):
            rejected[item.reason] += 1
            log.debug("%s: %s", what, item)
        else:
            events.append(item.event)
    return events, rejected


def event_stamp(ev) -> int:
    stamp = getattr(ev, "stamp_ns", None)
    return int(stamp if stamp is not None else ev.stamp_cur_ns)


class Mailbox:
    """A transport whose datagrams are routed by the replay's main loop (``transport.Transport``)."""

    def __init__(self) -> None:
        self.inbox: list[bytes] = []
        self.outbox: list[tuple[int, bytes]] = []

    def send(self, to: int, data: bytes) -> bool:
        self.outbox.append((int(to), bytes(data)))
        return True

    def receive(self, max_datagrams: int | None = None) -> list[tuple[int | None, bytes]]:
        out: list[tuple[int | None, bytes]] = [(None, d) for d in self.inbox]
        self.inbox = []
        return out

    def close(self) -> None:
        pass


class BufferedUdp:
    """A RADIO/DISH transport whose received datagrams are collected before each round."""

    def __init__(self, radio: Any) -> None:
        self.radio = radio
        self.buffer: list[tuple[int | None, bytes]] = []
        self.outbox: list[tuple[int, bytes]] = []

    def send(self, to: int, data: bytes) -> bool:
        self.outbox.append((int(to), bytes(data)))
        return self.radio.send(to, data)

    def pull(self) -> int:
        got = self.radio.receive()
        self.buffer.extend(got)
        return len(got)

    def receive(self, max_datagrams: int | None = None):
        # arrival order on UDP is not deterministic; the content order is
        out = sorted(self.buffer, key=lambda x: x[1])
        self.buffer = []
        return out

    def close(self) -> None:
        self.radio.close()


def _udp_transport(cfg, fleet: str) -> BufferedUdp:
    from dran_edge.comms.radio import RadioParams, RadioTransport

    neighbours = {}
    for n in cfg.neighbours:
        host, port = n.address.rsplit(":", 1)
        neighbours[n.id] = f"udp://{host.strip('[]')}:{port}"
    params = RadioParams(
        group=fleet,
        bind=f"udp://{cfg.comms.bind_address}:{cfg.comms.port}",
        neighbours=neighbours,
        max_datagram_bytes=cfg.comms.datagram_max_bytes,
    )
    return BufferedUdp(RadioTransport(params))


@dataclass(frozen=True)
class RobotSpec:
    """What a runner needs to build one robot (picklable, for worker processes)."""

    run_dir: str
    name: str
    drop_recorded_observations: bool = False
    """Leave out ingest.bin's observation records (perception re-detects them from frames)."""


@dataclass
class RobotResult:
    """What the replay writes out for one robot (picklable)."""

    robot_id: int
    name: str
    last: EstimateUpdate | None
    initial: tuple[np.ndarray, np.ndarray] | None
    """(stamps_ns, T_world_body) by odometry alone, when the core provides it."""
    first_seen: dict
    graph: dict | None
    """keys, stamps, factor arrays of the robot's local graph, when the core has one."""
    health: dict
    rejected: Counter
    observations: int


def robot_result(
    rid: int,
    name: str,
    core,
    last: EstimateUpdate | None,
    *,
    first_seen: dict | None = None,
    health: dict | None = None,
    rejected: Counter | None = None,
    observations: int = 0,
) -> RobotResult:
    """What the replay's outputs need of one robot's core (its local graph and odometry-only
    estimate, when the core has them) and of its last estimate. ``dran-edge rehearse`` builds
    it from a daemon's checkpointed core."""
    graph = None
    g = getattr(core, "local_graph", None)
    if g is not None and hasattr(g, "factor_arrays"):
        from dran_edge.robot.keyframe_graph import OBJ

        try:  # without the marginalisation prior (it would pin old nodes in g2o)
            fa = g.factor_arrays(include_prior=False)
        except TypeError:
            fa = g.factor_arrays()
        graph = {
            "keys": g.node_keys(),
            "stamps": g.node_stamps_ns(),
            "factors": fa,
            "obj_base": OBJ,
        }
    initial = core.initial_estimate() if hasattr(core, "initial_estimate") else None
    return RobotResult(
        rid,
        name,
        last,
        initial,
        dict(first_seen or {}),
        graph,
        dict(health or {}),
        Counter(rejected or {}),
        observations,
    )


@dataclass
class _Robot:
    info: rd.RunRobot
    cfg: Any
    core: Any
    link: Any
    transport: Any
    events: list = field(default_factory=list)
    next_event: int = 0
    last: EstimateUpdate | None = None
    first_seen: dict = field(default_factory=dict)
    health: dict = field(default_factory=dict)
    rejected: Counter = field(default_factory=Counter)
    observations: int = 0
    next_order: int = 0


class RobotRunner:
    """Some robots of a run, stepped round by round (see the module docstring)."""

    def __init__(self, specs: list[RobotSpec], transport: str = "mailbox"):
        from dran_edge.comms.auth import AuthPolicy
        from dran_edge.comms.link import NeighbourLink

        self.robots: dict[int, _Robot] = {}
        if not specs:
            return
        run = rd.open_run(specs[0].run_dir)
        mission = run.mission
        ids = frozenset(r.id for r in mission.robots)
        for spec in specs:
            info = mission.robot(spec.name)
            cfg = run.load_config(info.name)
            core = make_core(cfg, info)
            events, rejected = decode_ingest(
                run.read_ingest(info.name), str(run.ingest_path(info.name))
            )
            if spec.drop_recorded_observations:
                events = [ev for ev in events if not isinstance(ev, ObservationBatch)]
            timeline, release = [], 0
            for order, ev in enumerate(events):
                release = max(release, event_stamp(ev))
                timeline.append((release, order, ev))
            n_obs = sum(
                len(ev.observations) for _, _, ev in timeline if isinstance(ev, ObservationBatch)
            )
            tr = Mailbox() if transport == "mailbox" else _udp_transport(cfg, mission.fleet)
            policy = AuthPolicy(
                fleet_id=fleet_id(mission.fleet),
                self_id=info.id,
                fleet_robots=ids,
                neighbours=frozenset(mission.neighbours(info.id)),
                relay_from=frozenset(cfg.comms.allow_relay_from),
            )
            link = NeighbourLink(
                tr,
                key=REPLAY_KEY,
                policy=policy,
                boot_epoch=1,
                max_datagram_bytes=cfg.comms.datagram_max_bytes,
                delta_every=cfg.comms.delta_every,
            )
            self.robots[info.id] = _Robot(
                info,
                cfg,
                core,
                link,
                tr,
                timeline,
                rejected=rejected,
                observations=n_obs,
                next_order=len(timeline),
            )

    def last_stamp(self) -> int:
        return max([r.events[-1][0] for r in self.robots.values() if r.events], default=0)

    def stamp_span(self) -> tuple[int, int] | None:
        """(first, last) recorded stamp over every robot's ingest records; None if none."""
        have = [r.events for r in self.robots.values() if r.events]
        if not have:
            return None
        return min(e[0][0] for e in have), max(e[-1][0] for e in have)

    def add_records(self, records: dict[int, bytes]) -> None:
        """More ingest records for some robots (perception's observation batches of a window).

        They take order numbers after the robot's ingest.bin records, in the order given, so
        the timeline (sorted by stamp, then order) does not depend on when they arrive — only
        that every record of a window arrives before the rounds reach the window's start.
        """
        for rid, data in records.items():
            r = self.robots.get(rid)
            if r is None or not data:
                continue
            events, rejected = decode_ingest(data, f"{r.info.name} observations")
            r.rejected.update(rejected)
            new = []
            for ev in events:
                new.append((event_stamp(ev), r.next_order, ev))
                r.next_order += 1
                if isinstance(ev, ObservationBatch):
                    r.observations += len(ev.observations)
            rest = r.events[r.next_event :] + new
            rest.sort(key=lambda x: (x[0], x[1]))
            r.events[r.next_event :] = rest

    def step(self, t_k: int, inboxes: dict[int, list[bytes]] | None) -> dict[int, dict]:
        """One round for every robot held; returns per robot its outbox and estimate summary."""
        out: dict[int, dict] = {}
        for rid in sorted(self.robots):
            r = self.robots[rid]
            if inboxes is not None:
                r.transport.inbox = list(inboxes.get(rid, ()))
            outputs: list = []
            end = bisect.bisect_right(r.events, (t_k, math.inf), lo=r.next_event)
            for _, _, ev in r.events[r.next_event : end]:
                outputs.extend(r.core.handle(ev) or ())
            r.next_event = end
            for msg in r.link.poll(now_ns=t_k):
                outputs.extend(r.core.handle(NeighbourData(t_k, msg)) or ())
            outputs.extend(r.core.handle(Tick(t_k)) or ())
            r.transport.outbox = []
            for o in outputs:
                if isinstance(o, Outgoing):
                    r.link.send_message(o.message, o.to)
                elif isinstance(o, EstimateUpdate):
                    r.last = o
                    for s, T in zip(o.keyframe_stamps_ns.tolist(), o.T_world_body):
                        if s not in r.first_seen:
                            r.first_seen[s] = T.copy()
                elif isinstance(o, Health):
                    r.health.update(o.counters)
            u = r.last
            out[rid] = {
                "outbox": r.transport.outbox,
                "cost": u.cost if u is not None else math.nan,
                "consensus_error": u.consensus_error if u is not None else math.nan,
                "converged": bool(u is not None and u.converged),
            }
        return out

    def snapshot(self) -> dict[int, RobotResult]:
        """:meth:`results` between rounds (the same, in this process)."""
        return self.results()

    def pull_udp(self) -> dict[int, int]:
        return {rid: r.transport.pull() for rid, r in self.robots.items()}

    def results(self) -> dict[int, RobotResult]:
        """What the replay's outputs need of every robot held, as it is now (also between
        rounds: the per-round costs sample it)."""
        return {
            rid: robot_result(
                rid,
                r.info.name,
                r.core,
                r.last,
                first_seen=r.first_seen,
                health=r.health,
                rejected=r.rejected,
                observations=r.observations,
            )
            for rid, r in self.robots.items()
        }

    def close(self) -> None:
        for r in self.robots.values():
            r.transport.close()


# ------------------------------------------------------------------------------ worker pool
def _worker_main(conn, specs: list[RobotSpec]) -> None:
    try:
        set_blas_threads(1)
        runner = RobotRunner(specs)
        conn.send(("ok", runner.stamp_span()))
        while True:
            cmd, arg = conn.recv()
            if cmd == "step":
                conn.send(("ok", runner.step(*arg)))
            elif cmd == "add":
                runner.add_records(arg)
            elif cmd == "snapshot":
                conn.send(("ok", runner.results()))
            elif cmd == "finish":
                conn.send(("ok", runner.results()))
                return
    except DranError as exc:
        conn.send(("input_error" if isinstance(exc, InputError) else "dran_error", str(exc)))
    except BaseException:  # noqa: BLE001 - report anything to the parent, then exit
        conn.send(("crash", traceback.format_exc()))


def _unwrap(reply: tuple) -> Any:
    status, value = reply
    if status == "ok":
        return value
    if status == "input_error":
        raise InputError(value)
    if status == "dran_error":
        raise DranError(value)
    raise RuntimeError(f"replay worker failed:\n{value}")


class WorkerPool:
    """Robots spread over worker processes; same interface as one :class:`RobotRunner`."""

    def __init__(self, specs: list[RobotSpec], ids: list[int], workers: int):
        ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else mp.get_context()
        groups = [[s for k, s in enumerate(specs) if k % workers == w] for w in range(workers)]
        self._conns, self._procs = [], []
        for group in groups:
            parent, child = ctx.Pipe()
            p = ctx.Process(target=_worker_main, args=(child, group), daemon=True)
            p.start()
            child.close()
            self._conns.append(parent)
            self._procs.append(p)
        spans = [s for s in (_unwrap(c.recv()) for c in self._conns) if s is not None]
        self._span = (min(s[0] for s in spans), max(s[1] for s in spans)) if spans else None
        self._last = self._span[1] if self._span is not None else 0
        self._ids_of = [
            [ids[k] for k in range(len(specs)) if k % workers == w] for w in range(workers)
        ]

    def last_stamp(self) -> int:
        return self._last

    def stamp_span(self) -> tuple[int, int] | None:
        return self._span

    def add_records(self, records: dict[int, bytes]) -> None:
        for conn, ids in zip(self._conns, self._ids_of):
            mine = {i: records[i] for i in ids if i in records}
            if mine:
                conn.send(("add", mine))

    def step(self, t_k: int, inboxes: dict[int, list[bytes]] | None) -> dict[int, dict]:
        """One round of every robot; ``inboxes`` as for :meth:`RobotRunner.step` (the pool
        runs the bus transport only: None is no datagram)."""
        inboxes = inboxes or {}
        for conn, ids in zip(self._conns, self._ids_of):
            conn.send(("step", (t_k, {i: inboxes.get(i, []) for i in ids})))
        return self._gather()

    def results(self) -> dict[int, RobotResult]:
        """Every robot's result; the workers then exit."""
        for conn in self._conns:
            conn.send(("finish", None))
        return self._gather()

    def snapshot(self) -> dict[int, RobotResult]:
        """Every robot's result between rounds; the workers go on."""
        for conn in self._conns:
            conn.send(("snapshot", None))
        return self._gather()

    def _gather(self) -> dict:
        """Every worker's reply, keyed by robot id in ascending order as one RobotRunner
        gives it: callers sum over the values, and float sums depend on their order."""
        out: dict = {}
        for conn in self._conns:
            out.update(_unwrap(conn.recv()))
        return {rid: out[rid] for rid in sorted(out)}

    def close(self) -> None:
        for p in self._procs:
            p.join(timeout=5)
            if p.is_alive():
                p.terminate()
        for c in self._conns:
            c.close()
