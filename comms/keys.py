"""Key files of the two key policies (docs/wire-format.md, "Authentication").

- fleet HMAC key (``hmac`` policy): one line of 64..128 hex digits, mode 0600;
- robot secret key (``ed25519`` policy): ``ed25519-secret <64 hex digits>`` (the RFC 8032
  seed), mode 0600, with its public half next to it in ``<path>.pub`` (``robot_id`` and
  ``public_key``, shareable);
- fleet public keys: ``fleet: NAME`` and ``public_keys: {ID: HEX or [HEX, HEX]}``, the same
  file on every robot (``dran-edge fleet-key export`` writes it; two keys while a robot
  rotates).

Secret files must give no group/other access; loading refuses them otherwise, naming the file
and its mode. The ``cryptography`` package is imported only for the ed25519 policy.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Mapping
from dataclasses import dataclass

from dran_edge.errors import ConfigError, DependencyError

#: Accepted key lengths in bytes (the key file holds them hex-encoded).
KEY_MIN_BYTES = 32
KEY_MAX_BYTES = 64
#: Ed25519 secret seed and public key lengths (RFC 8032).
ED25519_KEY_BYTES = 32
#: First word of a robot's secret key file (tells it apart from a fleet HMAC key).
_ROBOT_KEY_WORD = "ed25519-secret"
#: Key policies (the config's ``comms.auth``).
POLICIES = ("hmac", "ed25519", "pairwise")


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
            f"{what} has mode {mode:04o}; expected no group/other access (run: chmod 600 {path})",
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


def write_fleet_public_keys(
    path: str | os.PathLike, fleet: str, keys: Mapping[int, tuple[bytes, ...]]
) -> None:
    """Write the fleet public-key file read by ``load_fleet_public_keys`` (overwrites: no secret)."""
    lines = [
        "# dran-edge fleet public keys (Ed25519): the same file on every robot",
        f"fleet: {fleet}",
        "public_keys:",
    ]
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


def fleet_public_keys(cfg) -> dict[int, tuple[bytes, ...]]:
    """Robot id -> accepted public keys named by a robot config (``dran_edge.config``): its
    ``comms.public_keys_file`` plus every ``neighbours[].public_keys``; ConfigError naming the
    file when the key file does not load or names another fleet."""
    keys: dict[int, tuple[bytes, ...]] = {}
    path = cfg.resolve(cfg.comms.public_keys_file)
    if path is not None:
        fleet, keys = load_fleet_public_keys(path)
        if fleet and fleet != cfg.robot.fleet:
            raise ConfigError(
                f"comms.public_keys_file is for fleet {fleet!r}, this robot is in "
                f"{cfg.robot.fleet!r}",
                path=str(path),
            )
    for n in cfg.neighbours:
        extra = tuple(bytes.fromhex(k) for k in n.public_keys)
        keys[n.id] = tuple(dict.fromkeys(keys.get(n.id, ()) + extra))
        if not keys[n.id]:
            del keys[n.id]
    return keys


def credentials_from_config(cfg) -> bytes | RobotIdentity:
    """What ``comms.auth`` and ``comms.key_file`` of a robot config name: the fleet HMAC key
    (``hmac``) or this robot's ``RobotIdentity`` (``ed25519``; its ``PairwiseIdentity``
    subclass for ``pairwise``). ConfigError on a missing or unreadable key, a key file of the
    other policy, or a neighbour without a public key."""
    key_path = cfg.resolve(cfg.comms.key_file)
    if key_path is None:
        raise ConfigError(
            "comms.key_file: not set, but comms.transport is 'udp'", path=cfg.source_path or None
        )
    if cfg.comms.auth == "hmac":
        return load_fleet_key(key_path)
    secret = load_robot_key(key_path)
    keys = fleet_public_keys(cfg)
    missing = sorted({n.id for n in cfg.neighbours} - set(keys))
    if missing:
        raise ConfigError(
            f"comms.auth {cfg.comms.auth}: no public key for neighbour(s) {missing} (add them to "
            "comms.public_keys_file, or neighbours[].public_keys)",
            path=cfg.source_path or None,
        )
    own = keys.get(cfg.robot.id)
    if own is not None and public_key_of(secret) not in own:
        raise ConfigError(
            f"comms.key_file's public key is not robot {cfg.robot.id}'s in the fleet's public "
            "keys (a key file of another robot, or public keys not yet exported)",
            path=str(key_path),
        )
    if cfg.comms.auth == "pairwise":
        from dran_edge.comms.pairwise import PairwiseIdentity

        return PairwiseIdentity(secret, keys)
    return RobotIdentity(secret, keys)
