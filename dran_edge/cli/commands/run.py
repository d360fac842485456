"""``dran-edge run``: the robot daemon (what systemd's dran-edge.service starts)."""

from __future__ import annotations

import argparse
import logging
import signal

HELP = "run the robot daemon (ingest, bounded graph, DRAN rounds, neighbours)"


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        description=(
            "Run one robot's daemon: open the ingest socket for the VINS bridge, start the "
            "camera worker, run a DRAN round every comms.period_s and exchange with the "
            "configured neighbours. Under systemd (Type=notify) it reports READY=1 once its "
            "sockets and sensors are up, pings the watchdog after each fully handled round and "
            "keeps its checkpoint in $STATE_DIRECTORY. Stop it with SIGTERM or Ctrl-C."
        ),
    )
    p.add_argument(
        "--config",
        required=True,
        metavar="ROBOT.yaml",
        help="the robot's config file (docs/config.md)",
    )
    p.add_argument(
        "--record",
        metavar="DIR",
        help="also write the consumed inputs as a recorded run into DIR "
        "(robots/<name>/robot.yaml + ingest.bin, and mission.yaml at exit; "
        "docs/run-format.md)",
    )
    p.add_argument(
        "--max-rounds", type=int, default=None, metavar="N", help="stop after N rounds (testing)"
    )
    return p


def run(args: argparse.Namespace) -> int:
    import os

    # One BLAS thread: the round's matrices are small, and OpenBLAS worker threads spinning on a
    # shared CPU made the Schur step 30-70x slower here (docs/notes/benchmarks-history.md).
    # Must be set before numpy loads OpenBLAS, i.e. before the imports below.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    from dran_edge.config import load_config
    from dran_edge.daemon.service import Daemon
    from dran_edge.daemon.notify import setup_logging
    from dran_edge.errors import ConfigError

    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        raise ConfigError(
            f"{exc} (every problem at once: dran-edge check-config {args.config})"
        ) from None
    level = logging.getLogger().level or logging.INFO
    where = setup_logging(min(level, logging.INFO))
    logging.getLogger(__name__).info("logging to %s", where)
    daemon = Daemon(cfg, record_dir=args.record)

    def on_signal(signum, _frame):
        logging.getLogger(__name__).info("received %s: stopping", signal.Signals(signum).name)
        daemon.request_stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    daemon.start()
    daemon.run(max_ticks=args.max_rounds)
    return 0
