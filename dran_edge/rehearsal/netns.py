"""The rehearsal's network: one Linux network namespace per robot, or loopback addresses.

:class:`NamespaceNet` (root and ``ip`` needed; :func:`probe_namespaces` says whether they are
permitted here) builds, for a fleet of ``n`` robots::

    <prefix>hub        a namespace holding the bridge br0 (nothing in the host's namespace)
    <prefix>r<k>       robot k's namespace: lo + v0 (10.77.0.<k+1>/24), the veth whose other
                       end p<k> is a port of br0 in the hub

so each daemon has its own address and network stack, and datagrams between robots cross
real veth links and a real bridge. Faults on this network (docs/rehearsal.md):

- a partition moves the hub ports of one group onto a second bridge (br1): datagrams between
  the groups are dropped by the network, the senders see nothing (as over a radio);
- a silent robot has its hub port set down (its radio is off: it neither sends nor hears).

:class:`LoopbackNet` is the fallback where namespaces are not permitted: robot k binds
127.0.0.<k+10> on a free UDP port of that address, in the host's namespace (no network
faults there; the daemons' drop hook, :mod:`dran_edge.comms.drop_hook`, does them).

Namespaces are named with the creating process id (``dre<pid>-``); :meth:`NamespaceNet.close`
deletes them (and their veths with them), and :func:`sweep_stale` removes those of a process
that no longer runs (a rehearsal killed before it could clean up).
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import socket
import subprocess
from dataclasses import dataclass

from dran_edge.errors import DranError

log = logging.getLogger(__name__)

SUBNET = "10.77.0"
#: At most this many robots per rehearsal (addresses .1 ... .MAX_ROBOTS of one /24).
MAX_ROBOTS = 64
_PREFIX_RE = re.compile(r"^dre(\d+)-")


class NetError(DranError):
    """A namespace or link could not be set up."""


def _ip(*args: str, check: bool = True, timeout_s: float = 10.0) -> subprocess.CompletedProcess:
    cmd = ["ip", *args]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    if check and res.returncode != 0:
        raise NetError(f"'{' '.join(cmd)}' failed: {res.stderr.strip() or res.returncode}")
    return res


def probe_namespaces() -> tuple[bool, str]:
    """(True, "") if this process may create network namespaces and veth pairs; else (False,
    the reason). Creates and deletes one namespace with a veth pair inside."""
    if shutil.which("ip") is None:
        return False, "the 'ip' tool (iproute2) is not installed"
    if os.geteuid() != 0:
        return False, "creating network namespaces needs root (this process is not root)"
    name = f"dre{os.getpid()}-probe"
    try:
        _ip("netns", "add", name)
    except (NetError, OSError, subprocess.TimeoutExpired) as exc:
        return False, f"network namespaces are not permitted here ({exc})"
    try:
        _ip("-n", name, "link", "add", "a0", "type", "veth", "peer", "name", "b0")
        _ip("-n", name, "link", "add", "br0", "type", "bridge")
        return True, ""
    except (NetError, subprocess.TimeoutExpired) as exc:
        return False, f"veth pairs or bridges cannot be created in a namespace ({exc})"
    finally:
        _ip("netns", "del", name, check=False)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_stale() -> list[str]:
    """Delete the namespaces left by rehearsals whose process is gone; returns their names."""
    if shutil.which("ip") is None:
        return []
    res = _ip("netns", "list", check=False)
    gone = []
    for line in res.stdout.splitlines():
        name = line.split()[0] if line.split() else ""
        m = _PREFIX_RE.match(name)
        if m and int(m.group(1)) != os.getpid() and not _pid_alive(int(m.group(1))):
            _ip("netns", "del", name, check=False)
            gone.append(name)
    return gone


@dataclass(frozen=True)
class Endpoint:
    """Where one robot's daemon lives on the network."""

    address: str
    port: int
    netns: str | None
    """The robot's namespace, or None (host namespace, loopback)."""

    @property
    def dish(self) -> str:
        return f"{self.address}:{self.port}"


class LoopbackNet:
    """Robot k on 127.0.0.<k+10>, on a UDP port free on that address (host namespace)."""

    kind = "loopback"

    def __init__(self, n: int):
        if not 1 <= n <= MAX_ROBOTS:
            raise NetError(f"expected 1..{MAX_ROBOTS} robots, got {n}")
        self.endpoints = []
        for k in range(n):
            addr = f"127.0.0.{k + 10}"
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.bind((addr, 0))
                port = s.getsockname()[1]
            self.endpoints.append(Endpoint(addr, port, None))

    def wrap(self, k: int, argv: list[str]) -> list[str]:
        return list(argv)

    def partition(self, group: list[int]) -> bool:
        return False

    def heal(self) -> None:
        pass

    def silence(self, k: int, silent: bool) -> bool:
        return False

    def close(self) -> None:
        pass


class NamespaceNet:
    """One namespace per robot behind a bridge (see the module docstring). Use as a context
    manager or call :meth:`close`; every namespace it made is deleted."""

    kind = "netns"

    def __init__(self, n: int, port: int = 5600):
        if not 1 <= n <= MAX_ROBOTS:
            raise NetError(f"expected 1..{MAX_ROBOTS} robots, got {n}")
        self.prefix = f"dre{os.getpid()}-"
        self.hub = self.prefix + "hub"
        self.made: list[str] = []
        self.endpoints: list[Endpoint] = []
        self._isolated: list[int] = []
        try:
            self._add_ns(self.hub)
            for br in ("br0", "br1"):
                _ip("-n", self.hub, "link", "add", br, "type", "bridge")
                _ip("-n", self.hub, "link", "set", br, "up")
            for k in range(n):
                ns = f"{self.prefix}r{k}"
                self._add_ns(ns)
                addr = f"{SUBNET}.{k + 1}"
                _ip(
                    "-n",
                    ns,
                    "link",
                    "add",
                    "v0",
                    "type",
                    "veth",
                    "peer",
                    "name",
                    f"p{k}",
                    "netns",
                    self.hub,
                )
                _ip("-n", self.hub, "link", "set", f"p{k}", "master", "br0")
                _ip("-n", self.hub, "link", "set", f"p{k}", "up")
                _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", "v0")
                _ip("-n", ns, "link", "set", "v0", "up")
                _ip("-n", ns, "link", "set", "lo", "up")
                self.endpoints.append(Endpoint(addr, port, ns))
        except BaseException:
            self.close()
            raise

    def _add_ns(self, name: str) -> None:
        _ip("netns", "add", name)
        self.made.append(name)

    def wrap(self, k: int, argv: list[str]) -> list[str]:
        """``argv`` run inside robot k's namespace (``ip netns exec`` execs it: same pid)."""
        return ["ip", "netns", "exec", self.endpoints[k].netns or "", *argv]

    def partition(self, group: list[int]) -> bool:
        """Cut robots ``group`` (indices) off from the others: their ports go to br1."""
        for k in group:
            _ip("-n", self.hub, "link", "set", f"p{k}", "master", "br1")
        self._isolated = sorted(set(self._isolated) | set(group))
        return True

    def heal(self) -> None:
        for k in self._isolated:
            _ip("-n", self.hub, "link", "set", f"p{k}", "master", "br0")
        self._isolated = []

    def silence(self, k: int, silent: bool) -> bool:
        """Robot k's radio off (its hub port down) or on again."""
        _ip("-n", self.hub, "link", "set", f"p{k}", "down" if silent else "up")
        return True

    def close(self) -> None:
        for name in reversed(self.made):
            _ip("netns", "del", name, check=False)
        self.made = []

    def __enter__(self) -> NamespaceNet:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def make_net(n: int, mode: str = "auto") -> tuple[LoopbackNet | NamespaceNet, str]:
    """The rehearsal's network: ``netns``, ``loopback`` or ``auto`` (namespaces if permitted).
    Returns it and, when it fell back to loopback, why (else "")."""
    if mode not in ("auto", "netns", "loopback"):
        raise NetError(f"--net: expected auto, netns or loopback, got {mode!r}")
    if mode == "loopback":
        return LoopbackNet(n), "loopback asked for"
    ok, reason = probe_namespaces()
    if ok:
        sweep_stale()
        return NamespaceNet(n), ""
    if mode == "netns":
        raise NetError(f"--net netns: {reason}")
    log.warning("network namespaces unavailable (%s): robots on loopback addresses", reason)
    return LoopbackNet(n), reason
