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

from collections.abc import Mapping

from dran_edge.comms.codec import (
    MAGIC,
    SCHEMA_VERSION,
    SIGNATURE_BYTES,
    TAG_BYTES,
    decode_datagram,
    decode_header,
)
from dran_edge.errors import ConfigError, DecodeError, DependencyError
from dran_edge.messages import NeighbourMessage

#: Accepted key lengths in bytes (the key file holds them hex-encoded).
KEY_MIN_BYTES = 32
KEY_MAX_BYTES = 64
#: Ed25519 secret seed and public key lengths (RFC 8032).
ED25519_KEY_BYTES = 32
#: First word of a robot's secret key file (tells it apart from a fleet HMAC key).
_ROBOT_KEY_WORD = "ed25519-secret"
#: Key policies (the config's ``comms.auth``).
POLICIES = ("hmac", "ed25519")


# --------------------------------------------------------------------------- keys
def _read_secret_file(path: str, what: str) -> list[str]:
    """The non-comment words of a secret file, after checking it is private (mode 0600)."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise ConfigError(f"cannot read the {what}: {exc.strerror}", path=path) from None
    if not stat.S_ISREG(st.st_mode):
        raise ConfigError(f"the {what} must be a regular file", path=path)
    mode = stat.S_IMODE(st.st_mode)
    if mode & 0o077:
        raise ConfigError(
            f"{what} has mode {mode:04o}; expected no group/other access "
            f"(run: chmod 600 {path})",
            path=path,
        )
    try:
        with open(path, encoding="ascii", errors="replace") as f:
            lines = [ln.split("#", 1)[0].strip() for ln in f]
    except OSError as exc:
        raise ConfigError(f"cannot read the {what}: {exc.strerror}", path=path) from None
    return " ".join(ln for ln in lines if ln).split()


def load_fleet_key(path: str | os.PathLike) -> bytes:
    """Read a fleet key file: one line of 64..128 hex digits (32..64 bytes); '#' comments allowed.

    Refuses (``ConfigError`` naming the file and its mode) a key that the group or others
    may read or write: ``chmod 600`` it.
    """
    path = os.fspath(path)
    words = _read_secret_file(path, "fleet key")
    if words and words[0] == _ROBOT_KEY_WORD:
        raise ConfigError(
            "this is a robot's Ed25519 secret key, not a fleet HMAC key "
            "(set comms.auth: ed25519 to use it)",
            path=path,
        )
    try:
        key = bytes.fromhex("".join(words))
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


def _ed25519():
    """The ``cryptography`` package's Ed25519 module (imported only for the ed25519 policy)."""
    try:
        from cryptography.hazmat.primitives.asymmetric import ed25519
    except ImportError as exc:
        raise DependencyError(
            f"comms.auth ed25519 needs the 'cryptography' package ({exc}); "
            "install it with: pip install 'dran-edge[comms]'"
        ) from None
    return ed25519


def _exclusive_write(path: str, text: str, mode: int, what: str) -> None:
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    except FileExistsError:
        raise ConfigError(f"{what} exists; not overwriting it", path=path) from None
    with os.fdopen(fd, "w") as f:
        f.write(text)


def parse_public_key(text: str, where: str = "public key") -> bytes:
    """A 64-hex-digit Ed25519 public key -> 32 bytes; ConfigError naming ``where`` otherwise."""
    try:
        key = bytes.fromhex(str(text).strip())
    except ValueError:
        key = b""
    if len(key) != ED25519_KEY_BYTES:
        raise ConfigError(
            f"{where}: expected an Ed25519 public key as {2 * ED25519_KEY_BYTES} hex digits, "
            f"got {str(text)[:80]!r}"
        )
    return key


def public_key_of(secret: bytes) -> bytes:
    """The 32-byte Ed25519 public key of a 32-byte secret seed."""
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    private = _ed25519().Ed25519PrivateKey.from_private_bytes(secret)
    return private.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)


def load_robot_key(path: str | os.PathLike) -> bytes:
    """Read a robot's Ed25519 secret key file (written by ``write_robot_key``): the 32-byte seed.

    Same mode rule as the fleet key (no group/other access)."""
    path = os.fspath(path)
    words = _read_secret_file(path, "robot key")
    if not words or words[0] != _ROBOT_KEY_WORD:
        raise ConfigError(
            f"expected a robot's Ed25519 secret key ('{_ROBOT_KEY_WORD} <64 hex digits>', "
            "made by 'dran-edge fleet-key pair'); a fleet HMAC key needs comms.auth: hmac",
            path=path,
        )
    try:
        seed = bytes.fromhex("".join(words[1:]))
    except ValueError:
        seed = b""
    if len(seed) != ED25519_KEY_BYTES:
        raise ConfigError(
            f"expected {2 * ED25519_KEY_BYTES} hex digits after '{_ROBOT_KEY_WORD}'", path=path
        )
    return seed


def public_key_path(secret_path: str | os.PathLike) -> str:
    """Where ``write_robot_key`` puts the public half: ``<secret path>.pub``."""
    return os.fspath(secret_path) + ".pub"


def write_robot_key(path: str | os.PathLike, robot_id: int, seed: bytes | None = None) -> bytes:
    """Create a robot's key pair: the secret at ``path`` (mode 0600) and the public half at
    ``path + '.pub'`` (mode 0644, ``robot_id: N`` and ``public_key: <hex>``); refuses to
    overwrite either. Returns the public key."""
    path = os.fspath(path)
    seed = os.urandom(ED25519_KEY_BYTES) if seed is None else seed
    public = public_key_of(seed)
    pub_path = public_key_path(path)
    if os.path.exists(pub_path):
        raise ConfigError("public key file exists; not overwriting it", path=pub_path)
    _exclusive_write(
        path,
        "# dran-edge robot secret key (Ed25519, RFC 8032 seed); keep mode 0600, never copy it\n"
        f"{_ROBOT_KEY_WORD} {seed.hex()}\n",
        0o600,
        "robot key file",
    )
    _exclusive_write(
        pub_path,
        "# dran-edge robot public key (Ed25519); share it with the fleet (fleet-key export)\n"
        f"robot_id: {int(robot_id)}\npublic_key: {public.hex()}\n",
        0o644,
        "public key file",
    )
    return public


def load_public_key_file(path: str | os.PathLike) -> tuple[int, bytes]:
    """A robot's ``.pub`` file -> (robot id, 32-byte public key)."""
    import yaml

    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            doc = yaml.safe_load(f)
    except OSError as exc:
        raise ConfigError(f"cannot read the public key: {exc.strerror}", path=path) from None
    except yaml.YAMLError:
        doc = None
    if not isinstance(doc, dict) or not isinstance(doc.get("robot_id"), int):
        raise ConfigError("expected 'robot_id: N' and 'public_key: <hex>'", path=path)
    try:
        return doc["robot_id"], parse_public_key(doc.get("public_key", ""))
    except ConfigError as exc:
        raise ConfigError(str(exc), path=path) from None


def load_fleet_public_keys(path: str | os.PathLike) -> tuple[str, dict[int, tuple[bytes, ...]]]:
    """A fleet public-key file (``fleet-key export``) -> (fleet name, robot id -> keys).

    Format: ``fleet: NAME`` and ``public_keys: {ID: HEX or [HEX, ...]}``; two keys for one
    robot while it rotates its key pair (either is accepted)."""
    import yaml

    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as f:
            doc = yaml.safe_load(f)
    except OSError as exc:
        raise ConfigError(f"cannot read the fleet public keys: {exc.strerror}", path=path) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"not valid YAML: {exc}", path=path) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("public_keys"), dict):
        raise ConfigError("expected 'fleet: NAME' and a 'public_keys' mapping", path=path)
    keys: dict[int, tuple[bytes, ...]] = {}
    for rid, value in doc["public_keys"].items():
        if not isinstance(rid, int) or not 0 <= rid <= 0xFFFF:
            raise ConfigError(f"public_keys: expected robot ids 0..65535, got {rid!r}", path=path)
        items = value if isinstance(value, list) else [value]
        try:
            keys[rid] = tuple(parse_public_key(v, f"public_keys.{rid}") for v in items)
        except ConfigError as exc:
            raise ConfigError(str(exc), path=path) from None
        if not keys[rid]:
            raise ConfigError(f"public_keys.{rid}: expected at least one key", path=path)
    return str(doc.get("fleet", "")), keys


def write_fleet_public_keys(path: str | os.PathLike, fleet: str,
                            keys: Mapping[int, tuple[bytes, ...]]) -> None:
    """Write the fleet public-key file read by ``load_fleet_public_keys`` (overwrites: no secret)."""
    lines = ["# dran-edge fleet public keys (Ed25519): the same file on every robot",
             f"fleet: {fleet}", "public_keys:"]
    for rid in sorted(keys):
        hexes = [k.hex() for k in keys[rid]]
        lines.append(f"  {rid}: " + (hexes[0] if len(hexes) == 1 else "[" + ", ".join(hexes) + "]"))
    with open(os.fspath(path), "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


@dataclass(frozen=True)
class RobotIdentity:
    """The ed25519 policy's credentials of one robot: its own secret and the fleet's public keys."""

    #: This robot's 32-byte Ed25519 secret seed.
    secret: bytes
    #: Robot id -> accepted public keys (one; two while that robot rotates its key pair).
    public_keys: Mapping[int, tuple[bytes, ...]]


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

    def __init__(self, secret: bytes):
        if len(secret) != ED25519_KEY_BYTES:
            raise ConfigError(f"expected a {ED25519_KEY_BYTES}-byte Ed25519 secret, got {len(secret)}")
        self._private = _ed25519().Ed25519PrivateKey.from_private_bytes(bytes(secret))

    def sign(self, datagram: bytes) -> bytes:
        if len(datagram) < SIGNATURE_BYTES:
            raise ValueError(f"datagram of {len(datagram)} bytes has no signature slot")
        body = bytes(datagram[:-SIGNATURE_BYTES])
        return body + self._private.sign(body)


def make_signer(credentials: bytes | RobotIdentity) -> Signer | Ed25519Signer:
    """The signer of a fleet HMAC key (bytes) or of a robot's identity."""
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
    keys. Under ed25519 every robot the policy accepts must have a public key."""

    def __init__(self, credentials: bytes | RobotIdentity | Mapping, policy: AuthPolicy):
        self.policy = policy
        self._key: bytes | None = None
        self._public: dict[int, tuple] = {}
        if isinstance(credentials, (RobotIdentity, Mapping)):
            keys = (credentials.public_keys if isinstance(credentials, RobotIdentity)
                    else credentials)
            missing = sorted((policy.neighbours | policy.relay_from) - set(keys))
            if missing:
                raise ConfigError(
                    f"no Ed25519 public key for robot(s) {missing} (neighbours and "
                    "allow_relay_from need one: comms.public_keys_file or neighbours[].public_keys)"
                )
            Public = _ed25519().Ed25519PublicKey
            self._public = {int(r): tuple(Public.from_public_bytes(bytes(k)) for k in ks)
                            for r, ks in keys.items()}
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
        return self._key is None

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

    def _authentic(self, datagram: bytes, sender: int) -> bool:
        if self._key is not None:
            tag = bytes(datagram[-TAG_BYTES:])
            return hmac.compare_digest(tag, compute_tag(self._key, datagram))
        body = bytes(datagram[:-SIGNATURE_BYTES])
        signature = bytes(datagram[-SIGNATURE_BYTES:])
        for public in self._public.get(sender, ()):
            try:
                public.verify(signature, body)
                return True
            except Exception:  # cryptography's InvalidSignature; nothing else is raised here
                continue
        return False

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
        if h.signed != self.signed:
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
