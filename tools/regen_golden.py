#!/usr/bin/env python3
"""Regenerate the golden summary of the tiny replay (tests/data/golden/tiny_replay.json).

Run this only when a change to the simulator, the perception pipeline, the agent or the replay
is *meant* to change the numbers; review the diff it prints before committing. The test
(tests/test_replay.py) never rewrites the golden file.

    .venv/bin/python tools/regen_golden.py [--check]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "data" / "golden" / "tiny_replay.json"


def tiny_run(directory: Path) -> dict:
    """Simulate the tiny mission into ``directory`` and replay it; returns the report."""
    from dran_edge.replay.run import ReplayOptions, replay_run
    from dran_edge.sim.writer import write_run
    from dran_edge.sim.mission import SimParams, generate_mission

    params = SimParams(**json.loads(GOLDEN.with_suffix(".params.json").read_text()))
    write_run(generate_mission(params), directory / "run", frames="render", workers=1)
    return replay_run(directory / "run", ReplayOptions(workers=1, settle_rounds=10)).report


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="compare only; do not write")
    args = ap.parse_args(argv)
    from dran_edge.replay.run import compare_summary, golden_summary

    with tempfile.TemporaryDirectory() as tmp:
        summary = golden_summary(tiny_run(Path(tmp)))
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
