"""Replay a recorded run through the robot code: every robot, same decoders, same agent.

``replay_run(RUN, ReplayOptions())`` (the shell behind ``dran-edge replay``, docs/replay.md):

1. **Inputs, through the same decoders as live.** Each robot's ``ingest.bin`` is decoded by the
   ingest stream decoder (:func:`dran_edge.comms.ingest.iter_records`); a record that does not
   decode is counted by reason and skipped, like on the robot. Recorded frames go through the
   perception pipeline (detector -> tag poses -> objects), and each observation batch crosses the
   same boundary the daemon's journal does: encoded as an ingest record and decoded again.
   Perception depends only on the frames, so it runs first, one worker process per robot
   (``workers``), and its output does not depend on the number of workers.
2. **Rounds.** Time advances in rounds of the robots' ``comms.period_s`` (2 Hz) from the mission
   start. In round k (stamp ``t_k = start + (k+1)·period``) each robot, in id order, gets: every
   input whose stamp is ≤ t_k (ingest records in file order), then the neighbour messages that
   arrived, then ``Tick(t_k)``; its outgoing messages are encoded, signed and sent. After the
   mission's data ends, ``settle_rounds`` more rounds let consensus finish.
3. **Communication.** By default the in-process bus (:mod:`dran_edge.comms.bus`) with its loss,
   latency and partition model, carrying the same authenticated datagrams as the radio
   (:class:`~dran_edge.comms.link.NeighbourLink`). ``transport="udp"`` uses real ZeroMQ
   RADIO/DISH sockets on loopback (the addresses of each robot's config); each round waits until
   every datagram sent in the previous round has arrived (or ``udp_wait_s`` passed), so a
   loopback replay without loss gives the bus's numbers.
4. **Outputs** in ``RUN/out/`` (docs/run-format.md): per-robot TUM trajectories (final and
   initial), object maps, ``merged.g2o`` + ``merged_vertices.csv``, ``rounds.csv`` and
   ``report.json``; with mocap, the metrics of :mod:`dran_edge.evaluate`.

Nothing here reads a clock except to report the wall time and, with ``speed > 0``, to pace
rounds (``speed`` = times real time). Same run, same options -> same numbers.
"""

from __future__ import annotations

import bisect
import csv
import json
import logging
import math
import time
import zlib
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from dran_edge import geometry as geo
from dran_edge import run_dir as rd
from dran_edge.errors import DependencyError, InputError
from dran_edge.events import EstimateUpdate, Health, NeighbourData, ObservationBatch, Outgoing, Tick

log = logging.getLogger(__name__)

#: HMAC key of replayed links. A run never stores the fleet's secret; replay signs and verifies
#: with this fixed key so the authentication code path runs as on the robot.
REPLAY_KEY = bytes(range(32))
REPORT_FORMAT = "dran-edge-replay/1"
#: Fields of report.json that depend on the machine's speed (golden comparisons ignore them).
WALL_CLOCK_FIELDS = ("replay_wall_s", "realtime_factor", "perception_wall_s", "rounds_wall_s")


@dataclass(frozen=True)
class PartitionSpec:
    """Robots cut off from all others between two mission times (seconds from the start)."""

    robots: tuple[int, ...]
    start_s: float
    end_s: float

    @staticmethod
    def parse(text: str) -> "PartitionSpec":
        """``"3,4:20:40"`` -> robots 3 and 4 cut off from 20 s to 40 s."""
        try:
            ids, start, end = text.split(":")
            robots = tuple(int(x) for x in ids.split(",") if x)
            spec = PartitionSpec(robots, float(start), float(end))
        except ValueError:
            raise InputError(f"--partition: expected ROBOT[,ROBOT...]:START_S:END_S, got {text!r}"
                             ) from None
        if not robots or not 0 <= spec.start_s < spec.end_s:
            raise InputError(f"--partition: expected robots and 0 <= START_S < END_S, got {text!r}")
        return spec


@dataclass(frozen=True)
class ReplayOptions:
    """How to replay a run."""

    transport: str = "bus"
    """``bus`` (in-process, with the network model) or ``udp`` (loopback RADIO/DISH)."""
    loss: float = 0.0
    """Probability that a datagram is lost on a link (bus only)."""
    latency_rounds: int = 1
    """Rounds between sending and delivery (bus only; 1 = next round)."""
    partitions: tuple[PartitionSpec, ...] = ()
    """Communication partitions (bus only)."""
    speed: float = 0.0
    """0: as fast as compute allows; X > 0: pace rounds at X times real time."""
    settle_rounds: int = 20
    """Extra rounds after the mission's data ends (consensus finishes)."""
    workers: int | None = None
    """Perception worker processes (default: one per core, at most one per robot)."""
    seed: int = 0
    """Seed of the bus's loss model."""
    evaluate: bool = True
    """Score against the run's mocap (when it has one) and put the metrics in report.json."""
    udp_wait_s: float = 0.5
    """UDP only: how long a round waits for the datagrams of the previous round."""

    def __post_init__(self) -> None:
        if self.transport not in ("bus", "udp"):
            raise InputError(f"transport: expected 'bus' or 'udp', got {self.transport!r}")
        if not 0.0 <= self.loss <= 1.0:
            raise InputError(f"loss: expected a probability in [0, 1], got {self.loss}")
        if self.latency_rounds < 0 or self.settle_rounds < 0 or self.speed < 0:
            raise InputError("latency, settle rounds and speed must be >= 0")
        if self.transport == "udp" and (self.loss or self.partitions or self.latency_rounds != 1):
            raise InputError("--loss/--latency/--partition model the in-process bus; "
                             "with --transport udp the network is the real loopback")


# ---------------------------------------------------------------------------------- perception
def _perceive_robot(args: tuple[str, str, str]) -> tuple[str, list[bytes], int, float]:
    """One robot's frames -> observation batches as ingest records (runs in a worker)."""
    config_path, calib_dir, name = args
    from dran_edge.comms.ingest import encode_event
    from dran_edge.config import load_config
    from dran_edge.perception.calib import load_calibration
    from dran_edge.perception.pipeline import ObservationPipeline
    from dran_edge.perception.sources import RecordedFramesSource

    t0 = time.perf_counter()
    cfg = load_config(config_path)
    pipeline = ObservationPipeline(load_calibration(calib_dir, name))
    records, frames = [], 0
    source = RecordedFramesSource(cfg.resolve(cfg.camera.recording))
    try:
        for frame in source:
            frames += 1
            batch = pipeline.process(frame)
            if batch.observations:
                records.append(encode_event(batch))
    finally:
        source.close()
    return name, records, frames, time.perf_counter() - t0


# ---------------------------------------------------------------------------------- robots
@dataclass
class _Robot:
    """One replayed robot: its core, its link and its input queue."""

    info: rd.RunRobot
    cfg: Any
    core: Any
    link: Any = None
    events: list = field(default_factory=list)
    """(release_stamp_ns, order, event), sorted."""
    next_event: int = 0
    last: EstimateUpdate | None = None
    first_seen: dict = field(default_factory=dict)
    """keyframe stamp -> T_world_body of the first estimate that contained it."""
    health: dict = field(default_factory=dict)
    rejected: Counter = field(default_factory=Counter)
    frames: int = 0
    observations: int = 0


def _decode_ingest(data: bytes, what: str) -> tuple[list, Counter]:
    from dran_edge.comms.ingest import IngestDecodeError, iter_records

    events, rejected = [], Counter()
    for item in iter_records(data):
        if isinstance(item, IngestDecodeError):
            rejected[item.reason] += 1
            log.debug("%s: %s", what, item)
        else:
            events.append(item.event)
    return events, rejected


def _event_stamp(ev) -> int:
    stamp = getattr(ev, "stamp_ns", None)
    return int(stamp if stamp is not None else getattr(ev, "stamp_cur_ns"))


def make_core(cfg, robot: rd.RunRobot):
    """The robot's agent as the daemon builds it (ingest events in, outputs out).

    The run's ``T_world_odom`` (the paper's protocol: the robot's initial frame in the world,
    from mocap) is handed to agents that accept it.
    """
    from dran_edge.daemon import default_agent_factory

    core = default_agent_factory(cfg, None)
    if not hasattr(core, "set_world_frame"):
        # The daemon's factory returned the bare agent, which ignores ingest events: put the
        # online core (bounded local graph + agent) around it, as the robot needs.
        from dran_edge.online_agent import OnlineAgent

        core = OnlineAgent(cfg.agent)
    if robot.T_world_odom is not None:
        core.set_world_frame(robot.T_world_odom)
    return core


def _fleet_id(fleet: str) -> int:
    return zlib.crc32(fleet.encode("utf-8")) & 0xFFFF


def _make_links(run: rd.Run, robots: dict[int, _Robot], opt: ReplayOptions, period_s: float):
    from dran_edge.comms.auth import AuthPolicy
    from dran_edge.comms.link import NeighbourLink

    mission = run.mission
    ids = sorted(robots)
    fleet_id = _fleet_id(mission.fleet)
    bus = None
    if opt.transport == "bus":
        from dran_edge.comms.bus import Bus, BusParams, Partition

        parts = [Partition(frozenset(p.robots), int(math.floor(p.start_s / period_s)),
                           int(math.ceil(p.end_s / period_s))) for p in opt.partitions]
        bus = Bus(ids, graph=mission.comm_graph,
                  params=BusParams(loss_probability=opt.loss, latency_rounds=opt.latency_rounds,
                                   seed=opt.seed),
                  partitions=parts)
    for rid in ids:
        r = robots[rid]
        policy = AuthPolicy(fleet_id=fleet_id, self_id=rid, fleet_robots=frozenset(ids),
                            neighbours=frozenset(mission.neighbours(rid)),
                            relay_from=frozenset(r.cfg.comms.allow_relay_from))
        if bus is not None:
            transport = bus.endpoint(rid)
        else:
            transport = _udp_transport(r.cfg, mission)
        r.link = NeighbourLink(transport, key=REPLAY_KEY, policy=policy, boot_epoch=1,
                               max_datagram_bytes=r.cfg.comms.datagram_max_bytes)
    return bus


class _BufferedUdp:
    """A RADIO/DISH transport whose received datagrams are collected by the round loop."""

    def __init__(self, radio):
        self.radio = radio
        self.buffer: list[tuple[int | None, bytes]] = []

    def send(self, to: int, data: bytes) -> bool:
        return self.radio.send(to, data)

    def pull(self) -> int:
        got = self.radio.receive()
        self.buffer.extend(got)
        return len(got)

    def receive(self, max_datagrams: int | None = None):
        out = sorted(self.buffer, key=lambda x: x[1])
        self.buffer = []
        return out

    def close(self) -> None:
        self.radio.close()


def _udp_transport(cfg, mission: rd.Mission) -> _BufferedUdp:
    from dran_edge.comms.radio import RadioParams, RadioTransport

    neighbours = {n.id: f"udp://{n.address.rsplit(':', 1)[0].strip('[]')}:"
                  f"{n.address.rsplit(':', 1)[1]}" for n in cfg.neighbours}
    params = RadioParams(group=mission.fleet, bind=f"udp://{cfg.comms.bind_address}:{cfg.comms.port}",
                         neighbours=neighbours, max_datagram_bytes=cfg.comms.datagram_max_bytes)
    return _BufferedUdp(RadioTransport(params))


# ---------------------------------------------------------------------------------- the replay
@dataclass
class ReplayResult:
    report: dict
    out_dir: Path


def _load_robots(run: rd.Run) -> dict[int, _Robot]:
    from dran_edge.comms.ingest import decode_record  # noqa: F401  (fail early if missing)

    robots: dict[int, _Robot] = {}
    for info in run.mission.robots:
        cfg = run.load_config(info.name)
        try:
            core = make_core(cfg, info)
        except DependencyError:
            raise
        events, rejected = _decode_ingest(run.read_ingest(info.name),
                                          str(run.ingest_path(info.name)))
        r = _Robot(info, cfg, core, rejected=rejected)
        release = 0
        for order, ev in enumerate(events):
            release = max(release, _event_stamp(ev))
            r.events.append((release, order, ev))
            if isinstance(ev, ObservationBatch):
                r.observations += len(ev.observations)
        robots[info.id] = r
    return robots


def _run_perception(run: rd.Run, robots: dict[int, _Robot], opt: ReplayOptions,
                    progress: Callable[[str, int, int], None] | None) -> float:
    jobs = []
    for r in robots.values():
        if r.cfg.camera.source != "recorded" or run.frames_dir(r.info.name) is None:
            continue
        calib = r.cfg.resolve(r.cfg.camera.calib_dir) or run.calib_dir
        jobs.append((str(run.config_path(r.info.name)), str(calib), r.info.name))
    if not jobs:
        return 0.0
    t0 = time.perf_counter()
    by_name = {r.info.name: r for r in robots.values()}
    import os

    workers = opt.workers or min(len(jobs), os.cpu_count() or 1)
    if progress:
        progress("perception", 0, len(jobs))
    results = []
    if workers <= 1:
        for k, job in enumerate(jobs):
            results.append(_perceive_robot(job))
            if progress:
                progress("perception", k + 1, len(jobs))
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            for k, res in enumerate(pool.map(_perceive_robot, jobs)):
                results.append(res)
                if progress:
                    progress("perception", k + 1, len(jobs))
    for name, records, frames, _wall in results:
        r = by_name[name]
        r.frames = frames
        events, rejected = _decode_ingest(b"".join(records), f"{name} observations")
        r.rejected.update(rejected)
        base = len(r.events)
        for k, ev in enumerate(events):
            r.events.append((_event_stamp(ev), base + k, ev))
            r.observations += len(ev.observations)
        r.events.sort(key=lambda x: (x[0], x[1]))
    return time.perf_counter() - t0


def replay_run(run_dir: str | Path, opt: ReplayOptions = ReplayOptions(),
               progress: Callable[[str, int, int], None] | None = None) -> ReplayResult:
    """Replay the run at ``run_dir`` and write ``run_dir/out`` (see the module docstring)."""
    wall0 = time.perf_counter()
    run = rd.open_run(run_dir)
    mission = run.mission
    robots = _load_robots(run)
    periods = {r.cfg.comms.period_s for r in robots.values()}
    if len(periods) != 1:
        raise InputError(f"robots of one run must share comms.period_s, got {sorted(periods)}",
                         path=str(run.root))
    period_s = periods.pop()
    period_ns = int(round(period_s * 1e9))
    perception_wall = _run_perception(run, robots, opt, progress)
    bus = _make_links(run, robots, opt, period_s)
    last_stamp = max([mission.start_ns + int(mission.duration_s * 1e9)]
                     + [r.events[-1][0] for r in robots.values() if r.events])
    mission_rounds = max(1, int(math.ceil((last_stamp - mission.start_ns) / period_ns)))
    total_rounds = mission_rounds + opt.settle_rounds
    ids = sorted(robots)
    rounds_rows = []
    bytes_total = 0
    expected: Counter = Counter()
    t_rounds = time.perf_counter()
    try:
        for k in range(total_rounds):
            t_k = mission.start_ns + (k + 1) * period_ns
            if opt.speed > 0:
                target = t_rounds + (k + 1) * period_s / opt.speed
                delay = target - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            if bus is None:
                _udp_collect(robots, expected, opt.udp_wait_s)
            bytes_round = 0
            expected = Counter()
            for rid in ids:
                r = robots[rid]
                outputs: list = []
                stamps = r.events
                end = bisect.bisect_right(stamps, (t_k, math.inf), lo=r.next_event)
                for _, _, ev in stamps[r.next_event:end]:
                    outputs.extend(r.core.handle(ev) or ())
                r.next_event = end
                for msg in r.link.poll(now_ns=t_k):
                    outputs.extend(r.core.handle(NeighbourData(t_k, msg)) or ())
                outputs.extend(r.core.handle(Tick(t_k)) or ())
                for out in outputs:
                    if isinstance(out, Outgoing):
                        grams = r.link.send_message(out.message, out.to)
                        n = sum(len(g) for g in grams) * len(out.to)
                        bytes_round += n
                        for j in out.to:
                            expected[j] += len(grams)
                    elif isinstance(out, EstimateUpdate):
                        r.last = out
                        for s, T in zip(out.keyframe_stamps_ns.tolist(), out.T_world_body):
                            if s not in r.first_seen:
                                r.first_seen[s] = T.copy()
                    elif isinstance(out, Health):
                        r.health.update(out.counters)
            if bus is not None:
                bus.advance()
            bytes_total += bytes_round
            lasts = [robots[i].last for i in ids]
            costs = [u.cost for u in lasts if u is not None and math.isfinite(u.cost)]
            cerr = [u.consensus_error for u in lasts if u is not None
                    and math.isfinite(u.consensus_error)]
            rounds_rows.append({
                "round": k, "stamp_ns": t_k, "bytes_total": bytes_total, "bytes_round": bytes_round,
                "cost": float(np.sum(costs)) if costs else math.nan,
                "consensus_error": float(np.max(cerr)) if cerr else math.nan,
                "converged_robots": sum(1 for u in lasts if u is not None and u.converged),
                "datagrams_lost": int(sum(bus.lost.values())) if bus is not None else 0,
            })
            if progress:
                progress("rounds", k + 1, total_rounds)
    finally:
        for r in robots.values():
            if r.link is not None and bus is None:
                r.link.transport.close()
    rounds_wall = time.perf_counter() - t_rounds
    out_dir = run.out_dir
    out_dir.mkdir(exist_ok=True)
    write_outputs(run, robots, rounds_rows)
    wall = time.perf_counter() - wall0
    frames = sum(r.frames for r in robots.values())
    report: dict[str, Any] = {
        "format": REPORT_FORMAT,
        "run": str(run.root),
        "robots": len(robots),
        "mission_s": float(mission.duration_s),
        "replay_wall_s": round(wall, 3),
        "perception_wall_s": round(perception_wall, 3),
        "rounds_wall_s": round(rounds_wall, 3),
        "realtime_factor": round(mission.duration_s / wall, 3) if wall > 0 else None,
        "rounds": total_rounds,
        "mission_rounds": mission_rounds,
        "bytes_total": int(bytes_total),
        "transport": opt.transport,
        "options": {k: v for k, v in asdict(opt).items() if k not in ("workers",)},
        "frames_processed": frames,
        "observations": sum(r.observations for r in robots.values()),
        "ingest_rejected": dict(sum((r.rejected for r in robots.values()), Counter())),
        "converged_robots": sum(1 for r in robots.values() if r.last is not None
                                and r.last.converged),
        "keyframes": {r.info.name: int(len(r.last.keyframe_stamps_ns)) if r.last else 0
                      for r in robots.values()},
        "objects_known": {r.info.name: len(r.last.object_ids) if r.last else 0
                          for r in robots.values()},
        "final_cost": rounds_rows[-1]["cost"] if rounds_rows else None,
        "final_consensus_error": rounds_rows[-1]["consensus_error"] if rounds_rows else None,
    }
    if bus is not None:
        report["datagrams_lost"] = {k: int(v) for k, v in bus.lost.items()}
    _write_report(out_dir, report)
    if opt.evaluate and mission.mocap_file:
        report.update(_metrics(run))
        _write_report(out_dir, report)
    return ReplayResult(report, out_dir)


def _udp_collect(robots: dict[int, _Robot], expected: Counter, wait_s: float) -> None:
    """Wait until each robot's DISH has the datagrams sent to it last round (or time out)."""
    deadline = time.monotonic() + wait_s
    got: Counter = Counter()
    while True:
        for rid, r in robots.items():
            got[rid] += r.link.transport.pull()
        if all(got[rid] >= expected[rid] for rid in robots) or time.monotonic() > deadline:
            missing = {rid: expected[rid] - got[rid] for rid in robots if got[rid] < expected[rid]}
            if missing:
                log.warning("udp: datagrams not arrived within %.2f s: %s", wait_s, missing)
            return
        time.sleep(0.0005)


def _json_clean(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _json_clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def _write_report(out_dir: Path, report: dict) -> None:
    (out_dir / "report.json").write_text(json.dumps(_json_clean(report), indent=2) + "\n",
                                         encoding="utf-8")


def _metrics(run: rd.Run) -> dict:
    """sr_ate, sr_cost, ate_m, ce, bias from dran_edge.evaluate (the numbers `eval` reports)."""
    from dran_edge.evaluate import EvalOptions, evaluate_run

    try:
        ev = evaluate_run(run.root, EvalOptions(plots=False))
    except InputError as exc:
        log.warning("evaluation failed: %s", exc)
        return {"evaluation_error": str(exc)}
    return {"metrics": pick_metrics(ev), **pick_metrics(ev)}


def pick_metrics(ev: dict) -> dict:
    """The headline numbers of an evaluation report (names of docs/run-format.md)."""
    def find(d: Any, *keys: str) -> Any:
        for key in keys:
            cur = d
            for part in key.split("."):
                if not isinstance(cur, dict) or part not in cur:
                    cur = None
                    break
                cur = cur[part]
            if cur is not None:
                return cur
        return None

    return {
        "sr_ate": find(ev, "sr_ate_pct", "summary.sr_ate_pct", "sr_ate"),
        "sr_cost": find(ev, "sr_cost_pct", "summary.sr_cost_pct", "cost.sr_cost_pct", "sr_cost"),
        "ate_m": find(ev, "ate_m", "summary.ate_m", "ate.final.rmse_m", "ate_rmse_m"),
        "ce": find(ev, "ce", "summary.ce", "objects.ce"),
        "bias": find(ev, "bias", "summary.bias", "objects.bias"),
    }


# ---------------------------------------------------------------------------------- outputs
def write_outputs(run: rd.Run, robots: dict[int, _Robot], rounds_rows: list[dict]) -> None:
    from dran_edge.tum import write_tum

    out = run.out_dir
    for r in robots.values():
        d = out / r.info.name
        d.mkdir(parents=True, exist_ok=True)
        u = r.last
        if u is None or len(u.keyframe_stamps_ns) == 0:
            for f in ("trajectory.tum", "trajectory_init.tum", "objects.csv"):
                (d / f).unlink(missing_ok=True)
            log.warning("robot %s produced no estimate", r.info.name)
            continue
        stamps = np.asarray(u.keyframe_stamps_ns, dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        stamps = stamps[order]
        write_tum(d / "trajectory.tum", stamps * 1e-9, np.asarray(u.T_world_body)[order],
                  header=f"{r.info.name}: final estimate (dran-edge replay)")
        if hasattr(r.core, "initial_estimate"):
            s0, T0 = r.core.initial_estimate()
            what = "odometry alone, before any optimisation"
        else:
            s0 = stamps
            T0 = np.stack([r.first_seen.get(int(s), u.T_world_body[i]) for s, i in
                           zip(stamps.tolist(), order.tolist())])
            what = "each keyframe's first estimate"
        o0 = np.argsort(s0, kind="stable")
        write_tum(d / "trajectory_init.tum", s0[o0] * 1e-9, T0[o0],
                  header=f"{r.info.name}: initial estimate, {what} (dran-edge replay)")
        with open(d / "objects.csv", "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(["object_id", "x", "y", "z", "qx", "qy", "qz", "qw"])
            for oid, T in sorted(zip(u.object_ids, u.T_world_object), key=lambda x: x[0]):
                w.writerow([int(oid)] + [f"{v:.9f}" for v in geo.se3_to_xyz_quat_xyzw(T)])
    with open(out / "rounds.csv", "w", newline="", encoding="utf-8") as f:
        cols = ["round", "stamp_ns", "bytes_total", "bytes_round", "cost", "consensus_error",
                "converged_robots", "datagrams_lost"]
        w = csv.writer(f, lineterminator="\n")
        w.writerow(cols)
        for row in rounds_rows:
            w.writerow(["" if isinstance(row[c], float) and not math.isfinite(row[c])
                        else (f"{row[c]:.9g}" if isinstance(row[c], float) else row[c])
                        for c in cols])
    write_merged_g2o(run, robots)


def write_merged_g2o(run: rd.Run, robots: dict[int, _Robot]) -> bool:
    """``merged.g2o`` + ``merged_vertices.csv`` from every robot's local graph (if it has one).

    Vertices: robot ``r``'s keyframe ``j`` is ``r * 1_000_000 + j`` (by stamp order), object
    ``k`` is ``1_000_000_000 + k`` (shared by every robot that observed it). Edges: every
    odometry, loop and observation factor with information ``Σ⁻¹``; a robot's gauge prior fixes
    its node (FIX). Values: the final decentralized estimate (each robot's agent, world frame;
    an object takes the copy of the lowest robot id that has one).
    """
    from dran_edge.g2o import G2oGraph, write_g2o

    vid: list[int] = []
    poses: list[np.ndarray] = []
    rows: list[tuple[int, str, str, int]] = []
    edges, meas, info, fixed_ids = [], [], [], set()
    obj_vertex: dict[int, np.ndarray] = {}
    for rid in sorted(robots):
        r = robots[rid]
        graph = _local_graph(r.core)
        if graph is None or r.last is None:
            continue
        fa = graph.factor_arrays()
        keys = graph.node_keys()
        stamps = graph.node_stamps_ns()
        # vertex values: the agent's final estimate (world frame), matched by keyframe stamp
        final = {int(s): T for s, T in zip(r.last.keyframe_stamps_ns.tolist(), r.last.T_world_body)}
        keep = np.array([int(s) in final for s in stamps.tolist()], bool)
        keys, stamps = keys[keep], stamps[keep]
        est = np.stack([final[int(s)] for s in stamps.tolist()]) if len(stamps) else np.zeros((0, 4, 4))
        order = np.argsort(stamps, kind="stable")
        key_vid = {}
        for j, i in enumerate(order.tolist()):
            v = rid * 1_000_000 + j
            key_vid[int(keys[i])] = v
            vid.append(v)
            poses.append(est[i])
            rows.append((v, "pose", r.info.name, int(stamps[i])))
        from dran_edge.local_graph import OBJ

        for oid, T in zip(r.last.object_ids, r.last.T_world_object):
            obj_vertex.setdefault(int(oid), T)

        def vertex(key: int) -> int | None:
            if key >= OBJ:
                return 1_000_000_000 + int(key - OBJ)
            return key_vid.get(int(key))

        for p, q, Z, S in zip(fa["p"].tolist(), fa["q"].tolist(), fa["Z"], fa["S"]):
            vq = vertex(q)
            if p < 0:
                if vq is not None:
                    fixed_ids.add(vq)
                continue
            vp = vertex(p)
            if vp is None or vq is None:
                continue
            edges.append((vp, vq))
            meas.append(Z)
            info.append(np.linalg.inv(S))
    if not vid:
        log.warning("no robot exposes its local graph: merged.g2o not written")
        for f in ("merged.g2o", "merged_vertices.csv"):
            (run.out_dir / f).unlink(missing_ok=True)
        return False
    for oid in sorted(obj_vertex):
        v = 1_000_000_000 + oid
        vid.append(v)
        poses.append(obj_vertex[oid])
        rows.append((v, "object", str(oid), 0))
    vid_arr = np.asarray(vid, np.int64)
    order = np.argsort(vid_arr)
    pos = {int(v): k for k, v in enumerate(vid_arr[order].tolist())}
    e = np.array([[pos[a], pos[b]] for a, b in edges], np.int64).reshape(-1, 2)
    info_arr = np.stack(info) if info else np.zeros((0, 6, 6))
    info_arr = 0.5 * (info_arr + np.swapaxes(info_arr, -1, -2))
    g = G2oGraph(
        dim=3, vertex_ids=vid_arr[order], poses=np.stack(poses)[order],
        has_pose=np.ones(len(vid), bool), edges=e,
        measurements=np.stack(meas) if meas else np.zeros((0, 4, 4)),
        information=info_arr,
        fixed=np.isin(vid_arr[order], sorted(fixed_ids)),
        edge_lines=np.zeros(len(edges), np.int64),
    )
    write_g2o(run.out_dir / "merged.g2o", g)
    with open(run.out_dir / "merged_vertices.csv", "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["vertex_id", "kind", "name", "stamp_ns"])
        for row in sorted(rows):
            w.writerow(row)
    return True


def _local_graph(core):
    """The core's bounded local graph (``LocalGraph``) when it exposes one."""
    for name in ("local_graph", "graph"):
        g = getattr(core, name, None)
        if g is not None and hasattr(g, "factor_arrays") and hasattr(g, "node_keys"):
            return g
    return None


# ---------------------------------------------------------------------------------- golden
#: Keys of report.json kept in a golden summary (wall-clock fields are never among them).
GOLDEN_KEYS = ("robots", "mission_s", "rounds", "mission_rounds", "bytes_total",
               "frames_processed", "observations", "ingest_rejected", "keyframes",
               "objects_known", "converged_robots", "final_cost", "final_consensus_error",
               "sr_ate", "sr_cost", "ate_m", "ce", "bias")


def golden_summary(report: dict) -> dict:
    """The machine-independent part of a replay report (see ``WALL_CLOCK_FIELDS``)."""
    return _json_clean({k: report.get(k) for k in GOLDEN_KEYS})


#: Counts that must match exactly; other integer counts (bytes, observations, keyframes) may
#: move by ``count_rtol`` across machines (a float that differs in the last bit can flip one
#: send or detection decision).
EXACT_KEYS = ("robots", "mission_s", "rounds", "mission_rounds", "frames_processed")


def compare_summary(actual: Any, golden: Any, *, rtol: float = 1e-3, atol: float = 1e-6,
                    count_rtol: float = 0.02, path: str = "") -> list[str]:
    """Differences between two summaries: floats within ``rtol``/``atol``, integer counts
    within ``count_rtol`` except ``EXACT_KEYS``, everything else exactly."""
    diffs: list[str] = []
    if isinstance(golden, dict) and isinstance(actual, dict):
        for k in sorted(set(golden) | set(actual)):
            p = f"{path}.{k}" if path else str(k)
            if k not in actual or k not in golden:
                diffs.append(f"{p}: {'missing' if k not in actual else 'not in golden'}")
            else:
                diffs += compare_summary(actual[k], golden[k], rtol=rtol, atol=atol,
                                         count_rtol=count_rtol, path=p)
    elif (isinstance(golden, int) and isinstance(actual, int) and not isinstance(golden, bool)
          and path.split(".")[0] not in EXACT_KEYS):
        if not math.isclose(actual, golden, rel_tol=count_rtol, abs_tol=0):
            diffs.append(f"{path}: {actual!r} != golden {golden!r} (count rtol {count_rtol})")
    elif isinstance(golden, float) or isinstance(actual, float):
        if golden is None or actual is None:
            if golden is not actual:
                diffs.append(f"{path}: {actual!r} != golden {golden!r}")
        elif not math.isclose(float(actual), float(golden), rel_tol=rtol, abs_tol=atol):
            diffs.append(f"{path}: {actual!r} != golden {golden!r} (rtol {rtol})")
    elif actual != golden:
        diffs.append(f"{path}: {actual!r} != golden {golden!r}")
    return diffs
