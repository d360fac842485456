#!/usr/bin/env python3
"""CPU budget of one robot: per round (DRAN) and per camera frame (perception), on this machine,
projected to a core ``--slowdown`` times slower (Jetson Orin Nano's Cortex-A78AE vs this x86;
docs/benchmarks.md "Robot time budget").

    OPENBLAS_NUM_THREADS=1 .venv/bin/python tools/bench/bench_robot_budget.py [--quick]

Rounds: the demo's mission (``make demo``: 6 robots, 9 boxes, 180 s; ``--quick``: 3 robots, 4
boxes, 40 s), simulated with ``--frames none`` (tag observations from the geometry, the same
graph sizes as the rendered demo), run round by round through the robot code exactly as replay
does it (``RobotRunner``: ingest events into the ``RobotCore``, neighbour datagrams through
``NeighbourLink``, ``Tick``), over the in-process bus, in this one process. Every call of the
phases below is timed with process CPU time and attributed to the robot and round:

- ``ingest``      ingest events into the bounded local graph (RobotCore.handle of VIO/loops/obs)
- ``rebuild``     the graph turned into the agent's problem when it changed (RobotCore._rebuild)
- ``association`` cross-robot association check, provenance, adopting objects (Agent)
- ``local_step``  linearisation + the damped Schur-complement LM step (eqs. 7-12)
- ``acceptance``  retraction and cost of each trial step (the acceptance test)
- ``codec``       encode + sign outgoing, verify + decode incoming messages (NeighbourLink)
- ``round``       everything the robot does in the round (the sum above plus the rest: dual
                  update, structure, outputs)

Reported: the round of the largest local graph (nodes) of any robot, and the worst round over
the mission (max; 99th percentile), each projected (x slowdown) against the daemon's 500 ms
period. Frames: ``ObservationPipeline.process`` with the daemon's default parameters on 640x480
renders of 1-3 boxes (cluttered background; tools/bench/bench_perception.py's frames), min of
``--repeats`` per frame, projected against the camera's frame interval (15 fps) and the round.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ROUND_S = 0.5
CAMERA_FPS = 15.0

ACC: dict = defaultdict(float)  # (robot, phase) -> CPU seconds this round
CURRENT = [0]


def _timed(phase: str, fn):
    def wrapper(*args, **kwargs):
        t = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            ACC[(CURRENT[0], phase)] += time.process_time() - t

    wrapper.__wrapped__ = fn
    return wrapper


def _instrument() -> None:
    from dran_edge.dran import agent
    from dran_edge.dran.association import ObjectAssociation
    from dran_edge.robot import core as online_agent

    for name in ("linearize", "schur_step"):
        setattr(agent, name, _timed("local_step", getattr(agent, name)))
    for name in ("retract", "evaluate_cost"):
        setattr(agent, name, _timed("acceptance", getattr(agent, name)))
    for name in ("adopt_unknown", "check", "update_provenance"):
        setattr(ObjectAssociation, name, _timed("association", getattr(ObjectAssociation, name)))
    online_agent.RobotCore._rebuild = _timed("rebuild", online_agent.RobotCore._rebuild)


def _wrap_robot(rid: int, r) -> None:
    """Per-robot wrappers: who is running, and the phases that are per object instance."""
    from dran_edge.events import Tick

    core_handle, send, poll = r.core.handle, r.link.send_message, r.link.poll

    def handle(ev):
        CURRENT[0] = rid
        t = time.process_time()
        try:
            return core_handle(ev)
        finally:
            dt = time.process_time() - t
            ACC[
                (
                    rid,
                    "tick"
                    if isinstance(ev, Tick)
                    else "ingest"
                    if not hasattr(ev, "message")
                    else "neighbour",
                )
            ] += dt

    def timed_send(*a, **k):
        CURRENT[0] = rid
        t = time.process_time()
        try:
            return send(*a, **k)
        finally:
            ACC[(rid, "codec")] += time.process_time() - t

    def timed_poll(*a, **k):
        CURRENT[0] = rid
        t = time.process_time()
        try:
            return poll(*a, **k)
        finally:
            ACC[(rid, "codec")] += time.process_time() - t

    r.core.handle, r.link.send_message, r.link.poll = handle, timed_send, timed_poll


PHASES = ("ingest", "rebuild", "association", "local_step", "acceptance", "codec")


def run_rounds(run_dir: Path, settle_rounds: int) -> list[dict]:
    """Every round of every robot: CPU per phase (s) and the graph size."""
    from dran_edge.formats import run_dir as rd
    from dran_edge.comms.bus import Bus, BusParams
    from dran_edge.replay.robots import RobotRunner, RobotSpec

    _instrument()
    run = rd.open_run(run_dir)
    mission = run.mission
    ids = sorted(r.id for r in mission.robots)
    by_id = {r.id: r for r in mission.robots}
    runner = RobotRunner([RobotSpec(str(run.root), by_id[i].name) for i in ids])
    for rid, r in runner.robots.items():
        _wrap_robot(rid, r)
    period_ns = int(round(ROUND_S * 1e9))
    bus = Bus(ids, graph=mission.comm_graph, params=BusParams())
    last = max(mission.start_ns + int(mission.duration_s * 1e9), runner.last_stamp())
    rounds = int(math.ceil((last - mission.start_ns) / period_ns)) + settle_rounds
    rows = []
    for k in range(rounds):
        t_k = mission.start_ns + (k + 1) * period_ns
        inboxes = {i: [d for _, d in bus.endpoint(i).receive()] for i in ids}
        ACC.clear()
        outs = runner.step(t_k, inboxes)
        for i in ids:
            for to, data in outs[i]["outbox"]:
                bus.endpoint(i).send(to, data)
            g = runner.robots[i].core.local_graph
            row = {"round": k, "robot": i, "nodes": int(len(g.node_keys()))}
            for p in PHASES:
                row[p] = ACC[(i, p)]
            # the tick's own total holds association/local step/acceptance/rebuild; a round is
            # ingest + neighbour data + tick + codec (send and poll are outside core.handle)
            row["round"] = (
                ACC[(i, "ingest")] + ACC[(i, "neighbour")] + ACC[(i, "tick")] + ACC[(i, "codec")]
            )
            row["k"] = k
            rows.append(row)
        bus.advance()
    return rows


def perception_per_frame(n: int, repeats: int) -> np.ndarray:
    """CPU seconds per frame of the daemon's pipeline (min over repeats)."""
    from dran_edge.perception.calib import load_calibration
    from dran_edge.perception.pipeline import ObservationPipeline

    spec = importlib.util.spec_from_file_location(
        "bench_perception", ROOT / "tools" / "bench" / "bench_perception.py"
    )
    bp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bp)
    calib = load_calibration(ROOT / "calib", "dingo1")
    frames = bp.typical_frames(calib, n, seed=1, clutter=True)
    pipeline = ObservationPipeline(calib)
    best = np.full(n, np.inf)
    for _ in range(repeats):
        for i, f in enumerate(frames):
            t = time.process_time()
            pipeline.process(f)
            best[i] = min(best[i], time.process_time() - t)
    return best


def _ms(x: float) -> str:
    return f"{1e3 * x:7.1f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 robots, 40 s, 20 frames")
    ap.add_argument(
        "--slowdown",
        type=float,
        default=2.5,
        help="how many times slower the robot's core is (default 2.5)",
    )
    ap.add_argument("--frames", type=int, default=None, help="perception frames (default 60)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    from dran_edge.sim.writer import write_run
    from dran_edge.sim.mission import SimParams, generate_mission

    robots, objects, duration = (3, 4, 40.0) if args.quick else (6, 9, 180.0)
    n_frames = args.frames or (20 if args.quick else 60)
    params = SimParams(
        robots=robots,
        objects=objects,
        duration_s=duration,
        seed=0,
        arena_m=max(6.0, 3.0 * math.sqrt(objects)),
    )
    s = args.slowdown
    with tempfile.TemporaryDirectory() as tmp:
        write_run(generate_mission(params), Path(tmp) / "run", frames="none", workers=1)
        t = time.perf_counter()
        rows = run_rounds(Path(tmp) / "run", settle_rounds=20)
        wall = time.perf_counter() - t
    n_rounds = max(r["k"] for r in rows) + 1
    print(
        f"mission: {robots} robots, {objects} boxes, {duration:g} s (demo's parameters"
        f"{'; --quick' if args.quick else ''}), {n_rounds} rounds x {robots} robots, "
        f"{wall:.1f} s wall in one process; robot core assumed {s:g}x slower than this one"
    )
    big = max(rows, key=lambda r: (r["nodes"], r["round"]))
    worst = max(rows, key=lambda r: r["round"])
    totals = np.array([r["round"] for r in rows])
    print(
        f"\nCPU per round (ms)         {'here':>7} {'robot':>7}   "
        f"[largest graph: robot {big['robot']}, {big['nodes']} nodes, round {big['k']}]"
    )
    for p in PHASES + ("round",):
        print(f"  {p:<24} {_ms(big[p])} {_ms(s * big[p])}")
    print(
        f"\nworst round over the mission: {_ms(worst['round'])} ms here "
        f"(robot {worst['robot']}, round {worst['k']}, {worst['nodes']} nodes), 99th percentile "
        f"{_ms(float(np.percentile(totals, 99)))} ms, median {_ms(float(np.median(totals)))} ms"
    )
    for name, r in (("largest graph", big), ("worst round", worst)):
        t = s * r["round"]
        print(
            f"  {name:<14} on the robot: {t * 1e3:6.1f} ms of the {ROUND_S * 1e3:.0f} ms round "
            f"-> headroom {(ROUND_S - t) * 1e3:6.1f} ms ({t / ROUND_S:.2f} of the budget)"
        )
    over = int(np.sum(s * totals > ROUND_S))
    print(
        f"  rounds that would exceed {ROUND_S * 1e3:.0f} ms on the robot: {over} of {len(rows)}"
        " (the daemon skips the missed periods and counts them: status 'missed')"
    )
    pf = perception_per_frame(n_frames, args.repeats)
    med, p95 = float(np.median(pf)), float(np.percentile(pf, 95))
    print(
        f"\nperception per frame (ms, {n_frames} frames 640x480, 1-3 boxes, min of "
        f"{args.repeats}): median {_ms(med)} here, {_ms(s * med)} on the robot; "
        f"95th percentile {_ms(p95)} / {_ms(s * p95)}"
    )
    rate = 1.0 / (s * med)
    print(
        f"  on the robot one core runs the pipeline at {rate:.1f} frames/s "
        f"({'keeps up with' if rate >= CAMERA_FPS else 'below'} the camera's "
        f"{CAMERA_FPS:g} fps; excess frames are dropped oldest-first and counted: "
        f"status obs_dropped/frames_dropped)"
    )
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
