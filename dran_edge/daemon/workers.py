"""The daemon's worker plumbing: a bounded drop-oldest queue between threads and the thread
that turns camera frames into observation batches."""

from __future__ import annotations

import collections
import logging
import threading
from typing import Any, Callable

from dran_edge.events import ObservationBatch

log = logging.getLogger(__name__)


class DropOldestQueue:
    """A bounded FIFO between threads: when full, the oldest item is dropped and counted."""

    def __init__(self, maxlen: int):
        self._q: collections.deque = collections.deque()
        self.maxlen = maxlen
        self.dropped = 0
        self.put_count = 0
        self._cv = threading.Condition()

    def put(self, item: Any) -> None:
        with self._cv:
            if len(self._q) >= self.maxlen:
                self._q.popleft()
                self.dropped += 1
            self._q.append(item)
            self.put_count += 1
            self._cv.notify()

    def get(self, timeout_s: float) -> Any:
        """The oldest item, or None after ``timeout_s``."""
        with self._cv:
            if not self._q:
                self._cv.wait(timeout_s)
            return self._q.popleft() if self._q else None

    def drain(self) -> list:
        with self._cv:
            items = list(self._q)
            self._q.clear()
            return items

    def __len__(self) -> int:
        with self._cv:
            return len(self._q)


class PerceptionWorker:
    """Runs ``produce()`` (frame -> ObservationBatch or None) in a thread into a drop-oldest queue."""

    def __init__(self, produce: Callable[[], ObservationBatch | None], out: DropOldestQueue):
        self.produce = produce
        self.out = out
        self.errors = 0
        self.batches = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="perception", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                batch = self.produce()
            except StopIteration:
                log.info("perception: frame source ended")
                return
            except Exception:
                self.errors += 1
                log.exception("perception: a frame failed; continuing")
                self._stop.wait(0.1)
                continue
            if batch is not None:
                self.batches += 1
                self.out.put(batch)
