"""The bag mapping file (docs/bags.md): which topic of which bag is what, per robot.

Read strictly like every dran-edge file: an unknown key, a missing key or a wrong type is an
:class:`~dran_edge.errors.InputError` naming the file, the line and the key. Pure (pyyaml,
numpy, :mod:`dran_edge.formats.run_dir`'s YAML helpers).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dran_edge.formats import run_dir as rd

MAP_FORMAT = "dran-edge-bag-map/1"
CLOCKS = ("header", "receive")
LOOP_FORMS = ("vins", "pose_pair")


@dataclass(frozen=True, eq=False)
class ImageMap:
    """A robot's camera topics."""

    topic: str
    camera_info: str | None = None
    depth: str | None = None
    T_body_camera: np.ndarray | None = None
    depth_unit_m: float = 0.001
    max_rate_hz: float | None = None
    """Keep at most this many frames per second (None: every frame)."""
    encode: str = "png"
    """How raw sensor_msgs/Image frames are stored: png (compressed) or pnm (PGM/PPM, fast)."""


@dataclass(frozen=True, eq=False)
class LoopMap:
    form: str  # "vins" | "pose_pair"
    topic: str | None = None  # vins
    old: str | None = None  # pose_pair
    cur: str | None = None  # pose_pair


@dataclass(frozen=True, eq=False)
class RobotMap:
    id: int
    name: str
    odometry: str
    bag: str | None = None
    """File or folder name of the robot's bag among the BAG arguments (None: any bag)."""
    clock_offset_ns: int = 0
    """Added to every stamp of this robot (its clock -> the fleet's clock)."""
    keyframes: str | None = None
    keyframe_every: int = 5
    reset: str | None = None
    loops: LoopMap | None = None
    image: ImageMap | None = None
    config: str | None = None
    """A robot.yaml to use as is (relative to the mapping file); None: generate one."""
    mocap_body: str | None = None
    T_body_marker: np.ndarray = field(default_factory=lambda: np.eye(4))
    T_world_odom: np.ndarray | None = None

    def topics(self) -> dict[str, str]:
        """role -> topic of every topic this robot reads."""
        out = {"odometry": self.odometry}
        if self.keyframes:
            out["keyframes"] = self.keyframes
        if self.reset:
            out["reset"] = self.reset
        if self.loops is not None:
            lp = self.loops
            if lp.form == "vins":
                assert lp.topic is not None  # _loops requires it for this form
                out["loops"] = lp.topic
            else:
                assert lp.old is not None and lp.cur is not None  # required for pose_pair
                out["loop_old"], out["loop_cur"] = lp.old, lp.cur
        if self.image is not None:
            out["image"] = self.image.topic
            if self.image.depth:
                out["depth"] = self.image.depth
            if self.image.camera_info:
                out["camera_info"] = self.image.camera_info
        return out


@dataclass(frozen=True, eq=False)
class MocapMap:
    bodies: dict[str, str]
    """Motive-style rigid-body name -> geometry_msgs/PoseStamped topic."""
    up_axis: str = "z"
    """Up axis of the poses' world frame (z: ROS convention; y: Motive's own)."""
    clock_offset_ns: int = 0
    bag: str | None = None


@dataclass(frozen=True, eq=False)
class BagMapping:
    path: str
    fleet: str
    clock: str
    robots: tuple[RobotMap, ...]
    comm_graph: tuple[tuple[int, int], ...]
    objects: tuple[rd.RunObject, ...] = ()
    mocap: MocapMap | None = None
    calib: str | None = None
    """Folder with tags.yaml (and optionally cameras/<robot>.yaml), relative to the file."""
    start_ns: int | None = None
    duration_s: float | None = None
    reorder_window_s: float = 2.0

    def resolve(self, rel: str) -> Path:
        p = Path(rel)
        return p if p.is_absolute() else Path(self.path).parent / p


def _topic(n: rd._Node, key: str, required: bool = False) -> str | None:
    v = n.get(key, "str")
    if v is None:
        if required:
            raise n._err(f"{n.key(key)}: required key is missing", n.where)
        return None
    if not v.startswith("/"):
        v = "/" + v
    return v


def _required_topic(n: rd._Node, key: str) -> str:
    v = _topic(n, key, True)
    assert v is not None  # _topic raises for a missing required key
    return v


def _image(n: rd._Node) -> ImageMap:
    n.check(
        {"topic"},
        {"camera_info", "depth", "T_body_camera", "depth_unit_m", "max_rate_hz", "encode"},
    )
    enc = n.get("encode", "str", "png")
    if enc not in ("png", "pnm"):
        raise n._err(f"{n.key('encode')}: expected png or pnm, got {enc!r}", n.key("encode"))
    rate = n.get("max_rate_hz", "float")
    unit = n.get("depth_unit_m", "float", 0.001)
    if (rate is not None and rate <= 0) or unit <= 0:
        raise n._err(f"{n.where}: max_rate_hz and depth_unit_m must be > 0", n.where)
    return ImageMap(
        _required_topic(n, "topic"),
        _topic(n, "camera_info"),
        _topic(n, "depth"),
        n.get("T_body_camera", "pose"),
        unit,
        rate,
        enc,
    )


def _loops(n: rd._Node) -> LoopMap:
    form = n.data.get("form", "vins")
    if form == "vins":
        n.check({"topic"}, {"form"})
        return LoopMap("vins", topic=_required_topic(n, "topic"))
    if form == "pose_pair":
        n.check({"old", "cur", "form"})
        return LoopMap("pose_pair", old=_required_topic(n, "old"), cur=_required_topic(n, "cur"))
    raise n._err(f"{n.key('form')}: expected one of {LOOP_FORMS}, got {form!r}", n.key("form"))


def _robot(n: rd._Node, path: str, lines: dict) -> RobotMap:
    n.check(
        {"id", "name", "odometry"},
        {
            "bag",
            "clock_offset_ns",
            "keyframes",
            "keyframe_every",
            "reset",
            "loops",
            "image",
            "config",
            "mocap_body",
            "T_body_marker",
            "T_world_odom",
        },
    )
    rid = n.get("id", "int")
    if not 0 <= rid <= 65535:
        raise n._err(f"{n.key('id')}: expected 0..65535, got {rid}", n.key("id"))
    every = n.get("keyframe_every", "int", 5)
    if every < 1:
        raise n._err(f"{n.key('keyframe_every')}: expected >= 1", n.key("keyframe_every"))
    loops = image = None
    if "loops" in n.data:
        loops = _loops(rd._Node(n.get("loops", "dict"), n.key("loops"), path, lines))
    if "image" in n.data:
        image = _image(rd._Node(n.get("image", "dict"), n.key("image"), path, lines))
    return RobotMap(
        rid,
        n.get("name", "name"),
        _required_topic(n, "odometry"),
        n.get("bag", "str"),
        n.get("clock_offset_ns", "int", 0),
        _topic(n, "keyframes"),
        every,
        _topic(n, "reset"),
        loops,
        image,
        n.get("config", "str"),
        n.get("mocap_body", "str"),
        n.get("T_body_marker", "pose", np.eye(4)),
        n.get("T_world_odom", "pose"),
    )


def read_mapping(path: str | Path) -> BagMapping:
    """Load and validate a bag mapping file (docs/bags.md)."""
    # Long: the strict reader of one file format, one key check after the other (docs/bags.md).
    path = Path(path)
    data, lines = rd._yaml_with_lines(path)
    top = rd._Node(data if data is not None else {}, "", str(path), lines)
    top.check(
        {"format", "robots"},
        {
            "fleet",
            "clock",
            "comm_graph",
            "objects",
            "mocap",
            "calib",
            "start_ns",
            "duration_s",
            "reorder_window_s",
        },
    )
    if data["format"] != MAP_FORMAT:
        raise top._err(f"format: expected {MAP_FORMAT!r}, got {data['format']!r}", "format")
    clock = top.get("clock", "str", "header")
    if clock not in CLOCKS:
        raise top._err(f"clock: expected one of {CLOCKS}, got {clock!r}", "clock")
    robots = [
        _robot(rd._Node(item, f"robots[{i}]", str(path), lines), str(path), lines)
        for i, item in enumerate(top.get("robots", "list"))
    ]
    rd.check_robot_list(top, robots)
    seen: dict[tuple[str | None, str], str] = {}
    for r in robots:
        for role, t in r.topics().items():
            key = (r.bag, t)
            if key in seen:
                raise top._err(
                    f"robots: topic {t} is mapped twice ({seen[key]} and "
                    f"{r.name}.{role}); give each robot its own bag or topic",
                    "robots",
                )
            seen[key] = f"{r.name}.{role}"
    ids = {r.id for r in robots}
    if "comm_graph" in data:
        edges = set()
        for i, e in enumerate(top.get("comm_graph", "list")):
            if (
                not isinstance(e, list)
                or len(e) != 2
                or any(x not in ids for x in e)
                or e[0] == e[1]
            ):
                raise top._err(
                    f"comm_graph[{i}]: expected two different robot ids of this "
                    f"mapping ({sorted(ids)}), got {e!r}",
                    f"comm_graph[{i}]",
                )
            edges.add((min(e), max(e)))
        comm = tuple(sorted(edges))
    else:
        s = sorted(ids)
        comm = tuple((a, b) for i, a in enumerate(s) for b in s[i + 1 :])
    objects = []
    for i, item in enumerate(top.get("objects", "list", [])):
        n = rd._Node(item, f"objects[{i}]", str(path), lines)
        n.check({"id"}, {"name", "mocap_body", "T_object_marker"})
        oid = n.get("id", "int")
        objects.append(
            rd.RunObject(
                oid,
                n.get("name", "str", f"object{oid}"),
                n.get("mocap_body", "str"),
                n.get("T_object_marker", "pose", np.eye(4)),
            )
        )
    mocap = None
    if "mocap" in data:
        m = rd._Node(top.get("mocap", "dict"), "mocap", str(path), lines)
        m.check({"bodies"}, {"up_axis", "clock_offset_ns", "bag"})
        bodies = m.get("bodies", "dict")
        if not bodies or not all(
            isinstance(k, str) and isinstance(v, str) and v for k, v in bodies.items()
        ):
            raise m._err(
                "mocap.bodies: expected a mapping of rigid-body name -> topic", "mocap.bodies"
            )
        up = m.get("up_axis", "str", "z")
        if up not in ("y", "z"):
            raise m._err(f"mocap.up_axis: expected 'y' or 'z', got {up!r}", "mocap.up_axis")
        mocap = MocapMap(
            {k: v if v.startswith("/") else "/" + v for k, v in bodies.items()},
            up,
            m.get("clock_offset_ns", "int", 0),
            m.get("bag", "str"),
        )
    start = top.get("start_ns", "int")
    dur = top.get("duration_s", "float")
    window = top.get("reorder_window_s", "float", 2.0)
    if (start is not None and start <= 0) or (dur is not None and dur <= 0) or window < 0:
        raise top._err("start_ns and duration_s must be > 0, reorder_window_s >= 0", "start_ns")
    return BagMapping(
        str(path),
        top.get("fleet", "name", "bagfleet"),
        clock,
        tuple(robots),
        comm,
        tuple(objects),
        mocap,
        top.get("calib", "str"),
        start,
        dur,
        window,
    )
