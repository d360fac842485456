"""The golden replay's tiny run (tests/data/golden/): where it lives, how it is simulated and
replayed, and what re-detecting its frames changes against the recorded observations.
tests/test_replay.py compares with it; tools/regen_golden.py rewrites it and
tools/redetect_diff.py prints the re-detection differences."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "data" / "golden" / "tiny_replay.json"
GOLDEN_RUN = ROOT / "tests" / "data" / "golden" / "tiny_run"
#: Replay options of the golden summary (and of the tests that compare with it).
SETTLE_ROUNDS = 10


def simulate_tiny(directory: Path) -> Path:
    """Simulate the tiny mission with rendered frames into ``directory/run``; returns it."""
    from dran_edge.sim.writer import write_run
    from dran_edge.sim.mission import SimParams, generate_mission

    params = SimParams(**json.loads(GOLDEN.with_suffix(".params.json").read_text()))
    return write_run(generate_mission(params), directory / "run", frames="render", workers=1)


def replay_tiny(run: Path, redetect: bool = False) -> dict:
    """Replay ``run`` with the golden options; returns the report."""
    from dran_edge.replay.run import ReplayOptions, replay_run

    opt = ReplayOptions(workers=1, settle_rounds=SETTLE_ROUNDS, redetect=redetect)
    return replay_run(run, opt).report


def tiny_run(directory: Path) -> dict:
    """Simulate the tiny mission into ``directory/run`` and replay it; returns the report."""
    return replay_tiny(simulate_tiny(directory))


def store_recorded_run(run: Path, dest: Path = GOLDEN_RUN) -> None:
    """Copy ``run`` to ``dest`` as robots record it: without frames and outputs."""
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(run, dest, ignore=shutil.ignore_patterns("frames", "out", "eval"))


def replay_stored(directory: Path, src: Path = GOLDEN_RUN) -> dict:
    """Replay a copy of the stored recorded run (the tests never write into tests/data)."""
    run = directory / "stored"
    shutil.copytree(src, run)
    return replay_tiny(run)


def observations(data: bytes) -> dict[tuple[int, int], np.ndarray]:
    """(stamp_ns, object_id) -> T_body_object of every observation record in ingest bytes."""
    from dran_edge.events import ObservationBatch
    from dran_edge.replay.robots import decode_ingest

    events, _ = decode_ingest(data, "observations")
    return {
        (o.stamp_ns, o.object_id): o.T_body_object
        for ev in events
        if isinstance(ev, ObservationBatch)
        for o in ev.observations
    }


def compare(recorded: dict, here: dict) -> dict:
    """Matched / one-side counts and the largest pose differences of matched observations."""
    from dran_edge import geometry as geo

    common = sorted(set(recorded) & set(here))
    dt, dr = [0.0], [0.0]
    for k in common:
        d = np.linalg.inv(recorded[k]) @ here[k]
        dt.append(float(np.linalg.norm(d[:3, 3])))
        dr.append(float(np.degrees(np.linalg.norm(geo.so3_log(d[:3, :3])))))
    return {
        "recorded": len(recorded),
        "here": len(here),
        "matched": len(common),
        "only_recorded": len(set(recorded) - set(here)),
        "only_here": len(set(here) - set(recorded)),
        "max_translation_m": max(dt),
        "max_rotation_deg": max(dr),
    }


def redetect(run: Path, name: str) -> dict:
    from dran_edge.comms.ingest import encode_event
    from dran_edge.perception.recorded import perceive_frames

    d = run / "robots" / name
    batches, _ = perceive_frames(d / "robot.yaml", run / "calib", name)
    return observations(b"".join(encode_event(b) for b in batches))
