"""A robot's recorded frames through the perception pipeline, exactly as its daemon runs it.

Used where frames were recorded but the perception output is wanted: the simulator records what
the robot's perception would have journalled, and ``dran-edge replay --redetect`` detects again.
"""

from __future__ import annotations

from pathlib import Path

from dran_edge.config import load_config
from dran_edge.events import ObservationBatch


def perceive_frames(
    config_path: str | Path,
    calib_dir: str | Path,
    name: str,
    lo_ns: int = 0,
    hi_ns: int = 2**63 - 1,
) -> tuple[list[ObservationBatch], int]:
    """One robot's recorded frames with stamps in [lo_ns, hi_ns) through the perception
    pipeline -> (the observation batches that hold observations, frames read). Encoded as
    ingest records, these are what the daemon journals."""
    from dran_edge.perception.calib import load_calibration
    from dran_edge.perception.pipeline import ObservationPipeline
    from dran_edge.perception.sources import RecordedFramesSource

    cfg = load_config(config_path)
    pipeline = ObservationPipeline(load_calibration(calib_dir, name))
    batches, frames = [], 0
    source = RecordedFramesSource(cfg.resolve(cfg.camera.recording))
    source.rows = [row for row in source.rows if lo_ns <= row[0] < hi_ns]
    try:
        for frame in source:
            frames += 1
            batch = pipeline.process(frame)
            if batch.observations:
                batches.append(batch)
    finally:
        source.close()
    return batches, frames
