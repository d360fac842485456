"""Config -> objects: where the daemon keeps its state, and the factories of the robot's core,
its neighbour link and its perception source (the daemon's defaults; tests pass their own)."""

from __future__ import annotations

import logging
import os
import time
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np

from dran_edge.config import RobotConfig, parse_address
from dran_edge.daemon.workers import DropOldestQueue
from dran_edge.errors import DependencyError
from dran_edge.events import NeighbourData, ObservationBatch

log = logging.getLogger(__name__)


class AgentLike(Protocol):
    """What the daemon needs of the robot's core (:class:`~dran_edge.robot.core.RobotCore`)."""

    local_graph: Any

    def handle(self, event: Any) -> list: ...

    def to_state(self) -> dict: ...


class Transport(Protocol):
    """What the daemon needs of the neighbour link (``RadioLink`` below is the real one)."""

    def send(self, message: Any, to: tuple[int, ...]) -> None: ...

    def receive(self) -> list: ...

    def stats(self) -> dict: ...

    def close(self) -> None: ...


def resolve_dirs(cfg: RobotConfig, environ: Mapping[str, str] | None = None) -> tuple[Path, Path]:
    """(state_dir, runtime_dir): config, else systemd's $STATE_DIRECTORY/$RUNTIME_DIRECTORY."""
    env = os.environ if environ is None else environ
    state = cfg.resolve(cfg.daemon.state_dir)
    if state is None:
        sd = env.get("STATE_DIRECTORY", "").split(":")[0]
        state = Path(sd) if sd else Path.cwd() / "dran-edge-state"
    runtime = cfg.resolve(cfg.daemon.runtime_dir)
    if runtime is None:
        rd = env.get("RUNTIME_DIRECTORY", "").split(":")[0]
        runtime = Path(rd) if rd else state / "run"
    return state, runtime


def default_agent_factory(cfg: RobotConfig, state: dict | None) -> AgentLike:
    """The robot's core: an :class:`~dran_edge.robot.core.RobotCore`, from ``state`` (its
    :meth:`~dran_edge.robot.core.RobotCore.to_state`) when given; a fresh one anchored at
    ``robot.T_world_odom`` when the config has it."""
    try:
        from dran_edge.robot.core import RobotCore
    except ImportError as exc:
        raise DependencyError(
            f"the DRAN agent (dran_edge.robot.core) is not available: {exc}"
        ) from None
    if state is not None:
        return RobotCore.from_state(cfg.agent, state)
    T_world_odom = None
    if cfg.robot.T_world_odom:
        from dran_edge import geometry as geo

        T_world_odom = geo.se3_from_xyz_quat_xyzw(np.asarray(cfg.robot.T_world_odom, np.float64))
    return RobotCore(cfg.agent, T_world_odom)


class LinkTransport:
    """The daemon's neighbour link: comms' authenticated ``NeighbourLink`` over RADIO/DISH.

    ``neighbours`` (id -> name) are listed in the status from the start ("never heard" until a
    datagram of theirs is accepted). ``heartbeat_period_s`` > 0: ``heartbeat`` sends an
    entry-less message to each neighbour this link sent nothing for that long (counted)."""

    def __init__(
        self, link: Any, neighbours: dict[int, str] | None = None, heartbeat_period_s: float = 0.0
    ):
        self.link = link
        self.neighbours = dict(neighbours or {})
        self.heartbeat_period_s = float(heartbeat_period_s)
        self._last_sent_ns: dict[int, int] = {}
        self.heartbeats_sent = 0
        self.heartbeats_received = 0

    def send(self, message: Any, to: tuple[int, ...]) -> None:
        self.link.send_message(message, to)
        now = time.time_ns()
        for j in to:
            self._last_sent_ns[j] = now

    def heartbeat(self, now_ns: int, round_: int = 0) -> int:
        """Send a heartbeat to every neighbour not sent anything for ``heartbeat_period_s``."""
        if self.heartbeat_period_s <= 0:
            return 0
        from dran_edge.messages import NeighbourMessage

        due = tuple(
            j
            for j in self.neighbours
            if now_ns - self._last_sent_ns.get(j, -(1 << 62)) >= self.heartbeat_period_s * 1e9
        )
        if due:
            self.send(NeighbourMessage(self.link.policy.self_id, max(0, int(round_)), now_ns), due)
            self.heartbeats_sent += len(due)
        return len(due)

    def receive(self) -> list:
        now = time.time_ns()
        out = []
        for m in self.link.poll(now):
            if not (m.separators or m.objects or m.init):
                self.heartbeats_received += 1
            out.append(NeighbourData(now, m))
        return out

    def stats(self) -> dict:
        snap = self.link.counters.snapshot()
        now = time.time_ns()
        neighbours = {}
        peers = snap["peers"]  # keyed by str(robot id) or "unknown"
        names = {str(j): name for j, name in self.neighbours.items()}
        for peer in sorted(set(names) | set(peers), key=lambda p: (not p.isdigit(), p.zfill(6))):
            c = peers.get(peer, {})
            heard = c.get("last_heard_ns")
            neighbours[peer] = {
                "name": names.get(peer, ""),
                "bytes_sent": c.get("bytes_sent", 0),
                "bytes_received": c.get("bytes_received", 0),
                "datagrams_rejected": c.get("datagrams_rejected", 0),
                "last_heard_s_ago": None if not heard else round((now - heard) * 1e-9, 1),
            }
        return {
            **snap["totals"],
            "neighbours": neighbours,
            "next_sequence": self.link.next_sequence,
            "heartbeats_sent": self.heartbeats_sent,
            "heartbeats_received": self.heartbeats_received,
        }

    def to_state(self) -> dict:
        return self.link.to_state()

    def restore(self, state: dict | None) -> int:
        return self.link.restore(state)

    def close(self) -> None:
        self.link.transport.close()


def fleet_id(fleet: str) -> int:
    """16-bit fleet id of the datagram header (CRC-32 of the name; as the replay computes it)."""
    return zlib.crc32(fleet.encode("utf-8")) & 0xFFFF


def default_transport_factory(cfg: RobotConfig, boot_epoch: int) -> Transport | None:
    """RADIO/DISH to the configured neighbours, authenticated by ``comms.auth``'s key policy."""
    if cfg.comms.transport == "none":
        return None
    from dran_edge.comms.auth import AuthPolicy
    from dran_edge.comms.keys import credentials_from_config
    from dran_edge.comms.link import NeighbourLink
    from dran_edge.comms.radio import RadioParams, RadioTransport

    key = credentials_from_config(cfg)
    neighbours = {}
    for n in cfg.neighbours:
        host, port = parse_address(n.address, "address")
        neighbours[n.id] = f"udp://{host}:{port}" if ":" not in host else f"udp://[{host}]:{port}"
    bind = cfg.comms.bind_address
    bind = f"[{bind}]" if ":" in bind else bind
    params = RadioParams(
        group=cfg.robot.fleet,
        bind=f"udp://{bind}:{cfg.comms.port}",
        neighbours=neighbours,
        max_datagram_bytes=cfg.comms.datagram_max_bytes,
    )
    ids = {n.id for n in cfg.neighbours}
    policy = AuthPolicy(
        fleet_id=fleet_id(cfg.robot.fleet),
        self_id=cfg.robot.id,
        fleet_robots=frozenset(ids | set(cfg.comms.allow_relay_from) | {cfg.robot.id}),
        neighbours=frozenset(ids),
        relay_from=frozenset(cfg.comms.allow_relay_from),
    )
    radio: Any = RadioTransport(params)
    if cfg.agent.sor_omega != 1.0:  # docs/config.md, agent.sor_omega
        log.warning(
            "agent.sor_omega is %g: over-relaxation needs every neighbour's newest values each "
            "round; over a lossy network it diverged in the benches (use 1)",
            cfg.agent.sor_omega,
        )
    drop_file = os.environ.get("DRAN_EDGE_DROP_FILE")
    if drop_file:  # set by `dran-edge rehearse` only (docs/rehearsal.md)
        from dran_edge.comms.drop_hook import DropHookTransport

        log.warning("rehearsal drop hook on: datagram loss by %s", drop_file)
        radio = DropHookTransport(radio, drop_file, seed=cfg.robot.id * 7919 + boot_epoch)
    link = NeighbourLink(
        radio,
        key=key,
        policy=policy,
        boot_epoch=boot_epoch,
        max_datagram_bytes=cfg.comms.datagram_max_bytes,
        delta_every=cfg.comms.delta_every,
    )
    return LinkTransport(link, {n.id: n.name for n in cfg.neighbours}, cfg.comms.heartbeat_period_s)


def default_perception_factory(
    cfg: RobotConfig, frames: DropOldestQueue
) -> Callable[[], ObservationBatch | None] | None:
    if cfg.camera.source == "none":
        return None
    try:
        from dran_edge.perception.pipeline import make_observation_source  # perception issue
    except ImportError as exc:
        raise DependencyError(
            f"camera.source is {cfg.camera.source!r} but the perception pipeline is not "
            f"available ({exc}); set camera.source: none to run without a camera"
        ) from None
    return make_observation_source(cfg, frames)
