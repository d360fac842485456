"""One robot's authenticated neighbour link: codec + signer + verifier over any transport.

The daemon (over ``radio.RadioTransport``), simulation/replay (over ``bus.BusEndpoint``) and
the loopback harness all send and receive ``NeighbourMessage`` s through this one class, so
the bytes on the wire and their accounting are the same everywhere.

- ``key``: the fleet's HMAC key (bytes) or this robot's ``auth.RobotIdentity`` (its Ed25519
  secret and the fleet's public keys; a ``pairwise.PairwiseIdentity`` for the pairwise
  policy); the key policy decides the datagrams' trailer.
- ``send_message(msg, to)`` encodes the message once (datagrams numbered from this robot's
  sequence counter), signs each datagram, and hands it to the transport for every robot in
  ``to`` (the same datagram to each: replay windows are per receiver; under the pairwise policy
  the same bytes with each receiver's own tag).
- ``poll(now_ns)`` drains the transport, verifies and decodes every datagram, counts it
  (accepted per sender and kind with last-heard time; rejected per reason), and returns the
  accepted messages. Nothing an attacker sends makes it raise.
- ``delta_every > 0``: the delta layout (``comms.delta``, docs/wire-format.md). Each message is
  encoded once per recipient against that link's ``DeltaEncoder``; received datagrams are
  rebuilt against the sender's ``DeltaDecoder`` only after they pass authentication and the
  replay window, and a sender's new boot epoch starts a fresh decoder (a restarted robot's
  rounds start over). Delta entries whose base is not held are left out and counted
  (``delta_unresolved``).
"""

from __future__ import annotations

from typing import Iterable

from dran_edge.comms.auth import AuthPolicy, Reject, RobotIdentity, Verifier, make_signer
from dran_edge.comms.pairwise import PairwiseIdentity, pairwise_keys
from dran_edge.comms.codec import DEFAULT_MAX_DATAGRAM_BYTES, encode_datagrams
from dran_edge.comms.counters import CommCounters
from dran_edge.comms.delta import DeltaDecoder, DeltaEncoder
from dran_edge.comms.transport import Transport
from dran_edge.messages import NeighbourMessage


class NeighbourLink:
    """See the module docstring."""

    def __init__(
        self,
        transport: Transport,
        *,
        key: bytes | RobotIdentity,
        policy: AuthPolicy,
        boot_epoch: int,
        max_datagram_bytes: int = DEFAULT_MAX_DATAGRAM_BYTES,
        first_sequence: int = 0,
        delta_every: int = 0,
    ):
        self.transport = transport
        self.policy = policy
        self.boot_epoch = int(boot_epoch)
        self.max_datagram_bytes = int(max_datagram_bytes)
        credentials = (
            pairwise_keys(key, policy.self_id, policy.fleet_id)
            if isinstance(key, PairwiseIdentity)
            else key
        )
        self._signer = make_signer(credentials)
        self.verifier = Verifier(credentials, policy)
        self._next_sequence = int(first_sequence)
        #: Link-level counters: bytes per neighbour and kind, rejections by reason.
        self.counters = CommCounters()
        #: Set to a list to record every accepted datagram's bytes (tests, harnesses).
        self.accepted_datagrams: list[bytes] | None = None
        self.delta_every = int(delta_every)
        self._enc: dict[int, DeltaEncoder] = {}
        self._dec: dict[int, tuple[int, DeltaDecoder]] = {}  # sender -> (boot epoch, state)
        #: Delta entries received whose base was not held (lost or reordered datagrams).
        self.delta_unresolved = 0

    @property
    def next_sequence(self) -> int:
        return self._next_sequence

    def to_state(self) -> dict:
        """What a restarted robot needs back: the receivers' replay windows (so a datagram
        captured before the restart is not accepted again) and our next sequence number."""
        return {"next_sequence": self._next_sequence, "windows": self.verifier.windows_state()}

    def restore(self, state: dict | None) -> int:
        """Take back ``to_state``'s replay windows (the sending side starts a new boot epoch,
        so its sequence restarts at 0). Returns the number of senders restored."""
        if not state:
            return 0
        return self.verifier.restore_windows(state.get("windows") or [])

    def send_message(self, message: NeighbourMessage, to: Iterable[int]) -> list[bytes]:
        """Encode, sign and send ``message`` to each robot in ``to``; returns the datagrams."""
        if message.sender_id != self.policy.self_id:
            raise ValueError(
                f"message sender {message.sender_id} is not this robot ({self.policy.self_id})"
            )
        targets = list(to)
        if not self.delta_every:  # one encoding for every recipient
            return self._send(self._encode(message, None), targets)
        out = []
        for j in targets:  # one encoding per link: each link has its own delta state
            enc = self._enc.setdefault(j, DeltaEncoder(self.delta_every))
            out += self._send(self._encode(message, enc), [j])
        return out

    def _encode(self, message: NeighbourMessage, enc: DeltaEncoder | None) -> list:
        grams = encode_datagrams(
            message,
            fleet_id=self.policy.fleet_id,
            boot_epoch=self.boot_epoch,
            first_sequence=self._next_sequence,
            max_datagram_bytes=self.max_datagram_bytes,
            delta=enc,
            signed=self._signer.signed,
            pairwise=self._signer.pairwise,
        )
        self._next_sequence += len(grams)
        return grams

    def _send(self, grams: list, targets: list[int]) -> list[bytes]:
        out = []
        for g in grams:
            if self._signer.pairwise:  # one tag per receiver
                signed = [(j, self._signer.sign_for(g.data, j)) for j in targets]
                out += [data for _, data in signed]
            else:
                data = self._signer.sign(g.data)
                signed = [(j, data) for j in targets]
                out.append(data)
            for j, data in signed:
                if self.transport.send(j, data):
                    self.counters.sent(j, len(data), g.bytes_by_kind)
                else:
                    self.counters.dropped(j, len(data), "transport_refused")
        return out

    def _decoder_for(self, header) -> DeltaDecoder:
        held = self._dec.get(header.sender_id)
        if held is None or header.boot_epoch > held[0]:
            held = (header.boot_epoch, DeltaDecoder())
            self._dec[header.sender_id] = held
        return held[1]

    def poll(
        self, now_ns: int | None = None, max_datagrams: int | None = None
    ) -> list[NeighbourMessage]:
        """Accepted messages among the datagrams that arrived; the rest counted and dropped."""
        accepted = []
        delta_for = self._decoder_for if self.delta_every else None
        for _hint, data in self.transport.receive(max_datagrams):
            msg, reason = self.verifier.check(data, delta_for)
            if reason is None:
                self.delta_unresolved += msg.extra.get("delta_unresolved", 0)
                self.counters.received(msg.sender_id, len(data), msg.extra["bytes_by_kind"], now_ns)
                accepted.append(msg)
                if self.accepted_datagrams is not None:
                    self.accepted_datagrams.append(bytes(data))
            else:
                claimed = self.verifier.last_claimed_sender
                # Only fleet members get their own counter row (bounded memory under attack).
                peer = (
                    claimed
                    if claimed in self.policy.fleet_robots and reason != Reject.MALFORMED
                    else None
                )
                self.counters.rejected(peer, len(data), reason.value)
        return accepted
