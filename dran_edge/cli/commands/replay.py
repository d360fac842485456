"""``dran-edge replay RUN_DIR``: replay a recorded run through the robot code."""

from __future__ import annotations

import argparse

HELP = "replay a recorded run through the robot code"


def build_parser(prog: str) -> argparse.ArgumentParser:
    # Long but flat: one add_argument per flag (the parser is the command's documentation).
    p = argparse.ArgumentParser(
        prog=prog,
        description=(
            "Start every robot of RUN_DIR with the same agent code the daemon runs, feed it the "
            "recorded ingest bytes through the same decoders (tag observations the robot "
            "recorded included; frames go through the AprilTag perception pipeline only for a "
            "robot without recorded observations, or with --redetect), and let the robots talk over the in-process bus "
            "(default) or loopback UDP RADIO/DISH. Runs as fast as compute allows unless "
            "--speed is given. Writes RUN_DIR/out/ (trajectories, object maps, merged g2o, "
            "rounds.csv, report.json; docs/run-format.md) and prints a summary. "
            "Exit codes: 0 done, 2 bad run directory, 3 missing dependency."
        ),
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory (docs/run-format.md)")
    p.add_argument(
        "--transport",
        choices=("bus", "udp"),
        default="bus",
        help="in-process bus with a network model (default) or loopback UDP",
    )
    p.add_argument(
        "--loss",
        type=float,
        default=0.0,
        help="bus: probability that a datagram is lost (default 0)",
    )
    p.add_argument(
        "--latency",
        type=int,
        default=1,
        metavar="ROUNDS",
        help="bus: rounds between send and delivery (default 1)",
    )
    p.add_argument(
        "--partition",
        action="append",
        default=[],
        metavar="IDS:START_S:END_S",
        help="bus: cut robots IDS (comma-separated) off from the others between two "
        "mission times, e.g. 3,4:30:60 (repeatable)",
    )
    p.add_argument(
        "--speed",
        type=float,
        default=0.0,
        metavar="X",
        help="pace the replay at X times real time (default: as fast as possible)",
    )
    p.add_argument(
        "--settle-rounds",
        type=int,
        default=20,
        help="extra rounds after the recorded data ends (default 20)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="perception worker processes (default: one per core)",
    )
    p.add_argument(
        "--redetect",
        action="store_true",
        help="ignore the tag observations recorded in ingest.bin and run perception "
        "on the recorded frames again (results may differ slightly across CPU "
        "architectures; the recorded ones are the same everywhere)",
    )
    p.add_argument(
        "--loss-seed",
        type=int,
        default=0,
        help="seed of the bus loss model (default 0); --seed is the simulation's "
        "seed in 'simulate' and 'demo'",
    )
    p.add_argument(
        "--cost-every",
        type=int,
        default=None,
        metavar="N",
        help="every N rounds and at the last, solve the merged graph as it stands for SR_cost "
        "and F/F* per round (report.json round_costs; default 20, 0: never)",
    )
    p.add_argument("--no-eval", action="store_true", help="do not score against the run's mocap")
    p.add_argument(
        "--mcap",
        metavar="FILE",
        help="also write the outputs and the mocap ground truth as an MCAP file for "
        "Foxglove (docs/viz.md; needs foxglove-sdk)",
    )
    p.add_argument("--json", action="store_true", help="print report.json instead of a summary")
    return p


def _fmt(v, spec: str) -> str:
    return "n/a" if v is None else format(v, spec)


def _sources(sources: dict) -> str:
    """``recorded: dingo1, dingo2; redetected: dingo3``."""
    by: dict[str, list[str]] = {}
    for name, src in sources.items():
        by.setdefault(src, []).append(name)
    return "; ".join(f"{src}: {', '.join(names)}" for src, names in sorted(by.items())) or "none"


def run(args: argparse.Namespace) -> int:
    import json

    from dran_edge.replay.run import PartitionSpec, ReplayOptions, replay_run

    opt = ReplayOptions(
        transport=args.transport,
        loss=args.loss,
        latency_rounds=args.latency,
        partitions=tuple(PartitionSpec.parse(p) for p in args.partition),
        speed=args.speed,
        settle_rounds=args.settle_rounds,
        workers=args.workers,
        seed=args.loss_seed,
        evaluate=not args.no_eval,
        redetect=args.redetect,
        **({} if args.cost_every is None else {"cost_every": args.cost_every}),
    )
    from dran_edge.cli.progress import ProgressBar, note

    res = replay_run(args.run_dir, opt, progress=ProgressBar())
    r = res.report
    if args.mcap:
        from dran_edge.viz.record import write_run_mcap

        counts = write_run_mcap(res.out_dir.parent, args.mcap)
        note(f"mcap: {args.mcap} ({len(counts)} topics, {sum(counts.values())} messages)")
    if args.json:
        print(json.dumps(r, indent=2))
        return 0
    print(
        f"replayed {r['robots']} robots, {r['mission_s']:g} s mission in "
        f"{r['replay_wall_s']:.1f} s ({_fmt(r.get('realtime_factor'), '.1f')}x real time) over "
        f"{r['transport']}: {r['rounds']} rounds, {r['bytes_total'] / 1e6:.3f} MB sent, "
        f"{r['frames_processed']} frames, {r['observations']} tag observations "
        f"({_sources(r.get('observation_sources', {}))})"
    )
    if "sr_ate" in r:
        print(
            f"SR_ATE {_fmt(r.get('sr_ate'), '.1f')} %   SR_cost {_fmt(r.get('sr_cost'), '.1f')} %"
            f"   ATE/ATE* {_fmt(r.get('ate_over_atestar'), '.3f')}"
            f"   F/F* {_fmt(r.get('f_over_fstar'), '.4f')}"
            f"   ATE {_fmt(r.get('ate_m'), '.3f')} m   CE {_fmt(r.get('ce'), '.4f')}"
            f"   Bias {_fmt(r.get('bias'), '.4f')}"
        )
    elif "evaluation_error" in r:
        print(f"evaluation: {r['evaluation_error']}")
    if r.get("ingest_rejected"):
        print(f"ingest records rejected: {r['ingest_rejected']}")
    for w in r.get("warnings", ()):  # also logged when found, before the first round
        print(f"warning: {w}")
    print(f"outputs: {res.out_dir}/ (report.json, rounds.csv, merged.g2o, <robot>/<robot>.tum)")
    return 0
