#!/usr/bin/env python3
"""Regenerate the golden replay (tests/data/golden/): the recorded tiny run and its summary.

- ``tests/data/golden/tiny_run/`` is a tiny 3-robot run *as robots record it*: each robot's
  ``ingest.bin`` holds its odometry, keyframes, loops and the tag observations its perception
  found (no frames). Replaying it needs no perception, so every architecture gets the same
  inputs, and the summary (floats to ``GOLDEN_SIGNIFICANT_DIGITS`` digits) is the same on
  each (tests/test_replay.py::test_matches_the_golden_summary compares it exactly).
- ``tests/data/golden/tiny_replay.json`` is the golden summary of that replay.

Run this only when a change to the simulator, the perception pipeline, the agent or the replay
is *meant* to change the numbers; review the diff it prints before committing. The tests never
rewrite these files. ``--resimulate`` rewrites the recorded run itself from the simulator (its
observations then come from this machine's perception: do it on x86-64, where it was made);
without it only the summary is recomputed from the stored run.

    .venv/bin/python tools/regen_golden.py [--check] [--resimulate]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
from golden_helpers import GOLDEN, replay_stored, simulate_tiny, store_recorded_run  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="compare only; do not write")
    ap.add_argument(
        "--resimulate",
        action="store_true",
        help="rewrite the recorded run from the simulator first",
    )
    args = ap.parse_args(argv)
    from dran_edge.replay.run import compare_summary, golden_summary

    with tempfile.TemporaryDirectory() as tmp:
        if args.resimulate and not args.check:
            store_recorded_run(simulate_tiny(Path(tmp)))
        summary = golden_summary(replay_stored(Path(tmp)))
    old = json.loads(GOLDEN.read_text()) if GOLDEN.exists() else None
    diffs = compare_summary(summary, old) if old is not None else ["(no golden file yet)"]
    for d in diffs:
        print(d)
    if args.check:
        return 1 if diffs else 0
    GOLDEN.parent.mkdir(parents=True, exist_ok=True)
    GOLDEN.write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    print(f"wrote {GOLDEN}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
