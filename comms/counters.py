"""Traffic counters per neighbour and per message kind (health is data, docs/architecture.md).

Every transport owns one ``CommCounters``: datagrams and bytes sent / received / dropped,
per peer (robot id, or ``None`` when the sender is not known, e.g. a datagram that did not
parse) and per kind (``codec.KINDS``: header, separator, object, init), rejections by reason,
and the last time each peer was heard (caller-supplied nanoseconds; the counters own no
clock). ``snapshot()`` is a JSON-ready dict for the daemon's status and the benchmarks.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field


@dataclass
class PeerCounters:
    datagrams_sent: int = 0
    bytes_sent: int = 0
    datagrams_received: int = 0
    bytes_received: int = 0
    datagrams_rejected: int = 0
    bytes_rejected: int = 0
    datagrams_dropped: int = 0
    bytes_dropped: int = 0
    last_heard_ns: int | None = None
    sent_bytes_by_kind: dict = field(default_factory=lambda: defaultdict(int))
    received_bytes_by_kind: dict = field(default_factory=lambda: defaultdict(int))
    #: A datagram counts once under every entry kind it carries ("header" if it carries none).
    sent_datagrams_by_kind: dict = field(default_factory=lambda: defaultdict(int))
    received_datagrams_by_kind: dict = field(default_factory=lambda: defaultdict(int))
    rejected_by_reason: dict = field(default_factory=lambda: defaultdict(int))
    dropped_by_reason: dict = field(default_factory=lambda: defaultdict(int))


def _add_kinds(bytes_by_kind: dict, datagrams_by_kind: dict, by_kind: dict | None) -> None:
    if not by_kind:
        return
    carried = False
    for k, v in by_kind.items():
        bytes_by_kind[k] += v
        if v and k != "header":
            datagrams_by_kind[k] += 1
            carried = True
    if not carried:
        datagrams_by_kind["header"] += 1


class CommCounters:
    """Counts traffic; all methods are O(1) and never raise on unexpected values."""

    def __init__(self) -> None:
        self.peers: dict[int | None, PeerCounters] = defaultdict(PeerCounters)

    def sent(self, peer: int, nbytes: int, by_kind: dict | None = None) -> None:
        c = self.peers[peer]
        c.datagrams_sent += 1
        c.bytes_sent += nbytes
        _add_kinds(c.sent_bytes_by_kind, c.sent_datagrams_by_kind, by_kind)

    def dropped(self, peer: int | None, nbytes: int, reason: str) -> None:
        """A datagram we did not send or deliver (over cap, no link, lost on the bus)."""
        c = self.peers[peer]
        c.datagrams_dropped += 1
        c.bytes_dropped += nbytes
        c.dropped_by_reason[reason] += 1

    def received(
        self, peer: int, nbytes: int, by_kind: dict | None = None, now_ns: int | None = None
    ) -> None:
        c = self.peers[peer]
        c.datagrams_received += 1
        c.bytes_received += nbytes
        _add_kinds(c.received_bytes_by_kind, c.received_datagrams_by_kind, by_kind)
        if now_ns is not None:
            c.last_heard_ns = now_ns

    def rejected(self, peer: int | None, nbytes: int, reason: str) -> None:
        c = self.peers[peer]
        c.datagrams_rejected += 1
        c.bytes_rejected += nbytes
        c.rejected_by_reason[reason] += 1

    def totals(self) -> dict:
        keys = (
            "datagrams_sent",
            "bytes_sent",
            "datagrams_received",
            "bytes_received",
            "datagrams_rejected",
            "bytes_rejected",
            "datagrams_dropped",
            "bytes_dropped",
        )
        return {k: sum(getattr(c, k) for c in self.peers.values()) for k in keys}

    def snapshot(self) -> dict:
        """JSON-ready: {"totals": {...}, "peers": {"<id>"|"unknown": {...}}}."""
        peers = {}
        for peer, c in sorted(self.peers.items(), key=lambda kv: (kv[0] is None, kv[0] or 0)):
            d = {k: v for k, v in vars(c).items()}
            for k in (
                "sent_bytes_by_kind",
                "received_bytes_by_kind",
                "sent_datagrams_by_kind",
                "received_datagrams_by_kind",
                "rejected_by_reason",
                "dropped_by_reason",
            ):
                d[k] = dict(d[k])
            peers["unknown" if peer is None else str(peer)] = d
        return {"totals": self.totals(), "peers": peers}
