"""``dran-edge simulate OUT_DIR``: write a simulated multi-robot mission as a run directory."""

from __future__ import annotations

import argparse
import time

HELP = "simulate a multi-robot mission and write it as a run directory"


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description=(
            "Simulate Dingo-like robots driving approximately circular paths among AprilTag "
            "boxes and write what they record, in the run-directory format that "
            "'dran-edge replay' reads (docs/run-format.md): VIO odometry with drift and "
            "occasional resets, keyframes, loop closures (a few wrong), rendered 640x480 "
            "colour + depth frames, each robot's config, the calibration, the communication "
            "graph and a ground-truth OptiTrack Motive CSV. The same seed gives the same run."
        ),
    )
    p.add_argument(
        "out_dir",
        nargs="?",
        metavar="OUT_DIR",
        help="new (or empty) directory for the run (or give it as -o/--out)",
    )
    p.add_argument("-o", "--out", metavar="OUT_DIR", help="the same as OUT_DIR")
    p.add_argument("--robots", type=int, default=6, help="number of robots (default 6)")
    p.add_argument("--objects", type=int, default=9, help="number of tagged boxes (default 9)")
    p.add_argument(
        "--duration-s", type=float, default=180.0, help="mission length in seconds (default 180)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--frame-rate-hz",
        type=float,
        default=2.0,
        help="recorded camera frames per second (default 2; 0 = no frames)",
    )
    p.add_argument(
        "--frames",
        choices=("render", "none"),
        default="render",
        help="'render': write PNG frames (replay runs the AprilTag pipeline); "
        "'none': write tag observations into ingest.bin instead (fast)",
    )
    p.add_argument(
        "--arena-m",
        type=float,
        default=None,
        help="edge of the square arena in metres (default: grows with --objects)",
    )
    p.add_argument(
        "--workers", type=int, default=None, help="rendering processes (default: one per CPU core)"
    )
    return p


def run(args: argparse.Namespace) -> int:
    import math

    from dran_edge.cli.progress import ProgressBar
    from dran_edge.sim.writer import write_run
    from dran_edge.sim.mission import SimParams, generate_mission

    from dran_edge.errors import InputError

    if (args.out_dir is None) == (args.out is None):
        raise InputError("give the run directory once: OUT_DIR or -o/--out OUT_DIR")
    args.out = args.out or args.out_dir
    arena = args.arena_m if args.arena_m is not None else max(6.0, 3.0 * math.sqrt(args.objects))
    params = SimParams(
        robots=args.robots,
        objects=args.objects,
        duration_s=args.duration_s,
        seed=args.seed,
        frame_rate_hz=args.frame_rate_hz,
        arena_m=arena,
    )
    t0 = time.monotonic()
    mission = generate_mission(params)
    write_run(mission, args.out, frames=args.frames, workers=args.workers, progress=ProgressBar())
    n_loops = sum(len(r.loops) for r in mission.robots)
    n_out = sum(int(r.loop_outlier.sum()) for r in mission.robots)
    n_resets = sum(len(r.reset_stamps_ns) for r in mission.robots)
    n_frames = sum(len(r.frame_stamps_ns) for r in mission.robots) if args.frames == "render" else 0
    print(
        f"simulated {args.robots} robots, {args.objects} boxes, {args.duration_s:g} s "
        f"(seed {args.seed}): {n_loops} loops ({n_out} wrong), {n_resets} VIO resets, "
        f"{n_frames} frames, {len(mission.comm_edges)} radio links; "
        f"wrote {args.out} in {time.monotonic() - t0:.1f} s"
    )
    return 0
