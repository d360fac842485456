"""``dran-edge rehearse RUN_DIR``: a fleet of real robot daemons through a recorded run."""

from __future__ import annotations

import argparse
import sys

HELP = "run a recorded mission through real daemons, one per robot, with faults"


def build_parser(prog: str) -> argparse.ArgumentParser:
    # Long but flat: one add_argument per flag (the parser is the command's documentation).
    p = argparse.ArgumentParser(
        prog=prog,
        description=(
            "Start one real 'dran-edge run' daemon per robot of RUN_DIR (a recorded run or "
            "'dran-edge simulate' output), each in its own network namespace with its own "
            "address (loopback addresses where namespaces are not permitted: needs root and "
            "iproute2), its own state directory and a config written from the run's robot.yaml. "
            "Each daemon gets its robot's recorded ingest stream through its real Unix socket "
            "at mission pace (or --speed times faster) and talks to the run's neighbours over "
            "UDP RADIO/DISH. Faults (kill -9 and restart, partition, silence, datagram loss, "
            "clock step) come from --faults FILE or the flags below; times are mission seconds. "
            "At the end each daemon's checkpoint is written as replay's outputs and scored like "
            "'dran-edge eval'. Writes OUT (default RUN_DIR/rehearsal): rehearsal.json, "
            "timeline.json, out/, daemons/<robot>/ (config, state, daemon.log). "
            "docs/rehearsal.md. Exit codes: 0 done, 1 a check failed (an accepted input lost), "
            "2 bad input."
        ),
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory (docs/run-format.md)")
    p.add_argument(
        "-o",
        "--out",
        default=None,
        metavar="DIR",
        help="where to write (default RUN_DIR/rehearsal; a previous rehearsal there is replaced)",
    )
    p.add_argument(
        "--speed",
        type=float,
        default=1.0,
        metavar="X",
        help="mission seconds per wall second (default 1; the daemons' round period "
        "is divided by it)",
    )
    p.add_argument(
        "--net",
        choices=("auto", "netns", "loopback"),
        default="auto",
        help="network namespaces per robot (netns), loopback addresses, or "
        "namespaces where permitted (auto, default)",
    )
    p.add_argument(
        "--settle-rounds",
        type=int,
        default=20,
        help="rounds after the recorded data ends (default 20, as replay)",
    )
    p.add_argument("--faults", metavar="FILE", help="fault file (YAML; docs/rehearsal.md)")
    p.add_argument(
        "--kill",
        action="append",
        default=[],
        metavar="ROBOT:AT_S[:RESTART_S]",
        help="kill -9 ROBOT at AT_S and start it again at RESTART_S",
    )
    p.add_argument(
        "--partition",
        action="append",
        default=[],
        metavar="R[,R...]:AT_S:END_S",
        help="cut robots R off from the others between two mission times",
    )
    p.add_argument(
        "--silent",
        action="append",
        default=[],
        metavar="ROBOT:AT_S:END_S",
        help="ROBOT's radio off (it neither sends nor hears) between two times",
    )
    p.add_argument(
        "--loss",
        action="append",
        default=[],
        metavar="A-B:P[:AT_S:END_S]",
        help="lose datagrams between robots A and B with probability P",
    )
    p.add_argument(
        "--clock-step",
        action="append",
        default=[],
        metavar="ROBOT:AT_S:STEP_S",
        help="step ROBOT's wall clock by STEP_S at AT_S (needs libfaketime)",
    )
    p.add_argument("--no-eval", action="store_true", help="do not score against the mocap")
    p.add_argument(
        "--mcap",
        metavar="FILE",
        help="also write the outputs and the mocap ground truth as an MCAP file for "
        "Foxglove (docs/viz.md; needs foxglove-sdk)",
    )
    p.add_argument("--json", action="store_true", help="print rehearsal.json")
    return p


def _fmt(v, spec: str) -> str:
    return "n/a" if v is None else format(v, spec)


def run(args: argparse.Namespace) -> int:
    import json
    import signal

    from dran_edge.formats import run_dir as rd
    from dran_edge.cli.progress import ProgressBar
    from dran_edge.rehearsal.faults import faults_from_flags, load_faults
    from dran_edge.rehearsal.fleet import RehearsalOptions, rehearse

    mission = rd.open_run(args.run_dir).mission
    ids = {r.name: r.id for r in mission.robots}
    faults = load_faults(args.faults, ids, mission.duration_s) if args.faults else []
    faults += faults_from_flags(
        kill=args.kill,
        partition=args.partition,
        silent=args.silent,
        loss=args.loss,
        clock_step=args.clock_step,
        ids=ids,
        mission_s=mission.duration_s,
    )
    opt = RehearsalOptions(
        speed=args.speed,
        net=args.net,
        settle_rounds=args.settle_rounds,
        faults=tuple(faults),
        out_dir=args.out,
        evaluate=not args.no_eval,
    )

    def on_term(signum, _frame):  # the daemons and namespaces are cleaned up on the way out
        raise KeyboardInterrupt(f"received signal {signum}")

    signal.signal(signal.SIGTERM, on_term)
    res = rehearse(args.run_dir, opt, progress=ProgressBar())
    r = res.report
    if args.mcap:
        from dran_edge.viz.record import write_run_mcap

        counts = write_run_mcap(res.out_dir, args.mcap)
        print(
            f"mcap: {args.mcap} ({len(counts)} topics, {sum(counts.values())} messages)",
            file=sys.stderr,
        )
    if args.json:
        print(json.dumps(r, indent=2))
    else:
        print(
            f"rehearsed {r['robots']} daemons, {r['mission_s']:g} s mission at {r['speed']:g}x "
            f"in {r['rehearsal_wall_s']:.1f} s on {r['net']}"
            + (f" ({r['net_note']})" if r["net_note"] else "")
        )
        for name, p in r["per_robot"].items():
            i = p["ingest"]
            print(
                f"  {name:<10} {p['address']:<21} starts {p['starts']}  rounds {p['ticks']} "
                f"(late {p['late']}, missed {p['missed']})  keyframes {p['keyframes']}  "
                f"objects {p['objects']}  records sent {i['records_sent']}/"
                f"{i['records_in_run']}, accepted lost {i['accepted_lost']}"
            )
        for f in r["fault_log"]:
            print(
                f"  fault {f['action']:<5} at {f['t_s']:7.1f} s: {f['fault']} "
                f"({f.get('by', 'process')})"
            )
        for j in r["rejoin"]:
            print(
                f"  after '{j['fault']}': {j['robot']} heard by {j['heard_by_s']} s, "
                f"hears {j['hears_s']} s"
            )
        if "sr_ate" in r:
            print(
                f"SR_ATE {_fmt(r.get('sr_ate'), '.1f')} %   SR_cost "
                f"{_fmt(r.get('sr_cost'), '.1f')} %   ATE {_fmt(r.get('ate_m'), '.3f')} m   "
                f"CE {_fmt(r.get('ce'), '.4f')}   Bias {_fmt(r.get('bias'), '.4f')}"
            )
        elif "evaluation_error" in r:
            print(f"evaluation: {r['evaluation_error']}")
        print(f"outputs: {res.out_dir}/ (rehearsal.json, out/, daemons/)")
    return 1 if r["accepted_lost"] else 0
