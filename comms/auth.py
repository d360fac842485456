"""Datagram authentication: HMAC-SHA256 tags, fleet key files, and the drop-and-count verifier.

docs/wire-format.md. UDP RADIO/DISH has no security mechanism of its own (no CURVE, no peer
identity), so every neighbour datagram carries a tag in the codec's last ``TAG_BYTES`` = 16
bytes: HMAC-SHA256 (RFC 2104) over everything before the tag, truncated to 128 bits as in
RFC 4868 (HMAC-SHA-256-128). One secret key per fleet.

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
import stat
import time
from dataclasses import dataclass, field

from dran_edge.comms.codec import MAGIC, SCHEMA_VERSION, TAG_BYTES, decode_datagram, decode_header
from dran_edge.errors import ConfigError, DecodeError
from dran_edge.messages import NeighbourMessage

#: Accepted key lengths in bytes (the key file holds them hex-encoded).
KEY_MIN_BYTES = 32
KEY_MAX_BYTES = 64


# --------------------------------------------------------------------------- keys
def load_fleet_key(path: str | os.PathLike) -> bytes:
    """Read a fleet key file: one line of 64..128 hex digits (32..64 bytes); '#' comments allowed.

    Refuses (``ConfigError`` naming the file and its mode) a key that the group or others
    may read or write: ``chmod 600`` it.
    """
    path = os.fspath(path)
    try:
        st = os.stat(path)
    except OSError as exc:
        raise ConfigError(f"cannot read the fleet key: {exc.strerror}", path=path) from None
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError("the fleet key must be a regular file", path=path)
    mode = stat.S_IMODE(st.st_mode)
    if mode & 0o077:
        raise ConfigError(
            f"fleet key has mode {mode:04o}; expected no group/other access "
            f"(run: chmod 600 {path})",
            path=path,
        )
    with open(path, encoding="ascii", errors="replace") as f:
        lines = [ln.split("#", 1)[0].strip() for ln in f]
    digits = "".join(ln for ln in lines if ln)
    try:
        key = bytes.fromhex(digits)
    except ValueError:
        raise ConfigError("expected the key as hexadecimal digits", path=path) from None
    if not KEY_MIN_BYTES <= len(key) <= KEY_MAX_BYTES:
        raise ConfigError(
            f"expected a key of {KEY_MIN_BYTES}..{KEY_MAX_BYTES} bytes, got {len(key)}", path=path
        )
    return key


def write_fleet_key(path: str | os.PathLike, key: bytes | None = None) -> bytes:
    """Create a new key file (mode 0600, refuses to overwrite); returns the key."""
    key = os.urandom(KEY_MIN_BYTES) if key is None else key
    if not KEY_MIN_BYTES <= len(key) <= KEY_MAX_BYTES:
        raise ConfigError(
            f"expected a key of {KEY_MIN_BYTES}..{KEY_MAX_BYTES} bytes, got {len(key)}"
        )
    try:
        fd = os.open(os.fspath(path), os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise ConfigError(
            "fleet key file exists; not overwriting it", path=os.fspath(path)
        ) from None
    with os.fdopen(fd, "w") as f:
        f.write("# dran-edge fleet key (HMAC-SHA256); keep mode 0600\n" + key.hex() + "\n")
    return key


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
    """Fills the tag slot of encoded datagrams with the fleet key."""

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
    """Authenticates and decodes datagrams for one robot; drops and counts the rest."""

    def __init__(self, key: bytes, policy: AuthPolicy):
        Signer(key)  # validates the length
        self._key = bytes(key)
        self.policy = policy
        self._windows: dict[int, _Window] = {}
        self.counts = VerifierCounts()
        #: The claimed sender of the last datagram examined (None if its header did not parse).
        self.last_claimed_sender: int | None = None

    def check(self, datagram: bytes, delta_for=None
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

    def _check(self, datagram: bytes, delta_for=None
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
        tag = bytes(datagram[-TAG_BYTES:])
        if not hmac.compare_digest(tag, compute_tag(self._key, datagram)):
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
