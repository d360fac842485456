"""Tag observations of a replay: recorded ones, or perception re-run on the recorded frames.

Which robots use which (:func:`observation_sources`), and :class:`WindowedPerception`: the
recorded frames through the perception pipeline in worker processes, window by window of
mission time (``PERCEPTION_WINDOW_S``), ahead of the replay's rounds. A window's observations
are handed over, encoded as ingest records, just before the rounds reach its start, in the same
order whatever the timing, so the output does not depend on the number of workers.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import Future, ProcessPoolExecutor

from dran_edge.errors import InputError
from dran_edge.events import ObservationBatch
from dran_edge.formats import run_dir as rd

#: Perception runs in windows of this much mission time, so the rounds can start before all
#: frames are processed (the window's results are needed only once the rounds reach it).
PERCEPTION_WINDOW_S = 15.0


#: Where a robot's tag observations come from in a replay (report.json ``observation_sources``).
OBSERVATION_SOURCES = ("recorded", "redetected", "none")


def observation_sources(run: rd.Run, redetect: bool = False) -> dict[str, str]:
    """Per robot name: ``recorded`` (its ingest.bin holds observation records: replay uses
    them), ``redetected`` (perception runs on its frames: it has frames and either no recorded
    observations or ``redetect``), or ``none``."""
    from dran_edge.replay.robots import decode_ingest

    out: dict[str, str] = {}
    for info in run.mission.robots:
        cfg = run.load_config(info.name)
        has_frames = cfg.camera.source == "recorded" and run.frames_dir(info.name) is not None
        events, _ = decode_ingest(run.read_ingest(info.name), str(run.ingest_path(info.name)))
        has_recorded = any(isinstance(ev, ObservationBatch) for ev in events)
        if redetect and has_recorded and not has_frames:
            raise InputError(
                f"--redetect: robot {info.name} has recorded observations but no "
                "frames to detect them again from",
                path=str(run.robot_dir(info.name)),
            )
        if has_frames and (redetect or not has_recorded):
            out[info.name] = "redetected"
        else:
            out[info.name] = "recorded" if has_recorded else "none"
    return out


def perceive_window(args: tuple[str, str, str, int, int]) -> tuple[str, int, list[bytes], int]:
    """One robot's frames with stamps in [lo, hi) -> observation batches as ingest records."""
    config_path, calib_dir, name, lo, hi = args
    from dran_edge.blas import set_blas_threads

    from dran_edge.comms.ingest import encode_event
    from dran_edge.perception.recorded import perceive_frames

    set_blas_threads(1)  # one perception process per core already
    batches, frames = perceive_frames(config_path, calib_dir, name, lo, hi)
    return name, lo, [encode_event(b) for b in batches], frames


class WindowedPerception:
    """Recorded frames through the pipeline in worker processes, window by window, ahead of
    the rounds; ``ready_until(t)`` hands over every window that starts at or before ``t``."""

    def __init__(
        self, run: rd.Run, workers: int | None, start_ns: int, end_ns: int, sources: dict[str, str]
    ):
        self.jobs: list[tuple[str, str, str, int, int]] = []
        self.frames: dict[str, int] = {}
        step = int(PERCEPTION_WINDOW_S * 1e9)
        robots: list[tuple[str, str, str]] = []
        for info in run.mission.robots:
            cfg = run.load_config(info.name)
            if sources[info.name] != "redetected":
                continue
            calib = cfg.resolve(cfg.camera.calib_dir) or run.calib_dir
            robots.append((str(run.config_path(info.name)), str(calib), info.name))
            self.frames[info.name] = 0
        # windows cover every possible stamp: (-inf, start + step), ..., [.., +inf)
        edges = list(range(start_ns + step, end_ns, step))
        bounds = list(zip([0] + edges, edges + [2**63 - 1]))
        for lo, hi in bounds:
            for r in robots:
                self.jobs.append((*r, lo, hi))
        self.pool: ProcessPoolExecutor | None = None
        self.futures: list[Future[tuple[str, int, list[bytes], int]]] = []
        self.next = 0
        self.t0 = time.perf_counter()
        self.done_s = 0.0
        self.wait_s = 0.0
        if self.jobs:
            n_workers = max(1, min(len(robots), workers or os.cpu_count() or 1))
            self.pool = ProcessPoolExecutor(max_workers=n_workers)
            self.futures = [self.pool.submit(perceive_window, job) for job in self.jobs]

    def ready_until(self, t_ns: int) -> dict[str, bytes]:
        """Records of the windows starting at or before ``t_ns`` not handed over yet."""
        out: dict[str, list[bytes]] = {}
        while self.next < len(self.jobs) and self.jobs[self.next][3] <= t_ns:
            w0 = time.perf_counter()
            name, _lo, records, frames = self.futures[self.next].result()
            self.wait_s += time.perf_counter() - w0
            self.frames[name] += frames
            out.setdefault(name, []).extend(records)
            self.next += 1
            if self.next == len(self.jobs):
                self.done_s = time.perf_counter() - self.t0
        return {name: b"".join(recs) for name, recs in out.items()}

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)
