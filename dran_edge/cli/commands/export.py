"""'dran-edge export WHAT RUN': a run's parts in other tools' formats.

- 'export mocap RUN --format tum|euroc|kitti [--out DIR]': each mocap rigid body's track
  (docs/trajectory-formats.md), in the robot clock ('mocap.start_ns'), world frame, one
  file per body: '<body>.tum' and so on. Robots' bodies are converted to the body frame
  with 'T_body_marker' (what evo_ape compares with 'out/<robot>/<robot>.tum').
- 'export bag RUN --format ros1|sqlite3|mcap --out DIR [--per-robot] [--raw-images]': the
  run as ROS bags plus the mapping file that imports them back (docs/bags.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "export a run's mocap as TUM/EuRoC/KITTI files, or the run as ROS bags"


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description=__doc__.split("\n\n")[0] + "\n\n" + __doc__.split("\n\n")[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="what", required=True, metavar="WHAT")
    m = sub.add_parser("mocap", help="each mocap body's track as a trajectory file")
    m.add_argument("run", metavar="RUN", help="run directory (docs/run-format.md)")
    m.add_argument(
        "--format",
        choices=("tum", "euroc", "kitti"),
        default="tum",
        help="file format (default tum; docs/trajectory-formats.md)",
    )
    m.add_argument("-o", "--out", help="output folder (default RUN/export/mocap)")
    m.add_argument(
        "--marker",
        action="store_true",
        help="write the rigid bodies' own poses (no T_body_marker / T_object_marker)",
    )
    b = sub.add_parser("bag", help="the run as ROS bags + the mapping file (docs/bags.md)")
    b.add_argument("run", metavar="RUN", help="run directory (docs/run-format.md)")
    b.add_argument(
        "--format",
        choices=("ros1", "sqlite3", "mcap"),
        default="mcap",
        help="ros1 (.bag), sqlite3 (ROS 2 .db3) or mcap (ROS 2; default)",
    )
    b.add_argument("-o", "--out", required=True, help="new output folder")
    b.add_argument(
        "--per-robot",
        action="store_true",
        help="one bag per robot (+ mocap) instead of one bag with /<robot>/ topics",
    )
    b.add_argument(
        "--raw-images", action="store_true", help="sensor_msgs/Image instead of CompressedImage"
    )
    return p


def run(args: argparse.Namespace) -> int:
    if args.what == "bag":
        import yaml

        from dran_edge.errors import InputError
        from dran_edge.formats.run_bag import write_run_bags

        out = Path(args.out)
        if out.exists() and any(out.iterdir()):
            raise InputError("expected an empty or new folder", path=str(out))
        paths, mapping = write_run_bags(
            args.run, out, args.format, per_robot=args.per_robot, raw_images=args.raw_images
        )
        (out / "mapping.yaml").write_text(
            "# dran-edge import-bag mapping (docs/bags.md), written by dran-edge export bag\n"
            + yaml.safe_dump(mapping, sort_keys=False, default_flow_style=None, width=100),
            encoding="utf-8",
        )
        for p in paths:
            print(p)
        print(out / "mapping.yaml")
        return 0
    from dran_edge.formats.trajectory import export_mocap

    for path in export_mocap(args.run, args.format, args.out, marker=args.marker):
        print(path)
    return 0
