"""Simulated Dingo missions: the world, the robots' paths and everything their sensors report.

A mission is generated from :class:`SimParams` and one seed, deterministically:

- **World.** ``objects`` boxes (cubes of ``box_size_m``) on a jittered grid in a square arena,
  each with one tag36h11 tag on each of its four vertical faces (tag ids ``4k .. 4k+3`` for
  object ``k``; tag frame as pupil-apriltags: x right, y down, z into the tag as seen by the
  viewer). Z-up world, metres.
- **Paths.** Each robot drives an approximately circular path (radius with a slow wobble) at
  ``speed_mps``, among the boxes: centres and radii are drawn until the path keeps
  ``clearance_m`` from every box and the robot sees at least two boxes. Planar truth: the
  body (IMU) frame is at ``imu_height_m`` with x forward, z up.
- **VIO** (after VINS-Mono, docs/vins-mono.md): odometry at ``odom_rate_hz`` in the VIO's own
  gravity-aligned world (``odom``), which starts at the body pose when a segment starts. Drift:
  a per-segment scale error, a yaw-rate bias doing a random walk, white noise per step, a slow
  height random walk and bounded roll/pitch noise (gravity keeps those observable).
  Occasional resets (Poisson, ``resets_per_min`` per robot): no output for ``reset_gap_s``,
  then a new segment whose ``odom`` frame is the body pose at restart.
- **Keyframes** from the VIO output by travelled distance / turned angle / elapsed time.
- **Loops** (DBoW2-like, within one robot): a keyframe near an old one (position and yaw) is
  detected with ``loop_probability``, against the oldest qualifying candidate at least
  ``loop_min_age_kf`` keyframes back; the measurement is the true ``T_old_cur`` with small
  noise. A fraction ``loop_outlier_fraction`` of loops are wrong: a random old keyframe with a
  plausible-looking relative pose (|yaw| < 30 deg, |t| < 2 m, the gates VINS applies).
- **Camera.** A D435i-like colour camera (``fx = fy = 615``, 640 x 480) at ``T_body_camera``;
  frames at ``frame_rate_hz``; a tag is visible if it faces the camera (< ``max_view_angle``),
  is within ``max_range_m``, projects inside the image, and no other box blocks the line of
  sight (boxes as circles in the plane).
- **Communication graph.** Random connected and sparse: a random spanning tree plus each other
  pair with probability ``comm_edge_probability``.
- **Mocap.** Every robot and box as a Motive rigid body (pivot offsets ``T_body_marker``,
  ``T_object_marker``) at ``mocap_rate_hz``, with a few short occlusions of robot bodies.

This module is pure numpy; the VIO, keyframe and loop models are in :mod:`dran_edge.sim.sensors`;
:mod:`dran_edge.sim.writer` turns a :class:`Mission` into a run
directory (frames rendered by the perception renderer, ingest records, Motive CSV).

Size: over ~500 lines because the world and path generation (sensor models are in
sim/sensors.py); over 500 only by ruff format's layout.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import InputError
from dran_edge.sim.sensors import (
    select_keyframes,
    simulate_loops,
    simulate_vio,
    stamps_at_rate,
    yaw_pose,
)

#: Wall-clock-like stamp of the mission start (2026-01-01T00:00:00Z), nanoseconds.
DEFAULT_START_NS = 1_767_225_600_000_000_000
TAGS_PER_OBJECT = 4


@dataclass(frozen=True)
class SimParams:
    """Everything that shapes a simulated mission (defaults: a 6-robot, 3-minute mission)."""

    robots: int = 6
    """Number of robots (1..32)."""
    objects: int = 9
    """Number of tagged boxes (1..64)."""
    duration_s: float = 180.0
    """Mission length, seconds."""
    seed: int = 0
    """Seed of every random choice; same seed, same mission, byte for byte."""
    start_ns: int = DEFAULT_START_NS
    """Stamp of the mission start, nanoseconds (robot clocks and mocap time 0)."""
    arena_m: float = 9.0
    """Edge of the square arena the boxes stand in, metres."""
    box_size_m: float = 0.4
    """Edge of a box (cube), metres."""
    tag_size_m: float = 0.2
    """Tag size (edge of the black square), metres."""
    speed_mps: float = 0.35
    """Robot forward speed, m/s."""
    radius_range_m: tuple[float, float] = (1.6, 3.0)
    """Range of the circles' radii, metres."""
    clearance_m: float = 0.6
    """Least distance between a path and a box centre, metres."""
    imu_height_m: float = 0.12
    """Height of the body (IMU) frame above the floor, metres."""
    odom_rate_hz: float = 10.0
    """VIO odometry rate, Hz (VINS-Mono publishes once per processed image)."""
    frame_rate_hz: float = 2.0
    """Rate of recorded camera frames, Hz (kept low so simulate and replay stay fast)."""
    mocap_rate_hz: float = 30.0
    """Motive export frame rate, Hz."""
    # --- VIO drift
    scale_error_sigma: float = 0.02
    """Per-segment scale error of the VIO translation (1 sigma, fraction)."""
    yaw_bias_sigma_rad_s: float = 5e-4
    """Initial yaw-rate bias of a segment (1 sigma), rad/s."""
    yaw_bias_walk_rad_s_sqrt_s: float = 5e-5
    """Random walk of the yaw-rate bias, rad/s per sqrt(s)."""
    step_noise_m: float = 0.002
    """White translation noise per odometry step, metres."""
    step_noise_rad: float = 0.0005
    """White yaw noise per odometry step, radians."""
    height_walk_m_sqrt_s: float = 0.002
    """Random walk of the VIO height, metres per sqrt(s)."""
    tilt_noise_rad: float = 0.003
    """Bounded roll/pitch noise of the VIO attitude, radians."""
    resets_per_min: float = 0.15
    """Expected VIO resets per robot per minute (none in the first and last 20 s)."""
    reset_gap_s: float = 1.5
    """No VIO output for this long after a failure (re-initialisation), seconds."""
    announce_resets: bool = True
    """Write a RESET record at each restart (else the daemon must detect the gap itself)."""
    # --- keyframes and loops
    keyframe_distance_m: float = 0.25
    """A VIO keyframe every this many metres travelled ..."""
    keyframe_angle_rad: float = 0.2
    """... or this much turned ..."""
    keyframe_interval_s: float = 2.0
    """... or this long since the last one."""
    loop_probability: float = 0.3
    """Probability that an eligible keyframe (near an old one) is detected as a loop."""
    loop_max_distance_m: float = 0.8
    """Largest true distance between the two keyframes of a correct loop, metres."""
    loop_max_yaw_rad: float = 0.35
    """Largest true yaw difference of a correct loop, radians."""
    loop_min_age_kf: int = 30
    """The old keyframe is at least this many keyframes back (VINS uses 50 pose-graph frames)."""
    loop_min_interval_s: float = 3.0
    """At most one loop per robot in this time, seconds."""
    loop_noise_m: float = 0.02
    """Translation noise of a correct loop (1 sigma per axis), metres."""
    loop_noise_rad: float = 0.01
    """Rotation noise of a correct loop (1 sigma per axis), radians."""
    loop_outlier_fraction: float = 0.05
    """Fraction of loops that are wrong (false DBoW2 matches that passed PnP)."""
    # --- camera and observations
    max_range_m: float = 5.0
    """Tags farther than this are not seen, metres."""
    max_view_angle_rad: float = math.radians(70.0)
    """Tags seen more obliquely than this are not seen, radians."""
    obs_noise_m: float = 0.01
    """Noise of a direct tag observation per metre of range (no-frames mode), metres."""
    obs_noise_rad: float = 0.02
    """Rotation noise of a direct tag observation (no-frames mode), radians."""
    # --- communication
    comm_edge_probability: float = 0.2
    """Probability of each extra link beyond the random spanning tree."""
    # --- mocap
    mocap_dropout_per_min: float = 1.0
    """Short occlusions (0.1-0.5 s) of each robot's rigid body per minute."""

    def __post_init__(self) -> None:
        checks = [
            ("robots", 1 <= self.robots <= 32, "1..32"),
            ("objects", 1 <= self.objects <= 64, "1..64"),
            ("duration_s", 1.0 <= self.duration_s <= 24 * 3600, "1 s .. 24 h"),
            ("seed", self.seed >= 0, ">= 0"),
            ("frame_rate_hz", 0.0 <= self.frame_rate_hz <= 60.0, "0..60 Hz (0 = no frames)"),
            ("odom_rate_hz", 1.0 <= self.odom_rate_hz <= 400.0, "1..400 Hz"),
            ("mocap_rate_hz", 1.0 <= self.mocap_rate_hz <= 360.0, "1..360 Hz"),
            ("speed_mps", 0.05 <= self.speed_mps <= 1.3, "0.05..1.3 m/s (a Dingo)"),
            ("loop_outlier_fraction", 0.0 <= self.loop_outlier_fraction < 1.0, "0 <= f < 1"),
            ("comm_edge_probability", 0.0 <= self.comm_edge_probability <= 1.0, "0..1"),
        ]
        for name, ok, expected in checks:
            if not ok:
                raise InputError(f"{name}: expected {expected}, got {getattr(self, name)!r}")


# ------------------------------------------------------------------------------------ camera
#: D435i-like colour intrinsics at 640 x 480 (no distortion, docs/perception.md).
CAMERA_K = np.array([[615.0, 0.0, 319.5], [0.0, 615.0, 239.5], [0.0, 0.0, 1.0]])
CAMERA_WIDTH, CAMERA_HEIGHT = 640, 480
#: Camera 0.15 m ahead of and 0.1 m above the IMU, looking forward (z_cam = x_body).
T_BODY_CAMERA = geo.se3_from_rt(
    np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), np.array([0.15, 0.0, 0.10])
)
#: Mocap pivot of a robot: 0.3 m above the IMU (markers on a mast), same axes.
T_BODY_MARKER = geo.se3_from_rt(np.eye(3), np.array([0.0, 0.0, 0.30]))


#: Mocap pivot of a box: the centre of its top face.
def _object_marker(box_size_m: float) -> np.ndarray:
    return geo.se3_from_rt(np.eye(3), np.array([0.0, 0.0, box_size_m / 2]))


# ------------------------------------------------------------------------------------- world
@dataclass(frozen=True, eq=False)
class World:
    """The boxes and their tags (static), Z-up world frame, metres."""

    object_ids: np.ndarray
    """(n,) object ids 0..n-1."""
    T_world_object: np.ndarray
    """(n, 4, 4) box centre poses."""
    box_size_m: float
    tag_size_m: float
    T_object_tag: np.ndarray
    """(4, 4, 4) the four face tags in the box frame (the same for every box)."""

    @property
    def tag_ids(self) -> np.ndarray:
        """(n, 4) tag ids of each object's faces."""
        return self.object_ids[:, None] * TAGS_PER_OBJECT + np.arange(TAGS_PER_OBJECT)

    @property
    def T_world_tag(self) -> np.ndarray:
        """(n, 4, 4, 4) every tag in the world."""
        return self.T_world_object[:, None] @ self.T_object_tag[None]


def face_tags(box_size_m: float) -> np.ndarray:
    """T_object_tag of the four vertical faces (outward normals +x, +y, -x, -y)."""
    out = []
    down = np.array([0.0, 0.0, -1.0])
    for k in range(TAGS_PER_OBJECT):
        a = k * math.pi / 2
        n = np.array([math.cos(a), math.sin(a), 0.0])
        z = -n
        x = np.cross(down, z)
        R = np.column_stack([x, down, z])
        out.append(geo.se3_from_rt(R, n * (box_size_m / 2 + 0.001)))
    return np.stack(out)


def make_world(p: SimParams, rng: np.random.Generator) -> World:
    """Boxes on a jittered grid filling the arena, each turned by a random yaw."""
    cols = math.ceil(math.sqrt(p.objects))
    rows = math.ceil(p.objects / cols)
    spacing = p.arena_m / max(cols, rows)
    cells = [(r, c) for r in range(rows) for c in range(cols)]
    chosen = rng.permutation(len(cells))[: p.objects]
    centres = []
    for k in sorted(chosen.tolist()):
        r, c = cells[k]
        jitter = rng.uniform(-0.2, 0.2, size=2) * spacing
        centres.append([(c + 0.5) * spacing + jitter[0], (r + 0.5) * spacing + jitter[1]])
    xy = np.asarray(centres) - p.arena_m / 2
    yaw = rng.uniform(-math.pi, math.pi, size=p.objects)
    T = yaw_pose(xy[:, 0], xy[:, 1], p.box_size_m / 2, yaw)
    return World(np.arange(p.objects), T, p.box_size_m, p.tag_size_m, face_tags(p.box_size_m))


# -------------------------------------------------------------------------------------- paths
@dataclass(frozen=True)
class CirclePath:
    """An approximately circular path: radius ``r (1 + wobble sin(2 pi f t + psi))``."""

    centre_xy: tuple[float, float]
    radius_m: float
    direction: int
    """+1 counter-clockwise, -1 clockwise."""
    phase_rad: float
    wobble: float
    wobble_hz: float
    wobble_phase_rad: float
    speed_mps: float
    height_m: float

    def _xy(self, t_s: np.ndarray) -> np.ndarray:
        theta = self.phase_rad + self.direction * self.speed_mps * t_s / self.radius_m
        r = self.radius_m * (
            1 + self.wobble * np.sin(2 * np.pi * self.wobble_hz * t_s + self.wobble_phase_rad)
        )
        return np.stack(
            [self.centre_xy[0] + r * np.cos(theta), self.centre_xy[1] + r * np.sin(theta)], axis=-1
        )

    def poses(self, t_s: np.ndarray) -> np.ndarray:
        """T_world_body at times ``t_s`` (seconds from the mission start), heading along the path."""
        t_s = np.asarray(t_s, dtype=np.float64)
        xy = self._xy(t_s)
        d = self._xy(t_s + 1e-3) - self._xy(t_s - 1e-3)
        return yaw_pose(xy[..., 0], xy[..., 1], self.height_m, np.arctan2(d[..., 1], d[..., 0]))


def _random_path(p: SimParams, rng: np.random.Generator) -> CirclePath:
    r = rng.uniform(*p.radius_range_m)
    half = p.arena_m / 2
    return CirclePath(
        centre_xy=tuple(rng.uniform(-half + r * 0.5, half - r * 0.5, size=2).tolist()),
        radius_m=float(r),
        direction=int(rng.choice([-1, 1])),
        phase_rad=float(rng.uniform(-math.pi, math.pi)),
        wobble=float(rng.uniform(0.03, 0.1)),
        wobble_hz=float(rng.uniform(0.01, 0.03)),
        wobble_phase_rad=float(rng.uniform(-math.pi, math.pi)),
        speed_mps=float(p.speed_mps * rng.uniform(0.85, 1.15)),
        height_m=p.imu_height_m,
    )


# --------------------------------------------------------------------------------- visibility
def visible_tags(
    world: World, T_world_camera: np.ndarray, p: SimParams
) -> tuple[np.ndarray, np.ndarray]:
    """Which tags each camera pose sees, and their poses in the camera.

    Returns ``(visible (m, n, 4) bool, T_camera_tag (m, n, 4, 4, 4))`` for ``m`` camera poses.
    """
    T_cam_world = geo.se3_inverse(T_world_camera)  # (m, 4, 4)
    T_ct = T_cam_world[:, None, None] @ world.T_world_tag[None]  # (m, n, 4, 4, 4)
    t = T_ct[..., :3, 3]
    z_axis = T_ct[..., :3, 2]
    dist = np.linalg.norm(t, axis=-1)
    # facing: the tag's z (into the tag) points away from the camera: cos = z . t / |t|
    cos_view = np.einsum("...i,...i->...", z_axis, t) / np.maximum(dist, 1e-9)
    half = p.tag_size_m / 2 * 1.25
    corners = np.array(
        [[-half, -half, 0, 1], [half, -half, 0, 1], [half, half, 0, 1], [-half, half, 0, 1.0]]
    )
    pc = np.einsum("...ij,kj->...ki", T_ct[..., :3, :], corners)  # (m, n, 4, 4 corners, 3)
    z = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = CAMERA_K[0, 0] * pc[..., 0] / z + CAMERA_K[0, 2]
        v = CAMERA_K[1, 1] * pc[..., 1] / z + CAMERA_K[1, 2]
    inside = np.all(
        (z > 0.1) & (u >= 2) & (u <= CAMERA_WIDTH - 3) & (v >= 2) & (v <= CAMERA_HEIGHT - 3),
        axis=-1,
    )
    vis = inside & (dist < p.max_range_m) & (cos_view > math.cos(p.max_view_angle_rad))
    # line of sight blocked by another box (circles of the box's half diagonal in the plane)
    cam_xy = T_world_camera[:, None, None, :2, 3]
    tag_xy = world.T_world_tag[None, ..., :2, 3]
    seg = tag_xy - cam_xy  # (m, n, 4, 2)
    box_xy = world.T_world_object[:, :2, 3]  # (n, 2)
    rel = box_xy[None, None, None] - cam_xy[..., None, :]  # (m, n, 4, n_box, 2)
    seg_len2 = np.maximum(np.sum(seg**2, -1), 1e-12)[..., None]
    s = np.clip(np.einsum("...kj,...j->...k", rel, seg) / seg_len2, 0.0, 1.0)
    closest = cam_xy[..., None, :] + s[..., None] * seg[..., None, :]
    d_box = np.linalg.norm(closest - box_xy[None, None, None], axis=-1)
    own = np.eye(len(box_xy), dtype=bool)[None, :, None, :]
    blocked = np.any((d_box < world.box_size_m * 0.6) & ~own & (s < 0.98), axis=-1)
    return vis & ~blocked, T_ct


# ------------------------------------------------------------------------------------ robots
@dataclass(frozen=True, eq=False)
class RobotMission:
    """One robot's truth and sensor outputs."""

    robot_id: int
    name: str
    path: CirclePath
    odom_stamps_ns: np.ndarray
    """(k,) stamps of VIO outputs."""
    T_world_body: np.ndarray
    """(k, 4, 4) truth at the odometry stamps."""
    T_odom_body: np.ndarray
    """(k, 4, 4) VIO output (in the segment's own odom frame)."""
    segment: np.ndarray
    """(k,) segment index of each VIO output (0, 1, ... after each reset)."""
    T_world_odom: np.ndarray
    """(s, 4, 4) the true odom frame of each segment in the world."""
    reset_stamps_ns: np.ndarray
    """(s-1,) stamp of the first output of each new segment."""
    keyframes: np.ndarray
    """(j,) indices into the odometry arrays of the keyframes."""
    loops: np.ndarray
    """(l, 2) keyframe indices (into ``keyframes``) (old, cur)."""
    loop_T_old_cur: np.ndarray
    """(l, 4, 4) measured loop relative poses."""
    loop_outlier: np.ndarray
    """(l,) bool: the loop is wrong."""
    frame_stamps_ns: np.ndarray
    """(f,) camera frame stamps."""
    T_world_body_frames: np.ndarray
    """(f, 4, 4) truth at the frame stamps."""


@dataclass(frozen=True, eq=False)
class Mission:
    """A whole simulated mission."""

    params: SimParams
    world: World
    robots: tuple[RobotMission, ...]
    comm_edges: tuple[tuple[int, int], ...]
    """Undirected communication links as pairs of robot ids (i < j)."""
    mocap_time_s: np.ndarray = field(repr=False)
    """(k,) Motive times from take start (= mission start)."""


def comm_graph(
    n: int, edge_probability: float, rng: np.random.Generator
) -> tuple[tuple[int, int], ...]:
    """A random connected graph on 0..n-1: a random spanning tree plus extra edges."""
    order = rng.permutation(n)
    edges = set()
    for k in range(1, n):
        a, b = int(order[k]), int(order[rng.integers(0, k)])
        edges.add((min(a, b), max(a, b)))
    for a in range(n):
        for b in range(a + 1, n):
            if (a, b) not in edges and rng.random() < edge_probability:
                edges.add((a, b))
    return tuple(sorted(edges))


def _seen_objects(world: World, path: CirclePath, p: SimParams) -> np.ndarray:
    t = np.arange(0.0, p.duration_s, 1.0)
    T_wc = path.poses(t) @ T_BODY_CAMERA
    vis, _ = visible_tags(world, T_wc, p)
    return np.flatnonzero(np.any(vis, axis=(0, 2)))


def _path_ok(world: World, path: CirclePath, p: SimParams) -> bool:
    t = np.linspace(0.0, 2 * math.pi * path.radius_m * 1.2 / path.speed_mps, 400)
    xy = path.poses(t)[:, :2, 3]
    d = np.linalg.norm(xy[:, None] - world.T_world_object[None, :, :2, 3], axis=-1)
    half = p.arena_m / 2 + 1.0
    return bool(d.min() >= p.clearance_m and np.all(np.abs(xy) <= half))


def generate_mission(p: SimParams) -> Mission:
    """The mission of ``p`` (deterministic in ``p.seed``)."""
    root = np.random.SeedSequence(p.seed)
    world_seq, graph_seq, *robot_seqs = root.spawn(2 + p.robots)
    world = make_world(p, np.random.default_rng(world_seq))
    robots = []
    for i, seq in enumerate(robot_seqs):
        path_rng, vio_rng, loop_rng = (np.random.default_rng(s) for s in seq.spawn(3))
        path = None
        for _ in range(500):
            cand = _random_path(p, path_rng)
            if _path_ok(world, cand, p) and (
                p.objects < 2 or len(_seen_objects(world, cand, p)) >= 2
            ):
                path = cand
                break
        if path is None:
            raise InputError(
                f"robot {i + 1}: no path among the {p.objects} boxes keeps "
                f"{p.clearance_m} m clearance and sees two boxes; use a larger arena"
            )
        robots.append(_robot(p, i + 1, path, vio_rng, loop_rng))
    graph = comm_graph(p.robots, p.comm_edge_probability, np.random.default_rng(graph_seq))
    edges = tuple((a + 1, b + 1) for a, b in graph)
    mocap_t = np.arange(int(math.floor(p.duration_s * p.mocap_rate_hz)) + 1) / p.mocap_rate_hz
    return Mission(p, world, tuple(robots), edges, mocap_t)


def _robot(p: SimParams, robot_id: int, path: CirclePath, vio_rng, loop_rng) -> RobotMission:
    stamps = stamps_at_rate(p.start_ns, p.duration_s, p.odom_rate_hz)
    t_s = (stamps - p.start_ns) / 1e9
    T_wb = path.poses(t_s)
    keep, T_ob, segment, T_wo = simulate_vio(p, T_wb, t_s, vio_rng)
    stamps, T_wb, T_ob, segment, t_s = (
        stamps[keep],
        T_wb[keep],
        T_ob[keep],
        segment[keep],
        t_s[keep],
    )
    reset_stamps = stamps[np.flatnonzero(np.diff(segment)) + 1]
    kf = select_keyframes(p, T_ob, t_s, segment)
    pairs, meas, outl = simulate_loops(p, T_wb[kf], t_s[kf], loop_rng)
    if p.frame_rate_hz > 0:
        # frames start half a frame period in, so they are not synchronous with odometry
        f_stamps = stamps_at_rate(
            p.start_ns, p.duration_s, p.frame_rate_hz, 0.5 / p.frame_rate_hz + 0.0137 * robot_id
        )
    else:
        f_stamps = np.zeros(0, np.int64)
    T_wb_f = path.poses((f_stamps - p.start_ns) / 1e9) if len(f_stamps) else np.zeros((0, 4, 4))
    return RobotMission(
        robot_id,
        f"dingo{robot_id}",
        path,
        stamps,
        T_wb,
        T_ob,
        segment,
        T_wo,
        reset_stamps,
        kf,
        pairs,
        meas,
        outl,
        f_stamps,
        T_wb_f,
    )


def mocap_poses(m: Mission, rng: np.random.Generator | None = None) -> dict[str, np.ndarray]:
    """Rigid-body poses per Motive body name at ``m.mocap_time_s`` (NaN where occluded)."""
    rng = rng if rng is not None else np.random.default_rng(m.params.seed + 99)
    p = m.params
    out = {}
    t = m.mocap_time_s
    for r in m.robots:
        T = r.path.poses(t) @ T_BODY_MARKER
        n_drop = int(rng.poisson(p.mocap_dropout_per_min * p.duration_s / 60.0))
        for _ in range(n_drop):
            t0, length = rng.uniform(1.0, max(p.duration_s - 1.0, 1.0)), rng.uniform(0.1, 0.5)
            T[(t >= t0) & (t < t0 + length)] = np.nan
        out[r.name] = T
    T_om = _object_marker(m.world.box_size_m)
    for k in m.world.object_ids:
        out[f"box{k}"] = np.broadcast_to(m.world.T_world_object[k] @ T_om, (len(t), 4, 4)).copy()
    return out


def direct_observations(
    m: Mission, robot: RobotMission, rng: np.random.Generator
) -> list[tuple[int, list[tuple[int, np.ndarray, np.ndarray]]]]:
    """No-frames mode: per frame stamp, the objects seen as (object_id, T_body_object, cov).

    The noise grows with range (``obs_noise_m`` per metre); the covariance given is the one
    the noise was drawn from, in [translation, rotation] order.
    """
    p = m.params
    if len(robot.frame_stamps_ns) == 0:
        return []
    T_wc = robot.T_world_body_frames @ T_BODY_CAMERA
    vis, _ = visible_tags(m.world, T_wc, p)
    seen = np.any(vis, axis=2)  # (f, n)
    out = []
    T_bw = geo.se3_inverse(robot.T_world_body_frames)
    for f, stamp in enumerate(robot.frame_stamps_ns.tolist()):
        obs = []
        for k in np.flatnonzero(seen[f]).tolist():
            T_bo = T_bw[f] @ m.world.T_world_object[k]
            rng_m = float(np.linalg.norm(T_bo[:3, 3]))
            sig_t, sig_r = max(p.obs_noise_m * rng_m, 0.002), p.obs_noise_rad
            xi = np.r_[sig_t * rng.standard_normal(3), sig_r * rng.standard_normal(3)]
            cov = np.diag([sig_t**2] * 3 + [sig_r**2] * 3)
            obs.append((int(m.world.object_ids[k]), T_bo @ geo.se3_exp(xi), cov))
        if obs:
            out.append((stamp, obs))
    return out


def params_to_dict(p: SimParams) -> dict:
    """Plain values for ``mission.yaml``'s ``simulation`` section."""
    d = dataclasses.asdict(p)
    d["radius_range_m"] = list(p.radius_range_m)
    return d
