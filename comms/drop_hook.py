"""The transport's drop hook: datagram loss, partitions and silence where the network can't.

The daemon wraps its radio in :class:`DropHookTransport` only when the environment variable
``DRAN_EDGE_DROP_FILE`` names a file (``dran-edge rehearse`` sets it; a robot's service never
does). The file is JSON, rewritten atomically by the rehearsal whenever a fault starts or
ends (docs/rehearsal.md)::

    {"drop_to": {"2": 1.0, "3": 0.25}}

``drop_to[j]`` is the probability that a datagram this robot sends to robot ``j`` is lost.
A lost datagram is reported as sent, as a radio would: the sender cannot tell. The file is
re-read when its modification time changes (checked at most every ``RECHECK_S``); a missing
or unreadable file means no loss.
"""

from __future__ import annotations

import json
import logging
import os
import random
import time
from pathlib import Path

log = logging.getLogger(__name__)

ENV = "DRAN_EDGE_DROP_FILE"
RECHECK_S = 0.02


def read_rules(path: Path) -> dict[int, float]:
    """``{robot id: loss probability}`` of a drop file (empty when absent or unreadable)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return {int(k): min(1.0, max(0.0, float(v))) for k, v in data.get("drop_to", {}).items()}
    except (OSError, ValueError, AttributeError, TypeError):
        return {}


def write_rules(path: Path, drop_to: dict[int, float]) -> None:
    """Atomically replace the drop file (the daemon never sees a half-written one)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(
        json.dumps({"drop_to": {str(k): float(v) for k, v in drop_to.items() if v > 0}}),
        encoding="utf-8",
    )
    os.replace(tmp, path)


class DropHookTransport:
    """A comms transport (``send``/``receive``/``close``) that loses datagrams by the rules of
    a drop file; everything else goes to ``inner`` unchanged."""

    def __init__(self, inner, path: str | os.PathLike, seed: int = 0):
        self.inner = inner
        self.path = Path(path)
        self.rng = random.Random(seed)
        self.rules: dict[int, float] = {}
        self.dropped: dict[int, int] = {}
        self._mtime: int | None = None
        self._checked = float("-inf")

    def _refresh(self) -> None:
        now = time.monotonic()
        if now - self._checked < RECHECK_S:
            return
        self._checked = now
        try:
            mtime = self.path.stat().st_mtime_ns
        except OSError:
            mtime = None
        if mtime != self._mtime:
            self._mtime = mtime
            self.rules = read_rules(self.path) if mtime is not None else {}
            log.info("drop hook: losing datagrams to %s", self.rules or "nobody")

    def send(self, to: int, data: bytes) -> bool:
        self._refresh()
        p = self.rules.get(int(to), 0.0)
        if p > 0 and self.rng.random() < p:
            self.dropped[int(to)] = self.dropped.get(int(to), 0) + 1
            return True
        return self.inner.send(to, data)

    def receive(self, max_datagrams: int | None = None):
        return self.inner.receive(max_datagrams)

    def close(self) -> None:
        self.inner.close()

    def __getattr__(self, name: str):
        return getattr(self.inner, name)
