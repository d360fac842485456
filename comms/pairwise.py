"""The ``pairwise`` key policy: a secret per ordered pair of robots, agreed from their key pairs.

Each robot keeps the Ed25519 key pair of the ``ed25519`` policy (same key files, same fleet
public-key file, docs/wire-format.md "Authentication"), but does not sign every datagram.
Instead, for every other robot ``j`` it derives, once at start, a 32-byte key per direction by
static Diffie-Hellman on Curve25519 (RFC 7748) and HKDF-SHA256 (RFC 5869):

    s_ij    = X25519(a_i, u_j) = X25519(a_j, u_i)          (the same on both robots)
    K_{i→j} = HKDF(salt = "dran-edge pairwise v1", ikm = s_ij,
                   info = fleet ‖ i ‖ j ‖ A_i ‖ A_j)         (i sends, j receives)

where ``a_i`` is robot i's Ed25519 secret scalar (the clamped first half of SHA-512 of its
RFC 8032 seed, which is exactly X25519's private scalar), ``A_i`` its Ed25519 public key and
``u_i`` the same point on the Montgomery curve, u = (1 + y) / (1 − y) mod 2²⁵⁵ − 19 (RFC 7748
§4.1's birational map; y is the Edwards coordinate A_i encodes). A datagram from i to j ends in
HMAC-SHA256 over all bytes before it with K_{i→j}, truncated to 16 bytes (as the fleet
``hmac`` policy), flagged in the header (flag bit 4).

Why this holds against a stolen robot: K_{1→2} needs a_1 or a_2. Robot 3's secret gives it
every K_{3→j} and K_{j→3} and nothing else, so it can send as itself, or "as robot 1" only to
itself. What it gives up against ``ed25519``: a datagram is meant for one receiver (the
transport sends one datagram per neighbour anyway) and the receiver could have made it itself
(no non-repudiation, which nothing here uses). What it buys: an HMAC instead of a signature and
a signature verification per datagram (about 5 µs instead of 40 + 150 µs here,
docs/benchmarks.md) and 16-byte trailers instead of 64.

Key rotation (a robot listing two public keys): a receiver tries K derived from each key the
sender lists, so a sender may switch to its new secret at any time. A sender to j uses the key
of j's under which j's last accepted datagram verified (before j is heard: the last key listed,
the newest), so when j switches to its new secret its neighbours follow after its first
datagram (at 2 Hz, within a round).
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Mapping

from dran_edge.comms.keys import RobotIdentity, _ed25519, public_key_of
from dran_edge.errors import ConfigError, DependencyError

#: Field prime of Curve25519 / edwards25519.
_P = 2**255 - 19
#: HKDF salt: names the scheme and its version (a new derivation gets a new salt).
_SALT = b"dran-edge pairwise v1"
#: Truncated HMAC-SHA256 tag length (RFC 4868's HMAC-SHA-256-128), as the fleet policy's.
TAG_BYTES = 16


def _x25519():
    try:
        from cryptography.hazmat.primitives.asymmetric import x25519
    except ImportError as exc:
        raise DependencyError(
            f"comms.auth pairwise needs the 'cryptography' package ({exc}); "
            "install it with: pip install 'dran-edge[comms]'"
        ) from None
    return x25519


def montgomery_u(ed25519_public: bytes) -> bytes:
    """The X25519 public key (u coordinate, 32 bytes little-endian) of an Ed25519 public key.

    RFC 8032 §5.1.2 encodes y (255 bits, little-endian) and the sign of x in the top bit;
    RFC 7748 §4.1 maps (x, y) on edwards25519 to u = (1 + y) / (1 − y) on Curve25519. The
    sign of x does not matter (u is the same for ±x). y = 1 (the neutral point) has no image
    and is refused, as is a y outside the field."""
    if len(ed25519_public) != 32:
        raise ConfigError(f"expected a 32-byte Ed25519 public key, got {len(ed25519_public)}")
    y = int.from_bytes(ed25519_public, "little") & ((1 << 255) - 1)
    if y >= _P or y == 1:
        raise ConfigError(f"Ed25519 public key {ed25519_public.hex()} is not a usable point")
    u = (1 + y) * pow(1 - y, _P - 2, _P) % _P
    return u.to_bytes(32, "little")


def x25519_private(seed: bytes) -> bytes:
    """The X25519 private key bytes of an Ed25519 seed: the first half of SHA-512(seed)
    (X25519 clamps it exactly as RFC 8032 clamps the Ed25519 secret scalar)."""
    return hashlib.sha512(seed).digest()[:32]


def _hkdf_sha256(ikm: bytes, info: bytes, length: int = 32) -> bytes:
    """RFC 5869 with SHA-256 (extract, then expand; one or two blocks)."""
    prk = hmac.digest(_SALT, ikm, "sha256")
    out, block, i = b"", b"", 1
    while len(out) < length:
        block = hmac.digest(prk, block + info + bytes([i]), "sha256")
        out, i = out + block, i + 1
    return out[:length]


def _info(fleet_id: int, sender: int, receiver: int, a_sender: bytes, a_receiver: bytes) -> bytes:
    return (
        fleet_id.to_bytes(2, "big")
        + sender.to_bytes(2, "big")
        + receiver.to_bytes(2, "big")
        + a_sender
        + a_receiver
    )


class PairwiseIdentity(RobotIdentity):
    """A robot's credentials under the ``pairwise`` policy: the same secret and fleet public
    keys as ``RobotIdentity`` (``ed25519`` policy), used to agree pairwise keys instead of
    signing."""


class PairwiseKeys:
    """One robot's directional pair keys with every robot that has a public key, and the key
    choice per receiver (shared by this robot's signer and verifier)."""

    def __init__(self, identity: RobotIdentity, self_id: int, fleet_id: int):
        self.self_id, self.fleet_id = int(self_id), int(fleet_id)
        x25519 = _x25519()
        own_public = public_key_of(identity.secret)
        private = x25519.X25519PrivateKey.from_private_bytes(x25519_private(identity.secret))
        #: robot -> [K_{self→robot}, ...] and [K_{robot→self}, ...], one per listed public key.
        self._send: dict[int, tuple[bytes, ...]] = {}
        self._recv: dict[int, tuple[bytes, ...]] = {}
        #: robot -> index of the public key it was last heard with (default: the newest).
        self._choice: dict[int, int] = {}
        for robot, publics in identity.public_keys.items():
            robot = int(robot)
            if robot == self.self_id:
                continue
            send, recv = [], []
            for a_other in publics:
                try:
                    shared = private.exchange(
                        x25519.X25519PublicKey.from_public_bytes(montgomery_u(bytes(a_other)))
                    )
                except ValueError as exc:  # a low-order point: the shared secret would be zero
                    raise ConfigError(
                        f"public key {bytes(a_other).hex()} of robot {robot} cannot be used for "
                        f"a pair key ({exc})"
                    ) from None
                send.append(
                    _hkdf_sha256(
                        shared,
                        _info(self.fleet_id, self.self_id, robot, own_public, bytes(a_other)),
                    )
                )
                recv.append(
                    _hkdf_sha256(
                        shared,
                        _info(self.fleet_id, robot, self.self_id, bytes(a_other), own_public),
                    )
                )
            self._send[robot], self._recv[robot] = tuple(send), tuple(recv)
            self._choice[robot] = len(send) - 1

    def robots(self) -> frozenset[int]:
        """The robots this robot shares pair keys with."""
        return frozenset(self._send)

    def tag_for(self, receiver: int, body: bytes | memoryview) -> bytes:
        """The trailer of a datagram body sent to ``receiver`` (KeyError: no public key)."""
        key = self._send[receiver][self._choice[receiver]]
        return hmac.digest(key, body, "sha256")[:TAG_BYTES]

    def verify(self, sender: int, body: bytes | memoryview, tag: bytes) -> int | None:
        """The index of ``sender``'s public key whose pair key made ``tag``, else None."""
        for index, key in enumerate(self._recv.get(sender, ())):
            if hmac.compare_digest(tag, hmac.digest(key, body, "sha256")[:TAG_BYTES]):
                return index
        return None

    def heard(self, sender: int, index: int) -> None:
        """``sender`` was accepted under its ``index``-th public key: answer it with that one."""
        if sender in self._choice:
            self._choice[sender] = index


def pairwise_keys(
    credentials: RobotIdentity | Mapping, self_id: int, fleet_id: int
) -> PairwiseKeys:
    """``PairwiseKeys`` of a ``PairwiseIdentity`` (the link's policy gives ids)."""
    if not isinstance(credentials, RobotIdentity):
        raise TypeError("pairwise keys need the robot's own secret (a PairwiseIdentity)")
    _ed25519()  # the same dependency message as the ed25519 policy when cryptography is missing
    return PairwiseKeys(credentials, self_id, fleet_id)
