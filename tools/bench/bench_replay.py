"""Replay speed: mission time vs wall time of `dran-edge replay` on the default simulated mission.

    .venv/bin/python tools/bench/bench_replay.py [--robots 6] [--duration-s 180] [--workdir DIR]
    .venv/bin/python tools/bench/bench_replay.py --blas-ablation
    .venv/bin/python tools/bench/bench_replay.py --quick      # 2 robots, 2 s, in a temporary folder

Simulates the mission twice with the same seed into ``--workdir`` (kept between runs; the
simulation itself is not timed): once with rendered camera frames (the replay runs the AprilTag
pipeline on every frame, like ``make demo``) and once with tag observations written directly
into ingest.bin (the back-end alone). Both are replayed back to back in this process with the
default options (in-process bus, as fast as possible, evaluation off) and the script prints
mission time, wall time and the real-time factor (mission / wall) of each, the wall-time split
(perception / rounds) and the ratio of the two arms. The target is a real-time factor
>= 5 for the full replay of the default 6-robot, 180 s mission on the 2-core reference machine.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path


def _simulate(workdir: Path, frames: str, args) -> Path:
    from dran_edge.sim.mission import SimParams, generate_mission
    from dran_edge.sim.writer import write_run

    tag = f"r{args.robots}_d{args.duration_s:g}_s{args.seed}_{frames}"
    run = workdir / tag
    if (run / "mission.yaml").exists() and (run / ".complete").exists():
        return run
    if run.exists():
        shutil.rmtree(run)
    p = SimParams(
        robots=args.robots, objects=9, duration_s=args.duration_s, seed=args.seed, arena_m=9.0
    )
    write_run(generate_mission(p), run, frames=frames)
    (run / ".complete").write_text("")
    return run


def _replay(run: Path, workers: int | None, settle_rounds: int) -> dict:
    from dran_edge.replay.run import ReplayOptions, replay_run

    if (run / "out").exists():
        shutil.rmtree(run / "out")
    t0 = time.perf_counter()
    opts = ReplayOptions(evaluate=False, workers=workers, settle_rounds=settle_rounds)
    rep = replay_run(run, opts).report
    rep["bench_wall_s"] = time.perf_counter() - t0
    return rep


def _blas_ablation(run: Path, robot: str = "dingo1", last: int = 80) -> None:
    """One robot's DRAN rounds alone, OpenBLAS threads as loaded vs 1, interleaved per round."""
    import bisect

    import numpy as np

    from dran_edge.events import Tick
    from dran_edge.blas import restore_blas_threads, set_blas_threads
    from dran_edge.replay.robots import RobotRunner, RobotSpec
    from dran_edge.formats import run_dir as rd

    mission = rd.open_run(run).mission
    cpu = {"default": [], "1 thread": []}
    runners = {k: RobotRunner([RobotSpec(str(run), robot)]) for k in cpu}
    rounds = int(math.ceil(mission.duration_s / 0.5))
    default = set_blas_threads(None)
    for k in range(rounds):
        t_k = mission.start_ns + (k + 1) * 500_000_000
        for arm, runner in runners.items():
            r = next(iter(runner.robots.values()))
            end = bisect.bisect_right(r.events, (t_k, math.inf), lo=r.next_event)
            for _, _, ev in r.events[r.next_event : end]:
                r.core.handle(ev)
            r.next_event = end
            prev = set_blas_threads(1) if arm == "1 thread" else None
            c0 = time.process_time()
            r.core.handle(Tick(t_k))
            cpu[arm].append(time.process_time() - c0)
            if prev:
                restore_blas_threads(prev)
    n_default = sorted(set(default.values()))
    a, b = (1e3 * np.mean(cpu[k][-last:]) for k in ("default", "1 thread"))
    print(
        f"{robot} alone, last {last} of {rounds} rounds, CPU per round: OpenBLAS threads "
        f"{n_default} {a:.1f} ms vs 1 thread {b:.1f} ms (ratio {a / b:.2f})"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", type=int, default=6)
    ap.add_argument("--duration-s", type=float, default=180.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=None, help="perception processes")
    ap.add_argument("--workdir", default="/tmp/dran-edge-bench-replay")
    ap.add_argument("--json", action="store_true")
    ap.add_argument(
        "--blas-ablation",
        action="store_true",
        help="only time one robot's rounds with OpenBLAS's default threads vs 1",
    )
    ap.add_argument(
        "--quick",
        action="store_true",
        help="2 robots, 2 s, 2 settle rounds, one perception process, a temporary "
        "--workdir: checks the script, not speed",
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.robots, args.duration_s, args.workers = 2, min(args.duration_s, 2.0), 1
        with tempfile.TemporaryDirectory(prefix="bench_replay_") as tmp:
            args.workdir = tmp
            return _main(args)
    return _main(args)


def _main(args) -> int:
    from dran_edge.replay.run import ReplayOptions

    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    if args.blas_ablation:
        _blas_ablation(_simulate(workdir, "none", args))
        return 0
    runs = {
        "full (frames -> perception -> agents)": _simulate(workdir, "render", args),
        "back-end only (observations in ingest.bin)": _simulate(workdir, "none", args),
    }
    settle = 2 if args.quick else ReplayOptions().settle_rounds
    results = {name: _replay(run, args.workers, settle) for name, run in runs.items()}
    print(
        f"machine: {os.cpu_count()} cores; mission {args.robots} robots x "
        f"{args.duration_s:g} s (seed {args.seed})"
    )
    cores = os.cpu_count() or 1
    print(
        f"load average before: {os.getloadavg()[0]:.1f} (a shared machine makes wall times "
        f"longer; cpu s / {cores} cores is the wall time with the cores to ourselves)"
    )
    print(
        f"{'arm':<44} {'mission s':>9} {'wall s':>8} {'x real':>7} {'cpu s':>7} "
        f"{'x real (cpu/cores)':>18} {'percep. s':>9} {'rounds s':>9} {'MB sent':>8}"
    )
    for name, r in results.items():
        wall = r["replay_wall_s"]
        ideal = max(r["cpu_s"] / cores, 1e-9)
        print(
            f"{name:<44} {r['mission_s']:>9.1f} {wall:>8.2f} {r['mission_s'] / wall:>7.2f} "
            f"{r['cpu_s']:>7.1f} {r['mission_s'] / ideal:>18.2f} "
            f"{r['perception_wall_s']:>9.2f} {r['rounds_wall_s']:>9.2f} "
            f"{r['bytes_total'] / 1e6:>8.3f}"
        )
    full, back = results.values()
    ratio = full["replay_wall_s"] / back["replay_wall_s"] if back["replay_wall_s"] else math.nan
    print(f"ratio wall(full) / wall(back-end only): {ratio:.2f}")
    print(
        f"target: full replay >= 5x real time -> "
        f"{'met' if full['mission_s'] / full['replay_wall_s'] >= 5 else 'NOT met'}"
    )
    if args.json:
        print(
            json.dumps(
                {
                    n: {
                        k: r[k]
                        for k in (
                            "mission_s",
                            "replay_wall_s",
                            "perception_wall_s",
                            "rounds_wall_s",
                            "rounds",
                            "bytes_total",
                            "cpu_s",
                        )
                    }
                    for n, r in results.items()
                },
                indent=2,
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
