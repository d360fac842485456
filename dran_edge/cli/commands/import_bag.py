"""``dran-edge import-bag BAG [BAG...] --out RUN_DIR --map MAPPING.yaml``: bags -> run directory."""

from __future__ import annotations

import argparse
import sys
import time

HELP = "import ROS 1 / ROS 2 bags (.bag, .db3, .mcap) as a run directory"


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description=(
            "Turn recorded ROS bags into a run directory that 'dran-edge replay' and\n"
            "'dran-edge eval' read (docs/run-format.md). A mapping file names, per robot, the\n"
            "odometry, keyframe, loop-edge, reset and image/depth/camera_info topics, and the\n"
            "mocap topics (geometry_msgs/PoseStamped, one per rigid body). Reads ROS 1 .bag\n"
            "files and ROS 2 bag folders (sqlite3 .db3 or MCAP) without ROS, one message at a\n"
            "time. Mapping format, clock handling and a worked example: docs/bags.md."
        ),
        epilog=(
            "example:\n  dran-edge import-bag --list dingo1.bag\n"
            "  dran-edge import-bag dingo1.bag dingo2.bag mocap.bag --map lab.yaml "
            "--out run01\n  dran-edge replay run01 && dran-edge eval run01"
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "bags",
        nargs="+",
        metavar="BAG",
        help="ROS 1 .bag file, or ROS 2 bag folder (or the .db3/.mcap inside it)",
    )
    p.add_argument("-o", "--out", metavar="RUN_DIR", help="new (or empty) run directory to write")
    p.add_argument("--map", metavar="MAPPING.yaml", help="topic mapping file (docs/bags.md)")
    p.add_argument(
        "--list", action="store_true", help="only list each bag's topics, message types and counts"
    )
    return p


def run(args: argparse.Namespace) -> int:
    from dran_edge.cli.progress import ProgressBar
    from dran_edge.errors import InputError
    from dran_edge.formats import bags

    if args.list:
        for b in args.bags:
            print(f"{b}:")
            for topic, typ, n in bags.list_topics(b):
                print(f"  {topic:<48} {typ:<40} {n}")
        return 0
    if not args.out or not args.map:
        raise InputError("--out RUN_DIR and --map MAPPING.yaml are required (or --list)")
    from dran_edge.formats.bag_map import read_mapping

    mapping = read_mapping(args.map)
    t0 = time.monotonic()
    summary = bags.import_bags(args.bags, mapping, args.out, progress=ProgressBar())
    for name, r in summary["robots"].items():
        w = r["written"]
        skipped = ", ".join(f"{k} {v}" for k, v in sorted(r["skipped"].items())) or "none"
        print(
            f"{name}: {w.get('odometry', 0)} odometry, {w.get('keyframes', 0)} keyframes, "
            f"{w.get('loops', 0)} loops, {w.get('resets', 0)} resets, "
            f"{w.get('frames', 0)} frames; skipped: {skipped}"
        )
        for reason, text in r["first_skip"].items():
            print(f"  first {reason}: {text}", file=sys.stderr)
    if summary["mocap"]:
        bodies = summary["mocap"]["bodies"]
        print("mocap: " + ", ".join(f"{b} {n} poses" for b, n in bodies.items()))
    if summary["undecodable"]:
        print(
            "undecodable messages: "
            + ", ".join(f"{t} {n}" for t, n in summary["undecodable"].items())
        )
    print(
        f"wrote {args.out} from {summary['messages']} messages in "
        f"{time.monotonic() - t0:.1f} s (details: {args.out}/import.json)"
    )
    return 0
