"""Helpers for tests that run the daemon as a real process (sd_notify listener, configs)."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import yaml

from dran_edge.daemon.notify import environ_without_systemd
from dran_edge.daemon.status import query_status


def feed_and_drain(d, events, max_ticks: int = 200) -> None:
    """Send ``events`` through the daemon's real ingest socket, tick until all are applied."""
    from dran_edge.comms.ingest import encode_event

    with socket.socket(socket.AF_UNIX) as s:
        s.connect(str(d.ingest.path))
        s.sendall(b"".join(encode_event(e) for e in events))
    for _ in range(max_ticks):
        d.tick()
        if d.ingest.counters.records == len(events) and d.journal.pending_count == 0:
            break


def write_config(tmp: Path, **overrides) -> Path:
    """A robot config with everything under ``tmp`` (no camera, no radio)."""
    cfg = {
        "robot": {"id": 1, "name": "testbot", "fleet": "testfleet"},
        "comms": {"transport": "none", "period_s": 0.2},
        "ingest": {"enabled": True, "socket_path": str(tmp / "run" / "ingest.sock")},
        "camera": {"source": "none"},
        "daemon": {
            "state_dir": str(tmp / "state"),
            "runtime_dir": str(tmp / "run"),
            "checkpoint_period_s": 30.0,
            "status_period_s": 0.5,
        },
        "agent": {"graph": {"max_nodes": 120, "max_edges": 480}},
    }
    for section, values in overrides.items():
        cfg.setdefault(section, {}).update(values)
    path = tmp / "robot.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


class NotifyListener:
    """The systemd side of sd_notify: a datagram socket collecting (monotonic time, message)."""

    def __init__(self, path: Path):
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.1)
        self.messages: list[tuple[float, str]] = []

    def collect(self, seconds: float, until: str | None = None) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                data = self.sock.recv(4096)
            except socket.timeout:
                continue
            msg = data.decode()
            self.messages.append((time.monotonic(), msg))
            if until is not None and until in msg:
                return

    def times(self, needle: str) -> list[float]:
        return [t for t, m in self.messages if needle in m]

    def close(self) -> None:
        self.sock.close()


def start_daemon(config: Path, env_extra: dict, cwd: Path | None = None) -> subprocess.Popen:
    env = environ_without_systemd()
    env.update(env_extra)
    return subprocess.Popen(
        [sys.executable, "-m", "dran_edge.cli.app", "-v", "run", "--config", str(config)],
        env=env,
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )


def wait_status(path: Path, predicate, timeout_s: float = 60.0, proc=None) -> dict:
    end = time.monotonic() + timeout_s
    last = None
    while time.monotonic() < end:
        if proc is not None and proc.poll() is not None:
            raise AssertionError(
                f"daemon exited early ({proc.returncode}):\n"
                + proc.stdout.read().decode(errors="replace")
            )
        try:
            last = query_status(path)
            if predicate(last):
                return last
        except Exception:
            pass
        time.sleep(0.1)
    raise AssertionError(f"status never satisfied the condition; last: {last}")


def stop(proc: subprocess.Popen, sig=signal.SIGTERM, timeout_s: float = 30.0) -> tuple[int, str]:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return proc.returncode, out.decode(errors="replace")
