#!/usr/bin/env python3
"""Perception on this machine against recorded observations: what re-detection changes.

    .venv/bin/python tools/redetect_diff.py [RUN_WITH_FRAMES] [--recorded RUN]

Runs the perception pipeline on RUN_WITH_FRAMES's frames (default: the tiny golden mission,
simulated here with rendered frames) and compares, per robot, with the observations recorded in
``--recorded``'s ingest.bin (default: tests/data/golden/tiny_run, recorded on x86-64):
observations matched by (stamp, object id), observations found on one side only, and the
largest pose difference of a matched observation (translation, rotation). Used by
tests/test_replay.py's re-detection tolerance test and printed by tools/arm64_check.sh.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
GOLDEN_RUN = ROOT / "tests" / "data" / "golden" / "tiny_run"


def observations(data: bytes) -> dict[tuple[int, int], np.ndarray]:
    """(stamp_ns, object_id) -> T_body_object of every observation record in ingest bytes."""
    from dran_edge.events import ObservationBatch
    from dran_edge.replay.robots import decode_ingest

    events, _ = decode_ingest(data, "observations")
    return {(o.stamp_ns, o.object_id): o.T_body_object for ev in events
            if isinstance(ev, ObservationBatch) for o in ev.observations}


def compare(recorded: dict, here: dict) -> dict:
    """Matched / one-side counts and the largest pose differences of matched observations."""
    from dran_edge import geometry as geo

    common = sorted(set(recorded) & set(here))
    dt, dr = [0.0], [0.0]
    for k in common:
        d = np.linalg.inv(recorded[k]) @ here[k]
        dt.append(float(np.linalg.norm(d[:3, 3])))
        dr.append(float(np.degrees(np.linalg.norm(geo.so3_log(d[:3, :3])))))
    return {"recorded": len(recorded), "here": len(here), "matched": len(common),
            "only_recorded": len(set(recorded) - set(here)),
            "only_here": len(set(here) - set(recorded)),
            "max_translation_m": max(dt), "max_rotation_deg": max(dr)}


def redetect(run: Path, name: str) -> dict:
    from dran_edge.comms.ingest import encode_event
    from dran_edge.perception.recorded import perceive_frames

    d = run / "robots" / name
    batches, _ = perceive_frames(d / "robot.yaml", run / "calib", name)
    return observations(b"".join(encode_event(b) for b in batches))


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
            sys.path.insert(0, str(ROOT / "tools"))
            import regen_golden

            run = regen_golden.simulate_tiny(Path(tmp))
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
