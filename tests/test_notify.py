"""sd_notify: the built-in datagram implementation and systemd-python speak the same protocol."""

from __future__ import annotations

import logging
import os
import socket
import uuid

import pytest

from dran_edge.daemon.notify import Notifier, setup_logging


@pytest.fixture
def listener(tmp_path):
    path = tmp_path / "notify.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(str(path))
    s.settimeout(2.0)
    yield path, s
    s.close()


@pytest.mark.parametrize("prefer_library", [False, True])
def test_messages_arrive(listener, prefer_library, monkeypatch):
    path, s = listener
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    n = Notifier(prefer_library=prefer_library)
    if prefer_library:
        pytest.importorskip("systemd.daemon")
        assert n.backend == "systemd-python"
    else:
        assert n.backend == "builtin"
    assert n.ready("starting up")
    assert s.recv(4096) == b"READY=1\nSTATUS=starting up"
    assert n.watchdog() and s.recv(4096) == b"WATCHDOG=1"
    assert n.status("a\nb") and s.recv(4096) == b"STATUS=a b"
    assert n.stopping() and s.recv(4096) == b"STOPPING=1"
    assert n.sent == 4


def test_abstract_socket_builtin():
    name = f"dran-edge-test-{uuid.uuid4().hex}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind("\0" + name)
    s.settimeout(2.0)
    try:
        n = Notifier({"NOTIFY_SOCKET": "@" + name}, prefer_library=False)
        assert n.ready()
        assert s.recv(100) == b"READY=1"
    finally:
        s.close()


def test_without_systemd_is_a_noop_said_once(caplog):
    with caplog.at_level(logging.INFO, logger="dran_edge.daemon.notify"):
        n = Notifier({})
    assert not n.enabled and n.backend == "none"
    assert not n.ready() and not n.watchdog()
    assert sum("not started by systemd" in r.message for r in caplog.records) == 1


def test_watchdog_interval_respects_pid():
    assert Notifier({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "3000000"}).watchdog_interval_s == 1.5
    other = str(os.getpid() + 1)
    n = Notifier({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "3000000", "WATCHDOG_PID": other})
    assert n.watchdog_interval_s is None
    mine = Notifier(
        {"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())}
    )
    assert mine.watchdog_interval_s == 1.0
    assert Notifier({"WATCHDOG_USEC": "bogus"}).watchdog_interval_s is None


def test_missing_socket_does_not_raise(tmp_path):
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "absent")}, prefer_library=False)
    assert n.ready() is False


def test_setup_logging_stderr_when_not_under_systemd(monkeypatch):
    monkeypatch.delenv("JOURNAL_STREAM", raising=False)
    monkeypatch.delenv("INVOCATION_ID", raising=False)
    assert setup_logging(logging.INFO) == "stderr"
