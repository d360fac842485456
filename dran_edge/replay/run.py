"""Replay a recorded run through the robot code: every robot, same decoders, same agent.

``replay_run(RUN, ReplayOptions())`` (the shell behind ``dran-edge replay``, docs/replay.md):

1. **Inputs, through the same decoders as live.** Each robot's ``ingest.bin`` is decoded by the
   ingest stream decoder (:func:`dran_edge.comms.ingest.iter_records`); a record that does not
   decode is counted by reason and skipped, like on the robot. Recorded frames go through the
   perception pipeline (detector -> tag poses -> objects), and each observation batch crosses the
   same boundary the daemon's journal does: encoded as an ingest record and decoded again.
   Perception depends only on the frames, so it runs in worker processes, window by window of
   mission time (``PERCEPTION_WINDOW_S``), ahead of the rounds: a window's observations are
   handed to the robots just before the rounds reach its start, in the same order whatever the
   timing, so the output does not depend on the number of workers.
2. **Rounds.** Time advances in rounds of the robots' ``comms.period_s`` (2 Hz) from the mission
   start. In round k (stamp ``t_k = start + (k+1)·period``) each robot, in id order, gets: every
   input whose stamp is ≤ t_k (ingest records in file order), then the neighbour messages that
   arrived, then ``Tick(t_k)``; its outgoing messages are encoded, signed and sent. After the
   mission's data ends, ``settle_rounds`` more rounds let consensus finish. A robot's round
   depends only on its own state and inbox, so robots are spread over ``workers`` processes
   (:mod:`dran_edge.replay.robots`); the numbers do not depend on how many.
3. **Communication.** By default the in-process bus (:mod:`dran_edge.comms.bus`) with its loss,
   latency and partition model, carrying the same authenticated datagrams as the radio
   (:class:`~dran_edge.comms.link.NeighbourLink`). ``transport="udp"`` uses real ZeroMQ
   RADIO/DISH sockets on loopback (the addresses of each robot's config); each round waits until
   every datagram sent in the previous round has arrived (or ``udp_wait_s`` passed), so a
   loopback replay without loss gives the bus's numbers.
4. **Outputs** in ``RUN/out/`` (docs/run-format.md): per-robot TUM trajectories (final and
   initial), object maps, ``merged.g2o`` + ``merged_vertices.csv``, ``rounds.csv`` and
   ``report.json``; with mocap, the metrics of :mod:`dran_edge.evaluation.score`.

Nothing here reads a clock except to report the wall time and, with ``speed > 0``, to pace
rounds (``speed`` = times real time). Same run, same options -> same numbers.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.formats import run_dir as rd
from dran_edge.errors import InputError
from dran_edge.events import ObservationBatch

log = logging.getLogger(__name__)

REPORT_FORMAT = "dran-edge-replay/1"
#: Fields of report.json that depend on the machine's speed (golden comparisons ignore them).
WALL_CLOCK_FIELDS = ("replay_wall_s", "realtime_factor", "perception_wall_s", "rounds_wall_s",
                     "cpu_s", "perception_wait_s")


@dataclass(frozen=True)
class PartitionSpec:
    """Robots cut off from all others between two mission times (seconds from the start)."""

    robots: tuple[int, ...]
    start_s: float
    end_s: float

    @staticmethod
    def parse(text: str) -> PartitionSpec:
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
    redetect: bool = False
    """Ignore the observations recorded in ``ingest.bin`` and re-run perception on the recorded
    frames (a robot with recorded observations and no frames is then an error)."""
    udp_wait_s: float = 5.0
    """UDP only: the longest a round waits for the datagrams of the previous round. The wait
    ends as soon as every one has arrived, so only a datagram really lost costs the whole wait.
    With 0.5 s the UDP-equals-bus test failed once on a loaded machine (a late datagram is the
    likely cause: the round goes ahead without it); with 5 s it passed 4 of 4 under load."""

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
#: Perception runs in windows of this much mission time, so the rounds can start before all
#: frames are processed (the window's results are needed only once the rounds reach it).
PERCEPTION_WINDOW_S = 15.0


#: Where a robot's tag observations come from in a replay (report.json ``observation_sources``).
OBSERVATION_SOURCES = ("recorded", "redetected", "none")


def observation_sources(run: rd.Run, redetect: bool = False) -> dict[str, str]:
    """Per robot name: ``recorded`` (its ingest.bin holds observation records: replay uses
    them), ``redetected`` (perception runs on its frames: it has frames and either no recorded
    observations or ``redetect``), or ``none``."""
    from dran_edge.replay.robots import decode_ingest

    out: dict[str, str] = {}
    for info in run.mission.robots:
        cfg = run.load_config(info.name)
        has_frames = cfg.camera.source == "recorded" and run.frames_dir(info.name) is not None
        events, _ = decode_ingest(run.read_ingest(info.name), str(run.ingest_path(info.name)))
        has_recorded = any(isinstance(ev, ObservationBatch) for ev in events)
        if redetect and has_recorded and not has_frames:
            raise InputError(f"--redetect: robot {info.name} has recorded observations but no "
                             "frames to detect them again from", path=str(run.robot_dir(info.name)))
        if has_frames and (redetect or not has_recorded):
            out[info.name] = "redetected"
        else:
            out[info.name] = "recorded" if has_recorded else "none"
    return out


def _perceive_window(args: tuple[str, str, str, int, int]) -> tuple[str, int, list[bytes], int]:
    """One robot's frames with stamps in [lo, hi) -> observation batches as ingest records."""
    config_path, calib_dir, name, lo, hi = args
    from dran_edge.blas import set_blas_threads

    from dran_edge.comms.ingest import encode_event
    from dran_edge.perception.recorded import perceive_frames

    set_blas_threads(1)  # one perception process per core already
    batches, frames = perceive_frames(config_path, calib_dir, name, lo, hi)
    return name, lo, [encode_event(b) for b in batches], frames


class _Perception:
    """Recorded frames through the pipeline in worker processes, window by window, ahead of
    the rounds; ``ready_until(t)`` hands over every window that starts at or before ``t``."""

    def __init__(self, run: rd.Run, opt: ReplayOptions, start_ns: int, end_ns: int,
                 sources: dict[str, str]):
        self.jobs: list[tuple] = []
        self.frames: dict[str, int] = {}
        step = int(PERCEPTION_WINDOW_S * 1e9)
        robots = []
        for info in run.mission.robots:
            cfg = run.load_config(info.name)
            if sources[info.name] != "redetected":
                continue
            calib = cfg.resolve(cfg.camera.calib_dir) or run.calib_dir
            robots.append((str(run.config_path(info.name)), str(calib), info.name))
            self.frames[info.name] = 0
        # windows cover every possible stamp: (-inf, start + step), ..., [.., +inf)
        edges = list(range(start_ns + step, end_ns, step))
        bounds = list(zip([0] + edges, edges + [2**63 - 1]))
        for lo, hi in bounds:
            for r in robots:
                self.jobs.append((*r, lo, hi))
        self.pool = None
        self.futures: list = []
        self.next = 0
        self.t0 = time.perf_counter()
        self.done_s = 0.0
        self.wait_s = 0.0
        if self.jobs:
            workers = max(1, min(len(robots), opt.workers or os.cpu_count() or 1))
            self.pool = ProcessPoolExecutor(max_workers=workers)
            self.futures = [self.pool.submit(_perceive_window, job) for job in self.jobs]

    def ready_until(self, t_ns: int) -> dict[str, bytes]:
        """Records of the windows starting at or before ``t_ns`` not handed over yet."""
        out: dict[str, list[bytes]] = {}
        while self.next < len(self.jobs) and self.jobs[self.next][3] <= t_ns:
            w0 = time.perf_counter()
            name, _lo, records, frames = self.futures[self.next].result()
            self.wait_s += time.perf_counter() - w0
            self.frames[name] += frames
            out.setdefault(name, []).extend(records)
            self.next += 1
            if self.next == len(self.jobs):
                self.done_s = time.perf_counter() - self.t0
        return {name: b"".join(recs) for name, recs in out.items()}

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)


# ---------------------------------------------------------------------------------- the replay
@dataclass
class ReplayResult:
    report: dict
    out_dir: Path


def replay_run(run_dir: str | Path, opt: ReplayOptions = ReplayOptions(),
               progress: Callable[[str, int, int], None] | None = None) -> ReplayResult:
    """Replay the run at ``run_dir`` and write ``run_dir/out`` (see the module docstring)."""
    from dran_edge.blas import restore_blas_threads, set_blas_threads

    blas = set_blas_threads(1)
    cpu0 = _cpu_s()
    try:
        result = _replay(run_dir, opt, progress)
    finally:
        restore_blas_threads(blas)
    # CPU time of this process and every worker it reaped: with the replay's cores to itself,
    # the wall time would be about cpu_s / cores (the machine may be shared).
    result.report["cpu_s"] = round(_cpu_s() - cpu0, 3)
    _write_report(result.out_dir, result.report)
    return result


def _cpu_s() -> float:
    import resource

    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        ru = resource.getrusage(who)
        total += ru.ru_utime + ru.ru_stime
    return total


def _replay(run_dir: str | Path, opt: ReplayOptions,
            progress: Callable[[str, int, int], None] | None) -> ReplayResult:
    from dran_edge.replay.robots import RobotRunner, RobotSpec, WorkerPool

    wall0 = time.perf_counter()
    run = rd.open_run(run_dir)
    mission = run.mission
    ids = sorted(r.id for r in mission.robots)
    configs = {r.id: run.load_config(r.name) for r in mission.robots}
    periods = {c.comms.period_s for c in configs.values()}
    if len(periods) != 1:
        raise InputError(f"robots of one run must share comms.period_s, got {sorted(periods)}",
                         path=str(run.root))
    period_s = periods.pop()
    period_ns = int(round(period_s * 1e9))
    by_id = {r.id: r for r in mission.robots}
    name_of = {r.name: r.id for r in mission.robots}
    sources = observation_sources(run, opt.redetect)
    specs = [RobotSpec(str(run.root), by_id[i].name,
                       drop_recorded_observations=sources[by_id[i].name] == "redetected")
             for i in ids]
    workers = 1 if opt.transport == "udp" else max(1, min(len(ids), opt.workers or
                                                         os.cpu_count() or 1))
    if workers > 1:
        robots = WorkerPool(specs, ids, workers)
    else:
        robots = RobotRunner(specs, "mailbox" if opt.transport == "bus" else "udp")
    bus = None
    if opt.transport == "bus":
        from dran_edge.comms.bus import Bus, BusParams, Partition

        parts = [Partition(frozenset(p.robots), int(math.floor(p.start_s / period_s)),
                           int(math.ceil(p.end_s / period_s))) for p in opt.partitions]
        bus = Bus(ids, graph=mission.comm_graph,
                  params=BusParams(loss_probability=opt.loss, latency_rounds=opt.latency_rounds,
                                   seed=opt.seed),
                  partitions=parts)
    try:
        clock_warnings = rd.check_mission_clock(mission, robots.stamp_span(), period_s,
                                                str(run.root / "mission.yaml"))
    except InputError:
        robots.close()
        raise
    for w in clock_warnings:
        log.warning("%s", w)
    last_stamp = max(mission.start_ns + int(mission.duration_s * 1e9), robots.last_stamp())
    mission_rounds = max(1, int(math.ceil((last_stamp - mission.start_ns) / period_ns)))
    total_rounds = mission_rounds + opt.settle_rounds
    perception = _Perception(run, opt, mission.start_ns,
                             mission.start_ns + mission_rounds * period_ns, sources)
    rounds_rows = []
    bytes_total = 0
    expected: Counter = Counter()
    t_rounds = time.perf_counter()
    try:
        for k in range(total_rounds):
            t_k = mission.start_ns + (k + 1) * period_ns
            if opt.speed > 0:
                delay = t_rounds + (k + 1) * period_s / opt.speed - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            new_obs = perception.ready_until(t_k)
            if new_obs:
                robots.add_records({name_of[n]: data for n, data in new_obs.items()})
            if bus is not None:
                inboxes = {i: [d for _, d in bus.endpoint(i).receive()] for i in ids}
            else:
                _udp_collect(robots, expected, opt.udp_wait_s)
                inboxes = None
            outs = robots.step(t_k, inboxes)
            expected = Counter()
            bytes_round = 0
            for i in ids:
                for to, data in outs[i]["outbox"]:
                    bytes_round += len(data)
                    expected[to] += 1
                    if bus is not None:
                        bus.endpoint(i).send(to, data)
            if bus is not None:
                bus.advance()
            bytes_total += bytes_round
            costs = [o["cost"] for o in outs.values() if math.isfinite(o["cost"])]
            cerr = [o["consensus_error"] for o in outs.values()
                    if math.isfinite(o["consensus_error"])]
            rounds_rows.append({
                "round": k, "stamp_ns": t_k, "bytes_total": bytes_total, "bytes_round": bytes_round,
                "cost": float(np.sum(costs)) if costs else math.nan,
                "consensus_error": float(np.max(cerr)) if cerr else math.nan,
                "converged_robots": sum(1 for o in outs.values() if o["converged"]),
                "datagrams_lost": int(sum(bus.lost.values())) if bus is not None else 0,
            })
            if progress:
                progress("rounds", k + 1, total_rounds)
        results = robots.results()
    finally:
        robots.close()
        perception.close()
    rounds_wall = time.perf_counter() - t_rounds
    out_dir = run.out_dir
    out_dir.mkdir(exist_ok=True)
    write_outputs(run, results, rounds_rows)
    wall = time.perf_counter() - wall0
    res = [results[i] for i in ids]
    report: dict[str, Any] = {
        "format": REPORT_FORMAT,
        "run": str(run.root),
        "robots": len(ids),
        "mission_s": float(mission.duration_s),
        "replay_wall_s": round(wall, 3),
        "perception_wall_s": round(perception.done_s, 3),
        "perception_wait_s": round(perception.wait_s, 3),
        "rounds_wall_s": round(rounds_wall, 3),
        "realtime_factor": round(mission.duration_s / wall, 3) if wall > 0 else None,
        "round_workers": workers,
        "rounds": total_rounds,
        "mission_rounds": mission_rounds,
        "bytes_total": int(bytes_total),
        "transport": opt.transport,
        "options": {k: v for k, v in asdict(opt).items() if k not in ("workers",)},
        "frames_processed": sum(perception.frames.values()),
        "observation_sources": {n: sources[n] for n in sorted(sources)},
        "observations": sum(r.observations for r in res),
        "ingest_rejected": dict(sum((r.rejected for r in res), Counter())),
        "converged_robots": rounds_rows[-1]["converged_robots"] if rounds_rows else 0,
        "keyframes": {r.name: len(r.last.keyframe_stamps_ns) if r.last else 0 for r in res},
        "objects_known": {r.name: len(r.last.object_ids) if r.last else 0 for r in res},
        "final_cost": rounds_rows[-1]["cost"] if rounds_rows else None,
        "final_consensus_error": rounds_rows[-1]["consensus_error"] if rounds_rows else None,
    }
    if clock_warnings:
        report["warnings"] = clock_warnings
    if bus is not None:
        report["datagrams_lost"] = {k: int(v) for k, v in bus.lost.items()}
    _write_report(out_dir, report)
    if opt.evaluate and mission.mocap_file:
        report.update(_metrics(run))
        _write_report(out_dir, report)
    return ReplayResult(report, out_dir)


def _udp_collect(robots, expected: Counter, wait_s: float) -> None:
    """Wait until each robot's DISH has the datagrams sent to it last round (or time out)."""
    deadline = time.monotonic() + wait_s
    got: Counter = Counter()
    while True:
        got.update(robots.pull_udp())
        ids = list(robots.robots)
        if all(got[i] >= expected[i] for i in ids) or time.monotonic() > deadline:
            missing = {i: expected[i] - got[i] for i in ids if got[i] < expected[i]}
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
    """sr_ate, sr_cost, ate_m, ce, bias from dran_edge.evaluation.score (the numbers `eval` reports)."""
    from dran_edge.evaluation.score import EvalOptions, evaluate_run

    try:
        ev = evaluate_run(run.root, EvalOptions(plots=False)).report
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
        "f_over_fstar": find(ev, "f_over_fstar", "summary.f_over_fstar", "cost.F_over_Fstar"),
        "ate_over_atestar": find(ev, "ate_over_atestar", "summary.ate_over_atestar",
                                 "overall.ate_over_atestar"),
        "ate_m": find(ev, "ate_m", "summary.ate_m", "ate.final.rmse_m", "ate_rmse_m"),
        "ce": find(ev, "ce", "summary.ce", "objects.ce"),
        "bias": find(ev, "bias", "summary.bias", "objects.bias"),
    }


# ---------------------------------------------------------------------------------- outputs
def write_outputs(run: rd.Run, results: dict, rounds_rows: list[dict]) -> None:
    """Per-robot TUM files and object maps, rounds.csv, merged.g2o (docs/run-format.md)."""
    from dran_edge.formats.tum import write_tum

    out = run.out_dir
    for r in results.values():
        d = out / r.name
        d.mkdir(parents=True, exist_ok=True)
        u = r.last
        if u is None or len(u.keyframe_stamps_ns) == 0:
            for f in (f"{r.name}.tum", f"{r.name}_init.tum", "objects.csv"):
                (d / f).unlink(missing_ok=True)
            log.warning("robot %s produced no estimate", r.name)
            continue
        stamps = np.asarray(u.keyframe_stamps_ns, dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        stamps = stamps[order]
        for f in ("trajectory.tum", "trajectory_init.tum"):  # the names of older replays
            (d / f).unlink(missing_ok=True)
        write_tum(d / f"{r.name}.tum", stamps * 1e-9, np.asarray(u.T_world_body)[order],
                  header=f"{r.name}: final estimate (dran-edge replay)")
        if r.initial is not None and len(r.initial[0]):
            s0, T0 = r.initial
            what = "odometry alone, before any optimisation"
        else:
            s0 = stamps
            T0 = np.stack([r.first_seen.get(int(s), u.T_world_body[i]) for s, i in
                           zip(stamps.tolist(), order.tolist())])
            what = "each keyframe's first estimate"
        o0 = np.argsort(s0, kind="stable")
        write_tum(d / f"{r.name}_init.tum", s0[o0] * 1e-9, T0[o0],
                  header=f"{r.name}: initial estimate, {what} (dran-edge replay)")
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
    write_merged_g2o(run, results)


#: A unary prior at most this tight (variance, m² / rad²) is a gauge: FIX in merged.g2o.
GAUGE_VARIANCE_MAX = 1e-6


def write_merged_g2o(run: rd.Run, results: dict) -> bool:
    """``merged.g2o`` + ``merged_vertices.csv`` from every robot's local graph (if it has one).

    Vertices: robot ``r``'s keyframe ``j`` is ``r * 1_000_000 + j`` (by stamp order), object
    ``k`` is ``1_000_000_000 + k`` (shared by every robot that observed it). Edges: every
    odometry, loop and observation factor with information ``Σ⁻¹``; a robot's gauge prior fixes
    its node (FIX); the bounded graph's marginalisation prior is not exported. Values: the
    final decentralized estimate (each robot's agent, world frame; an object takes the chordal
    mean of the robots' copies).
    """
    from dran_edge.formats.g2o import G2oGraph, write_g2o

    vid: list[int] = []
    poses: list[np.ndarray] = []
    rows: list[tuple[int, str, str, int]] = []
    edges, meas, info, fixed_ids = [], [], [], set()
    obj_vertex: dict[int, np.ndarray] = {}
    for rid in sorted(results):
        r = results[rid]
        if r.graph is None or r.last is None:
            continue
        fa, keys, stamps, OBJ = (r.graph["factors"], r.graph["keys"], r.graph["stamps"],
                                 r.graph["obj_base"])
        final = {int(s): T for s, T in zip(r.last.keyframe_stamps_ns.tolist(), r.last.T_world_body)}
        keep = np.array([int(s) in final for s in stamps.tolist()], bool)
        keys, stamps = keys[keep], stamps[keep]
        order = np.argsort(stamps, kind="stable")
        key_vid = {}
        for j, i in enumerate(order.tolist()):
            v = rid * 1_000_000 + j
            key_vid[int(keys[i])] = v
            vid.append(v)
            poses.append(final[int(stamps[i])])
            rows.append((v, "pose", r.name, int(stamps[i])))
        for oid, T in zip(r.last.object_ids, r.last.T_world_object):
            obj_vertex.setdefault(int(oid), []).append(T)

        def vertex(key: int, OBJ=OBJ, key_vid=key_vid) -> int | None:
            if key >= OBJ:
                return 1_000_000_000 + int(key - OBJ) if int(key - OBJ) in obj_vertex else None
            return key_vid.get(int(key))

        for p, q, Z, S in zip(fa["p"].tolist(), fa["q"].tolist(), fa["Z"], fa["S"]):
            vq = vertex(q)
            if p < 0:
                # the gauge prior (sub-millimetre) fixes its node; weaker unary priors have no
                # g2o form and are left out
                if vq is not None and np.max(np.diag(S)) <= GAUGE_VARIANCE_MAX:
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
        copies = np.stack(obj_vertex[oid])  # the robots' copies: their chordal mean
        poses.append(geo.se3_from_rt(geo.so3_project(copies[:, :3, :3].mean(axis=0)),
                                     copies[:, :3, 3].mean(axis=0)))
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


# ---------------------------------------------------------------------------------- golden
#: Keys of report.json kept in a golden summary (wall-clock fields are never among them).
GOLDEN_KEYS = ("robots", "mission_s", "rounds", "mission_rounds", "bytes_total",
               "frames_processed", "observation_sources", "observations", "ingest_rejected",
               "keyframes",
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
