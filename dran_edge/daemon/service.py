"""The robot daemon: the shell around one robot's pure agent (docs/architecture.md).

Threads and what they own:

- **main / tick thread** (:meth:`Daemon.run`): owns the robot's core, the
  :class:`~dran_edge.robot.core.RobotCore` (bounded local graph + DRAN agent; the same object
  replay and the tests drive). A tick every ``comms.period_s`` (2 Hz) on absolute deadlines
  ``t0 + k * period`` (no drift); a tick that starts later than its deadline counts lag, and
  whole periods missed are skipped and counted. Each tick: move queued observation batches into
  the journal, apply every journalled record to the core in journal order (a record the core
  raises on is counted, logged and dropped: the daemon never dies of its input), hand it the
  neighbour messages received, run the round (``Tick``), send its outgoing messages, fsync the
  journal, checkpoint when due, ping the systemd watchdog (only now, after a fully handled
  tick), publish status.
- **ingest** (:class:`~dran_edge.daemon.ingest_server.IngestServer`): decodes bridge records and
  appends them to the journal (accepted = journalled); forwarded frames go to the perception
  queue.
- **perception** (:class:`PerceptionWorker`): frames -> tag observation batches, handed over
  through a bounded drop-oldest queue (drops counted).
- **status** (:class:`StatusServer`): answers ``dran-edge status`` with the latest snapshot.

Crash safety: :mod:`dran_edge.daemon.journal` + :mod:`dran_edge.daemon.checkpoint`. On start the daemon loads
the newest checkpoint (the core's state, journal position, counters), re-applies the journal
after that position, and bumps the boot epoch (at least the wall clock's seconds; neighbours
then accept our restarted sequence numbers). The link's replay windows (per sender: boot
epoch, highest sequence, bitmap) are written to ``replay_windows.json`` after every tick that
accepted a datagram and restored at start, so a datagram captured before a restart (even a
kill -9) is not accepted again (docs/wire-format.md, "Acceptance rules").
"""

from __future__ import annotations

import collections
import json
import logging
import os
import socket
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np

from dran_edge.daemon.checkpoint import CheckpointStore, atomic_write, next_boot_epoch
from dran_edge.comms.ingest import KIND_OBSERVATIONS, Record, encode_event
from dran_edge.config import RobotConfig, config_to_dict, parse_address
from dran_edge.errors import DependencyError, DranError
from dran_edge.events import EstimateUpdate, Health, NeighbourData, ObservationBatch, Outgoing, Tick
from dran_edge.daemon.journal import IngestJournal
from dran_edge.daemon.notify import Notifier

log = logging.getLogger(__name__)

#: 2: the core is an RobotCore; its state's keys ("agent", "graph", "online") sit at the top
#: level of the checkpoint next to the daemon's own.
STATE_FORMAT = 2


# --------------------------------------------------------------------------- plumbing
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


class DropOldestQueue:
    """A bounded FIFO between threads: when full, the oldest item is dropped and counted."""

    def __init__(self, maxlen: int):
        self._q: collections.deque = collections.deque()
        self.maxlen = maxlen
        self.dropped = 0
        self.put_count = 0
        self._cv = threading.Condition()

    def put(self, item: Any) -> None:
        with self._cv:
            if len(self._q) >= self.maxlen:
                self._q.popleft()
                self.dropped += 1
            self._q.append(item)
            self.put_count += 1
            self._cv.notify()

    def get(self, timeout_s: float) -> Any:
        """The oldest item, or None after ``timeout_s``."""
        with self._cv:
            if not self._q:
                self._cv.wait(timeout_s)
            return self._q.popleft() if self._q else None

    def drain(self) -> list:
        with self._cv:
            items = list(self._q)
            self._q.clear()
            return items

    def __len__(self) -> int:
        with self._cv:
            return len(self._q)


class PerceptionWorker:
    """Runs ``produce()`` (frame -> ObservationBatch or None) in a thread into a drop-oldest queue."""

    def __init__(self, produce: Callable[[], ObservationBatch | None], out: DropOldestQueue):
        self.produce = produce
        self.out = out
        self.errors = 0
        self.batches = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="perception", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                batch = self.produce()
            except StopIteration:
                log.info("perception: frame source ended")
                return
            except Exception:
                self.errors += 1
                log.exception("perception: a frame failed; continuing")
                self._stop.wait(0.1)
                continue
            if batch is not None:
                self.batches += 1
                self.out.put(batch)


#: At most this many (newest) keyframes in the status document's ``estimate`` section.
STATUS_MAX_KEYFRAMES = 5000


def _estimate_section(est) -> dict | None:
    """The latest estimate for the ROS 2 bridge (dran_edge/ros/bridge2.py): keyframes as rows
    ``[stamp_ns, x, y, z, qx, qy, qz, qw]`` (world frame, newest STATUS_MAX_KEYFRAMES) and
    objects as ``[object_id, x, y, z, qx, qy, qz, qw]``."""
    if est is None or len(est.keyframe_stamps_ns) == 0:
        return None
    from dran_edge import geometry as geo

    order = np.argsort(np.asarray(est.keyframe_stamps_ns))[-STATUS_MAX_KEYFRAMES:]
    v = geo.se3_to_xyz_quat_xyzw(np.asarray(est.T_world_body)[order])
    kf = [[int(s)] + [round(float(x), 9) for x in row]
          for s, row in zip(np.asarray(est.keyframe_stamps_ns)[order].tolist(), v)]
    objs = []
    if len(est.object_ids):
        w = geo.se3_to_xyz_quat_xyzw(np.asarray(est.T_world_object))
        objs = [[int(i)] + [round(float(x), 9) for x in row] for i, row in zip(est.object_ids, w)]
    return {"round": int(est.round), "keyframes": kf, "objects": objs}


class StatusServer:
    """Unix stream socket: each connection gets the latest status as one JSON document."""

    def __init__(self, path: Path, snapshot: Callable[[], dict], mode: int = 0o660):
        self.path = Path(path)
        self.snapshot = snapshot
        if self.path.exists() or self.path.is_symlink():
            self.path.unlink()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        old = os.umask(0o777 & ~mode)
        try:
            self._sock.bind(str(self.path))
        finally:
            os.umask(old)
        self._sock.listen(4)
        self._sock.settimeout(0.2)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="status", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except (socket.timeout, BlockingIOError):
                continue
            except OSError:
                if self._stop.is_set():
                    return
                continue
            try:
                conn.settimeout(1.0)
                conn.sendall(json.dumps(self.snapshot(), default=_json_default).encode() + b"\n")
            except OSError:
                pass
            finally:
                conn.close()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close()
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


@dataclass
class TickStats:
    """Tick timing: lag against the absolute deadline and duration of the round."""

    ticks: int = 0
    late: int = 0
    missed: int = 0
    lag_max_s: float = 0.0
    lag_last_s: float = 0.0
    round_last_s: float = 0.0
    round_max_s: float = 0.0
    round_total_s: float = 0.0
    agent_errors: int = 0
    durations: collections.deque = field(default_factory=lambda: collections.deque(maxlen=120))

    def as_dict(self) -> dict:
        return {
            "ticks": self.ticks, "late": self.late, "missed": self.missed,
            "lag_max_s": self.lag_max_s, "lag_last_s": self.lag_last_s,
            "solve_last_s": self.round_last_s, "solve_max_s": self.round_max_s,
            "solve_mean_s": self.round_total_s / self.ticks if self.ticks else 0.0,
            "agent_errors": self.agent_errors,
        }


def resolve_dirs(cfg: RobotConfig, environ: dict | None = None) -> tuple[Path, Path]:
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
        raise DependencyError(f"the DRAN agent (dran_edge.robot.core) is not available: {exc}"
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

    def __init__(self, link: Any, neighbours: dict[int, str] | None = None,
                 heartbeat_period_s: float = 0.0):
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

        due = tuple(j for j in self.neighbours
                    if now_ns - self._last_sent_ns.get(j, -(1 << 62))
                    >= self.heartbeat_period_s * 1e9)
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
                "bytes_sent": c.get("bytes_sent", 0), "bytes_received": c.get("bytes_received", 0),
                "datagrams_rejected": c.get("datagrams_rejected", 0),
                "last_heard_s_ago": None if not heard else round((now - heard) * 1e-9, 1),
            }
        return {**snap["totals"], "neighbours": neighbours,
                "next_sequence": self.link.next_sequence,
                "heartbeats_sent": self.heartbeats_sent,
                "heartbeats_received": self.heartbeats_received}

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
    params = RadioParams(group=cfg.robot.fleet, bind=f"udp://{bind}:{cfg.comms.port}",
                         neighbours=neighbours, max_datagram_bytes=cfg.comms.datagram_max_bytes)
    ids = {n.id for n in cfg.neighbours}
    policy = AuthPolicy(fleet_id=fleet_id(cfg.robot.fleet), self_id=cfg.robot.id,
                        fleet_robots=frozenset(ids | set(cfg.comms.allow_relay_from)
                                               | {cfg.robot.id}),
                        neighbours=frozenset(ids), relay_from=frozenset(cfg.comms.allow_relay_from))
    radio: Any = RadioTransport(params)
    drop_file = os.environ.get("DRAN_EDGE_DROP_FILE")
    if drop_file:  # set by `dran-edge rehearse` only (docs/rehearsal.md)
        from dran_edge.comms.drop_hook import DropHookTransport

        log.warning("rehearsal drop hook on: datagram loss by %s", drop_file)
        radio = DropHookTransport(radio, drop_file, seed=cfg.robot.id * 7919 + boot_epoch)
    link = NeighbourLink(radio, key=key, policy=policy, boot_epoch=boot_epoch,
                         max_datagram_bytes=cfg.comms.datagram_max_bytes,
                         delta_every=cfg.comms.delta_every)
    return LinkTransport(link, {n.id: n.name for n in cfg.neighbours},
                         cfg.comms.heartbeat_period_s)


def default_perception_factory(cfg: RobotConfig, frames: DropOldestQueue
                               ) -> Callable[[], ObservationBatch | None] | None:
    if cfg.camera.source == "none":
        return None
    try:
        from dran_edge.perception.pipeline import make_observation_source  # perception issue
    except ImportError as exc:
        raise DependencyError(
            f"camera.source is {cfg.camera.source!r} but the perception pipeline is not "
            f"available ({exc}); set camera.source: none to run without a camera") from None
    return make_observation_source(cfg, frames)


# --------------------------------------------------------------------------- the daemon
class Daemon:
    """One robot's daemon. ``start()`` sets everything up and reports READY; ``run()`` ticks."""

    def __init__(
        self,
        cfg: RobotConfig,
        *,
        record_dir: str | Path | None = None,
        environ: dict | None = None,
        agent_factory: Callable[[RobotConfig, dict | None], AgentLike] = default_agent_factory,
        transport_factory: Callable[[RobotConfig, int], Transport | None]
        = default_transport_factory,
        perception_factory: Callable[..., Any] = default_perception_factory,
        notifier: Notifier | None = None,
    ):
        self.cfg = cfg
        self.environ = os.environ if environ is None else environ
        self.record_dir = Path(record_dir) if record_dir else None
        self.agent_factory = agent_factory
        self.transport_factory = transport_factory
        self.perception_factory = perception_factory
        self.notifier = notifier or Notifier(self.environ)
        self.state_dir, self.runtime_dir = resolve_dirs(cfg, self.environ)
        self.stats = TickStats()
        self.counters: collections.Counter = collections.Counter()
        self.agent_health: dict = {}
        self.last_estimate: EstimateUpdate | None = None
        self.applied_position: tuple[int, int] | None = None
        self._stop = threading.Event()
        self._status: dict = {"state": "starting", "robot": cfg.robot.name}
        self._started_mono = time.monotonic()
        self._last_checkpoint = 0.0
        self._last_watchdog = float("-inf")
        self._last_status = float("-inf")
        self.ingest = None
        self.perception: PerceptionWorker | None = None
        self.status_server: StatusServer | None = None
        self.transport: Transport | None = None
        self.live: Any = None
        self._record_file = None

    # ------------------------------------------------------------------ start-up
    def start(self) -> None:
        cfg = self.cfg
        self.state_dir.mkdir(parents=True, exist_ok=True)
        self.runtime_dir.mkdir(parents=True, exist_ok=True)
        self.boot_epoch = next_boot_epoch(self.state_dir, clock_floor_s=time.time())
        self.checkpoints = CheckpointStore(self.state_dir)
        saved = self.checkpoints.load()
        if saved is not None and saved.get("robot_id") != cfg.robot.id:
            log.error("checkpoint in %s belongs to robot %s, not %s: ignoring it",
                      self.state_dir, saved.get("robot_id"), cfg.robot.id)
            saved = None
        if saved is not None and saved.get("format") != STATE_FORMAT:
            log.error("checkpoint in %s has state format %s, this daemon writes %s: ignoring it",
                      self.state_dir, saved.get("format"), STATE_FORMAT)
            saved = None
        if saved is not None:
            pos = saved.get("journal_position")
            self.applied_position = (int(pos[0]), int(pos[1])) if pos else None
            self.counters.update(saved.get("counters", {}))
            log.info("resuming from checkpoint (journal position %s)", self.applied_position)
        try:
            self.agent = self.agent_factory(cfg, saved)
        except DranError:
            raise
        except Exception:
            if saved is None:
                raise
            log.exception("the checkpointed state does not load; starting afresh from the journal")
            self.agent = self.agent_factory(cfg, None)
            self.applied_position = None
        self.journal = IngestJournal(self.state_dir)
        recovered = self.journal.read_after(self.applied_position)
        if recovered:
            log.info("re-applying %d journalled records not in the checkpoint", len(recovered))
            self.counters["recovered_records"] += len(recovered)
        self.journal.requeue(recovered)
        if self.record_dir is not None:
            robot_dir = self.record_dir / "robots" / cfg.robot.name
            robot_dir.mkdir(parents=True, exist_ok=True)
            import yaml

            (robot_dir / "robot.yaml").write_text(yaml.safe_dump(config_to_dict(cfg),
                                                                 sort_keys=False))
            self._record_file = open(robot_dir / "ingest.bin", "ab")
        self.transport = self.transport_factory(cfg, self.boot_epoch)
        self._restore_windows(saved)
        self.frames = DropOldestQueue(cfg.camera.queue_size)
        self.observations = DropOldestQueue(cfg.camera.queue_size)
        produce = self.perception_factory(cfg, self.frames)
        if produce is not None:
            self.perception = PerceptionWorker(produce, self.observations)
        if cfg.ingest.enabled:
            from dran_edge.daemon.ingest_server import IngestServer

            path = cfg.resolve(cfg.ingest.socket_path) or self.runtime_dir / "ingest.sock"
            on_frame = self.frames.put if cfg.camera.source == "forwarded" else None
            self.ingest = IngestServer(path, self.journal.append, on_frame,
                                       mode=cfg.ingest.socket_mode)
            self.ingest.start()
        self.status_server = StatusServer(self.runtime_dir / "status.sock", self.snapshot)
        self.status_server.start()
        if cfg.daemon.foxglove:  # the live view (docs/viz.md)
            from dran_edge.viz.live import LiveView

            host, port = parse_address(cfg.daemon.foxglove, "daemon.foxglove")
            self.live = LiveView(cfg.robot.name, host, port,
                                 min_period_s=max(0.5, cfg.comms.period_s))
            log.info("live view: Foxglove WebSocket server on ws://%s:%d", host, self.live.port)
        if self.perception is not None:
            self.perception.start()
        self._publish_status("running")
        self.notifier.ready(self._status_line())
        log.info("dran-edge ready: robot %s (id %d), boot epoch %d, state %s, ingest %s, "
                 "camera %s, transport %s, systemd notify %s", cfg.robot.name, cfg.robot.id,
                 self.boot_epoch, self.state_dir,
                 self.ingest.path if self.ingest else "off", cfg.camera.source,
                 cfg.comms.transport, self.notifier.backend)

    # ------------------------------------------------------------------ the loop
    def request_stop(self) -> None:
        self._stop.set()

    def run(self, max_ticks: int | None = None) -> None:
        """Tick until :meth:`request_stop` (or ``max_ticks``); then shut down cleanly."""
        period = self.cfg.comms.period_s
        t0 = time.monotonic()
        k = 0
        try:
            while not self._stop.is_set():
                deadline = t0 + k * period
                wait = deadline - time.monotonic()
                if wait > 0 and self._stop.wait(wait):
                    break
                lag = max(0.0, time.monotonic() - deadline)
                self.stats.lag_last_s = lag
                self.stats.lag_max_s = max(self.stats.lag_max_s, lag)
                if lag > 0.1 * period:
                    self.stats.late += 1
                if lag >= period:
                    skipped = int(lag // period)
                    self.stats.missed += skipped
                    k += skipped
                self.tick()
                k += 1
                if max_ticks is not None and self.stats.ticks >= max_ticks:
                    break
        finally:
            self.shutdown()

    def tick(self) -> None:
        """One round: ingest, agent, transport, journal sync, checkpoint, watchdog, status."""
        ok = True
        for batch in self.observations.drain():
            try:
                self.journal.append(Record(KIND_OBSERVATIONS, batch, encode_event(batch)))
            except (ValueError, TypeError) as exc:
                self.counters["observations_unencodable"] += 1
                log.warning("dropping an observation batch that does not encode: %s", exc)
        outputs: list = []
        for record, pos in self.journal.take_pending():
            try:
                outputs.extend(self.agent.handle(record.event) or ())
            except Exception:
                self.stats.agent_errors += 1
                ok = False
                log.exception("local graph failed on %s; the record is dropped",
                              type(record.event).__name__)
            self.applied_position = pos
            self.counters[f"applied_{type(record.event).__name__}"] += 1
            if self._record_file is not None:
                self._record_file.write(record.raw)
        if self.transport is not None:
            try:
                incoming = self.transport.receive()
            except Exception:
                log.exception("transport receive failed")
                incoming = []
            for data in incoming:
                ok &= self._handle(data, outputs)
        t = time.perf_counter()
        # The core rebuilds the agent's problem when the graph changed, then runs the round.
        ok &= self._handle(Tick(time.time_ns()), outputs)
        dt = time.perf_counter() - t
        self.stats.ticks += 1
        self.stats.round_last_s = dt
        self.stats.round_max_s = max(self.stats.round_max_s, dt)
        self.stats.round_total_s += dt
        self._dispatch(outputs)
        self._heartbeat()
        self._save_windows()
        self.journal.sync()
        if self._record_file is not None:
            self._record_file.flush()
        now = time.monotonic()
        if now - self._last_checkpoint >= self.cfg.daemon.checkpoint_period_s:
            self.checkpoint()
        if ok:
            self._maybe_watchdog(now)
        self._publish_status("running")
        if self.live is not None:
            try:
                self.live.publish(self.last_estimate, self._status)
            except Exception:
                self.counters["live_view_errors"] += 1
                log.exception("live view: publishing failed; the daemon goes on")
        if now - self._last_status >= self.cfg.daemon.status_period_s:
            self._last_status = now
            line = self._status_line()
            self.notifier.status(line)
            log.info("status: %s", line)

    @property
    def graph(self) -> Any:
        """The core's bounded local graph (status and tests read it; only the core writes it)."""
        return self.agent.local_graph

    def _handle(self, event: Any, outputs: list) -> bool:
        try:
            outputs.extend(self.agent.handle(event) or ())
            return True
        except Exception:
            self.stats.agent_errors += 1
            log.exception("agent failed on %s; the event is dropped", type(event).__name__)
            return False

    def _dispatch(self, outputs: list) -> None:
        for out in outputs:
            if isinstance(out, Outgoing):
                if self.transport is None:
                    self.counters["outgoing_without_transport"] += 1
                    continue
                try:
                    self.transport.send(out.message, out.to)
                    self.counters["messages_sent"] += 1
                except Exception:
                    self.counters["send_errors"] += 1
                    log.exception("transport send failed")
            elif isinstance(out, EstimateUpdate):
                self.last_estimate = out
            elif isinstance(out, Health):
                self.agent_health = dict(out.counters)

    def _heartbeat(self) -> None:
        beat = getattr(self.transport, "heartbeat", None)
        if beat is None:
            return
        est = self.last_estimate
        try:
            self.counters["heartbeats_sent"] += beat(time.time_ns(), est.round if est else 0)
        except Exception:
            self.counters["send_errors"] += 1
            log.exception("heartbeat send failed")

    # ------------------------------------------------------------------ replay windows
    @property
    def windows_path(self) -> Path:
        return self.state_dir / "replay_windows.json"

    def _restore_windows(self, saved: dict | None) -> None:
        """Replay windows back from the checkpoint and from ``replay_windows.json`` (the newer
        of the two per sender wins: restoring only ever raises a window)."""
        restore = getattr(self.transport, "restore", None)
        if restore is None:
            return
        sources = [(saved or {}).get("transport")]
        try:
            sources.append(json.loads(self.windows_path.read_text()))
        except FileNotFoundError:
            pass
        except (OSError, ValueError) as exc:
            log.error("ignoring %s: %s", self.windows_path, exc)
        n = 0
        for state in sources:
            if isinstance(state, dict):
                try:
                    n += restore(state)
                except (TypeError, ValueError, IndexError) as exc:
                    log.error("ignoring saved replay windows: %s", exc)
        if n:
            log.info("replay windows restored for %d sender(s)", n)
        self._saved_windows = self._windows_rows()

    def _windows_rows(self) -> list | None:
        to_state = getattr(self.transport, "to_state", None)
        return None if to_state is None else to_state().get("windows")

    def _save_windows(self) -> None:
        """Write the replay windows when a tick moved them (atomic and fsynced, like the
        checkpoint), so that even a kill -9 loses no accepted (epoch, sequence)."""
        rows = self._windows_rows()
        if rows is None or rows == getattr(self, "_saved_windows", None):
            return
        try:
            atomic_write(self.windows_path, json.dumps({"windows": rows}).encode())
        except OSError:
            self.counters["window_save_errors"] += 1
            log.exception("could not save the replay windows")
            return
        self._saved_windows = rows
        self.counters["window_saves"] += 1

    def _maybe_watchdog(self, now: float) -> None:
        interval = self.notifier.watchdog_interval_s
        if interval is None:
            return
        # Ping at the watchdog cadence (half the timeout), never more often than once per tick.
        if now - self._last_watchdog >= interval - 0.5 * self.cfg.comms.period_s:
            self._last_watchdog = now
            self.notifier.watchdog()
            self.counters["watchdog_pings"] += 1

    # ------------------------------------------------------------------ state
    def state(self) -> dict:
        """The checkpoint: the daemon's own fields plus the core's state (whose ``to_state``
        writes the agent's estimates back into the graph first)."""
        core = self.agent.to_state()
        own = {
            "format": STATE_FORMAT,
            "robot_id": self.cfg.robot.id,
            "boot_epoch": self.boot_epoch,
            "journal_position": list(self.applied_position) if self.applied_position else None,
            "counters": dict(self.counters),
            "ticks": self.stats.ticks,
            "transport": (self.transport.to_state()  # type: ignore[attr-defined]
                          if self.transport is not None and hasattr(self.transport, "to_state")
                          else None),
        }
        clash = own.keys() & core.keys()
        if clash:
            raise ValueError(f"the core's state uses the daemon's checkpoint keys {sorted(clash)}")
        return {**own, **core}

    def _write_record_mission(self) -> None:
        """mission.yaml of the recording (dran_edge/formats/recorded.py): replay and eval read
        the record directory as it is."""
        from dran_edge.formats.recorded import write_recorded_mission

        try:
            path = write_recorded_mission(self.record_dir)
            log.info("recording: wrote %s", path)
        except Exception:  # a recording without mission.yaml can still be merged later
            log.exception("recording: could not write mission.yaml in %s", self.record_dir)

    def checkpoint(self) -> None:
        t = time.perf_counter()
        try:
            n = self.checkpoints.save(self.state())
        except Exception:
            self.counters["checkpoint_errors"] += 1
            log.exception("checkpoint failed; will retry")
            return
        self._last_checkpoint = time.monotonic()
        self.counters["checkpoints"] += 1
        self.counters["checkpoint_bytes"] = n
        self.stats_checkpoint_s = time.perf_counter() - t
        if self.applied_position is not None:
            self.journal.prune(self.applied_position)

    # ------------------------------------------------------------------ status
    def snapshot(self) -> dict:
        return dict(self._status)

    def _publish_status(self, state: str) -> None:
        est = self.last_estimate
        ingest = self.ingest
        transport_stats: dict = {}
        if self.transport is not None:
            try:
                transport_stats = self.transport.stats()
            except Exception:
                transport_stats = {"error": "stats unavailable"}
        self._status = {
            "state": state,
            "robot": {"id": self.cfg.robot.id, "name": self.cfg.robot.name,
                      "fleet": self.cfg.robot.fleet},
            "pid": os.getpid(),
            "boot_epoch": getattr(self, "boot_epoch", None),
            "uptime_s": time.monotonic() - self._started_mono,
            "rounds": self.stats.as_dict(),
            "graph": {"nodes": self.graph.num_nodes if hasattr(self, "graph") else 0,
                      "factors": self.graph.num_factors if hasattr(self, "graph") else 0,
                      **({} if est is None else {
                "round": est.round, "keyframes": int(len(est.keyframe_stamps_ns)),
                "objects": len(est.object_ids), "cost": est.cost,
                "consensus_error": est.consensus_error, "converged": est.converged})},
            "graph_counters": dict(self.graph.counters) if hasattr(self, "graph") else {},
            "neighbours": transport_stats.get("neighbours", {}),
            "transport": transport_stats,
            "ingest": None if ingest is None else {
                "socket": str(ingest.path), **dict(ingest.counters),
                "rejected_by_reason": dict(ingest.rejected)},
            "journal": {"pending": self.journal.pending_count if hasattr(self, "journal") else 0,
                        "position": self.applied_position},
            "queues": {"observations_dropped": self.observations.dropped
                       if hasattr(self, "observations") else 0,
                       "frames_dropped": self.frames.dropped if hasattr(self, "frames") else 0},
            "perception": None if self.perception is None else {
                "batches": self.perception.batches, "errors": self.perception.errors},
            "counters": dict(self.counters),
            "agent": self.agent_health,
            "estimate": _estimate_section(est),
            "systemd": self.notifier.backend,
        }

    def _status_line(self) -> str:
        s = self._status
        graph = s.get("graph") or {}
        ingest = s.get("ingest") or {}
        return (f"rounds={self.stats.ticks} late={self.stats.late} "
                f"solve_ms={1e3 * self.stats.round_last_s:.1f} "
                f"keyframes={graph.get('keyframes', 0)} objects={graph.get('objects', 0)} "
                f"records={ingest.get('records', 0)} rejected={ingest.get('rejected', 0)} "
                f"obs_dropped={s.get('queues', {}).get('observations_dropped', 0)} "
                f"neighbours={self._heard_line(s.get('neighbours') or {})}")

    @staticmethod
    def _heard_line(neighbours: dict) -> str:
        """``heard/configured``: neighbours heard within the last 10 s, of those listed."""
        heard = sum(1 for n in neighbours.values()
                    if n.get("last_heard_s_ago") is not None and n["last_heard_s_ago"] < 10.0)
        return f"{heard}/{len(neighbours)}"

    # ------------------------------------------------------------------ shutdown
    def shutdown(self) -> None:
        self.notifier.stopping()
        self._publish_status("stopping")
        if self.ingest is not None:
            self.ingest.stop()
        if self.perception is not None:
            self.perception.stop()
        # Records that arrived during shutdown are journalled; they are applied on the next start.
        try:
            self.checkpoint()
        finally:
            self.journal.close()
            if self._record_file is not None:
                self._record_file.close()
                self._write_record_mission()
            if self.transport is not None:
                self.transport.close()
            if self.status_server is not None:
                self.status_server.stop()
            if self.live is not None:
                self.live.close()
        log.info("dran-edge stopped after %d rounds", self.stats.ticks)
