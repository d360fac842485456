"""The one progress reporter of the command line.

Long work in the library reports through one signature, ``progress(stage, done, total)`` (a
:data:`Progress`): the simulator's rendering, replay's perception and rounds, the rehearsal's
mission seconds, the benchmarks' rounds. The CLI hands a :class:`ProgressBar` to each; a library
caller passes its own callable or None. Everything goes to stderr, so stdout stays the result
(a report, JSON) that scripts read.

Why not tqdm: on a robot the output lands in journald and CI logs, where a bar redrawn with
carriage returns is noise; this one redraws in place on a terminal and prints a plain line every
few seconds elsewhere, and costs no dependency on the robot.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``: ``done`` of ``total`` units of ``stage`` are finished."""

_quiet = False


def set_quiet(quiet: bool) -> None:
    """``dran-edge -q``: every ProgressBar and note of this process stays silent."""
    global _quiet
    _quiet = bool(quiet)


def is_quiet() -> bool:
    return _quiet


class ProgressBar:
    """A one-line progress bar on stderr (plain lines every few seconds when not a terminal)."""

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self._last = 0.0
        self._phase = None

    def __call__(self, phase: str, done: int, total: int) -> None:
        if _quiet:
            return
        now = time.monotonic()
        final = done >= total
        if phase == self._phase and not final and now - self._last < (0.1 if self.tty else 5.0):
            return
        self._phase, self._last = phase, now
        width = 30
        fill = int(width * done / max(total, 1))
        line = f"{phase:<11} [{'#' * fill}{'.' * (width - fill)}] {done}/{total}"
        if self.tty:
            print("\r" + line, end="\n" if final else "", file=self.stream, flush=True)
        else:
            print(line, file=self.stream, flush=True)


def note(message: str, stream=None) -> None:
    """One line of progress news on stderr (a stage that has no count, a milestone)."""
    if _quiet:
        return
    print(message, file=stream or sys.stderr, flush=True)
