"""The ingest journal: every accepted input record on disk before the agent sees it.

Crash safety of the daemon rests on two files in the StateDirectory: the atomic checkpoint
(:mod:`dran_edge.daemon.checkpoint`) and this append-only journal of ingest records (the framed bytes
of :mod:`dran_edge.comms.ingest`). A record is *accepted* once it is written here; the agent
applies records in journal order; a checkpoint stores the journal position up to which the
agent has applied them. After a crash the daemon loads the checkpoint and re-applies the
journal from that position, so no accepted keyframe, loop or observation is lost.

Layout: ``<dir>/journal/<segment:08d>.bin``. Each daemon start opens a fresh segment (a torn
tail of a crashed segment is then only ever read, never appended to); segments also rotate at
``segment_max_bytes``. Segments wholly before the checkpointed position are deleted after the
checkpoint is durable. Writes go straight to the kernel (``os.write``), so a kill -9 loses
nothing written; :meth:`IngestJournal.sync` (each tick) makes them durable across power loss.
"""

from __future__ import annotations

import logging
import os
import threading
from collections import deque
from pathlib import Path

from dran_edge.comms.ingest import IngestDecodeError, Record, StreamDecoder

log = logging.getLogger(__name__)

Position = tuple[int, int]  # (segment, byte offset after the record)


class IngestJournal:
    """Thread-safe append-only journal with an in-memory queue of records not yet applied."""

    def __init__(self, directory: str | Path, segment_max_bytes: int = 64 * 1024 * 1024):
        self.directory = Path(directory) / "journal"
        self.directory.mkdir(parents=True, exist_ok=True)
        self.segment_max_bytes = segment_max_bytes
        self._lock = threading.Lock()
        self._pending: deque[tuple[Record, Position]] = deque()
        existing = self.segments()
        self.segment = (existing[-1] + 1) if existing else 0
        self.offset = 0
        self._fd = self._open(self.segment)
        self.appended = 0
        self.torn_tails = 0

    def _path(self, segment: int) -> Path:
        return self.directory / f"{segment:08d}.bin"

    def _open(self, segment: int) -> int:
        return os.open(
            self._path(segment), os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC, 0o640
        )

    def segments(self) -> list[int]:
        out = []
        for p in self.directory.glob("*.bin"):
            try:
                out.append(int(p.stem))
            except ValueError:
                continue
        return sorted(out)

    @property
    def position(self) -> Position:
        with self._lock:
            return (self.segment, self.offset)

    def append(self, record: Record) -> Position:
        """Write one record and queue it for the agent; returns the position after it."""
        with self._lock:
            if self.offset and self.offset + len(record.raw) > self.segment_max_bytes:
                os.close(self._fd)
                self.segment += 1
                self.offset = 0
                self._fd = self._open(self.segment)
            view = memoryview(record.raw)
            while view:
                n = os.write(self._fd, view)
                view = view[n:]
            self.offset += len(record.raw)
            pos = (self.segment, self.offset)
            self._pending.append((record, pos))
            self.appended += 1
            return pos

    def take_pending(self, limit: int | None = None) -> list[tuple[Record, Position]]:
        """Records appended and not yet taken, in journal order."""
        with self._lock:
            n = len(self._pending) if limit is None else min(limit, len(self._pending))
            return [self._pending.popleft() for _ in range(n)]

    @property
    def pending_count(self) -> int:
        with self._lock:
            return len(self._pending)

    def sync(self) -> None:
        with self._lock:
            os.fsync(self._fd)

    def read_after(self, position: Position | None) -> list[tuple[Record, Position]]:
        """Records of earlier segments after ``position`` (None: all), for recovery at start."""
        start_seg, start_off = position if position is not None else (-1, 0)
        out: list[tuple[Record, Position]] = []
        for seg in self.segments():
            if seg < start_seg or seg >= self.segment:
                continue
            data = self._path(seg).read_bytes()
            dec = StreamDecoder()
            offset = 0
            for item in dec.feed(data):
                if isinstance(item, IngestDecodeError):
                    log.error("journal segment %d: skipping a bad record (%s)", seg, item.reason)
                    continue
                offset = data.index(item.raw, offset) + len(item.raw)
                if seg == start_seg and offset <= start_off:
                    continue
                out.append((item, (seg, offset)))
            if dec.pending_bytes:
                self.torn_tails += 1
                log.warning(
                    "journal segment %d ends in %d bytes of a torn record (ignored)",
                    seg,
                    dec.pending_bytes,
                )
        return out

    def requeue(self, items: list[tuple[Record, Position]]) -> None:
        """Put recovered records in front of the pending queue (start-up recovery)."""
        with self._lock:
            self._pending.extendleft(reversed(items))

    def prune(self, applied: Position) -> int:
        """Delete segments wholly before ``applied``'s segment; returns how many."""
        removed = 0
        for seg in self.segments():
            if seg < applied[0] and seg != self.segment:
                try:
                    self._path(seg).unlink()
                    removed += 1
                except FileNotFoundError:
                    pass
        return removed

    def close(self) -> None:
        with self._lock:
            if self._fd >= 0:
                os.fsync(self._fd)
                os.close(self._fd)
                self._fd = -1
