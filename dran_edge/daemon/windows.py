"""The link's replay windows on disk (docs/wire-format.md, "Acceptance rules").

Per sender the link keeps (boot epoch, highest sequence, bitmap); the daemon writes them to
``replay_windows.json`` after every tick that moved them (atomic and fsynced, like the
checkpoint) and restores them at start, so that a datagram captured before a restart (even a
kill -9) is not accepted again.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from dran_edge.daemon.checkpoint import atomic_write
from dran_edge.daemon.counters import DaemonCounters

log = logging.getLogger(__name__)

FILE_NAME = "replay_windows.json"


class ReplayWindows:
    """Saves and restores ``transport``'s replay windows (a transport without ``to_state`` /
    ``restore`` has none: both are then no-ops)."""

    def __init__(self, state_dir: Path, transport: Any, counters: DaemonCounters):
        self.path = Path(state_dir) / FILE_NAME
        self.transport = transport
        self.counters = counters
        self._saved: list | None = None

    def restore(self, saved: dict | None) -> None:
        """Windows back from the checkpoint ``saved`` and from the file (the newer of the two
        per sender wins: restoring only ever raises a window)."""
        restore = getattr(self.transport, "restore", None)
        if restore is None:
            return
        sources = [(saved or {}).get("transport")]
        try:
            sources.append(json.loads(self.path.read_text()))
        except FileNotFoundError:
            pass
        except (OSError, ValueError) as exc:
            log.error("ignoring %s: %s", self.path, exc)
        n = 0
        for state in sources:
            if isinstance(state, dict):
                try:
                    n += restore(state)
                except (TypeError, ValueError, IndexError) as exc:
                    log.error("ignoring saved replay windows: %s", exc)
        if n:
            log.info("replay windows restored for %d sender(s)", n)
        self._saved = self.rows()

    def rows(self) -> list | None:
        to_state = getattr(self.transport, "to_state", None)
        return None if to_state is None else to_state().get("windows")

    def save(self) -> None:
        """Write the windows when they moved since the last save."""
        rows = self.rows()
        if rows is None or rows == self._saved:
            return
        try:
            atomic_write(self.path, json.dumps({"windows": rows}).encode())
        except OSError:
            self.counters.window_save_errors += 1
            log.exception("could not save the replay windows")
            return
        self._saved = rows
        self.counters.window_saves += 1
