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

This module is the run loop and the checkpoint glue; the rest sits by job next to it:
``wiring`` (config -> core, link and perception factories), ``workers`` (queue, perception
thread), ``status`` (status document and socket), ``windows`` (replay windows on disk),
``counters`` (typed counters). Names callers have imported from here are re-exported.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO, Callable

from dran_edge.comms.ingest import KIND_OBSERVATIONS, Record, encode_event
from dran_edge.config import RobotConfig, config_to_dict, parse_address
from dran_edge.daemon.checkpoint import CheckpointStore, next_boot_epoch
from dran_edge.daemon.counters import DaemonCounters, TickStats
from dran_edge.daemon.journal import IngestJournal
from dran_edge.daemon.notify import Notifier
from dran_edge.daemon.status import StatusServer, status_document, status_line
from dran_edge.daemon.windows import ReplayWindows
from dran_edge.daemon.wiring import (
    AgentLike,
    LinkTransport,
    Transport,
    default_agent_factory,
    default_perception_factory,
    default_transport_factory,
    fleet_id,
    resolve_dirs,
)
from dran_edge.daemon.workers import DropOldestQueue, PerceptionWorker
from dran_edge.errors import DranError
from dran_edge.events import EstimateUpdate, Health, Outgoing, Tick

__all__ = [
    "STATE_FORMAT",
    "AgentLike",
    "Daemon",
    "DropOldestQueue",
    "LinkTransport",
    "PerceptionWorker",
    "StatusServer",
    "TickStats",
    "Transport",
    "default_agent_factory",
    "default_perception_factory",
    "default_transport_factory",
    "fleet_id",
    "resolve_dirs",
]

if TYPE_CHECKING:
    from dran_edge.daemon.ingest_server import IngestServer

log = logging.getLogger(__name__)

#: tag observations in the local graph before β is checked against their information
BETA_CHECK_MIN_OBSERVATIONS = 20

#: 2: the core is an RobotCore; its state's keys ("agent", "graph", "online") sit at the top
#: level of the checkpoint next to the daemon's own.
STATE_FORMAT = 2


# --------------------------------------------------------------------------- the daemon
class Daemon:
    """One robot's daemon. ``start()`` sets everything up and reports READY; ``run()`` ticks."""

    def __init__(
        self,
        cfg: RobotConfig,
        *,
        record_dir: str | Path | None = None,
        environ: Mapping[str, str] | None = None,
        agent_factory: Callable[[RobotConfig, dict | None], AgentLike] = default_agent_factory,
        transport_factory: Callable[
            [RobotConfig, int], Transport | None
        ] = default_transport_factory,
        perception_factory: Callable[..., Any] = default_perception_factory,
        notifier: Notifier | None = None,
    ):
        self.cfg = cfg
        self.environ: Mapping[str, str] = os.environ if environ is None else environ
        self.record_dir = Path(record_dir) if record_dir else None
        self.agent_factory = agent_factory
        self.transport_factory = transport_factory
        self.perception_factory = perception_factory
        self.notifier = notifier or Notifier(self.environ)
        self.state_dir, self.runtime_dir = resolve_dirs(cfg, self.environ)
        self.stats = TickStats()
        self.counters = DaemonCounters()
        self.agent_health: dict = {}
        self.last_estimate: EstimateUpdate | None = None
        self.applied_position: tuple[int, int] | None = None
        self._stop = threading.Event()
        self._status: dict = {"state": "starting", "robot": cfg.robot.name}
        self.started_mono = time.monotonic()
        self._last_checkpoint = 0.0
        self._last_watchdog = float("-inf")
        self._last_status = float("-inf")
        self.ingest: IngestServer | None = None
        self.perception: PerceptionWorker | None = None
        self.status_server: StatusServer | None = None
        self.transport: Transport | None = None
        self.live: Any = None
        self._record_file: BinaryIO | None = None
        self.beta_check: dict | None = None
        """β against this robot's tag observations (``dran.beta_scale``), at status periods."""
        self._beta_warned = False

    # ------------------------------------------------------------------ start-up
    def start(self) -> None:
        """Checkpoint and journal back, then the transport, queues, servers and live view."""
        self.state_dir.mkdir(parents=True, exist_ok=True)
        self.runtime_dir.mkdir(parents=True, exist_ok=True)
        self.boot_epoch = next_boot_epoch(self.state_dir, clock_floor_s=time.time())
        saved = self._load_checkpoint()
        self._open_io(saved)
        self._publish_status("running")
        self.notifier.ready(status_line(self))
        cfg = self.cfg
        log.info(
            "dran-edge ready: robot %s (id %d), boot epoch %d, state %s, ingest %s, "
            "camera %s, transport %s, systemd notify %s",
            cfg.robot.name,
            cfg.robot.id,
            self.boot_epoch,
            self.state_dir,
            self.ingest.path if self.ingest else "off",
            cfg.camera.source,
            cfg.comms.transport,
            self.notifier.backend,
        )

    def _load_checkpoint(self) -> dict | None:
        """The newest usable checkpoint (None: start afresh), the core built from it, the
        journalled records after its position queued for re-applying."""
        cfg = self.cfg
        self.checkpoints = CheckpointStore(self.state_dir)
        saved = self.checkpoints.load()
        if saved is not None and saved.get("robot_id") != cfg.robot.id:
            log.error(
                "checkpoint in %s belongs to robot %s, not %s: ignoring it",
                self.state_dir,
                saved.get("robot_id"),
                cfg.robot.id,
            )
            saved = None
        if saved is not None and saved.get("format") != STATE_FORMAT:
            log.error(
                "checkpoint in %s has state format %s, this daemon writes %s: ignoring it",
                self.state_dir,
                saved.get("format"),
                STATE_FORMAT,
            )
            saved = None
        if saved is not None:
            pos = saved.get("journal_position")
            self.applied_position = (int(pos[0]), int(pos[1])) if pos else None
            self.counters = DaemonCounters.from_dict(saved.get("counters", {}))
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
            self.counters.recovered_records += len(recovered)
        self.journal.requeue(recovered)
        return saved

    def _open_io(self, saved: dict | None) -> None:
        """Recording, transport (its replay windows restored), queues, perception thread,
        ingest and status sockets, live view."""
        cfg = self.cfg
        if self.record_dir is not None:
            robot_dir = self.record_dir / "robots" / cfg.robot.name
            robot_dir.mkdir(parents=True, exist_ok=True)
            import yaml

            (robot_dir / "robot.yaml").write_text(
                yaml.safe_dump(config_to_dict(cfg), sort_keys=False)
            )
            self._record_file = open(robot_dir / "ingest.bin", "ab")
        self.transport = self.transport_factory(cfg, self.boot_epoch)
        self.windows = ReplayWindows(self.state_dir, self.transport, self.counters)
        self.windows.restore(saved)
        self.frames = DropOldestQueue(cfg.camera.queue_size)
        self.observations = DropOldestQueue(cfg.camera.queue_size)
        produce = self.perception_factory(cfg, self.frames)
        if produce is not None:
            self.perception = PerceptionWorker(produce, self.observations)
        if cfg.ingest.enabled:
            from dran_edge.daemon.ingest_server import IngestServer

            path = cfg.resolve(cfg.ingest.socket_path) or self.runtime_dir / "ingest.sock"
            on_frame = self.frames.put if cfg.camera.source == "forwarded" else None
            self.ingest = IngestServer(
                path, self.journal.append, on_frame, mode=cfg.ingest.socket_mode
            )
            self.ingest.start()
        self.status_server = StatusServer(self.runtime_dir / "status.sock", self.snapshot)
        self.status_server.start()
        if cfg.daemon.foxglove:  # the live view (docs/viz.md)
            from dran_edge.viz.live import LiveView

            host, port = parse_address(cfg.daemon.foxglove, "daemon.foxglove")
            self.live = LiveView(
                cfg.robot.name, host, port, min_period_s=max(0.5, cfg.comms.period_s)
            )
            log.info("live view: Foxglove WebSocket server on ws://%s:%d", host, self.live.port)
        if self.perception is not None:
            self.perception.start()

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
                self.counters.observations_unencodable += 1
                log.warning("dropping an observation batch that does not encode: %s", exc)
        outputs: list = []
        for record, pos in self.journal.take_pending():
            try:
                outputs.extend(self.agent.handle(record.event) or ())
            except Exception:
                self.stats.agent_errors += 1
                ok = False
                log.exception(
                    "local graph failed on %s; the record is dropped", type(record.event).__name__
                )
            self.applied_position = pos
            self.counters.applied[type(record.event).__name__] += 1
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
        self.windows.save()
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
                self.counters.live_view_errors += 1
                log.exception("live view: publishing failed; the daemon goes on")
        if now - self._last_status >= self.cfg.daemon.status_period_s:
            self._last_status = now
            line = status_line(self)
            self.notifier.status(line)
            log.info("status: %s", line)
            self._check_beta()

    def _check_beta(self) -> None:
        """β against the information of this robot's tag observations (``dran.beta_scale``,
        docs/dran.md): in the status document, and one warning in the log when it is far
        outside the measured window (a camera or tag size that gives another information
        scale than the default β was set for)."""
        from dran_edge.dran import beta_scale
        from dran_edge.robot.factor_algebra import KIND_OBSERVATION

        graph = getattr(self.agent, "local_graph", None)
        if graph is None:
            return
        fa = graph.factor_arrays(include_prior=False)
        obs = fa["S"][fa["kind"] == KIND_OBSERVATION]
        if len(obs) < BETA_CHECK_MIN_OBSERVATIONS:
            return
        beta = self.cfg.agent.beta
        scale = beta_scale.observation_scale([obs])
        ratio, warning = beta_scale.check(beta, scale)
        self.beta_check = {"beta": beta, "observation_information": scale, "ratio": ratio}
        if warning and not self._beta_warned:
            self._beta_warned = True
            log.warning("%s", warning)

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
                    self.counters.outgoing_without_transport += 1
                    continue
                try:
                    self.transport.send(out.message, out.to)
                    self.counters.messages_sent += 1
                except Exception:
                    self.counters.send_errors += 1
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
            self.counters.heartbeats_sent += beat(time.time_ns(), est.round if est else 0)
        except Exception:
            self.counters.send_errors += 1
            log.exception("heartbeat send failed")

    def _maybe_watchdog(self, now: float) -> None:
        interval = self.notifier.watchdog_interval_s
        if interval is None:
            return
        # Ping at the watchdog cadence (half the timeout), never more often than once per tick.
        if now - self._last_watchdog >= interval - 0.5 * self.cfg.comms.period_s:
            self._last_watchdog = now
            self.notifier.watchdog()
            self.counters.watchdog_pings += 1

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
            "counters": self.counters.as_dict(),
            "ticks": self.stats.ticks,
            "transport": (
                self.transport.to_state()  # type: ignore[attr-defined]
                if self.transport is not None and hasattr(self.transport, "to_state")
                else None
            ),
        }
        clash = own.keys() & core.keys()
        if clash:
            raise ValueError(f"the core's state uses the daemon's checkpoint keys {sorted(clash)}")
        return {**own, **core}

    def _write_record_mission(self) -> None:
        """mission.yaml of the recording (dran_edge/formats/recorded.py): replay and eval read
        the record directory as it is."""
        from dran_edge.formats.recorded import write_recorded_mission

        assert self.record_dir is not None
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
            self.counters.checkpoint_errors += 1
            log.exception("checkpoint failed; will retry")
            return
        self._last_checkpoint = time.monotonic()
        self.counters.checkpoints += 1
        self.counters.checkpoint_bytes = n
        self.stats_checkpoint_s = time.perf_counter() - t
        if self.applied_position is not None:
            self.journal.prune(self.applied_position)

    # ------------------------------------------------------------------ status
    def snapshot(self) -> dict:
        return dict(self._status)

    def _publish_status(self, state: str) -> None:
        self._status = status_document(self, state)

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
