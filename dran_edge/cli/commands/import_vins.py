"""``dran-edge import-vins OUT_DIR``: VINS-Mono CSV outputs (+ pose_graph.txt, images) -> a run."""

from __future__ import annotations

import argparse

HELP = "import VINS-Mono CSV outputs (+ pose_graph.txt, images) as one robot of a run directory"


def _doc() -> str:
    from dran_edge.formats import vins_csv

    return (vins_csv.__doc__ or "").split("\n\n")[0]


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog, description=_doc(), formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("out", metavar="OUT_DIR", help="run directory to create or extend")
    p.add_argument("--name", required=True, help="robot name (folder under robots/)")
    p.add_argument("--id", type=int, required=True, help="robot id (0..65535)")
    p.add_argument("--fleet", default="vinsfleet", help="fleet name for a new run")
    p.add_argument("--no-loop-csv", required=True, help="VINS-Mono vins_result_no_loop.csv")
    p.add_argument("--loop-csv", help="VINS-Mono vins_result_loop.csv (keyframe stamps)")
    p.add_argument("--pose-graph", help="VINS-Mono pose_graph.txt (loop constraints)")
    p.add_argument(
        "--keyframe-every",
        type=int,
        default=5,
        help="without --loop-csv: a keyframe every N odometry samples (default 5)",
    )
    p.add_argument(
        "--gap-s",
        type=float,
        default=1.0,
        help="an odometry gap longer than this is a VIO restart (default 1.0)",
    )
    p.add_argument("--images", help="folder of images named by stamp (<t_ns>.png)")
    p.add_argument("--symlink", action="store_true", help="link images instead of copying")
    p.add_argument("--calib", help="folder with tags.yaml and cameras/<name>.yaml")
    p.add_argument(
        "--neighbours",
        type=lambda s: [int(x) for x in s.split(",") if x],
        default=[],
        help="comma-separated ids of this robot's communication neighbours",
    )
    p.add_argument("--mocap", help="OptiTrack Motive CSV of the mission (copied to mocap.csv)")
    p.add_argument("--mocap-body", help="this robot's Motive rigid-body name")
    p.add_argument(
        "--lenient",
        action="store_true",
        help="accept no-loop CSV lines without the velocity columns",
    )
    p.add_argument("--force", action="store_true", help="replace an existing robot")
    return p


def run(args: argparse.Namespace) -> int:
    from dran_edge.formats.vins_csv import convert

    res = convert(args)
    print(
        f"{res['run']}: robot {res['robot']}: {res['odometry']} odometry samples, "
        f"{res['keyframes']} keyframes, {res['loops']} loops, {res['resets']} resets, "
        f"{res['frames']} frames"
    )
    return 0
