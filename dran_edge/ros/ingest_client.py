"""A reconnecting client of the daemon's ingest socket (docs/ingest.md) with a bounded queue.

Records are bytes already framed by :mod:`dran_edge.comms.ingest`; while the daemon is away up
to ``max_queue`` records wait (the oldest are dropped and counted). One background thread.
"""

from __future__ import annotations

import collections
import socket
import threading
import time
from collections.abc import Callable


class IngestClient:
    def __init__(
        self,
        path: str,
        max_queue: int = 20000,
        log: Callable[[str], None] | None = None,
        retry_s: float = 0.5,
    ):
        self.path, self.max_queue, self.retry_s = str(path), max_queue, retry_s
        self.log = log or (lambda _m: None)
        self.queue: collections.deque[bytes] = collections.deque()
        self.sent = self.dropped = 0
        self._cv = threading.Condition()
        self._stop = False
        self._sock: socket.socket | None = None
        self._thread = threading.Thread(target=self._run, name="ingest-client", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def put(self, record: bytes) -> None:
        with self._cv:
            if len(self.queue) >= self.max_queue:
                self.queue.popleft()
                self.dropped += 1
            self.queue.append(record)
            self._cv.notify()

    def flush(self, timeout_s: float = 2.0) -> bool:
        """Wait until the queue is empty (True) or ``timeout_s`` passed (False)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            with self._cv:
                if not self.queue:
                    return True
            time.sleep(0.01)
        return False

    def stop(self, flush_s: float = 2.0) -> None:
        self.flush(flush_s)
        with self._cv:
            self._stop = True
            self._cv.notify()
        self._thread.join(timeout=2.0)
        if self._sock is not None:
            self._sock.close()

    def _connect(self) -> bool:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            s.connect(self.path)
        except OSError as exc:
            s.close()
            self.log(f"ingest socket {self.path}: {exc.strerror or exc}; retrying")
            return False
        self._sock = s
        self.log(f"connected to {self.path}")
        return True

    def _run(self) -> None:
        while True:
            with self._cv:
                while not self.queue and not self._stop:
                    self._cv.wait(0.5)
                if self._stop:
                    return
                rec = self.queue[0]
            if self._sock is None and not self._connect():
                time.sleep(self.retry_s)
                continue
            sock = self._sock
            assert sock is not None  # connected just above
            try:
                sock.sendall(rec)
            except OSError:
                sock.close()
                self._sock = None
                continue
            with self._cv:
                if self.queue and self.queue[0] is rec:
                    self.queue.popleft()
                self.sent += 1
