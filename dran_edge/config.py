"""One robot's configuration: frozen dataclasses and a strict YAML loader (docs/config.md).

A robot reads one YAML file (schema and examples: ``docs/config.md``, ``calib/fleet/``)::

    robot:      {id: 1, name: dingo1, fleet: dingo6}
    neighbours: [{id: 2, name: dingo2, address: "10.42.0.12:5600"}]
    comms:      {port: 5600, key_file: /etc/dran-edge/fleet.key}
    ingest:     {socket_path: ""}          # "" -> $RUNTIME_DIRECTORY/ingest.sock
    camera:     {source: realsense, calib_dir: calib/cameras}
    daemon:     {state_dir: ""}            # "" -> $STATE_DIRECTORY
    agent:      {beta: 1.0, graph: {max_nodes: 400}}

Loading is strict: an unknown key, a wrong type or an out-of-range value raises
:class:`~dran_edge.errors.ConfigError` naming the file, the line, the key path (``agent.beta``)
and the reason. Every field has a default except ``robot.id``/``robot.name``/``robot.fleet``.

The dataclasses are pure (stdlib only) so the core (``AgentConfig``, ``GraphBounds``) can use
them; each field carries its unit in its name or docstring and its valid range in
``metadata`` (checked by the loader and again on direct construction).
"""

from __future__ import annotations

import contextvars
import dataclasses
import ipaddress
import math
import re
import types
import typing
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

from dran_edge.errors import ConfigError

_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,15}$")


_Choice = typing.TypeVar("_Choice", bound="StrChoice")


class StrChoice(str, Enum):
    """A choice among fixed strings, checked once where a config is loaded or built: members
    compare equal to their strings and print, format and serialise (JSON) as them."""

    def __str__(self) -> str:
        return str.__str__(self)

    def __format__(self, format_spec: str) -> str:
        return str.__format__(self, format_spec)

    @classmethod
    def parse(cls: type[_Choice], value: Any, key: str) -> _Choice:
        """The member named by ``value`` (a member or its string); ValueError naming ``key``,
        the bad value and the allowed ones otherwise."""
        try:
            return cls(value)
        except ValueError:
            allowed = ", ".join(repr(m.value) for m in cls)
            raise ValueError(f"{key}: expected one of {allowed}, got {value!r}") from None


class Residual(StrChoice):
    """The edge residual of paper eq. 2."""

    GEODESIC = "geodesic"
    """Log(T̃⁻¹ T_p⁻¹ T_q) ∈ se(d)."""
    CHORDAL = "chordal"
    """The entries of T̃⁻¹ T_p⁻¹ T_q − I (rotation and translation parts)."""


class RobustKernel(StrChoice):
    """A robust kernel ρ on squared whitened residual norms (``none``: least squares)."""

    NONE = "none"
    HUBER = "huber"
    CAUCHY = "cauchy"


def _f(default: Any, *, lo: float | None = None, hi: float | None = None,
       choices: tuple | None = None, lo_open: bool = False) -> Any:
    """A dataclass field with its valid range (``lo <= v <= hi``; ``lo < v`` if ``lo_open``)."""
    meta = {"lo": lo, "hi": hi, "choices": choices, "lo_open": lo_open}
    if isinstance(default, (list, dict, tuple)) and not isinstance(default, tuple):
        return field(default_factory=lambda: default, metadata=meta)
    if dataclasses.is_dataclass(default):
        return field(default_factory=lambda d=default: d, metadata=meta)
    return field(default=default, metadata=meta)


def _check_value(value: Any, meta: dict, key: str) -> None:
    """Range / choice check of one scalar field; raises ConfigError naming ``key``."""
    if not meta:
        return
    choices = meta.get("choices")
    if choices is not None and value not in choices:
        allowed = ", ".join(repr(getattr(c, "value", c)) for c in choices)
        raise ConfigError(f"{key}: expected one of {allowed}, got {value!r}")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")
        lo, hi = meta.get("lo"), meta.get("hi")
        if lo is not None:
            if meta.get("lo_open") and not value > lo:
                raise ConfigError(f"{key}: expected a value > {lo}, got {value!r}")
            if not meta.get("lo_open") and not value >= lo:
                raise ConfigError(f"{key}: expected a value >= {lo}, got {value!r}")
        if hi is not None and not value <= hi:
            raise ConfigError(f"{key}: expected a value <= {hi}, got {value!r}")


def _validate_fields(obj: Any) -> None:
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if isinstance(f.default, StrChoice):
            # a string choice (from code) becomes its member, once, here
            _check_value(value, dict(f.metadata), f.name)
            object.__setattr__(obj, f.name, type(f.default)(value))
            continue
        if isinstance(value, tuple):
            for i, item in enumerate(value):
                if not dataclasses.is_dataclass(item):
                    _check_value(item, dict(f.metadata), f"{f.name}[{i}]")
        else:
            _check_value(value, dict(f.metadata), f.name)


class _Checked:
    """Mixin: validate field ranges on construction (also for configs built in code)."""

    def __post_init__(self) -> None:
        _validate_fields(self)
        self._check()

    def _check(self) -> None:
        """Cross-field checks; raise ConfigError naming the field."""


# --------------------------------------------------------------------------- core sections
@dataclass(frozen=True)
class NoiseModel(_Checked):
    """Isotropic-per-block noise of one measurement kind (VINS-Mono gives no covariances)."""

    sigma_translation_m: float = _f(0.05, lo=0.0, lo_open=True)
    """Standard deviation of each translation component, metres."""
    sigma_rotation_rad: float = _f(0.02, lo=0.0, lo_open=True)
    """Standard deviation of each rotation component (tangent), radians."""


@dataclass(frozen=True)
class OdometryNoise(_Checked):
    """Noise of an odometry edge between two kept keyframes, growing with the motion between them.

    sigma_t = sigma_translation_m + per_metre * |dt|;
    sigma_r = sigma_rotation_rad + per_radian * |dr|.
    """

    sigma_translation_m: float = _f(0.01, lo=0.0, lo_open=True)
    """Translation standard deviation of any odometry edge, metres."""
    sigma_rotation_rad: float = _f(0.005, lo=0.0, lo_open=True)
    """Rotation standard deviation of any odometry edge, radians."""
    per_metre: float = _f(0.02, lo=0.0)
    """Added translation standard deviation per metre travelled (VIO drift), m/m."""
    per_radian: float = _f(0.01, lo=0.0)
    """Added rotation standard deviation per radian turned, rad/rad."""


@dataclass(frozen=True)
class GraphBounds(_Checked):
    """Keyframe selection, segmenting and the hard size cap of the bounded local graph."""

    keyframe_min_distance_m: float = _f(0.3, lo=0.0)
    """A VIO keyframe becomes a graph node once it is this far from the last node, metres."""
    keyframe_min_angle_rad: float = _f(0.26, lo=0.0)
    """... or has turned this much since the last node, radians."""
    keyframe_max_interval_s: float = _f(5.0, lo=0.0, lo_open=True)
    """... or this much time has passed since the last node, seconds."""
    max_nodes: int = _f(400, lo=8, hi=1_000_000)
    """Hard cap on trajectory nodes; over it the oldest removable nodes are marginalised."""
    max_edges: int = _f(1600, lo=8, hi=10_000_000)
    """Hard cap on factors (odometry, loop, object, prior) in the local graph."""
    segment_gap_s: float = _f(1.0, lo=0.0, lo_open=True)
    """An odometry stamp gap longer than this starts a new segment, seconds (VINS restarts on 1 s)."""
    segment_jump_m: float = _f(1.0, lo=0.0, lo_open=True)
    """A position jump between consecutive odometry samples above this starts a new segment, metres."""
    segment_jump_rad: float = _f(0.8, lo=0.0, lo_open=True)
    """A rotation jump between consecutive odometry samples above this starts a new segment, rad."""
    observation_max_dt_s: float = _f(0.5, lo=0.0, lo_open=True)
    """An observation is attached to a keyframe only if odometry brackets it within this, seconds."""

    def _check(self) -> None:
        if self.max_edges < self.max_nodes:
            raise ConfigError(
                f"max_edges: expected >= max_nodes ({self.max_nodes}), got {self.max_edges}"
            )


@dataclass(frozen=True)
class AgentConfig(_Checked):
    """Parameters of one robot's DRAN agent (paper Sec. 4, Alg. 1; defaults from Sec. 5)."""

    robot_id: int = _f(0, lo=0, hi=65535)
    """This robot's id (copied from ``robot.id`` by the loader)."""
    neighbours: tuple[int, ...] = _f((), lo=0, hi=65535)
    """Ids of the communication neighbours (copied from ``neighbours`` by the loader)."""
    dim: int = _f(3, choices=(2, 3))
    """2 for SE(2), 3 for SE(3)."""
    residual: Residual = _f(Residual.GEODESIC, choices=tuple(Residual))
    """Residual of eq. 2: geodesic Log(T~^-1 Tp^-1 Tq) or chordal."""
    beta: float = _f(1.0, lo=0.0, lo_open=True)
    """Penalty parameter beta of the augmented Lagrangian (eq. 4)."""
    eta: float = _f(0.1, lo=0.0, lo_open=True)
    """Dual step eta of eq. 5b."""
    alpha: float = _f(1.0, lo=0.0, lo_open=True, hi=1.0)
    """Step size on the public variables v (objects): y <- Retr_y(alpha v) (Alg. 1 line 13)."""
    gamma: float = _f(1.0, lo=0.0, lo_open=True, hi=1.0)
    """Step size on the private variables u (trajectory): x <- Retr_x(gamma u) (Alg. 1 line 13)."""
    sor_omega: float = _f(1.0, lo=0.0, lo_open=True, hi=1.99)
    """Over-relaxation omega of the inter-robot iteration on the trajectory: after the accepted
    local step x <- Retr_x(gamma u) the robot keeps Retr_x(omega gamma u) instead (1: plain
    Alg. 1). With a colour schedule this is block SOR (docs/dran.md); the robot's first local
    step is always plain."""
    colours: int = _f(1, lo=1, hi=256)
    """Update schedule: the robot runs its local step only in rounds k with
    (k - 1) mod colours == colour; 1 is the paper's every-round (parallel) schedule, more give a
    Gauss-Seidel-like order when neighbours have different colours (docs/dran.md)."""
    colour: int = _f(0, lo=0, hi=255)
    """This robot's colour in the schedule (0 <= colour < colours)."""
    eps_u: float = _f(1e-2, lo=0.0)
    """Terminate when the private step norm |u| < eps_u."""
    eps_v: float = _f(1e-1, lo=0.0)
    """... and the public step norm |v| < eps_v."""
    eps_phi: float = _f(1e-1, lo=0.0)
    """... and the consensus error |phi| < eps_phi."""
    eps_cost_rel: float = _f(0.0, lo=0.0)
    """Also optimal when the round's local step lowered L̂_i by at most this fraction of it
    (0: off, the paper's ε_u/ε_v rule alone). Steps that no longer pay stop the traffic of a
    slowly converging tail (docs/dran.md)."""
    stop_rule: str = _f("steps", choices=("tail", "steps"))
    """Which local test feeds the stop (docs/notes/stopping-rule.md). "tail": the remaining
    decrease of L̂_i predicted from the local Newton decrement (the Schur-reduced gradient in the
    metric of the local Hessian) and its observed contraction rate, relative to L̂_i, at most
    stop_tol, with the consensus penalty energy also at most stop_tol × L̂_i; a robot reports
    convergence only once its done counter (propagated as the minimum over its neighbours)
    reaches stop_rounds; the done counter rides in every neighbour message (one byte).
    "steps" (default, the robot daemon's): the paper's eps_u/eps_v (and eps_cost_rel) test
    alone; the daemon never stops on it, it only reports it. The benchmarks that stop on the
    rule (bench g2o, bench objects) use "tail"."""
    stop_tol: float = _f(1e-3, lo=0.0, lo_open=True)
    """"tail" rule: bound on the predicted remaining relative decrease of L̂_i."""
    stop_window: int = _f(20, lo=4, hi=1000)
    """"tail" rule: own local steps over which the contraction rate is estimated (the test
    needs this many steps of history)."""
    stop_rounds: int = _f(10, lo=1, hi=255)
    """"tail" rule: done counter needed to report convergence. The counter is 0 while the local
    test fails, else one more than the smallest of its own last value and the neighbours'
    counters; so it reaches this only when every robot within (this − 1) hops has passed its
    local test for the last rounds. Set above the communication graph's diameter."""
    k_max: int = _f(500, lo=1, hi=1_000_000)
    """Maximum number of local steps (DRAN iterations) of one optimisation."""
    mu_init: float = _f(1e-4, lo=0.0, lo_open=True)
    """Initial Levenberg-Marquardt damping mu of M = J^T J + mu I (eq. 7)."""
    robust_kernel: RobustKernel = _f(RobustKernel.HUBER, choices=tuple(RobustKernel))
    """Robust kernel on loop and object residuals (whitened)."""
    robust_threshold: float = _f(1.345, lo=0.0, lo_open=True)
    """Kernel width on the whitened residual norm (1.345: 95 % efficiency for Huber)."""
    object_robust_threshold: float = _f(0.0, lo=0.0)
    """Kernel width on object observations alone (0: robust_threshold). Loops want a tight
    kernel (a false loop is wrong by metres and must not pull); an observation that passed the
    gates wants a wider one, or the kernel also holds back the right ones while the
    trajectories still drift (docs/dran.md, robustness)."""
    dual_max_phi2: float = _f(0.1, lo=0.0)
    """Anti-windup of eq. 5b: a dual λ_ij is updated only while φ²(y_i, y_j) is at most this
    (squared geodesic distance, same units as eps_phi; default = the paper's eps_phi)."""
    object_gate_m: float = _f(2.0, lo=0.0)
    """Consistency gate: an object observation whose predicted object position is farther than
    this from the medoid of the robot's predictions of that object is dropped (0: off), metres."""
    object_min_views: int = _f(1, lo=1, hi=100)
    """An own object observation is used only when at least this many own observations of that
    object (itself included) agree within object_gate_m, or a neighbour's copy lies within
    object_gate_m of it (1: every observation that passes the gate; 2 rejects lone wrong ids)."""
    object_exclusion_m: float = _f(0.5, lo=0.0)
    """Spatial exclusion for lone observations (object_min_views > 1): a lone observation whose
    predicted object position is farther than this from every own observation of another object
    is used at once instead of waiting for a neighbour's corroboration. Two objects do not occupy
    one place, so a wrong id (a second label on something seen there) lies within it of the
    right one's views. By the same rule an observation within it of another object's views, with
    no more views of its own object there than that object has, waits however many views it has
    (a tag misread the same way from several keyframes). 0: off, every lone observation waits
    and repeated ones are used. Metres."""
    corroboration_ratio: float = _f(2.0, lo=0.0)
    """A held-back observation (object_min_views > 1) is also corroborated when a neighbour's
    copy of its object lies within association_gate_m of its prediction and this many times
    nearer than any copy of another object (a ratio test: the view's stretch of trajectory may
    have drifted past object_gate_m, but a wrong id lies where the seen object's copies are).
    0: off, corroboration within object_gate_m only."""
    association_gate_m: float = _f(8.0, lo=0.0)
    """Cross-robot association check: an own object observation predicting the object farther
    than this from the evidence-weighted medoid of the copies (one vote per observing robot,
    weighted by its number of observations; docs/dran.md) is dropped as a wrong association
    (0: off), metres."""
    centre_reach_m: float = _f(16.0, lo=0.0)
    """With a robust kernel and association_gate_m > 0: a neighbour's copy farther than this
    from the association check's centre for its object (the copy the votes side with,
    ``ObjectAssociation.check``) is in conflict whatever its origin, and its consensus term
    gets the Cauchy kernel. A copy built from a lone wrong view in the first rounds is dropped
    by the check within a round or two, but least squares has by then averaged it into the
    relays around it, which carry the right origin and vouch for the dragged value. 16 m, like
    conflict_reach_m: a drifted copy and a centre each within association_gate_m of the object
    are at most that far apart; at 8 m the kernel also held honestly drifted copies apart (one
    simulation seed's 20 % outlier run fell 15-26 % behind the outlier-free one; docs/dran.md,
    robustness). 0: off. Metres."""
    conflict_reach_m: float = _f(16.0, lo=0.0)
    """With a robust kernel: a neighbour's copy from another observing robot that lies farther
    than this from ours stands for another hypothesis (a wrong id), and its consensus term gets
    the Cauchy kernel (``ObjectAssociation.conflicts``); closer copies pull as least squares. Two copies
    each within association_gate_m (8 m) of the object are at most twice that apart. The first
    rounds' drift can exceed it (drifted copies up to 21.5 m apart on simulation seeds 0 and
    5), and a wider reach lets nearer wrong hypotheses pull (docs/dran.md, robustness). 0: off
    (with centre_reach_m also 0 every consensus term is least squares). Metres."""
    send_threshold: float = _f(1e-4, lo=0.0)
    """A separator/object entry is re-sent to a neighbour only when an element of its pose matrix
    moved by more than this since it was last sent to that neighbour (metres / unitless)."""
    resend_period_rounds: int = _f(20, lo=1, hi=1_000_000)
    """... or when it was last sent this many rounds ago (recovers from lost datagrams)."""
    relay_max_hops: int = _f(3, lo=0, hi=32)
    """Object estimates learned from others are relayed at most this many hops (Sec. 4.2.2)."""
    init_max_iterations: int = _f(50, lo=1, hi=10_000)
    """Iterations of each stage of the distributed chordal initialisation (Sec. 4.2.1)."""
    seed: int = _f(0, lo=0)
    """Seed of any randomness inside the agent (determinism)."""
    odometry_noise: OdometryNoise = _f(OdometryNoise())
    """Noise model of odometry edges."""
    loop_noise: NoiseModel = _f(NoiseModel(0.1, 0.05))
    """Noise model of DBoW2 loop closures (relative pose T_old_cur)."""
    object_noise: NoiseModel = _f(NoiseModel(0.05, 0.05))
    """Noise of tag observations when perception gives no covariance."""
    inter_robot_noise: NoiseModel = _f(NoiseModel(0.1, 0.05))
    """Noise of inter-robot relative-pose measurements (object-free mode)."""
    graph: GraphBounds = _f(GraphBounds())
    """The bounded local graph."""

    @property
    def object_kernel_width(self) -> float:
        """The kernel width in use on object observations (object_robust_threshold, or else
        robust_threshold)."""
        return self.object_robust_threshold or self.robust_threshold

    def _check(self) -> None:
        if self.robot_id in self.neighbours:
            raise ConfigError(f"neighbours: a robot cannot neighbour itself (id {self.robot_id})")
        if len(set(self.neighbours)) != len(self.neighbours):
            raise ConfigError(f"neighbours: expected distinct ids, got {list(self.neighbours)}")
        if self.colour >= self.colours:
            raise ConfigError(f"colour: expected a value < colours ({self.colours}), got {self.colour}")


# --------------------------------------------------------------------------- shell sections
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
            raise ConfigError(f"T_world_odom: expected 7 finite numbers [x, y, z, qx, qy, qz, "
                              f"qw] or [], got {list(pose)}")
        if pose and abs(math.sqrt(sum(v * v for v in pose[3:])) - 1.0) > 1e-3:
            raise ConfigError(f"T_world_odom: expected a unit quaternion (norm within 1e-3 of "
                              f"1), got {list(pose[3:])}")


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


# --------------------------------------------------------------------------- loading
_SKIP_ON_LOAD = {("RobotConfig", "source_path")}
# Filled from other sections by the loader; a file may not set them.
_DERIVED = {("AgentConfig", "robot_id"), ("AgentConfig", "neighbours")}


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(value: Any, tp: Any, key: str, lines: dict[str, int]) -> Any:
    """Convert one YAML value to the annotated type ``tp`` strictly (no silent coercion)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _convert(value, args[0], key, lines)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, key, lines)
    if origin is tuple:
        if not isinstance(value, list):
            raise _err(f"{key}: expected a list, got {_describe(value)}", key, lines)
        (item_tp, _ellipsis) = typing.get_args(tp)
        return tuple(
            _convert(v, item_tp, f"{key}[{i}]", lines) for i, v in enumerate(value)
        )
    if tp is bool:
        if not isinstance(value, bool):
            raise _err(f"{key}: expected true or false, got {_describe(value)}", key, lines)
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _err(f"{key}: expected an integer, got {_describe(value)}", key, lines)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _err(f"{key}: expected a number, got {_describe(value)}", key, lines)
        return float(value)
    if isinstance(tp, type) and issubclass(tp, StrChoice):
        if not isinstance(value, str):
            raise _err(f"{key}: expected a string, got {_describe(value)}", key, lines)
        try:
            return tp.parse(value, key)
        except ValueError as exc:
            raise _err(str(exc), key, lines) from None
    if tp is str:
        if not isinstance(value, str):
            raise _err(f"{key}: expected a string, got {_describe(value)}", key, lines)
        return value
    raise AssertionError(f"unsupported config type {tp!r} at {key}")


def _describe(value: Any) -> str:
    if value is None:
        return "nothing (null)"
    return f"{type(value).__name__} {value!r}"


class _LoadError(Exception):
    def __init__(self, message: str, line: int | None):
        super().__init__(message)
        self.line = line


def _err(message: str, key: str, lines: dict[str, int]) -> _LoadError:
    while key and key not in lines:
        parent = re.sub(r"(\.[^.\[]*|\[\d+\])$", "", key)
        key = "" if parent == key else parent
    return _LoadError(message, lines.get(key))


class _Skip(Exception):
    """Collecting mode: this value failed and its errors are recorded; leave it out."""


#: Collecting mode (``load_config_report``): a list that receives every error instead of the
#: first one raising.
_COLLECT: contextvars.ContextVar[list | None] = contextvars.ContextVar("_COLLECT", default=None)


def _fail(exc: _LoadError) -> None:
    """Raise ``exc``, or in collecting mode record it and leave the value out."""
    errors = _COLLECT.get()
    if errors is None:
        raise exc
    errors.append(exc)
    raise _Skip


def _required(cls: type, name: str, f: dataclasses.Field) -> bool:
    has_default = f.default is not dataclasses.MISSING and f.default is not None
    return (not has_default and f.default_factory is dataclasses.MISSING  # type: ignore[misc]
            and (cls.__name__, name) not in _DERIVED)


def _build(cls: type, data: Any, prefix: str, lines: dict[str, int]) -> Any:
    where = prefix or "top level"
    if not isinstance(data, dict):
        _fail(_err(f"{where}: expected a mapping of keys, got {_describe(data)}", prefix, lines))
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)
              if (cls.__name__, f.name) not in _SKIP_ON_LOAD}
    settable = {n for n in fields if (cls.__name__, n) not in _DERIVED}
    kwargs: dict[str, Any] = {}
    failed: set[str] = set()
    for key, value in data.items():
        try:
            kwargs[key] = _build_key(key, value, prefix, lines, fields, settable, hints)
        except _Skip:
            failed.add(key)
    for name, f in fields.items():
        if name in kwargs or name in failed:
            continue
        if _required(cls, name, f):
            path = f"{prefix}.{name}" if prefix else name
            try:
                _fail(_err(f"{path}: required key is missing", prefix, lines))
            except _Skip:
                failed.add(name)
    if failed & {n for n, f in fields.items() if _required(cls, n, f)}:
        raise _Skip  # a required value failed: this section cannot be built
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        # Cross-field check: the message starts with the field name; prefix the section.
        msg = str(exc)
        path = f"{prefix}.{msg}" if prefix else msg
        _fail(_err(path, f"{prefix}.{msg.split(':', 1)[0]}" if prefix else msg.split(":", 1)[0],
                   lines))


def _build_key(key: Any, value: Any, prefix: str, lines: dict[str, int], fields: dict,
               settable: set, hints: dict) -> Any:
    """One key of a section, converted and range-checked."""
    path = f"{prefix}.{key}" if prefix else str(key)
    if key not in settable:
        known = ", ".join(sorted(settable))
        reason = "is set from robot/neighbours, not here" if key in fields else "unknown key"
        _fail(_err(f"{path}: {reason} (allowed here: {known})", path, lines))
    f = fields[key]
    try:
        converted = _convert(value, hints[key], path, lines)
    except _LoadError as exc:
        _fail(exc)
    if not dataclasses.is_dataclass(converted):
        items = converted if isinstance(converted, tuple) else (converted,)
        for i, item in enumerate(items):
            if dataclasses.is_dataclass(item):
                continue
            try:
                item_path = path if items is not converted else f"{path}[{i}]"
                _check_value(item, dict(f.metadata), item_path)
            except ConfigError as exc:
                _fail(_err(str(exc), path, lines))
    return converted


def _line_map(text: str) -> dict[str, int]:
    """Key path -> 1-based line, from the YAML node tree; also rejects duplicate keys."""
    import yaml

    lines: dict[str, int] = {}
    root = yaml.compose(text, Loader=yaml.SafeLoader)

    def walk(node: Any, path: str) -> None:
        if isinstance(node, yaml.MappingNode):
            seen: set[str] = set()
            for k_node, v_node in node.value:
                key = str(k_node.value)
                child = f"{path}.{key}" if path else key
                if key in seen:
                    raise _LoadError(f"{child}: duplicate key", k_node.start_mark.line + 1)
                seen.add(key)
                lines[child] = k_node.start_mark.line + 1
                walk(v_node, child)
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                child = f"{path}[{i}]"
                lines[child] = item.start_mark.line + 1
                walk(item, child)

    if root is not None:
        walk(root, "")
    return lines


def config_from_dict(data: Any, *, source_path: str = "", lines: dict[str, int] | None = None
                     ) -> RobotConfig:
    """Build a :class:`RobotConfig` from parsed YAML; ConfigError (with key path) on any problem."""
    lines = lines or {}
    try:
        cfg = _build(RobotConfig, data, "", lines)
    except _LoadError as exc:
        raise ConfigError(str(exc), path=source_path or None, line=exc.line) from None
    except ConfigError as exc:
        raise ConfigError(str(exc), path=source_path or None) from None
    agent = dataclasses.replace(
        cfg.agent, robot_id=cfg.robot.id, neighbours=tuple(n.id for n in cfg.neighbours)
    )
    return dataclasses.replace(cfg, agent=agent, source_path=source_path)


def _read_yaml(path: Path) -> tuple[Any, dict[str, int]]:
    """(parsed YAML, key path -> line) of a config file; ConfigError naming the file."""
    import yaml

    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read the config file: {exc.strerror}", path=str(path)) from None
    try:
        lines = _line_map(text)
        data = yaml.safe_load(text)
    except _LoadError as exc:
        raise ConfigError(str(exc), path=str(path), line=exc.line) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"not valid YAML: {problem}", path=str(path), line=line) from None
    if data is None:
        raise ConfigError("the file is empty; expected at least a 'robot' section", path=str(path))
    return data, lines


def load_config(path: str | Path) -> RobotConfig:
    """Read and strictly validate one robot's YAML file (the first problem raises)."""
    path = Path(path)
    data, lines = _read_yaml(path)
    return config_from_dict(data, source_path=str(path), lines=lines)


def load_config_report(path: str | Path) -> tuple[RobotConfig | None, list[ConfigError]]:
    """Like :func:`load_config`, but every problem of the file instead of the first: (the
    config, or None when a required part failed; the errors in file order). A key with a
    problem is left at its default, so the config returned is for further checks only."""
    path = Path(path)
    try:
        data, lines = _read_yaml(path)
    except ConfigError as exc:
        return None, [exc]
    errors: list = []
    token = _COLLECT.set(errors)
    try:
        try:
            cfg = _build(RobotConfig, data, "", lines)
        except _Skip:
            cfg = None
    finally:
        _COLLECT.reset(token)
    out = []
    for e in errors:
        err = ConfigError(str(e), path=str(path), line=e.line)
        #: the top-level section the problem is in ("comms", "neighbours", ...)
        err.section = re.split(r"[.\[:]", str(e), maxsplit=1)[0]
        out.append(err)
    out.sort(key=lambda e: e.line or 0)
    if cfg is None:
        return None, out
    agent = dataclasses.replace(
        cfg.agent, robot_id=cfg.robot.id, neighbours=tuple(n.id for n in cfg.neighbours))
    return dataclasses.replace(cfg, agent=agent, source_path=str(path)), out


def config_to_dict(cfg: Any) -> Any:
    """The inverse of loading: plain dicts/lists (for ``robot.yaml`` in a recorded run)."""
    if dataclasses.is_dataclass(cfg):
        out = {}
        for f in dataclasses.fields(cfg):
            if (type(cfg).__name__, f.name) in _SKIP_ON_LOAD | _DERIVED:
                continue
            out[f.name] = config_to_dict(getattr(cfg, f.name))
        return out
    if isinstance(cfg, tuple):
        return [config_to_dict(v) for v in cfg]
    if isinstance(cfg, StrChoice):
        return cfg.value  # plain YAML
    return cfg
