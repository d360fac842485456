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
   ``report.json``; with mocap, the metrics of :mod:`dran_edge.evaluation.score`. Every
   ``cost_every`` rounds and at the last, the costs of the merged graph as it stands (SR_cost
   per round, :mod:`dran_edge.replay.round_costs`).

Nothing here reads a clock except to report the wall time and, with ``speed > 0``, to pace
rounds (``speed`` = times real time). Same run, same options -> same numbers.

This module holds the options, the round loop, the report and the golden-summary comparison;
perception in :mod:`dran_edge.replay.perception`, the robots in :mod:`dran_edge.replay.robots`,
the files of ``out/`` in :mod:`dran_edge.replay.outputs` and :mod:`dran_edge.replay.merged_g2o`,
the per-round costs in :mod:`dran_edge.replay.round_costs`.

Size: over ~500 lines because the replay loop and its options (perception, outputs and
merged.g2o are in their own modules); over 500 only by ruff format's layout.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dran_edge.errors import InputError
from dran_edge.formats import run_dir as rd
from dran_edge.replay.outputs import evaluation_metrics, json_clean, write_outputs, write_report
from dran_edge.replay.perception import WindowedPerception, observation_sources
from dran_edge.replay.round_costs import COST_EVERY_DEFAULT, RoundCosts

if TYPE_CHECKING:
    from dran_edge.comms.bus import Bus
    from dran_edge.replay.robots import RobotResult, RobotRunner, WorkerPool

log = logging.getLogger(__name__)

REPORT_FORMAT = "dran-edge-replay/1"
#: Fields of report.json that depend on the machine's speed (golden comparisons ignore them).
WALL_CLOCK_FIELDS = (
    "replay_wall_s",
    "realtime_factor",
    "perception_wall_s",
    "rounds_wall_s",
    "cpu_s",
    "perception_wait_s",
    "round_costs_wall_s",
)


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
            raise InputError(
                f"--partition: expected ROBOT[,ROBOT...]:START_S:END_S, got {text!r}"
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
    cost_every: int = COST_EVERY_DEFAULT
    """Sample the merged graph's costs (F_init, F_k, F*: SR_cost per round) every this many
    rounds and at the last round (:mod:`dran_edge.replay.round_costs`); 0: never."""

    def __post_init__(self) -> None:
        if self.transport not in ("bus", "udp"):
            raise InputError(f"transport: expected 'bus' or 'udp', got {self.transport!r}")
        if not 0.0 <= self.loss <= 1.0:
            raise InputError(f"loss: expected a probability in [0, 1], got {self.loss}")
        if self.latency_rounds < 0 or self.settle_rounds < 0 or self.speed < 0:
            raise InputError("latency, settle rounds and speed must be >= 0")
        if self.cost_every < 0:
            raise InputError(f"cost_every: expected rounds >= 0 (0: never), got {self.cost_every}")
        if self.transport == "udp" and (self.loss or self.partitions or self.latency_rounds != 1):
            raise InputError(
                "--loss/--latency/--partition model the in-process bus; "
                "with --transport udp the network is the real loopback"
            )


# ---------------------------------------------------------------------------------- perception
# ---------------------------------------------------------------------------------- the replay
@dataclass
class ReplayResult:
    report: dict[str, Any]
    out_dir: Path


def replay_run(
    run_dir: str | Path,
    opt: ReplayOptions = ReplayOptions(),
    progress: Callable[[str, int, int], None] | None = None,
) -> ReplayResult:
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
    write_report(result.out_dir, result.report)
    return result


def _cpu_s() -> float:
    import resource

    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        ru = resource.getrusage(who)
        total += ru.ru_utime + ru.ru_stime
    return total


@dataclass
class _Setup:
    """A replay ready to run its rounds: the robots started, the network, the round count."""

    run: rd.Run
    ids: list[int]
    period_s: float
    sources: dict[str, str]
    """Robot name -> where its observations come from (OBSERVATION_SOURCES)."""
    robots: RobotRunner | WorkerPool
    workers: int
    bus: Bus | None
    """The in-process bus, None with transport udp."""
    clock_warnings: list[str]
    mission_rounds: int
    total_rounds: int

    @property
    def period_ns(self) -> int:
        return int(round(self.period_s * 1e9))


def _round_period_s(run: rd.Run) -> float:
    """The robots' common comms.period_s (InputError if they differ)."""
    periods = {run.load_config(r.name).comms.period_s for r in run.mission.robots}
    if len(periods) != 1:
        raise InputError(
            f"robots of one run must share comms.period_s, got {sorted(periods)}",
            path=str(run.root),
        )
    return periods.pop()


def _start_robots(
    run: rd.Run, ids: list[int], sources: dict[str, str], opt: ReplayOptions
) -> tuple[RobotRunner | WorkerPool, int]:
    """(the robots, in this process or spread over worker processes; how many workers)."""
    from dran_edge.replay.robots import RobotRunner, RobotSpec, WorkerPool

    by_id = {r.id: r for r in run.mission.robots}
    specs = [
        RobotSpec(
            str(run.root),
            by_id[i].name,
            drop_recorded_observations=sources[by_id[i].name] == "redetected",
        )
        for i in ids
    ]
    workers = (
        1 if opt.transport == "udp" else max(1, min(len(ids), opt.workers or os.cpu_count() or 1))
    )
    if workers > 1:
        return WorkerPool(specs, ids, workers), workers
    return RobotRunner(specs, "mailbox" if opt.transport == "bus" else "udp"), workers


def _make_bus(ids: list[int], comm_graph: Any, opt: ReplayOptions, period_s: float) -> Bus | None:
    """The in-process bus with the options' loss, latency and partitions (None for udp)."""
    if opt.transport != "bus":
        return None
    from dran_edge.comms.bus import Bus, BusParams, Partition

    parts = [
        Partition(
            frozenset(p.robots),
            int(math.floor(p.start_s / period_s)),
            int(math.ceil(p.end_s / period_s)),
        )
        for p in opt.partitions
    ]
    return Bus(
        ids,
        graph=comm_graph,
        params=BusParams(
            loss_probability=opt.loss, latency_rounds=opt.latency_rounds, seed=opt.seed
        ),
        partitions=parts,
    )


def _set_up(run: rd.Run, opt: ReplayOptions) -> _Setup:
    """Starts the robots and the network and checks the mission clock against the data."""
    mission = run.mission
    ids = sorted(r.id for r in mission.robots)
    period_s = _round_period_s(run)
    sources = observation_sources(run, opt.redetect)
    robots, workers = _start_robots(run, ids, sources, opt)
    bus = _make_bus(ids, mission.comm_graph, opt, period_s)
    try:
        clock_warnings = rd.check_mission_clock(
            mission, robots.stamp_span(), period_s, str(run.root / "mission.yaml")
        )
    except InputError:
        robots.close()
        raise
    for w in clock_warnings:
        log.warning("%s", w)
    period_ns = int(round(period_s * 1e9))
    last_stamp = max(mission.start_ns + int(mission.duration_s * 1e9), robots.last_stamp())
    mission_rounds = max(1, int(math.ceil((last_stamp - mission.start_ns) / period_ns)))
    return _Setup(
        run,
        ids,
        period_s,
        sources,
        robots,
        workers,
        bus,
        clock_warnings,
        mission_rounds,
        mission_rounds + opt.settle_rounds,
    )


def _round(
    s: _Setup, t_k: int, expected: Counter[int], opt: ReplayOptions
) -> tuple[dict[int, dict[str, Any]], Counter[int], int]:
    """The round at ``t_k``: deliver, step every robot, send. Returns (the robots' outputs, the
    datagrams each robot should receive next round, bytes sent)."""
    bus = s.bus
    inboxes: dict[int, list[bytes]] | None
    if bus is not None:
        inboxes = {i: [d for _, d in bus.endpoint(i).receive()] for i in s.ids}
    else:
        _udp_collect(s.robots, expected, opt.udp_wait_s)
        inboxes = None
    outs = s.robots.step(t_k, inboxes)
    sent: Counter[int] = Counter()
    bytes_round = 0
    for i in s.ids:
        for to, data in outs[i]["outbox"]:
            bytes_round += len(data)
            sent[to] += 1
            if bus is not None:
                bus.endpoint(i).send(to, data)
    if bus is not None:
        bus.advance()
    return outs, sent, bytes_round


def _round_row(
    k: int,
    t_k: int,
    outs: dict[int, dict[str, Any]],
    bytes_total: int,
    bytes_round: int,
    bus: Bus | None,
) -> dict[str, Any]:
    """One row of rounds.csv."""
    costs = [o["cost"] for o in outs.values() if math.isfinite(o["cost"])]
    cerr = [o["consensus_error"] for o in outs.values() if math.isfinite(o["consensus_error"])]
    return {
        "round": k,
        "stamp_ns": t_k,
        "bytes_total": bytes_total,
        "bytes_round": bytes_round,
        "cost": float(np.sum(costs)) if costs else math.nan,
        "consensus_error": float(np.max(cerr)) if cerr else math.nan,
        "converged_robots": sum(1 for o in outs.values() if o["converged"]),
        "datagrams_lost": int(sum(bus.lost.values())) if bus is not None else 0,
    }


def _run_rounds(
    s: _Setup,
    perception: WindowedPerception,
    opt: ReplayOptions,
    progress: Callable[[str, int, int], None] | None,
    costs: RoundCosts,
) -> list[dict[str, Any]]:
    """Every round, paced at ``opt.speed`` times real time when it is > 0; the rounds.csv rows.
    ``costs`` samples the merged graph after the rounds it is due."""
    start_ns = s.run.mission.start_ns
    name_of = {r.name: r.id for r in s.run.mission.robots}
    rounds_rows = []
    bytes_total = 0
    expected: Counter[int] = Counter()
    t_rounds = time.perf_counter()
    for k in range(s.total_rounds):
        t_k = start_ns + (k + 1) * s.period_ns
        if opt.speed > 0:
            delay = t_rounds + (k + 1) * s.period_s / opt.speed - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        new_obs = perception.ready_until(t_k)
        if new_obs:
            s.robots.add_records({name_of[n]: data for n, data in new_obs.items()})
        outs, expected, bytes_round = _round(s, t_k, expected, opt)
        bytes_total += bytes_round
        rounds_rows.append(_round_row(k, t_k, outs, bytes_total, bytes_round, s.bus))
        if costs.due(k):
            costs.sample(k, t_k, s.robots.snapshot())
        if progress:
            progress("rounds", k + 1, s.total_rounds)
    return rounds_rows


def _report(
    s: _Setup,
    opt: ReplayOptions,
    results: dict[int, RobotResult],
    rounds_rows: list[dict[str, Any]],
    perception: WindowedPerception,
    costs: RoundCosts,
    wall_s: float,
    rounds_wall_s: float,
) -> dict[str, Any]:
    """report.json of the replay (docs/run-format.md), without the metrics."""
    mission = s.run.mission
    res = [results[i] for i in s.ids]
    report: dict[str, Any] = {
        "format": REPORT_FORMAT,
        "run": str(s.run.root),
        "robots": len(s.ids),
        "mission_s": float(mission.duration_s),
        "replay_wall_s": round(wall_s, 3),
        "perception_wall_s": round(perception.done_s, 3),
        "perception_wait_s": round(perception.wait_s, 3),
        "rounds_wall_s": round(rounds_wall_s, 3),
        "round_costs_wall_s": round(costs.wall_s, 3),
        "realtime_factor": round(mission.duration_s / wall_s, 3) if wall_s > 0 else None,
        "round_workers": s.workers,
        "rounds": s.total_rounds,
        "mission_rounds": s.mission_rounds,
        "bytes_total": int(rounds_rows[-1]["bytes_total"]) if rounds_rows else 0,
        "transport": opt.transport,
        "options": {k: v for k, v in asdict(opt).items() if k not in ("workers",)},
        "frames_processed": sum(perception.frames.values()),
        "observation_sources": {n: s.sources[n] for n in sorted(s.sources)},
        "observations": sum(r.observations for r in res),
        "ingest_rejected": dict(sum((r.rejected for r in res), Counter())),
        "converged_robots": rounds_rows[-1]["converged_robots"] if rounds_rows else 0,
        "keyframes": {r.name: len(r.last.keyframe_stamps_ns) if r.last else 0 for r in res},
        "objects_known": {r.name: len(r.last.object_ids) if r.last else 0 for r in res},
        "final_cost": rounds_rows[-1]["cost"] if rounds_rows else None,
        "final_consensus_error": rounds_rows[-1]["consensus_error"] if rounds_rows else None,
        **costs.report(),
    }
    beta = _beta_check(s.run, res)
    if beta:
        report["beta_check"] = beta
    warnings = [*s.clock_warnings, *([beta["warning"]] if beta.get("warning") else [])]
    if warnings:
        report["warnings"] = warnings
    if s.bus is not None:
        report["datagrams_lost"] = {k: int(v) for k, v in s.bus.lost.items()}
    return report


def _beta_check(run: rd.Run, res: list[RobotResult]) -> dict[str, Any]:
    """β against the information of the robots' tag observations (``dran.beta_scale``): the
    robots' β (one value when they agree), the observations' scale, their ratio and a warning
    when the ratio is far outside the measured window; {} without observations."""
    from dran_edge.dran import beta_scale
    from dran_edge.robot.factor_algebra import KIND_OBSERVATION

    scale = beta_scale.observation_scale(
        r.graph["factors"]["S"][r.graph["factors"]["kind"] == KIND_OBSERVATION]
        for r in res
        if r.graph is not None
    )
    if scale is None:
        return {}
    betas = {r.name: run.load_config(r.name).agent.beta for r in res}
    out: dict[str, Any] = {"observation_information": scale}
    if len(set(betas.values())) > 1:  # eq. 5b keeps λ_ij + λ_ji = 0 only with one β per pair
        out["beta"] = betas
        out["warning"] = (
            f"the robots' agent.beta differ ({betas}): the consensus duals of a pair stay "
            "balanced only when both ends use the same beta (docs/dran.md)"
        )
        log.warning("%s", out["warning"])
        return out
    beta = next(iter(betas.values()))
    ratio, warning = beta_scale.check(beta, scale)
    out.update(beta=beta, ratio=ratio)
    if warning:
        log.warning("%s", warning)
        out["warning"] = warning
    return out


def _replay(
    run_dir: str | Path, opt: ReplayOptions, progress: Callable[[str, int, int], None] | None
) -> ReplayResult:
    wall0 = time.perf_counter()
    run = rd.open_run(run_dir)
    s = _set_up(run, opt)
    start_ns = run.mission.start_ns
    perception = WindowedPerception(
        run, opt.workers, start_ns, start_ns + s.mission_rounds * s.period_ns, s.sources
    )
    costs = RoundCosts(opt.cost_every, s.total_rounds)
    t_rounds = time.perf_counter()
    try:
        rounds_rows = _run_rounds(s, perception, opt, progress, costs)
        results = s.robots.results()
    finally:
        s.robots.close()
        perception.close()
    rounds_wall = time.perf_counter() - t_rounds
    out_dir = run.out_dir
    out_dir.mkdir(exist_ok=True)
    write_outputs(run, results, rounds_rows)
    report = _report(
        s,
        opt,
        results,
        rounds_rows,
        perception,
        costs,
        wall_s=time.perf_counter() - wall0,
        rounds_wall_s=rounds_wall,
    )
    write_report(out_dir, report)
    if opt.evaluate and run.mission.mocap_file:
        report.update(evaluation_metrics(run))
        write_report(out_dir, report)
    return ReplayResult(report, out_dir)


def _udp_collect(robots: RobotRunner | WorkerPool, expected: Counter[int], wait_s: float) -> None:
    """Wait until each robot's DISH has the datagrams sent to it last round (or time out)."""
    from dran_edge.replay.robots import RobotRunner

    assert isinstance(robots, RobotRunner)  # udp runs its robots in this process
    deadline = time.monotonic() + wait_s
    got: Counter[int] = Counter()
    while True:
        got.update(robots.pull_udp())
        ids = list(robots.robots)
        if all(got[i] >= expected[i] for i in ids) or time.monotonic() > deadline:
            missing = {i: expected[i] - got[i] for i in ids if got[i] < expected[i]}
            if missing:
                log.warning("udp: datagrams not arrived within %.2f s: %s", wait_s, missing)
            return
        time.sleep(0.0005)


# ---------------------------------------------------------------------------------- golden
#: Keys of report.json kept in a golden summary (wall-clock fields are never among them).
GOLDEN_KEYS = (
    "robots",
    "mission_s",
    "rounds",
    "mission_rounds",
    "bytes_total",
    "frames_processed",
    "observation_sources",
    "observations",
    "ingest_rejected",
    "keyframes",
    "objects_known",
    "converged_robots",
    "final_cost",
    "final_consensus_error",
    "sr_ate",
    "sr_cost",
    "ate_m",
    "ce",
    "bias",
)


#: Significant digits of the floats in a golden summary. The back end's arithmetic is not
#: bit-identical across CPUs (numpy's and scipy's compiled loops and LAPACK differ in the last
#: bits between x86-64 and aarch64), but the decisions that amplified such a difference are
#: taken at a stated resolution (costs equal below dran_edge.solver.damping.COST_RESOLUTION),
#: so the replays agree in every count and byte and their floats within ~1e-13 relative
#: (docs/notes/arm64-check.md): ten digits is what a summary states and the same on both.
GOLDEN_SIGNIFICANT_DIGITS = 10


def _round_significant(x: Any, digits: int) -> Any:
    if isinstance(x, float):
        return float(f"{x:.{digits}g}") if math.isfinite(x) else x
    if isinstance(x, dict):
        return {k: _round_significant(v, digits) for k, v in x.items()}
    if isinstance(x, list):
        return [_round_significant(v, digits) for v in x]
    return x


def golden_summary(report: dict) -> dict:
    """The machine-independent part of a replay report (see ``WALL_CLOCK_FIELDS``), floats to
    ``GOLDEN_SIGNIFICANT_DIGITS`` significant digits."""
    summary = json_clean({k: report.get(k) for k in GOLDEN_KEYS})
    return dict(_round_significant(summary, GOLDEN_SIGNIFICANT_DIGITS))


#: Counts that must match exactly; other integer counts (bytes, observations, keyframes) may
#: move by ``count_rtol`` across machines (a float that differs in the last bit can flip one
#: send or detection decision).
EXACT_KEYS = ("robots", "mission_s", "rounds", "mission_rounds", "frames_processed")


def compare_summary(
    actual: Any,
    golden: Any,
    *,
    rtol: float = 1e-3,
    atol: float = 1e-6,
    count_rtol: float = 0.02,
    path: str = "",
) -> list[str]:
    """Differences between two summaries: floats within ``rtol``/``atol``, integer counts
    within ``count_rtol`` except ``EXACT_KEYS``, everything else exactly."""
    diffs: list[str] = []
    if isinstance(golden, dict) and isinstance(actual, dict):
        for k in sorted(set(golden) | set(actual)):
            p = f"{path}.{k}" if path else str(k)
            if k not in actual or k not in golden:
                diffs.append(f"{p}: {'missing' if k not in actual else 'not in golden'}")
            else:
                diffs += compare_summary(
                    actual[k], golden[k], rtol=rtol, atol=atol, count_rtol=count_rtol, path=p
                )
    elif (
        isinstance(golden, int)
        and isinstance(actual, int)
        and not isinstance(golden, bool)
        and path.split(".")[0] not in EXACT_KEYS
    ):
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
