"""Selective-repeat ARQ: reliable delivery of datagrams over lossy links, as a pure state
machine per robot driven once per round (no clock, no socket; docs/dran.md, "Over lossy
links").

The tree protocols of the substructured initialisation and of the exact refinement
(``dran_edge.dran.substructure``, ``dran_edge.dran.exact_gn``) need every message of an
exchange; plain datagrams over a lossy radio do not give that. This module does, one robot's
side at a time:

- **ids**: a datagram's id is its header sequence number (per sender and boot epoch, +1 per
  datagram, docs/wire-format.md). A retransmission is the same bytes (same sequence), so a
  receiver that never got the original accepts it and one that did recognises a duplicate.
- **sender**: ``offer(to, sequence, data)`` registers a datagram; ``due()``, once per round,
  returns every datagram not yet acknowledged — its first transmission, then one
  retransmission per round — and raises ``LinkDown`` for one unacknowledged after
  ``max_rounds`` transmissions (a link down for that long, e.g. a partition: the caller falls
  back to what works without every message); ``acknowledged(peer, runs)`` drops what an ack
  covers.
- **receiver**: ``received(peer, sequence)`` is True the first time (deliver the datagram),
  False for a duplicate; ``acks()``, once per round after receiving, gives every peer heard
  from this round the runs ``(first sequence, length)`` of what arrived from it this round
  (duplicates too) and of every sequence received from it within the last ``ack_span`` —
  cumulative, so any one ack that arrives acknowledges everything of the exchange received
  so far, and a lost ack costs nothing once a later one arrives.
- **on the wire**: an ack is a ``NeighbourMessage`` of ``InitStage.ARQ_ACK`` entries
  (``ack_entries`` / ``ack_runs``), encoded by the codec like every other datagram: about 4
  bytes per run after a 29-byte header and tag, one ack per link and round in which data
  arrived (sent ``ack_copies`` times).

Over a real radio (not done: the daemon does not run the tree protocols) the replay window
of ``comms.auth`` drops a datagram whose sequence it has already accepted before the ARQ sees
it; a retransmission whose original arrived is then acknowledged by the cumulative part of the
next ack instead, which needs the receiver to hear some other datagram of the sender in that
round (or an ack sent every round while an exchange is open).

The harness that drives it over the in-process bus is ``dran_edge.experiments.fleet``
(``Fleet.reliable_exchange``).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from dran_edge.messages import InitEntry, InitStage

Run = tuple[int, int]
"""(first sequence, length ≥ 1): the sequences first … first + length − 1."""


class LinkDown(Exception):
    """A datagram stayed unacknowledged for ``max_rounds`` transmissions."""

    def __init__(self, sender: int, receiver: int, rounds: int, sequence: int):
        super().__init__(
            f"link {sender}->{receiver} down: datagram {sequence} unacknowledged after "
            f"{rounds} rounds"
        )
        self.sender, self.receiver, self.rounds, self.sequence = sender, receiver, rounds, sequence


@dataclass(frozen=True)
class ArqParams:
    max_rounds: int = 40
    """Transmissions of one datagram before ``LinkDown`` (at 30 % loss each way a datagram
    and its ack both get through with probability 0.49 per round: 40 rounds fail with
    probability 0.51⁴⁰ ≈ 2e-12)."""
    window: int = 1 << 16
    """Sequences per peer a receiver remembers to tell duplicates; older ones count as
    duplicates. Must exceed the sequences a sender uses while one datagram is outstanding."""
    ack_span: int = 1024
    """An ack repeats every sequence received from its peer within this many below the
    highest (besides what arrived since the last ack): one exchange's datagrams, not the
    whole history, so acks stay a few runs long."""
    ack_copies: int = 2
    """Copies of each ack datagram the harness sends (the same bytes): an ack is ~40 bytes
    against ~1 200 for the data datagram whose retransmission a lost ack causes; at 30 %
    loss two copies get through with probability 0.91 instead of 0.7."""


def runs(sequences: Iterable[int]) -> list[Run]:
    """Sorted sequences as maximal runs (first, length)."""
    out: list[list[int]] = []
    for s in sorted(set(int(x) for x in sequences)):
        if out and s == out[-1][0] + out[-1][1]:
            out[-1][1] += 1
        else:
            out.append([s, 1])
    return [(a, n) for a, n in out]


def ack_entries(acked: list[Run]) -> tuple[InitEntry, ...]:
    """The ack's entries: one ``ARQ_ACK`` per run (``keyframe_id`` first, ``owner_robot``
    length)."""
    return tuple(InitEntry(InitStage.ARQ_ACK, n, first, np.zeros(0)) for first, n in acked)


def ack_runs(entries: Iterable[InitEntry]) -> list[Run]:
    """The runs in a decoded message's ``ARQ_ACK`` entries (none: not an ack)."""
    return [
        (int(e.keyframe_id), int(e.owner_robot))
        for e in entries
        if InitStage(e.stage) == InitStage.ARQ_ACK
    ]


@dataclass
class _Outstanding:
    to: int
    data: bytes
    sent: int = 0  # transmissions so far


@dataclass
class Arq:
    """One robot's selective-repeat state, sender and receiver sides (module docstring)."""

    robot: int
    params: ArqParams = ArqParams()
    _out: dict[int, _Outstanding] = field(default_factory=dict)  # sequence -> datagram
    _got: dict[int, set[int]] = field(default_factory=dict)  # peer -> sequences received
    _top: dict[int, int] = field(default_factory=dict)  # peer -> highest sequence received
    _heard: dict[int, set[int]] = field(default_factory=dict)  # peer -> this round's sequences
    transmissions: int = 0
    """Datagrams handed out by ``due`` (first transmissions and retransmissions)."""
    retransmissions: int = 0
    duplicates: int = 0
    """Datagrams ``received`` saw again."""

    # ------------------------------------------------------------------ sender
    def offer(self, to: int, sequence: int, data: bytes) -> None:
        """Deliver ``data`` (this robot's datagram ``sequence``) to ``to`` reliably."""
        if sequence in self._out:
            raise ValueError(f"sequence {sequence} is already outstanding")
        self._out[int(sequence)] = _Outstanding(int(to), bytes(data))

    @property
    def pending(self) -> int:
        """Datagrams not yet acknowledged."""
        return len(self._out)

    def due(self) -> list[tuple[int, bytes]]:
        """This round's transmissions ``(to, data)``: every unacknowledged datagram, in
        sequence order. Raises ``LinkDown`` for one sent ``max_rounds`` times already."""
        out = []
        for seq in sorted(self._out):
            o = self._out[seq]
            if o.sent >= self.params.max_rounds:
                raise LinkDown(self.robot, o.to, o.sent, seq)
            self.retransmissions += o.sent > 0
            o.sent += 1
            out.append((o.to, o.data))
        self.transmissions += len(out)
        return out

    def acknowledged(self, peer: int, acked: Iterable[Run]) -> None:
        """``peer`` acknowledged the sequences of ``acked`` (runs of this robot's datagrams)."""
        for first, n in acked:
            for seq in range(int(first), int(first) + int(n)):
                o = self._out.get(seq)
                if o is not None and o.to == peer:
                    del self._out[seq]

    def abandon(self) -> None:
        """Forget every outstanding datagram (after ``LinkDown``, the exchange given up)."""
        self._out.clear()

    # ------------------------------------------------------------------ receiver
    def received(self, peer: int, sequence: int) -> bool:
        """Record datagram ``sequence`` from ``peer``: True if new (deliver it), False for a
        duplicate or one older than the window. Either way the next ``acks`` covers it."""
        peer, sequence = int(peer), int(sequence)
        self._heard.setdefault(peer, set()).add(sequence)
        got = self._got.setdefault(peer, set())
        top = max(self._top.get(peer, sequence), sequence)
        self._top[peer] = top
        floor = top - self.params.window
        if sequence in got or sequence <= floor:
            self.duplicates += 1
            return False
        got.add(sequence)
        if len(got) > 2 * self.params.window:  # forget what is below the window
            self._got[peer] = {s for s in got if s > floor}
        return True

    def acks(self) -> dict[int, list[Run]]:
        """Per peer heard from since the last call: the runs of what it received from it
        since then and of everything received from it within the last ``ack_span``
        sequences (cumulative acknowledgement)."""
        out = {}
        for peer in sorted(self._heard):
            floor = self._top[peer] - self.params.ack_span
            recent = (s for s in self._got.get(peer, ()) if s > floor)
            out[peer] = runs(itertools.chain(self._heard[peer], recent))
        self._heard.clear()
        return out
