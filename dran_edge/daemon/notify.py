"""systemd integration of the daemon: sd_notify and journald logging (systemd/README.md).

``Notifier`` sends ``READY=1``, ``WATCHDOG=1``, ``STATUS=...`` and ``STOPPING=1`` to the
datagram socket named by ``$NOTIFY_SOCKET``. It uses systemd-python's
``systemd.daemon.notify`` when that is importable, and otherwise a small implementation of
the same protocol (one ``AF_UNIX`` ``SOCK_DGRAM`` datagram per message; a leading ``@`` names
an abstract socket; see sd_notify(3)). Without ``$NOTIFY_SOCKET`` (not started by systemd) it
does nothing and logs that once.

The watchdog period comes from ``$WATCHDOG_USEC`` (honoured only when ``$WATCHDOG_PID`` is
unset or our pid, as sd_watchdog_enabled(3) specifies). The daemon pings at half that period,
and only after a fully handled tick, so a hung agent stops the pings and systemd restarts us.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


#: What systemd hands one service process (notify socket, watchdog, directories, socket
#: activation, journal): a daemon started by another process (rehearsal, tests) must not inherit
#: them from its parent.
SYSTEMD_SERVICE_ENV = (
    "NOTIFY_SOCKET",
    "WATCHDOG_USEC",
    "WATCHDOG_PID",
    "STATE_DIRECTORY",
    "RUNTIME_DIRECTORY",
    "INVOCATION_ID",
    "JOURNAL_STREAM",
    "LISTEN_FDS",
)


def environ_without_systemd(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """``environ`` (default: this process's) without :data:`SYSTEMD_SERVICE_ENV`: the
    environment for a ``dran-edge run`` child that is not itself a systemd service."""
    source = os.environ if environ is None else environ
    return {k: v for k, v in source.items() if k not in SYSTEMD_SERVICE_ENV}


def _own_notify(message: str, path: str) -> bool:
    addr = "\0" + path[1:] if path.startswith("@") else path
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
    try:
        sock.connect(addr)
        sock.sendall(message.encode("utf-8"))
        return True
    except OSError as exc:
        log.warning("sd_notify to %s failed: %s", path, exc)
        return False
    finally:
        sock.close()


class Notifier:
    """sd_notify for one process; a no-op (said once) without ``$NOTIFY_SOCKET``."""

    def __init__(self, environ: Mapping[str, str] | None = None, prefer_library: bool = True):
        env = os.environ if environ is None else environ
        self.socket_path = env.get("NOTIFY_SOCKET") or None
        self.watchdog_usec = 0
        usec = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        if usec and (not pid or pid == str(os.getpid())):
            try:
                self.watchdog_usec = max(0, int(usec))
            except ValueError:
                log.warning("ignoring WATCHDOG_USEC=%r: expected an integer", usec)
        self._library = None
        # libsystemd's sd_notify reads $NOTIFY_SOCKET from the process environment itself.
        if prefer_library and self.socket_path and env is os.environ:
            try:
                from systemd import daemon as sd_daemon  # type: ignore[attr-defined]

                self._library = sd_daemon
            except ImportError:
                self._library = None
        self.backend = (
            ("systemd-python" if self._library else "builtin") if self.socket_path else "none"
        )
        if not self.socket_path:
            log.info(
                "not started by systemd (no NOTIFY_SOCKET): readiness and watchdog "
                "notifications are off"
            )
        self.sent = 0

    @property
    def enabled(self) -> bool:
        return self.socket_path is not None

    @property
    def watchdog_interval_s(self) -> float | None:
        """How often to ping: half the watchdog timeout; None when there is no watchdog."""
        return self.watchdog_usec / 2e6 if self.watchdog_usec else None

    def notify(self, message: str) -> bool:
        if not self.socket_path:
            return False
        if self._library is not None:
            ok = bool(self._library.notify(message))
        else:
            ok = _own_notify(message, self.socket_path)
        self.sent += ok
        return ok

    def ready(self, status: str = "") -> bool:
        return self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self.notify("STATUS=" + text.replace("\n", " "))

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")


def setup_logging(level: int = logging.INFO, *, journal: bool | None = None) -> str:
    """Route the root logger to journald when under systemd and systemd-python is there.

    ``journal=None`` decides by ``$JOURNAL_STREAM`` / ``$INVOCATION_ID`` (set by systemd);
    returns ``"journald"`` or ``"stderr"``. stderr is captured by journald anyway; the handler
    adds structured fields (logger name, code location).
    """
    root = logging.getLogger()
    if journal is None:
        journal = bool(os.environ.get("JOURNAL_STREAM") or os.environ.get("INVOCATION_ID"))
    if journal:
        try:
            from systemd.journal import JournalHandler
        except ImportError:
            journal = False
        else:
            for h in list(root.handlers):
                root.removeHandler(h)
            root.addHandler(JournalHandler(SYSLOG_IDENTIFIER="dran-edge"))
            root.setLevel(level)
            return "journald"
    if not root.handlers:
        logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    root.setLevel(min(root.level or level, level))
    return "stderr"
