#!/usr/bin/env python3
"""Perception on this machine against recorded observations: what re-detection changes.

    .venv/bin/python tools/redetect_diff.py [RUN_WITH_FRAMES] [--recorded RUN]

Runs the perception pipeline on RUN_WITH_FRAMES's frames (default: the tiny golden mission,
simulated here with rendered frames) and compares, per robot, with the observations recorded in
``--recorded``'s ingest.bin (default: tests/data/golden/tiny_run, recorded on x86-64):
observations matched by (stamp, object id), observations found on one side only, and the
largest pose difference of a matched observation (translation, rotation). Printed by
tools/arm64_check.sh; the comparison itself lives in tests/golden_helpers.py, which
tests/test_replay.py's re-detection tolerance test uses.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from golden_helpers import (  # noqa: E402
    GOLDEN_RUN,
    compare,
    observations,
    redetect,
    simulate_tiny,
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", nargs="?", help="a run with frames (default: simulate the tiny one)")
    ap.add_argument("--recorded", default=str(GOLDEN_RUN), help="run with recorded observations")
    args = ap.parse_args(argv)
    recorded_run = Path(args.recorded)
    with tempfile.TemporaryDirectory() as tmp:
        if args.run:
            run = Path(args.run)
        else:
            run = simulate_tiny(Path(tmp))
        total: dict = {}
        for robot in sorted(p.name for p in (recorded_run / "robots").iterdir()):
            rec = observations((recorded_run / "robots" / robot / "ingest.bin").read_bytes())
            stats = compare(rec, redetect(run, robot))
            print(robot, json.dumps(stats))
            for k, v in stats.items():
                total[k] = max(total.get(k, 0), v) if k.startswith("max_") else total.get(k, 0) + v
        print("all", json.dumps(total))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
