#!/usr/bin/env python3
"""Bounded vs unbounded local graph on a long VIO mission (docs/benchmarks.md, bounded graph).

One simulated robot (``dran_edge.sim.vio``: laps among 9 AprilTag objects, 10 Hz odometry with
drift, DBoW2-like loops, tag observations, two VIO resets) streams N keyframes into

- the bounded :class:`KeyframeGraph` (``max_nodes``/``max_edges`` caps, composition and Schur
  marginalisation), solved every ``--round-every`` keyframes (a "round", 3 warm-started LM
  iterations), and
- the same graph without caps (the baseline), solved with the same settings at every report
  point only (its rounds get too slow to run them all),

side by side in this process, and prints per window: graph size, per-round solve time of both
and their ratio, and the process RSS. At the end both are solved to convergence and compared
with the ground truth on the nodes the bounded graph still holds (plus the object map), also
for the sparsified prior the DRAN agent receives (``factor_arrays(include_prior=True)``).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python tools/bench/bench_bounded_graph.py
    .venv/bin/python tools/bench/bench_bounded_graph.py --no-baseline   # RSS of the bounded graph
    .venv/bin/python tools/bench/bench_bounded_graph.py --quick   # 100 keyframes, caps 40 / 160
    .venv/bin/python tools/bench/bench_bounded_graph.py --checkpoints 2000,5000  # ATE on the way
    .venv/bin/python tools/bench/bench_bounded_graph.py --stop-after 2000 --seed 1  # its start

The mission is generated in a child process and written as ingest records (docs/ingest.md);
this process streams it back through the ingest decoder in 1 MiB chunks, as the daemon would,
so its RSS holds the graph, not the whole mission.
"""

from __future__ import annotations

import argparse
import copy
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import subprocess  # noqa: E402
import tempfile  # noqa: E402

import numpy as np  # noqa: E402
from dran_edge.comms.ingest import IngestDecodeError, StreamDecoder, encode_event  # noqa: E402

from dran_edge.config import AgentConfig, GraphBounds  # noqa: E402
from dran_edge.events import Keyframe  # noqa: E402
from dran_edge.robot.keyframe_graph import KeyframeGraph  # noqa: E402
from dran_edge.sim.vio import vio_mission  # noqa: E402
from dran_edge.solver import lm  # noqa: E402
from dran_edge.solver.graph import PoseGraph  # noqa: E402


def rss_mb(field: str = "VmRSS") -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def round_solve(g: KeyframeGraph, iterations: int) -> float:
    t = time.perf_counter()
    g.solve(lm.LMParams(max_iterations=iterations))
    return time.perf_counter() - t


def ate_m(mission, stamps: np.ndarray, T: np.ndarray) -> float:
    """Position RMSE (m) of poses ``T`` at keyframe ``stamps`` against the ground truth."""
    i = np.searchsorted(mission.keyframe_stamps_ns, stamps)
    return float(
        np.sqrt(np.mean(np.sum((T[:, :3, 3] - mission.T_world_body_true[i, :3, 3]) ** 2, axis=1)))
    )


def errors(
    g: KeyframeGraph, mission, stamps: np.ndarray, T: np.ndarray, objects: np.ndarray
) -> tuple[float, float]:
    ate = ate_m(mission, stamps, T)
    oid = g.object_ids()
    obj = float(
        np.sqrt(
            np.mean(
                np.sum((objects[:, :3, 3] - mission.T_world_object_true[oid, :3, 3]) ** 2, axis=1)
            )
        )
    )
    return ate, obj


def solve_sparsified(g: KeyframeGraph) -> tuple[np.ndarray, np.ndarray]:
    """The bounded graph as the agent sees it: sparsified prior instead of the dense one."""
    graph, poses, keys = g.problem()
    blocks = g._blocks(g.factor_arrays(include_prior=True), keys, g.config.residual)
    res = lm.solve(PoseGraph(3, graph.kinds, tuple(blocks)), poses, lm.LMParams(max_iterations=50))
    n = g.num_nodes
    return res.poses[:n], res.poses[n:]


def checkpoint(bounded: KeyframeGraph, unbounded: KeyframeGraph | None, mission, kf: int) -> None:
    """ATE of copies of both graphs solved to convergence now, on the bounded graph's nodes."""
    b = copy.deepcopy(bounded)
    b.solve(lm.LMParams(max_iterations=50))
    stamps = b.node_stamps_ns()
    b_ate, _ = errors(b, mission, stamps, b.T_world_body(), b.T_world_object())
    s_T, s_O = solve_sparsified(b)
    s_ate, _ = errors(b, mission, stamps, s_T, s_O)
    # the recent window alone (the nodes that are not skeleton nodes)
    win = np.array([k not in b.skeleton for k in b.node_keys().tolist()], dtype=bool)
    w_ate = ate_m(mission, stamps[win], b.T_world_body()[win])
    line = (
        f"checkpoint {kf} keyframes: ATE bounded dense {b_ate:.4f} m, sparsified {s_ate:.4f} m "
        f"({len(b.skeleton)} skeleton nodes; window alone {w_ate:.4f} m)"
    )
    if unbounded is not None:
        u = copy.deepcopy(unbounded)
        u.solve(lm.LMParams(max_iterations=50))
        idx = np.searchsorted(u.node_stamps_ns(), stamps)
        u_ate, _ = errors(u, mission, stamps, u.T_world_body()[idx], u.T_world_object())
        uw_ate = ate_m(mission, stamps[win], u.T_world_body()[idx][win])
        line += (
            f", unbounded {u_ate:.4f} m (bounded dense / unbounded {b_ate / u_ate:.2f}; "
            f"window alone {uw_ate:.4f} m, ratio {w_ate / uw_ate:.2f})"
        )
    print(line + f"; RSS {rss_mb():.0f} MB", flush=True)


def write_mission(path: str, n: int, seed: int) -> None:
    """Child process: generate the mission, write its ingest records and its ground truth."""
    mission = vio_mission(n, seed=seed, reset_at=(n // 3, 2 * n // 3))
    with open(path, "wb") as f:
        for e in mission.events:
            f.write(encode_event(e))
    np.savez(
        path + ".truth.npz",
        stamps=mission.keyframe_stamps_ns,
        T=mission.T_world_body_true,
        objects=mission.T_world_object_true,
    )


class Truth:
    def __init__(self, path: str):
        z = np.load(path + ".truth.npz")
        self.keyframe_stamps_ns = z["stamps"]
        self.T_world_body_true = z["T"]
        self.T_world_object_true = z["objects"]


def stream_events(path: str, chunk: int = 1 << 20):
    dec = StreamDecoder()
    with open(path, "rb") as f:
        while True:
            data = f.read(chunk)
            if not data:
                break
            for item in dec.feed(data):
                if isinstance(item, IngestDecodeError):
                    raise item
                yield item.event


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--keyframes", type=int, default=10_000)
    ap.add_argument("--max-nodes", type=int, default=400)
    ap.add_argument("--max-edges", type=int, default=1600)
    ap.add_argument(
        "--skeleton-fraction",
        type=float,
        default=GraphBounds().skeleton_fraction,
        help="graph.skeleton_fraction of the bounded graph (docs/config.md)",
    )
    ap.add_argument(
        "--archive-size",
        type=int,
        default=GraphBounds().archive_size,
        help="graph.archive_size of the bounded graph (docs/config.md; 0: off)",
    )
    ap.add_argument("--round-every", type=int, default=10, help="keyframes per round")
    ap.add_argument("--iterations", type=int, default=3, help="LM iterations per round")
    ap.add_argument("--report-every", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-baseline", action="store_true", help="skip the unbounded graph")
    ap.add_argument(
        "--stop-after",
        type=int,
        default=0,
        help="stop streaming after this many keyframes of the --keyframes mission (its resets "
        "stay at 1/3 and 2/3 of --keyframes): a shorter run of the same mission",
    )
    ap.add_argument(
        "--checkpoints",
        default="",
        help="comma-separated keyframe counts at which a copy of each graph is "
        "solved to convergence and its ATE printed (e.g. 2000,5000)",
    )
    ap.add_argument("--write-mission", metavar="PATH", help=argparse.SUPPRESS)
    ap.add_argument(
        "--mission",
        metavar="PATH",
        help="keep the generated mission's ingest records at PATH (and PATH.truth.npz) and "
        "reuse them when they exist (same --keyframes and --seed only)",
    )
    ap.add_argument(
        "--quick",
        action="store_true",
        help="100 keyframes, caps of 40 nodes / 160 edges: checks the script only",
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.keyframes, args.report_every = min(args.keyframes, 100), 50
        args.max_nodes, args.max_edges = 40, 160
    n = args.keyframes
    if args.write_mission:
        write_mission(args.write_mission, n, args.seed)
        return 0

    t0 = time.perf_counter()
    tmp = None if args.mission else tempfile.mkdtemp(prefix="bench_bounded_")
    path = args.mission or os.path.join(tmp, "ingest.bin")
    if args.mission and os.path.exists(path + ".truth.npz"):
        pass  # reuse the kept mission
    elif args.quick:  # no child process: the RSS figures do not matter here
        write_mission(path, n, args.seed)
    else:
        subprocess.run(
            [
                sys.executable,
                __file__,
                "--keyframes",
                str(n),
                "--seed",
                str(args.seed),
                "--write-mission",
                path,
            ],
            check=True,
        )
    mission = Truth(path)
    gen_s = time.perf_counter() - t0
    print(
        f"mission: {n} keyframes, {os.path.getsize(path) / 1e6:.1f} MB of ingest records, "
        f"generated in {gen_s:.1f} s (child process); RSS here {rss_mb():.0f} MB"
    )
    checkpoints = {int(k) for k in args.checkpoints.split(",") if k.strip()}
    base = AgentConfig(
        graph=GraphBounds(
            max_nodes=args.max_nodes,
            max_edges=args.max_edges,
            skeleton_fraction=args.skeleton_fraction,
            archive_size=args.archive_size,
        )
    )
    bounded = KeyframeGraph(base)
    unbounded = (
        None
        if args.no_baseline
        else KeyframeGraph(
            AgentConfig(graph=GraphBounds(max_nodes=1_000_000, max_edges=10_000_000))
        )
    )

    print(
        "\n| keyframes | bounded nodes / factors / prior vars | bounded round solve ms "
        "(mean / max) | unbounded nodes / factors | unbounded round solve ms | ratio "
        "unbounded / bounded | handle µs/event bounded | RSS MB |"
    )
    print("|---|---|---|---|---|---|---|---|")
    kf = 0
    window: list[float] = []
    handle_s = 0.0
    handled = 0
    peak_nodes = peak_edges = 0
    for ev in stream_events(path):
        t = time.perf_counter()
        bounded.handle(ev)
        handle_s += time.perf_counter() - t
        handled += 1
        if unbounded is not None:
            unbounded.handle(ev)
        peak_nodes = max(peak_nodes, bounded.num_nodes)
        peak_edges = max(peak_edges, bounded.num_factors)
        if not isinstance(ev, Keyframe):
            continue
        kf += 1
        if kf % args.round_every == 0:
            window.append(round_solve(bounded, args.iterations))
        if kf in checkpoints:
            checkpoint(bounded, unbounded, mission, kf)
        if kf % args.report_every == 0 or kf == args.stop_after:
            ub = "—"
            ub_ms = float("nan")
            if unbounded is not None:
                ub_ms = 1e3 * round_solve(unbounded, args.iterations)
                ub = f"{unbounded.num_nodes} / {unbounded.num_factors}"
            mean_ms = 1e3 * float(np.mean(window)) if window else float("nan")
            prior = 0 if bounded.prior is None else len(bounded.prior["keys"])
            print(
                f"| {kf} | {bounded.num_nodes} / {bounded.num_factors} / {prior} | "
                f"{mean_ms:.1f} / {1e3 * max(window, default=float('nan')):.1f} | {ub} | {ub_ms:.0f} | "
                f"{ub_ms / mean_ms:.1f} | {1e6 * handle_s / max(handled, 1):.0f} | "
                f"{rss_mb():.0f} |",
                flush=True,
            )
            window, handle_s, handled = [], 0.0, 0
        if kf == args.stop_after:
            break
    print(
        f"\nbounded graph peak: {peak_nodes} nodes, {peak_edges} factors (caps "
        f"{args.max_nodes} / {args.max_edges}); skeleton {len(bounded.skeleton)} nodes, stride "
        f"{bounded.skeleton.stride}; archive {len(bounded.archive)} keyframes; counters {bounded.counters}"
    )

    # final accuracy on the nodes the bounded graph holds
    bounded.solve(lm.LMParams(max_iterations=50))
    stamps = bounded.node_stamps_ns()
    b_ate, b_obj = errors(
        bounded, mission, stamps, bounded.T_world_body(), bounded.T_world_object()
    )
    s_T, s_O = solve_sparsified(bounded)
    s_ate, s_obj = errors(bounded, mission, stamps, s_T, s_O)
    print("\n| graph | ATE on the bounded graph's nodes (m, RMSE) | object map error (m, RMSE) |")
    print("|---|---|---|")
    if unbounded is not None:
        t = time.perf_counter()
        unbounded.solve(lm.LMParams(max_iterations=50))
        u_s = time.perf_counter() - t
        idx = np.searchsorted(unbounded.node_stamps_ns(), stamps)
        u_ate, u_obj = errors(
            unbounded, mission, stamps, unbounded.T_world_body()[idx], unbounded.T_world_object()
        )
        print(
            f"| unbounded ({unbounded.num_nodes} nodes, final solve {u_s:.1f} s) | "
            f"{u_ate:.3f} | {u_obj:.3f} |"
        )
    print(f"| bounded, dense marginal prior | {b_ate:.3f} | {b_obj:.3f} |")
    print(f"| bounded, sparsified prior (agent view) | {s_ate:.3f} | {s_obj:.3f} |")
    if tmp is not None:
        os.remove(path)
        os.remove(path + ".truth.npz")
        os.rmdir(tmp)
    print(
        f"\npeak RSS of the process (VmHWM): {rss_mb('VmHWM'):.0f} MB; total "
        f"{time.perf_counter() - t0:.0f} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
