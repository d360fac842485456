"""The transport interface: what the daemon, replay and simulation send datagrams through.

Two implementations carry the same bytes: ``dran_edge.comms.radio.RadioTransport`` (ZeroMQ
UDP RADIO/DISH between robots) and ``dran_edge.comms.bus.BusEndpoint`` (the in-process bus
with a loss / latency / partition model). Transports move opaque datagrams; encoding is the
codec's job and authentication the verifier's (``auth.Verifier``), so both are identical on
every transport.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from dran_edge.comms.counters import CommCounters


@runtime_checkable
class Transport(Protocol):
    """One robot's link to its neighbours."""

    #: Traffic counters (per neighbour, per kind, rejections by reason).
    counters: CommCounters

    def send(self, to: int, data: bytes) -> bool:
        """Queue ``data`` for neighbour ``to``; never blocks.

        Returns False when the datagram was dropped locally (unknown neighbour, over the
        size cap, no link); the reason is counted. True means handed to the network, which
        may still lose it.
        """

    def receive(self, max_datagrams: int | None = None) -> list[tuple[int | None, bytes]]:
        """Datagrams that have arrived, as (sender_hint, bytes); never blocks.

        ``sender_hint`` is the sending robot where the transport knows it (the bus) and None
        where it does not (UDP carries no authenticated identity: use the decoded header
        after ``auth.Verifier.check``).
        """

    def close(self) -> None:
        """Release sockets; idempotent."""
