"""The daemon's local ingest socket: a Unix-domain stream server for VIO records and frames.

The VINS bridge (``dran_edge/ros/vins_bridge.py``) connects and writes framed records
(:mod:`dran_edge.comms.ingest`, docs/ingest.md). Records are decoded strictly per connection;
a bad record is counted by reason, logged at most once per ``log_every_s`` per reason, and
dropped. Nothing a client sends can stop the server: decode problems are values, a client
that misbehaves at the socket level is disconnected, and the next one is accepted.

The socket lives in systemd's RuntimeDirectory (``/run/dran-edge/ingest.sock``) with mode
0660: the bridge's user must be in the daemon's group; other users cannot connect.
"""

from __future__ import annotations

import logging
import os
import selectors
import socket
import stat
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Callable

from dran_edge.comms.ingest import KIND_FRAME, IngestDecodeError, Record, StreamDecoder
from dran_edge.daemon.counters import IngestCounters
from dran_edge.errors import DranError

log = logging.getLogger(__name__)

MAX_CLIENTS = 8
RECV_BYTES = 256 * 1024


class RateLimitedLog:
    """Log a message per key at most once per ``period_s``, saying how many were suppressed."""

    def __init__(self, logger: logging.Logger, period_s: float = 10.0):
        self.logger = logger
        self.period_s = period_s
        self._last: dict[str, float] = {}
        self._suppressed: Counter = Counter()

    def warning(self, key: str, msg: str) -> None:
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self.period_s:
            self._suppressed[key] += 1
            return
        n = self._suppressed.pop(key, 0)
        self._last[key] = now
        self.logger.warning("%s%s", msg, f" ({n} more like it suppressed)" if n else "")


class IngestServer:
    """Accepts bridge connections and hands decoded records to ``on_record`` / ``on_frame``.

    Runs in its own thread (:meth:`start`); ``on_record`` is called from that thread for every
    good non-frame record, ``on_frame`` for forwarded frames (None: frames are counted and
    dropped). Counters (``counters``, an :class:`IngestCounters`) are plain ints safe to read
    from other threads.
    """

    def __init__(
        self,
        path: str | Path,
        on_record: Callable[[Record], object],
        on_frame: Callable[[Record], None] | None = None,
        mode: int = 0o660,
        log_every_s: float = 10.0,
    ):
        self.path = Path(path)
        self.on_record = on_record
        self.on_frame = on_frame
        self.counters = IngestCounters()
        self.rejected: Counter = Counter()
        self._ratelog = RateLimitedLog(log, log_every_s)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists() or self.path.is_symlink():
            if not stat.S_ISSOCK(self.path.lstat().st_mode):
                raise DranError(f"ingest socket path {self.path} exists and is not a socket")
            self.path.unlink()  # a stale socket of a previous run
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        old = os.umask(0o777 & ~mode)  # created with the right mode: no window where it is open
        try:
            self._sock.bind(str(self.path))
        finally:
            os.umask(old)
        os.chmod(self.path, mode)
        self._sock.listen(MAX_CLIENTS)
        self._sock.setblocking(False)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._sock, selectors.EVENT_READ, None)
        self._clients: dict[socket.socket, StreamDecoder] = {}

    # ------------------------------------------------------------------ thread
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="ingest", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        for c in list(self._clients):
            self._drop(c)
        self._sel.close()
        self._sock.close()
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.poll(0.2)
            except Exception:  # the server must outlive any bug in a handler
                self.counters.handler_errors += 1
                log.exception("ingest: unexpected error while handling input")

    # ------------------------------------------------------------------ work
    def poll(self, timeout_s: float) -> None:
        for key, _ in self._sel.select(timeout_s):
            if key.data is None:
                self._accept()
            else:
                self._read(key.fileobj)  # type: ignore[arg-type]

    def _accept(self) -> None:
        try:
            conn, _ = self._sock.accept()
        except (BlockingIOError, InterruptedError):
            return
        if len(self._clients) >= MAX_CLIENTS:
            self.counters.clients_refused += 1
            self._ratelog.warning("clients", f"ingest: refusing a client, {MAX_CLIENTS} connected")
            conn.close()
            return
        conn.setblocking(False)
        self._clients[conn] = StreamDecoder()
        self._sel.register(conn, selectors.EVENT_READ, "client")
        self.counters.clients_accepted += 1
        log.info("ingest: client connected (%d connected)", len(self._clients))

    def _drop(self, conn: socket.socket) -> None:
        dec = self._clients.pop(conn, None)
        if dec is not None and dec.pending_bytes:
            self._reject(
                IngestDecodeError(
                    "truncated", f"client left {dec.pending_bytes} bytes of an incomplete record"
                )
            )
        try:
            self._sel.unregister(conn)
        except (KeyError, ValueError):
            pass
        conn.close()

    def _read(self, conn: socket.socket) -> None:
        try:
            data = conn.recv(RECV_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            log.info("ingest: client error %s; disconnecting it", exc)
            data = b""
        if not data:
            self._drop(conn)
            log.info("ingest: client disconnected (%d connected)", len(self._clients))
            return
        self.counters.bytes += len(data)
        for item in self._clients[conn].feed(data):
            if isinstance(item, IngestDecodeError):
                self._reject(item)
            elif item.kind == KIND_FRAME:
                self.counters.frames += 1
                if self.on_frame is not None:
                    self.on_frame(item)
            else:
                self.counters.records += 1
                self.on_record(item)

    def _reject(self, err: IngestDecodeError) -> None:
        self.rejected[err.reason] += 1
        self.counters.rejected += 1
        self._ratelog.warning(err.reason, f"ingest: {err}")
