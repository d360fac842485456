"""Datagram authentication: fleet HMAC tags or per-robot Ed25519 signatures, key files, and
the drop-and-count verifier.

UDP RADIO/DISH has no security mechanism of its own (no CURVE, no peer identity), so every
neighbour datagram ends in an authentication trailer over everything before it. Two key
policies (docs/wire-format.md, "Authentication"; a fleet uses one):

- ``hmac``: one secret key per fleet; the trailer is HMAC-SHA256 (RFC 2104) truncated to 128
  bits as in RFC 4868 (HMAC-SHA-256-128), ``TAG_BYTES`` = 16. Any key holder can sign as any
  robot.
- ``ed25519``: one key pair per robot; the trailer is the sender's Ed25519 signature
  (RFC 8032), ``SIGNATURE_BYTES`` = 64, flagged in the header. Receivers hold only their
  neighbours' public keys, so a robot (or a thief of its secret) can sign only as itself.
- ``pairwise``: the same key pairs, used to agree one HMAC key per ordered pair of robots
  (X25519 + HKDF, ``comms.pairwise``); the trailer is a 16-byte tag for one receiver, flagged
  in the header. A thief of robot 3's secret can tag only as robot 3, or "as robot 1" only to
  robot 3 itself; an HMAC instead of a signature per datagram.

``Verifier.check`` is the only door into the agent for a datagram. It drops (and counts
under a ``Reject`` reason) anything malformed, from another fleet, from a robot that is not
in the fleet, from a robot that is not a configured neighbour (unless relaying is allowed for
it), with a bad tag, or with a replayed or stale (epoch, sequence). Replay protection is a
per-sender sliding window over sequence numbers (RFC 4303 §3.4.3 style) within a boot epoch;
a neighbour that restarts announces a *larger* boot epoch and is accepted from its first
datagram (``next_boot_epoch`` keeps the epoch increasing across restarts). A datagram is
checked in order of cost — header, identity, tag, window, full decode — and the window
advances only for a datagram that passed all of them, so an attacker can make us drop
datagrams but never accept one or crash.
"""

from __future__ import annotations

import enum
import hmac
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

from dran_edge.comms.codec import (
    MAGIC,
    SCHEMA_VERSION,
    SIGNATURE_BYTES,
    TAG_BYTES,
    decode_datagram,
    decode_header,
)

# Key files live in comms/keys.py; re-exported here, where callers have always found them.
from dran_edge.comms.keys import (  # noqa: F401
    ED25519_KEY_BYTES,
    KEY_MAX_BYTES,
    KEY_MIN_BYTES,
    POLICIES,
    RobotIdentity,
    _ed25519,
    load_fleet_key,
    load_fleet_public_keys,
    load_public_key_file,
    load_robot_key,
    parse_public_key,
    public_key_of,
    public_key_path,
    write_fleet_key,
    write_fleet_public_keys,
    write_robot_key,
)

from dran_edge.comms.pairwise import PairwiseKeys
from dran_edge.errors import ConfigError, DecodeError
from dran_edge.messages import NeighbourMessage


def next_boot_epoch(state_path: str | os.PathLike, *, now_s: float | None = None) -> int:
    """Return and persist this start's boot epoch: max(previous + 1, wall-clock seconds).

    Increases across restarts even when the wall clock is wrong (no RTC) or goes back;
    neighbours accept a restarted robot only with a larger epoch. Fits in u32 until 2106.
    """
    state_path = os.fspath(state_path)
    previous = -1
    try:
        with open(state_path, encoding="ascii") as f:
            previous = int(f.read().strip() or -1)
    except FileNotFoundError:
        pass
    except ValueError:
        raise ConfigError("boot epoch file does not hold an integer", path=state_path) from None
    now = int(time.time() if now_s is None else now_s)
    epoch = max(previous + 1, now) & 0xFFFFFFFF
    tmp = state_path + ".tmp"
    with open(tmp, "w", encoding="ascii") as f:
        f.write(f"{epoch}\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, state_path)
    return epoch


# --------------------------------------------------------------------------- tags
def compute_tag(key: bytes, datagram: bytes) -> bytes:
    """The truncated HMAC-SHA256 over ``datagram`` without its tag slot."""
    return hmac.digest(key, memoryview(datagram)[:-TAG_BYTES], "sha256")[:TAG_BYTES]


class Signer:
    """Fills the tag slot of encoded datagrams with the fleet key (the hmac policy)."""

    #: Datagrams for this signer are encoded with ``codec.encode_datagrams(signed=False)``.
    signed = False
    #: One trailer for every receiver (``PairwiseSigner`` makes one per receiver).
    pairwise = False

    def __init__(self, key: bytes):
        if not KEY_MIN_BYTES <= len(key) <= KEY_MAX_BYTES:
            raise ConfigError(
                f"expected a key of {KEY_MIN_BYTES}..{KEY_MAX_BYTES} bytes, got {len(key)}"
            )
        self._key = bytes(key)

    def sign(self, datagram: bytes) -> bytes:
        if len(datagram) < TAG_BYTES:
            raise ValueError(f"datagram of {len(datagram)} bytes has no tag slot")
        return bytes(datagram[:-TAG_BYTES]) + compute_tag(self._key, datagram)


class Ed25519Signer:
    """Fills the signature slot of datagrams encoded with ``signed=True`` (the ed25519 policy)."""

    signed = True
    pairwise = False

    def __init__(self, secret: bytes):
        if len(secret) != ED25519_KEY_BYTES:
            raise ConfigError(
                f"expected a {ED25519_KEY_BYTES}-byte Ed25519 secret, got {len(secret)}"
            )
        self._private = _ed25519().Ed25519PrivateKey.from_private_bytes(bytes(secret))

    def sign(self, datagram: bytes) -> bytes:
        if len(datagram) < SIGNATURE_BYTES:
            raise ValueError(f"datagram of {len(datagram)} bytes has no signature slot")
        body = bytes(datagram[:-SIGNATURE_BYTES])
        return body + self._private.sign(body)


class PairwiseSigner:
    """Fills the tag slot of a datagram for one receiver with that pair's key (the pairwise
    policy; datagrams encoded with ``pairwise=True``)."""

    signed = False
    pairwise = True

    def __init__(self, keys: PairwiseKeys):
        self.keys = keys

    def sign_for(self, datagram: bytes, receiver: int) -> bytes:
        """``datagram`` with the tag of the pair (this robot, ``receiver``); KeyError when the
        receiver has no public key."""
        if len(datagram) < TAG_BYTES:
            raise ValueError(f"datagram of {len(datagram)} bytes has no tag slot")
        body = memoryview(datagram)[:-TAG_BYTES]
        return bytes(body) + self.keys.tag_for(receiver, body)


def make_signer(
    credentials: bytes | RobotIdentity | PairwiseKeys,
) -> Signer | Ed25519Signer | PairwiseSigner:
    """The signer of a fleet HMAC key (bytes), a robot's identity (ed25519) or its pair keys."""
    if isinstance(credentials, PairwiseKeys):
        return PairwiseSigner(credentials)
    if isinstance(credentials, RobotIdentity):
        return Ed25519Signer(credentials.secret)
    return Signer(credentials)


# --------------------------------------------------------------------------- verifier
class Reject(str, enum.Enum):
    """Why a datagram was dropped (counter names)."""

    MALFORMED = "malformed"
    #: our magic, another schema version: a robot running another release (a fleet updates
    #: together; docs/wire-format.md, CHANGELOG)
    WRONG_VERSION = "wrong_version"
    WRONG_FLEET = "wrong_fleet"
    UNKNOWN_SENDER = "unknown_sender"
    NOT_NEIGHBOUR = "not_neighbour"
    #: the datagram's trailer is of the other key policy (an HMAC tag where this robot expects
    #: Ed25519 signatures, or the reverse): a robot configured with another ``comms.auth``
    WRONG_AUTH = "wrong_auth"
    BAD_TAG = "bad_tag"
    REPLAYED = "replayed"
    STALE = "stale"


@dataclass(frozen=True)
class AuthPolicy:
    """Who this robot accepts datagrams from."""

    #: This fleet's id (the codec header's ``fleet_id``).
    fleet_id: int
    #: This robot's id; datagrams claiming to come from it are dropped as ``unknown_sender``.
    self_id: int
    #: Every robot id of the fleet; anything else is ``unknown_sender``.
    fleet_robots: frozenset[int]
    #: Configured neighbours, accepted directly.
    neighbours: frozenset[int]
    #: Fleet robots that are not neighbours but whose datagrams are accepted anyway
    #: (relaying allowed for them); all others are ``not_neighbour``.
    relay_from: frozenset[int] = frozenset()
    #: Replay window length in sequence numbers (datagrams older than the newest seen by
    #: more than this are ``stale``).
    replay_window: int = 256

    def __post_init__(self):
        if not 1 <= self.replay_window <= 4096:
            raise ConfigError(f"replay_window must be in [1, 4096], got {self.replay_window}")


@dataclass
class _Window:
    epoch: int
    top: int  # highest sequence accepted in this epoch
    seen: int  # bit k set: sequence (top - k) accepted


@dataclass
class VerifierCounts:
    """Accepted / rejected datagrams; ``rejected`` keyed by ``Reject`` value."""

    accepted: int = 0
    rejected: dict = field(default_factory=lambda: {r.value: 0 for r in Reject})


class Verifier:
    """Authenticates and decodes datagrams for one robot; drops and counts the rest.

    ``credentials``: the fleet HMAC key (bytes; hmac policy) or a ``RobotIdentity`` (ed25519
    policy: only its ``public_keys`` are used here), or directly a mapping robot id -> public
    keys, or this robot's ``PairwiseKeys`` (pairwise policy). Under ed25519 and pairwise every
    robot the policy accepts must have a public key."""

    def __init__(
        self, credentials: bytes | RobotIdentity | Mapping | PairwiseKeys, policy: AuthPolicy
    ):
        self.policy = policy
        self._key: bytes | None = None
        self._public: dict[int, tuple] = {}
        self._pairs: PairwiseKeys | None = None
        self._pair_index: int | None = None  # which sender key the last good tag was made with
        self._invalid_signature: type[Exception] = Exception
        if isinstance(credentials, PairwiseKeys):
            missing = sorted((policy.neighbours | policy.relay_from) - credentials.robots())
            if missing:
                raise ConfigError(
                    f"no public key for robot(s) {missing} to agree a pair key with (neighbours "
                    "and allow_relay_from need one: comms.public_keys_file or "
                    "neighbours[].public_keys)"
                )
            self._pairs = credentials
        elif isinstance(credentials, (RobotIdentity, Mapping)):
            keys = (
                credentials.public_keys if isinstance(credentials, RobotIdentity) else credentials
            )
            missing = sorted((policy.neighbours | policy.relay_from) - set(keys))
            if missing:
                raise ConfigError(
                    f"no Ed25519 public key for robot(s) {missing} (neighbours and "
                    "allow_relay_from need one: comms.public_keys_file or neighbours[].public_keys)"
                )
            from cryptography.exceptions import InvalidSignature

            self._invalid_signature = InvalidSignature
            Public = _ed25519().Ed25519PublicKey
            self._public = {
                int(r): tuple(Public.from_public_bytes(bytes(k)) for k in ks)
                for r, ks in keys.items()
            }
        else:
            Signer(credentials)  # validates the length
            self._key = bytes(credentials)
        self._windows: dict[int, _Window] = {}
        self.counts = VerifierCounts()
        #: The claimed sender of the last datagram examined (None if its header did not parse).
        self.last_claimed_sender: int | None = None

    @property
    def signed(self) -> bool:
        """True under the ed25519 policy."""
        return self._key is None and self._pairs is None

    @property
    def pairwise(self) -> bool:
        """True under the pairwise policy."""
        return self._pairs is not None

    def check(
        self, datagram: bytes, delta_for=None
    ) -> tuple[NeighbourMessage | None, Reject | None]:
        """(message, None) if accepted, else (None, reason). Never raises.

        ``delta_for(header)``, if given, returns the receiving side of the delta state for that
        sender (``comms.delta.DeltaDecoder``); it is asked, and the state changed, only for a
        datagram that passed every other check (authenticated, not replayed, not stale)."""
        msg, reason = self._check(datagram, delta_for)
        if reason is None:
            self.counts.accepted += 1
        else:
            self.counts.rejected[reason.value] += 1
        return msg, reason

    def _authentic(self, datagram: bytes, sender: int) -> bool:
        if self._pairs is not None:
            view = memoryview(datagram)
            self._pair_index = self._pairs.verify(
                sender, view[:-TAG_BYTES], bytes(view[-TAG_BYTES:])
            )
            return self._pair_index is not None
        if self._key is not None:
            tag = bytes(datagram[-TAG_BYTES:])
            return hmac.compare_digest(tag, compute_tag(self._key, datagram))
        body = bytes(datagram[:-SIGNATURE_BYTES])
        signature = bytes(datagram[-SIGNATURE_BYTES:])
        for public in self._public.get(sender, ()):
            try:
                public.verify(signature, body)
                return True
            except self._invalid_signature:
                pass
        return False

    def _check(
        self, datagram: bytes, delta_for=None
    ) -> tuple[NeighbourMessage | None, Reject | None]:
        self.last_claimed_sender = None
        try:
            h = decode_header(datagram)
        except DecodeError:
            if datagram[:2] == MAGIC and len(datagram) > 2 and datagram[2] != SCHEMA_VERSION:
                return None, Reject.WRONG_VERSION
            return None, Reject.MALFORMED
        p = self.policy
        self.last_claimed_sender = h.sender_id
        if h.fleet_id != p.fleet_id:
            return None, Reject.WRONG_FLEET
        if h.sender_id not in p.fleet_robots or h.sender_id == p.self_id:
            return None, Reject.UNKNOWN_SENDER
        if h.sender_id not in p.neighbours and h.sender_id not in p.relay_from:
            return None, Reject.NOT_NEIGHBOUR
        if h.signed != self.signed or h.pairwise != self.pairwise:
            return None, Reject.WRONG_AUTH
        if not self._authentic(datagram, h.sender_id):
            return None, Reject.BAD_TAG
        verdict = self._window_verdict(h.sender_id, h.boot_epoch, h.sequence)
        if verdict is not None:
            return None, verdict
        try:
            msg = decode_datagram(datagram)  # strict and stateless: validates every value
            if delta_for is not None and h.delta:  # valid, so rebuilding cannot fail halfway
                msg = decode_datagram(datagram, delta_for(h))
        except DecodeError:
            return None, Reject.MALFORMED
        self._window_commit(h.sender_id, h.boot_epoch, h.sequence)
        if self._pairs is not None and self._pair_index is not None:
            self._pairs.heard(h.sender_id, self._pair_index)
        return msg, None

    def _window_verdict(self, sender: int, epoch: int, seq: int) -> Reject | None:
        w = self._windows.get(sender)
        if w is None or epoch > w.epoch:
            return None
        if epoch < w.epoch:
            return Reject.STALE
        if seq > w.top:
            return None
        age = w.top - seq
        if age >= self.policy.replay_window:
            return Reject.STALE
        return Reject.REPLAYED if (w.seen >> age) & 1 else None

    def _window_commit(self, sender: int, epoch: int, seq: int) -> None:
        w = self._windows.get(sender)
        mask = (1 << self.policy.replay_window) - 1
        if w is None or epoch > w.epoch:
            self._windows[sender] = _Window(epoch, seq, 1)
        elif seq > w.top:
            jump = seq - w.top
            w.seen = 1 if jump >= self.policy.replay_window else ((w.seen << jump) | 1) & mask
            w.top = seq
        else:
            w.seen |= 1 << (w.top - seq)

    def peer_state(self) -> dict[int, tuple[int, int]]:
        """Per accepted sender: (boot epoch, highest sequence)."""
        return {s: (w.epoch, w.top) for s, w in self._windows.items()}

    def windows_state(self) -> list[list]:
        """The replay windows as JSON-ready ``[sender, epoch, top, seen bitmap as hex]`` rows,
        for a receiver that restarts (``restore_windows``)."""
        return [[s, w.epoch, w.top, format(w.seen, "x")] for s, w in sorted(self._windows.items())]

    def restore_windows(self, rows: list) -> int:
        """Take back windows saved by ``windows_state``; a saved window only ever raises the
        one held (newer epoch, or same epoch and higher top). Malformed rows raise ValueError.
        Returns the number of senders restored."""
        n = 0
        for row in rows:
            sender, epoch, top, seen = int(row[0]), int(row[1]), int(row[2]), int(str(row[3]), 16)
            if min(sender, epoch, top, seen) < 0:
                raise ValueError(f"negative value in a saved replay window: {row!r}")
            held = self._windows.get(sender)
            if held is None or (epoch, top) > (held.epoch, held.top):
                mask = (1 << self.policy.replay_window) - 1
                self._windows[sender] = _Window(epoch, top, (seen & mask) | 1)
                n += 1
        return n
