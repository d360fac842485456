"""The ingest socket: permissions, many clients, hostile input counted and survived."""

from __future__ import annotations

import os
import socket
import stat
import threading
import time

import numpy as np

from dran_edge.comms import ingest as I
from dran_edge.daemon.ingest_server import IngestServer, RateLimitedLog


def wait_for(pred, timeout_s=10.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.02)
    return False


def test_socket_mode_records_frames_and_garbage(tmp_path):
    got, frames = [], []
    lock = threading.Lock()

    def on_record(r):
        with lock:
            got.append(r)

    srv = IngestServer(tmp_path / "run" / "ingest.sock", on_record, frames.append, mode=0o660)
    srv.start()
    try:
        mode = stat.S_IMODE(os.stat(srv.path).st_mode)
        assert mode == 0o660, oct(mode)
        rng = np.random.default_rng(0)
        good = [I.pack_keyframe(10 + i, [i, 0, 0], [0, 0, 0, 1]) for i in range(50)]
        clients = [socket.socket(socket.AF_UNIX) for _ in range(3)]
        for c in clients:
            c.connect(str(srv.path))
        clients[0].sendall(b"".join(good[:25]))
        clients[1].sendall(bytes(rng.integers(0, 256, 5000, dtype=np.uint8)))  # noise
        clients[1].sendall(I.HEADER.pack(I.MAGIC, 1, 5, 0, 0xFFFFFFF0, 0))  # absurd length
        clients[2].sendall(I.pack_frame(77, b"\x01" * 100_000))
        clients[0].sendall(b"".join(good[25:]))
        assert wait_for(lambda: len(got) == 50 and len(frames) == 1)
        clients[2].sendall(good[0][:10])  # half a record, then hang up
        clients[2].close()
        assert wait_for(lambda: srv.rejected.get("truncated", 0) == 1)
        assert [r.raw for r in got] == good
        assert frames[0].event.payload == b"\x01" * 100_000
        assert srv.rejected["bad_magic"] >= 1 and srv.counters.rejected >= 2
        # still serving after all that
        with socket.socket(socket.AF_UNIX) as c:
            c.connect(str(srv.path))
            c.sendall(good[0])
        assert wait_for(lambda: len(got) == 51)
        for c in clients[:2]:
            c.close()
    finally:
        srv.stop()
    assert not srv.path.exists()


def test_stale_socket_replaced_and_non_socket_refused(tmp_path):
    path = tmp_path / "ingest.sock"
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(path))
    s.close()  # a stale socket file of a crashed daemon
    srv = IngestServer(path, lambda r: None)
    srv.stop()
    path.write_text("not a socket")
    try:
        IngestServer(path, lambda r: None)
    except Exception as exc:
        assert "not a socket" in str(exc)
    else:
        raise AssertionError("a regular file at the socket path must be refused")


def test_rate_limited_log(caplog):
    import logging

    log = logging.getLogger("test.ratelimit")
    rl = RateLimitedLog(log, period_s=3600)
    with caplog.at_level(logging.WARNING, logger="test.ratelimit"):
        for _ in range(100):
            rl.warning("bad_crc", "bad")
    assert len(caplog.records) == 1
