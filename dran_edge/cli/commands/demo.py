"""``dran-edge demo --out DIR``: simulate -> replay -> evaluate, with no hardware and no network."""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

HELP = "run the end-to-end demo with no hardware"


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description=(
            "The whole system in one command: simulate a multi-robot mission (Dingo-like robots "
            "among AprilTag boxes; rendered camera frames, VIO odometry with drift and resets, "
            "loop closures, a ground-truth Motive CSV), replay it through the robot code (the "
            "AprilTag pipeline on every frame, one DRAN agent per robot, authenticated datagrams "
            "over the in-process bus) and score it against the ground truth. Prints the headline "
            "metrics and where the report and plots are."
        ),
    )
    p.add_argument(
        "-o", "--out", default="demo-run", help="directory for the run (default demo-run)"
    )
    p.add_argument("--robots", type=int, default=6, help="robots (default 6)")
    p.add_argument("--objects", type=int, default=9, help="tagged boxes (default 9)")
    p.add_argument("--duration-s", type=float, default=180.0, help="mission length (default 180)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--frames",
        choices=("render", "none"),
        default="render",
        help="render camera frames (default) or give the robots tag observations directly (faster)",
    )
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    return p


def _is_demo_run(path: Path) -> bool:
    mission = path / "mission.yaml"
    return mission.is_file() and "\nsimulation:" in mission.read_text(encoding="utf-8")


def run(args: argparse.Namespace) -> int:
    # Long: the demo's three stages with their printed summary, in the order a user reads them.
    import math

    from dran_edge.cli.progress import ProgressBar
    from dran_edge.errors import InputError
    from dran_edge.evaluation.score import EvalOptions, evaluate_run, write_report
    from dran_edge.replay.run import ReplayOptions, replay_run
    from dran_edge.sim.writer import write_run
    from dran_edge.sim.mission import SimParams, generate_mission

    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        if not _is_demo_run(out):
            raise InputError(
                "exists and is not a previous demo run; choose another --out", path=str(out)
            )
        shutil.rmtree(out)
    t0 = time.monotonic()
    bar = ProgressBar()
    arena = max(6.0, 3.0 * math.sqrt(args.objects))
    params = SimParams(
        robots=args.robots,
        objects=args.objects,
        duration_s=args.duration_s,
        seed=args.seed,
        arena_m=arena,
    )
    print(
        f"[1/3] simulating {args.robots} robots among {args.objects} AprilTag boxes for "
        f"{args.duration_s:g} s ...",
        flush=True,
    )
    mission = generate_mission(params)
    write_run(mission, out, frames=args.frames, progress=bar)
    t1 = time.monotonic()
    print(f"      wrote {out} in {t1 - t0:.1f} s", flush=True)
    print("[2/3] replaying it through the robot code ...", flush=True)
    res = replay_run(out, ReplayOptions(evaluate=False), progress=bar)
    r = res.report
    print(
        f"      {r['rounds']} rounds, {r['observations']} tag observations (recorded by the "
        f"simulated robots' perception), {r['bytes_total'] / 1e6:.3f} MB exchanged; "
        f"{r['replay_wall_s']:.1f} s ({r['realtime_factor']:.1f}x real time)",
        flush=True,
    )
    print("[3/3] scoring against the ground truth ...", flush=True)
    evaluation = evaluate_run(out, EvalOptions(plots=not args.no_plots))
    written = write_report(evaluation, out / "eval", plots=not args.no_plots)
    report = evaluation.report
    s = report["summary"]

    def f(v, spec):
        return "n/a" if v is None else format(v, spec)

    print()
    print(
        f"  SR_ATE  {f(s.get('sr_ate_pct'), '7.1f')} %   (share of the centralized solution's "
        f"ATE improvement reached)"
    )
    c = report.get("cost") or {}
    print(
        f"  SR_cost {f(s.get('sr_cost_pct'), '7.1f')} %   (SE-Sync cost: initial estimate "
        f"{f(c.get('F_init'), '.4g')}, ours {f(c.get('F_k'), '.4g')}, centralized "
        f"{f(c.get('F_star'), '.4g')})"
    )
    print(
        f"  F/F*    {f(s.get('f_over_fstar'), '7.4f')}     (our SE-Sync cost over the "
        f"centralized optimum's; 1 is the optimum)"
    )
    print(
        f"  ATE/ATE*{f(s.get('ate_over_atestar'), '7.3f')}     (our ATE over the centralized "
        f"solution's)"
    )
    print(f"  ATE     {f(s.get('ate_m'), '7.3f')} m   (keyframe positions vs OptiTrack)")
    print(f"  CE      {f(s.get('ce'), '7.4f')}     (disagreement between robots' object maps)")
    print(f"  Bias    {f(s.get('bias'), '7.4f')}     (object maps vs OptiTrack)")
    print(f"  bytes   {r['bytes_total'] / 1e6:7.3f} MB over {r['rounds']} rounds")
    print()
    print(f"report:   {out / 'eval' / 'summary.md'}  ({out / 'eval' / 'report.json'})")
    pngs = [p for p in written if p.suffix == ".png"]
    if pngs:
        print(f"plots:    {out / 'eval'}/*.png ({len(pngs)} files)")
    print(f"replay:   {out / 'out'}/ (trajectories, object maps, merged.g2o, rounds.csv)")
    print(f"demo finished in {time.monotonic() - t0:.0f} s", file=sys.stderr)
    return 0
