"""``dran-edge merge-records OUT REC [REC...]``: robots' recordings -> one run directory."""

from __future__ import annotations

import argparse

HELP = "combine robots' 'run --record' directories into one run (writes mission.yaml)"


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description=(
            "Copy robots/<name>/ of each recording made with 'dran-edge run --record' into\n"
            "OUT and write OUT/mission.yaml from them (fleet and robots from the configs,\n"
            "start and duration from the recorded stamps, links from the configured\n"
            "neighbours, the mocap CSV when given). 'dran-edge replay OUT' and 'dran-edge\n"
            "eval OUT' then work without editing. docs/run-format.md, 'Runs recorded on\n"
            "robots'."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("out", metavar="OUT", help="run directory to create or extend")
    p.add_argument(
        "recordings",
        nargs="*",
        metavar="REC",
        help="recording directories (none: only rewrite OUT/mission.yaml)",
    )
    p.add_argument("--mocap", metavar="FILE.csv", help="Motive CSV of the mission (copied)")
    p.add_argument(
        "--mocap-start-ns",
        type=int,
        metavar="NS",
        help="robot-clock stamp of the Motive take's time 0, when known (else eval "
        "estimates the clock offset)",
    )
    return p


def run(args: argparse.Namespace) -> int:
    from dran_edge.formats import run_dir as rd
    from dran_edge.formats.recorded import merge_recordings

    path = merge_recordings(args.out, args.recordings, args.mocap, args.mocap_start_ns)
    m = rd.read_mission(path)
    print(
        f"wrote {path}: {len(m.robots)} robots ({', '.join(r.name for r in m.robots)}), "
        f"{m.duration_s:.1f} s from start_ns {m.start_ns}, links {list(m.comm_graph)}, "
        f"mocap {m.mocap_file or 'none'}"
    )
    return 0
