"""A robot's wall clock stepped alone: libfaketime preloaded into its daemon (docs/rehearsal.md).

The daemon paces its rounds on the monotonic clock, which is not faked
(``FAKETIME_DONT_FAKE_MONOTONIC``); its wall clock (message stamps, "last heard") reads the
real one plus the offset in a file the rehearsal rewrites at the step (re-read every second).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from dran_edge.rehearsal.robot_daemon import RobotDaemon


def clock_env(d: RobotDaemon) -> dict:
    """libfaketime for a robot whose wall clock the faults may step (docs/rehearsal.md)."""
    if not d.faketime_lib:
        return {}
    return {
        "LD_PRELOAD": d.faketime_lib,
        "FAKETIME_TIMESTAMP_FILE": str(d.state_dir.parent / "faketime"),
        "FAKETIME_CACHE_DURATION": "1",
        "FAKETIME_DONT_FAKE_MONOTONIC": "1",
        "FAKETIME_FORCE_MONOTONIC_FIX": "1",
    }


FAKETIME_PATHS = (
    "/usr/lib/x86_64-linux-gnu/faketime/libfaketime.so.1",
    "/usr/lib/aarch64-linux-gnu/faketime/libfaketime.so.1",
    "/usr/lib/faketime/libfaketime.so.1",
    "/usr/local/lib/faketime/libfaketime.so.1",
)


def find_faketime() -> str | None:
    return next((p for p in FAKETIME_PATHS if Path(p).exists()), None)


def clock_step(d: RobotDaemon, step_s: float) -> dict:
    if not d.faketime_lib:
        return {
            "by": "skipped",
            "reason": "libfaketime is not installed (a robot's wall clock "
            "cannot be stepped alone without it)",
        }
    d.clock_offset_s += step_s
    write_faketime(d)
    return {"by": "libfaketime", "offset_s": d.clock_offset_s}


def write_faketime(d: RobotDaemon) -> None:
    path = d.state_dir.parent / "faketime"
    tmp = path.with_name("faketime.tmp")
    tmp.write_text(f"{d.clock_offset_s:+.3f}\n")
    os.replace(tmp, path)
