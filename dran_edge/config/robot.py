"""Configuration of the robot's shell: identity, neighbours, comms, ingest, camera, daemon, and the
whole file (``RobotConfig``)."""

from __future__ import annotations

import ipaddress
import math
import re
from dataclasses import dataclass
from pathlib import Path

from dran_edge.config.agent import AgentConfig
from dran_edge.config.fields import _NAME_RE, _Checked, _f
from dran_edge.errors import ConfigError


@dataclass(frozen=True)
class RobotSection(_Checked):
    """Who this robot is."""

    id: int = _f(None, lo=0, hi=65535)
    """Robot id, unique within the fleet (0..65535)."""
    name: str = _f(None)
    """Robot name (letters, digits, ``_.-``; <= 15 characters)."""
    fleet: str = _f(None)
    """Fleet name; also the RADIO/DISH group, so <= 15 characters."""
    T_world_odom: tuple[float, ...] = _f(())
    """The robot's first VIO frame in the fleet's world, ``[x, y, z, qx, qy, qz, qw]`` (metres,
    unit quaternion), when known (e.g. from mocap at the start, as a recorded run's
    mission.yaml has it); the robot then anchors its first keyframe there. Empty: unknown, only
    the robot whose id is below all its neighbours' carries the gauge prior."""

    def _check(self) -> None:
        for key in ("name", "fleet"):
            value = getattr(self, key)
            if value is not None and not _NAME_RE.match(value):
                raise ConfigError(
                    f"{key}: expected 1-15 characters of [A-Za-z0-9_.-], got {value!r}"
                )
        pose = self.T_world_odom
        if pose and (len(pose) != 7 or not all(math.isfinite(v) for v in pose)):
            raise ConfigError(
                f"T_world_odom: expected 7 finite numbers [x, y, z, qx, qy, qz, "
                f"qw] or [], got {list(pose)}"
            )
        if pose and abs(math.sqrt(sum(v * v for v in pose[3:])) - 1.0) > 1e-3:
            raise ConfigError(
                f"T_world_odom: expected a unit quaternion (norm within 1e-3 of "
                f"1), got {list(pose[3:])}"
            )


@dataclass(frozen=True)
class Neighbour(_Checked):
    """One communication neighbour."""

    id: int = _f(None, lo=0, hi=65535)
    """The neighbour's robot id."""
    name: str = _f("")
    """Its name (for logs and status)."""
    address: str = _f(None)
    """Its DISH endpoint ``ip:port`` (IPv6 as ``[addr]:port``)."""
    public_keys: tuple[str, ...] = _f(())
    """With ``comms.auth: ed25519``: its Ed25519 public key(s), 64 hex digits each (two while
    it rotates its key pair); adds to ``comms.public_keys_file``."""

    def _check(self) -> None:
        if self.address is not None:
            parse_address(self.address, "address")
        for i, text in enumerate(self.public_keys):
            if not re.fullmatch(r"[0-9A-Fa-f]{64}", text):
                raise ConfigError(
                    f"public_keys[{i}]: expected an Ed25519 public key as 64 hex digits, "
                    f"got {text[:80]!r}"
                )


def parse_address(text: str, key: str) -> tuple[str, int]:
    """``"10.0.0.2:5600"`` / ``"[::1]:5600"`` -> (ip, port); ConfigError otherwise."""
    m = re.match(r"^\[([0-9A-Fa-f:.]+)\]:(\d{1,5})$", text) or re.match(
        r"^([0-9.]+):(\d{1,5})$", text
    )
    if not m:
        raise ConfigError(f"{key}: expected 'ip:port' (IPv6 as '[ip]:port'), got {text!r}")
    host, port = m.group(1), int(m.group(2))
    try:
        ipaddress.ip_address(host)
    except ValueError:
        raise ConfigError(f"{key}: expected an IP address, got {host!r}") from None
    if not 1 <= port <= 65535:
        raise ConfigError(f"{key}: expected a port in 1..65535, got {port}")
    return host, port


@dataclass(frozen=True)
class CommsSection(_Checked):
    """Neighbour link (ZeroMQ UDP RADIO/DISH, docs/wire-format.md)."""

    transport: str = _f("udp", choices=("udp", "none"))
    """``udp``: RADIO/DISH to the neighbours; ``none``: no radio (a lone robot or a laptop)."""
    bind_address: str = _f("0.0.0.0")
    """Address the DISH binds to."""
    port: int = _f(5600, lo=1, hi=65535)
    """UDP port the DISH binds to."""
    auth: str = _f("hmac", choices=("hmac", "ed25519", "pairwise"))
    """Key policy (docs/wire-format.md, "Authentication"): ``hmac``, one secret key shared by
    the fleet (any holder can sign as any robot); ``ed25519``, one key pair per robot (a robot
    can sign only as itself); ``pairwise``, the same key pairs agreeing an HMAC key per pair of
    robots (a robot can send only as itself, at an HMAC's cost). Every robot of a fleet uses the
    same policy."""
    key_file: str = _f("")
    """Secret key file (mode 0600, owned by the daemon's user); relative to the config. ``hmac``:
    the fleet key (``dran-edge fleet-key new``); ``ed25519`` and ``pairwise``: this robot's
    secret key (``dran-edge fleet-key pair``)."""
    public_keys_file: str = _f("")
    """With ``auth: ed25519`` or ``pairwise``: the fleet's public keys (``dran-edge fleet-key export``), the same
    file on every robot; relative to the config. Needed unless every neighbour lists its
    ``public_keys``."""
    datagram_max_bytes: int = _f(1200, lo=256, hi=4096)
    """Largest datagram we send, bytes (the codec's hard cap is 4096; libzmq UDP breaks ~8 KB)."""
    period_s: float = _f(0.5, lo=0.01, hi=60.0)
    """Round period: one DRAN round and one exchange per period, seconds (2 Hz default)."""
    allow_relay_from: tuple[int, ...] = _f((), lo=0, hi=65535)
    """Robots not configured as neighbours whose relayed datagrams are still accepted."""
    heartbeat_period_s: float = _f(2.0, lo=0.0)
    """A neighbour sent nothing for this long gets an entry-less datagram (a heartbeat), so it
    can tell a quiet robot from a dead link (0: off), seconds."""
    delta_every: int = _f(20, lo=0, hi=10_000)
    """> 0: send separators and object estimates as quantised changes against per-neighbour
    state (the delta layout, docs/wire-format.md), each sent whole again at least every this
    many rounds; 0: whole values only (what builds before the layout read)."""

    def _check(self) -> None:
        try:
            ipaddress.ip_address(self.bind_address)
        except ValueError:
            raise ConfigError(
                f"bind_address: expected an IP address, got {self.bind_address!r}"
            ) from None


@dataclass(frozen=True)
class IngestSection(_Checked):
    """The local ingest socket the VINS bridge writes to (docs/ingest.md)."""

    enabled: bool = _f(True)
    """Open the ingest socket (false on a robot without VINS)."""
    socket_path: str = _f("")
    """Socket path; "" means ``$RUNTIME_DIRECTORY/ingest.sock`` (or ``<state_dir>/run/``)."""
    socket_mode: int = _f(0o660, lo=0, hi=0o777)
    """Permission bits of the socket (group-writable, never world-writable)."""
    max_pending_records: int = _f(20000, lo=16, hi=10_000_000)
    """Records held between ticks before the oldest odometry is dropped (counted)."""

    def _check(self) -> None:
        if self.socket_mode & 0o007:
            raise ConfigError(
                f"socket_mode: expected no permissions for others, got {oct(self.socket_mode)}"
            )


@dataclass(frozen=True)
class CameraSection(_Checked):
    """Where frames come from and how tags become object observations."""

    source: str = _f("none", choices=("none", "realsense", "oak", "forwarded", "recorded"))
    """Frame source: none, pyrealsense2 direct, depthai, frames over the ingest socket, a recording."""
    calib_dir: str = _f("")
    """Directory with the camera calibration (intrinsics, T_body_camera); relative to the file."""
    tags_file: str = _f("")
    """Tag -> object map (calib/tags.yaml format); relative to the config file."""
    serial: str = _f("")
    """Device serial number ("" = the first device found)."""
    recording: str = _f("")
    """For ``recorded``: the frames directory or a .bag; relative to the config file."""
    width: int = _f(640, lo=16, hi=8192)
    """Colour width, pixels."""
    height: int = _f(480, lo=16, hi=8192)
    """Colour height, pixels."""
    fps: int = _f(15, lo=1, hi=120)
    """Frame rate asked of the device, Hz."""
    queue_size: int = _f(8, lo=1, hi=1024)
    """Observation batches queued from the perception worker to the agent (drop-oldest)."""


@dataclass(frozen=True)
class DaemonSection(_Checked):
    """Where the daemon keeps its state and how often it checkpoints."""

    state_dir: str = _f("")
    """Checkpoint directory; "" means ``$STATE_DIRECTORY`` (systemd) or ``./dran-edge-state``."""
    runtime_dir: str = _f("")
    """Socket directory; "" means ``$RUNTIME_DIRECTORY`` (systemd) or ``<state_dir>/run``."""
    checkpoint_period_s: float = _f(5.0, lo=0.0, lo_open=True)
    """Checkpoint at most this often, seconds (and always on stop)."""
    status_period_s: float = _f(5.0, lo=0.1)
    """Send STATUS= to systemd and log a status line this often, seconds."""
    foxglove: str = _f("")
    """Publish the robot's estimate live (trajectory, object map, round statistics, neighbour
    links) on a Foxglove WebSocket server at ``ip:port`` (docs/viz.md; needs foxglove-sdk);
    "" = off."""

    def _check(self) -> None:
        if self.foxglove:
            parse_address(self.foxglove, "foxglove")


@dataclass(frozen=True)
class RobotConfig(_Checked):
    """A robot's whole configuration file."""

    robot: RobotSection
    neighbours: tuple[Neighbour, ...] = _f(())
    comms: CommsSection = _f(CommsSection())
    ingest: IngestSection = _f(IngestSection())
    camera: CameraSection = _f(CameraSection())
    daemon: DaemonSection = _f(DaemonSection())
    agent: AgentConfig = _f(AgentConfig())
    source_path: str = _f("")
    """The file this was loaded from ("" when built in code); relative paths resolve against it."""

    def _check(self) -> None:
        ids = [n.id for n in self.neighbours]
        if len(set(ids)) != len(ids):
            raise ConfigError(f"neighbours: expected distinct ids, got {ids}")
        if self.robot.id in ids:
            raise ConfigError(f"neighbours: robot {self.robot.id} lists itself as a neighbour")

    def resolve(self, path_text: str) -> Path | None:
        """A path from this config, relative ones against the config file's directory."""
        if not path_text:
            return None
        p = Path(path_text).expanduser()
        if not p.is_absolute() and self.source_path:
            p = Path(self.source_path).resolve().parent / p
        return p
