"""The ``dran-edge`` command line: one entry point, lazily loaded sub-commands.

``dran-edge --help`` imports nothing but this file, so it is instant and works on a
machine without the hardware extras. Each sub-command lives in
``dran_edge/cli/commands/<name>.py`` with ``HELP``, ``build_parser(prog)`` and ``run(args)``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from typing import Sequence

from dran_edge.cli import progress
from dran_edge.errors import DranError

# name -> (module, one-line help). Order is the order shown in --help.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("dran_edge.cli.commands.demo", "run the end-to-end demo with no hardware"),
    "solve": ("dran_edge.cli.commands.solve", "optimise a g2o pose graph (centralised Schur-LM)"),
    "bench": (
        "dran_edge.cli.commands.bench",
        "run the paper's experiments (Table 1, object simulation)",
    ),
    "run": ("dran_edge.cli.commands.run", "run the robot daemon (what systemd starts)"),
    "status": ("dran_edge.cli.commands.status", "show the running daemon's health"),
    "check-config": (
        "dran_edge.cli.commands.check_config",
        "load a robot config and everything it names, as 'run' does",
    ),
    "check-fleet": (
        "dran_edge.cli.commands.check_fleet",
        "check a directory of robot configs for consistency",
    ),
    "simulate": (
        "dran_edge.cli.commands.simulate",
        "simulate a multi-robot mission as a run directory",
    ),
    "replay": ("dran_edge.cli.commands.replay", "replay a recorded run through the robot code"),
    "rehearse": (
        "dran_edge.cli.commands.rehearse",
        "run a recorded mission through real daemons, one per robot, with faults",
    ),
    "detect": (
        "dran_edge.cli.commands.detect",
        "detect AprilTags in images, recordings or a camera",
    ),
    "import-bag": (
        "dran_edge.cli.commands.import_bag",
        "import ROS 1 / ROS 2 bags (.bag, .db3, .mcap) as a run directory",
    ),
    "import-vins": (
        "dran_edge.cli.commands.import_vins",
        "import VINS-Mono CSV outputs as one robot of a run directory",
    ),
    "merge-records": (
        "dran_edge.cli.commands.merge_records",
        "combine robots' 'run --record' directories into one run",
    ),
    "export": (
        "dran_edge.cli.commands.export",
        "export a run's mocap as TUM/EuRoC/KITTI files, or the run as ROS bags",
    ),
    "eval": ("dran_edge.cli.commands.eval", "score a run or a trajectory against OptiTrack mocap"),
    "fleet-key": (
        "dran_edge.cli.commands.fleet_key",
        "create or check the datagram keys (fleet HMAC key, robot key pairs)",
    ),
}

EXIT_USAGE = 2


def add_common_options(parser: argparse.ArgumentParser) -> None:
    """What every command takes: ``-v``/``--verbose`` (more log output, twice for debug) and
    ``-q``/``--quiet`` (errors only, no progress on stderr). The result on stdout is the same."""
    group = parser.add_argument_group("output")
    taken = parser._option_string_actions  # a command that defines one of them keeps its own
    if "--verbose" not in taken:
        group.add_argument(
            "-v",
            "--verbose",
            action="count",
            default=0,
            help="more log output on stderr (-vv: debug)",
        )
    if "--quiet" not in taken:
        group.add_argument(
            "-q",
            "--quiet",
            action="store_true",
            help="only errors on stderr: no progress, no warnings",
        )


def _top_parser() -> argparse.ArgumentParser:
    lines = [f"  {name:<14}{help_}" for name, (_, help_) in COMMANDS.items()]
    parser = argparse.ArgumentParser(
        prog="dran-edge",
        description=(
            "Decentralized object-based multi-robot SLAM (DRAN) for ground robots.\n\n"
            "commands:\n" + "\n".join(lines) + "\n\n"
            "Run 'dran-edge COMMAND --help' for the options of one command."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    parser.add_argument("command", nargs="?", metavar="COMMAND", help="one of the commands above")
    parser.add_argument("args", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the process exit code (0 success, 1 failure, 2 bad input)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    top = _top_parser()
    ns = top.parse_args(argv)
    if ns.version:
        from dran_edge import __version__

        print(__version__)
        return 0
    if ns.command is None:
        top.print_help()
        return EXIT_USAGE
    if ns.command not in COMMANDS:
        print(
            f"dran-edge: unknown command {ns.command!r}; expected one of: " + ", ".join(COMMANDS),
            file=sys.stderr,
        )
        return EXIT_USAGE
    module = importlib.import_module(COMMANDS[ns.command][0])
    parser = module.build_parser(f"dran-edge {ns.command}")
    add_common_options(parser)
    args = parser.parse_args(ns.args)
    verbose = ns.verbose + args.verbose
    logging.basicConfig(
        level=logging.ERROR if args.quiet else logging.WARNING - 10 * min(verbose, 2),
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    progress.set_quiet(args.quiet)
    try:
        return int(module.run(args) or 0)
    except DranError as exc:
        print(f"dran-edge {ns.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"dran-edge {ns.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
