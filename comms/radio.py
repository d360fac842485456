"""ZeroMQ UDP RADIO/DISH transport between robots (docs/wire-format.md, docs/zeromq.md).

Each robot binds one DISH (``udp://*:PORT`` or its WiFi address) joined to the fleet's group,
and opens one RADIO per configured neighbour, ``connect`` ed to that neighbour's DISH by
unicast (802.11 multicast is slow and unacknowledged; a UDP RADIO sends every message to
every endpoint it is connected to, hence one RADIO per neighbour).

Safety rules this module enforces:

- RADIO/DISH is a libzmq *draft* API. If the installed pyzmq lacks it, constructing the
  transport raises ``DependencyError`` with one line saying how to get it
  (``tools/build_zmq_draft.sh``); there is no silent fallback.
- Released libzmq (<= 4.3.5) aborts on hostile datagrams; the project's build carries a fix
  (``tools/patches/libzmq-udp-engine-hardening.patch``) and leaves a stamp next to it. By
  default (``require_hardened_libzmq``) a libzmq without that stamp is refused too.
- Nothing over ``max_datagram_bytes`` (<= ``codec.HARD_CAP_BYTES``, far below libzmq's
  8192-byte UDP buffer) is ever handed to libzmq, and longer received datagrams are dropped.
- Group names are 1..15 printable ASCII characters (the limit of libzmq <= 4.3.2 peers).

pyzmq is imported lazily, only when a ``RadioTransport`` is built.
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, field
from typing import Mapping

from dran_edge.comms.codec import HARD_CAP_BYTES
from dran_edge.comms.counters import CommCounters
from dran_edge.errors import ConfigError, DependencyError

log = logging.getLogger(__name__)

GROUP_MAX_CHARS = 15
STAMP_NAME = ".dran-stamp"
_ENDPOINT_RE = re.compile(r"^udp://(\*|\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+):([0-9]{1,5})$")

_BUILD_HINT = "run tools/build_zmq_draft.sh .venv (see docs/zeromq.md)"


def require_draft_zmq():
    """Import pyzmq and check that RADIO/DISH are usable; ``DependencyError`` otherwise."""
    try:
        import zmq
    except ImportError:
        raise DependencyError(
            f"UDP transport needs pyzmq, which is not installed; {_BUILD_HINT}"
        ) from None
    if not (zmq.has("draft") and getattr(zmq, "DRAFT_API", False) and hasattr(zmq, "RADIO")):
        raise DependencyError(
            f"UDP transport needs ZeroMQ RADIO/DISH (draft API), but pyzmq {zmq.__version__} / "
            f"libzmq {zmq.zmq_version()} was built without drafts; {_BUILD_HINT}"
        )
    return zmq


def loaded_libzmq_path() -> str | None:
    """Path of the libzmq shared object mapped into this process (Linux), else None."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as f:
            for line in f:
                path = line.rstrip("\n").split(" ", 5)[-1].strip()
                if "/libzmq" in path and ".so" in path:
                    return path
    except OSError:
        return None
    return None


def hardened_libzmq_stamp() -> str | None:
    """The build stamp of the loaded libzmq if it is the project's patched build, else None."""
    path = loaded_libzmq_path()
    if path is None:
        return None
    stamp = os.path.join(os.path.dirname(os.path.dirname(path)), STAMP_NAME)
    try:
        with open(stamp, encoding="utf-8") as f:
            text = f.read().strip()
    except OSError:
        return None
    return text if "patch=" in text else None


def _check_endpoint(endpoint: str, what: str, *, allow_wildcard: bool) -> str:
    m = _ENDPOINT_RE.match(endpoint)
    if not m or not 0 < int(m.group(2)) < 65536 or (m.group(1) == "*" and not allow_wildcard):
        raise ConfigError(
            f"{what}: expected 'udp://HOST:PORT'{' or udp://*:PORT' if allow_wildcard else ''}"
            f", got {endpoint!r}"
        )
    return endpoint


def check_group(group: str) -> str:
    if not (1 <= len(group) <= GROUP_MAX_CHARS and group.isascii() and group.isprintable()):
        raise ConfigError(
            f"fleet group must be 1..{GROUP_MAX_CHARS} printable ASCII characters, got {group!r}"
        )
    return group


@dataclass(frozen=True)
class RadioParams:
    """Sockets of one robot."""

    #: ZeroMQ group = the fleet name, 1..15 printable ASCII characters.
    group: str
    #: This robot's DISH endpoint, e.g. ``udp://*:5670`` or ``udp://192.168.1.21:5670``.
    bind: str
    #: Neighbour robot id -> its DISH endpoint ``udp://IP:PORT`` (unicast).
    neighbours: Mapping[int, str] = field(default_factory=dict)
    #: Largest datagram handed to or accepted from libzmq, bytes (<= codec.HARD_CAP_BYTES).
    max_datagram_bytes: int = HARD_CAP_BYTES
    #: libzmq queue limits in messages (beyond them a datagram is dropped, never blocks).
    send_hwm: int = 1000
    receive_hwm: int = 10000
    #: Refuse a libzmq that is not the project's hardened build (see module docstring).
    require_hardened_libzmq: bool = True

    def __post_init__(self):
        check_group(self.group)
        _check_endpoint(self.bind, "DISH bind endpoint", allow_wildcard=True)
        for rid, ep in self.neighbours.items():
            _check_endpoint(ep, f"neighbour {rid} endpoint", allow_wildcard=False)
        if not 1 <= self.max_datagram_bytes <= HARD_CAP_BYTES:
            raise ConfigError(
                f"max_datagram_bytes must be in [1, {HARD_CAP_BYTES}], "
                f"got {self.max_datagram_bytes}"
            )


class RadioTransport:
    """``transport.Transport`` over ZeroMQ UDP RADIO/DISH (unicast to each neighbour)."""

    def __init__(self, params: RadioParams, context=None):
        zmq = require_draft_zmq()
        if params.require_hardened_libzmq and hardened_libzmq_stamp() is None:
            raise DependencyError(
                f"libzmq at {loaded_libzmq_path() or '(unknown)'} is not the project's hardened "
                f"build (one malformed UDP datagram can abort this process); {_BUILD_HINT}"
            )
        self._zmq = zmq
        self.params = params
        self.counters = CommCounters()
        self._own_context = context is None
        self._ctx = zmq.Context() if context is None else context
        self._dish = None
        self._radios: dict = {}
        try:
            self._dish = self._ctx.socket(zmq.DISH)
            self._dish.setsockopt(zmq.IPV6, int("[" in params.bind))
            self._dish.setsockopt(zmq.RCVHWM, params.receive_hwm)
            self._dish.setsockopt(zmq.LINGER, 0)
            self._dish.bind(params.bind)
            self._dish.join(params.group)
            for rid, endpoint in params.neighbours.items():
                radio = self._ctx.socket(zmq.RADIO)
                radio.setsockopt(zmq.IPV6, int("[" in endpoint))
                radio.setsockopt(zmq.SNDHWM, params.send_hwm)
                radio.setsockopt(zmq.LINGER, 0)
                radio.connect(endpoint)
                self._radios[int(rid)] = radio
        except zmq.ZMQError as exc:
            self.close()
            raise ConfigError(f"cannot open RADIO/DISH sockets ({params.bind}): {exc}") from None
        log.info(
            "radio: DISH %s group %r, RADIO to %s",
            params.bind,
            params.group,
            dict(params.neighbours),
        )

    def send(self, to: int, data: bytes) -> bool:
        n = len(data)
        radio = self._radios.get(to)
        if radio is None:
            self.counters.dropped(to, n, "unknown_peer")
            return False
        if n > self.params.max_datagram_bytes:
            self.counters.dropped(to, n, "over_cap")
            return False
        try:
            radio.send(data, flags=self._zmq.NOBLOCK, group=self.params.group)
        except self._zmq.Again:
            self.counters.dropped(to, n, "send_queue_full")
            return False
        except self._zmq.ZMQError as exc:
            log.warning("radio: send to robot %s failed: %s", to, exc)
            self.counters.dropped(to, n, "send_error")
            return False
        self.counters.sent(to, n)
        return True

    def receive(self, max_datagrams: int | None = None) -> list[tuple[int | None, bytes]]:
        out: list[tuple[int | None, bytes]] = []
        zmq = self._zmq
        while max_datagrams is None or len(out) < max_datagrams:
            try:
                frame = self._dish.recv(flags=zmq.NOBLOCK, copy=False)
            except zmq.Again:
                break
            except zmq.ZMQError as exc:
                log.warning("radio: DISH receive failed: %s", exc)
                break
            data = frame.bytes
            if len(data) > self.params.max_datagram_bytes:
                self.counters.rejected(None, len(data), "over_cap")
                continue
            self.counters.received(None, len(data))
            out.append((None, data))
        return out

    def fileno(self) -> int:
        """A descriptor that becomes readable when datagrams may be waiting (for select/poll)."""
        return self._dish.getsockopt(self._zmq.FD)

    def wait(self, timeout_s: float) -> bool:
        """Block up to ``timeout_s`` for a datagram; True if one is waiting."""
        return bool(self._dish.poll(int(max(timeout_s, 0.0) * 1000), self._zmq.POLLIN))

    def close(self) -> None:
        for radio in self._radios.values():
            radio.close(0)
        self._radios = {}
        if self._dish is not None:
            self._dish.close(0)
            self._dish = None
        if self._own_context and self._ctx is not None:
            self._ctx.term()
            self._ctx = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
