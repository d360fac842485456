"""The recorded-run directory (docs/run-format.md): read it strictly, write its parts.

A run is everything needed to replay a multi-robot mission through the robot code and to
score it::

    RUN/mission.yaml             fleet-level description (format dran-edge-run/1)
    RUN/mocap.csv                optional OptiTrack Motive CSV export
    RUN/calib/                   tags.yaml + cameras/<robot>.yaml (docs/calibration.md)
    RUN/robots/<name>/robot.yaml the robot's config as used (docs/config.md)
    RUN/robots/<name>/ingest.bin ingest records, byte for byte (docs/ingest.md)
    RUN/robots/<name>/frames/    recorded frames (optional; perception's frames folder)
    RUN/out/                     written by ``dran-edge replay``

Reading never guesses: a missing file, an unknown key, a wrong type or an inconsistent id
raises :class:`~dran_edge.errors.InputError` naming the file (and the line and key where the
file has them). This module is pure (numpy, stdlib, pyyaml for the text files); the ingest
bytes and frames are handed to their own decoders by the replay.

Size: over ~500 lines because the strict reader and the writers of one file format; over 500
only by ruff format's layout.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import InputError

RUN_FORMAT = "dran-edge-run/1"
_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,15}$")


@dataclass(frozen=True, eq=False)
class RunRobot:
    """One robot of the run."""

    id: int
    name: str
    mocap_body: str | None = None
    """Motive rigid-body name, or None when the robot was not tracked."""
    T_body_marker: np.ndarray = field(default_factory=lambda: np.eye(4))
    """Mocap rigid-body pivot in the robot's body (IMU) frame."""
    T_world_odom: np.ndarray | None = None
    """The robot's first VIO frame in the world, when known (the paper's protocol: from mocap
    at the start); None otherwise."""


@dataclass(frozen=True, eq=False)
class RunObject:
    """One mapped object (tagged box) of the run."""

    id: int
    name: str
    mocap_body: str | None = None
    T_object_marker: np.ndarray = field(default_factory=lambda: np.eye(4))
    """Mocap rigid-body pivot in the object frame."""


@dataclass(frozen=True, eq=False)
class Mission:
    """``mission.yaml``: the fleet-level description of a run."""

    fleet: str
    start_ns: int
    """Stamp of the mission start (robot clock), nanoseconds."""
    duration_s: float
    robots: tuple[RunRobot, ...]
    objects: tuple[RunObject, ...]
    comm_graph: tuple[tuple[int, int], ...]
    """Undirected communication links as robot-id pairs (i < j), sorted."""
    mocap_file: str | None = None
    """Motive CSV, relative to the run directory."""
    mocap_start_ns: int | None = None
    """Robot-clock stamp of Motive's time 0 (None: unknown, estimate the offset)."""
    mocap_up_axis: str = "y"
    simulation: dict | None = None
    """Parameters of the simulator that made the run (informational)."""

    def robot(self, name: str) -> RunRobot:
        for r in self.robots:
            if r.name == name:
                return r
        raise KeyError(name)

    def neighbours(self, robot_id: int) -> tuple[int, ...]:
        out = [b if a == robot_id else a for a, b in self.comm_graph if robot_id in (a, b)]
        return tuple(sorted(out))


# ------------------------------------------------------------------------------ pose helpers
def pose_to_yaml(T: np.ndarray) -> dict:
    """``{xyz: [...], quat_xyzw: [...]}`` (the calibration files' pose layout)."""
    a = geo.se3_to_xyz_quat_xyzw(np.asarray(T, dtype=np.float64))
    return {
        "xyz": [round(float(v), 9) for v in a[:3]],
        "quat_xyzw": [round(float(v), 12) for v in a[3:]],
    }


class _Node:
    """A YAML mapping with typed, path-naming accessors."""

    def __init__(self, data: Any, where: str, path: str, lines: dict[str, int]):
        self.where, self.path, self.lines = where, path, lines
        if not isinstance(data, dict):
            raise self._err(
                f"{where or 'top level'}: expected a mapping, got {type(data).__name__}", where
            )
        self.data = data

    def _err(self, msg: str, key: str) -> InputError:
        k = key
        while k and k not in self.lines:
            k = re.sub(r"(\.[^.\[]*|\[\d+\])$", "", k) if re.search(r"(\.|\[)", k) else ""
        return InputError(msg, path=self.path, line=self.lines.get(k))

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def check(self, required: set[str], optional: frozenset[str] | set[str] = frozenset()) -> None:
        for k in self.data:
            if k not in required and k not in optional:
                raise self._err(
                    f"{self.key(str(k))}: unknown key (allowed: "
                    f"{', '.join(sorted(required | set(optional)))})",
                    self.key(str(k)),
                )
        for k in sorted(required):
            if k not in self.data:
                raise self._err(f"{self.key(k)}: required key is missing", self.where)

    def get(self, name: str, kind: str, default: Any = None) -> Any:
        if name not in self.data:
            return default
        v = self.data[name]
        key = self.key(name)
        if kind == "int":
            if isinstance(v, bool) or not isinstance(v, int):
                raise self._err(f"{key}: expected an integer, got {v!r}", key)
        elif kind == "float":
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise self._err(f"{key}: expected a finite number, got {v!r}", key)
            v = float(v)
        elif kind == "name":
            if not isinstance(v, str) or not _NAME_RE.match(v):
                raise self._err(
                    f"{key}: expected 1-15 characters of [A-Za-z0-9_.-], got {v!r}", key
                )
        elif kind == "str":
            if not isinstance(v, str) or not v:
                raise self._err(f"{key}: expected a non-empty string, got {v!r}", key)
        elif kind == "pose":
            n = _Node(v, key, self.path, self.lines)
            n.check({"xyz", "quat_xyzw"})
            xyz, q = n.vector("xyz", 3), n.vector("quat_xyzw", 4)
            if abs(np.linalg.norm(q) - 1.0) > 1e-3:
                raise self._err(
                    f"{key}.quat_xyzw: expected a unit quaternion, got norm "
                    f"{np.linalg.norm(q):.6g}",
                    key,
                )
            v = geo.se3_from_xyz_quat_xyzw(np.r_[xyz, q / np.linalg.norm(q)])
        elif kind == "list":
            if not isinstance(v, list):
                raise self._err(f"{key}: expected a list, got {type(v).__name__}", key)
        elif kind == "dict":
            if not isinstance(v, dict):
                raise self._err(f"{key}: expected a mapping, got {type(v).__name__}", key)
        return v

    def vector(self, name: str, n: int) -> np.ndarray:
        v = self.data.get(name)
        key = self.key(name)
        if (
            not isinstance(v, list)
            or len(v) != n
            or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in v)
            or not all(math.isfinite(x) for x in v)
        ):
            raise self._err(f"{key}: expected a list of {n} finite numbers, got {v!r}", key)
        return np.asarray(v, dtype=np.float64)


def _yaml_with_lines(path: Path) -> tuple[Any, dict[str, int]]:
    import yaml

    from dran_edge.config.loader import key_lines, parse_yaml

    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(
            "file not found (a run directory needs it; docs/run-format.md)", path=str(path)
        ) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", path=str(path)) from None
    try:
        data, root = parse_yaml(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise InputError(
            f"not valid YAML: {getattr(exc, 'problem', None) or exc}",
            path=str(path),
            line=mark.line + 1 if mark else None,
        ) from None
    return data, key_lines(root)


# ------------------------------------------------------------------------------ mission.yaml


def check_robot_list(top: _Node, robots: list) -> None:
    """At least one robot, and no id or name twice (the ``robots`` list of mission.yaml or of a
    bag mapping file)."""
    if not robots:
        raise top._err("robots: expected at least one robot", "robots")
    for attr in ("id", "name"):
        vals = [getattr(r, attr) for r in robots]
        dup = sorted({v for v in vals if vals.count(v) > 1})
        if dup:
            raise top._err(f"robots: {attr} {dup[0]!r} appears more than once", "robots")


def read_mission(path: str | Path) -> Mission:
    """Load and validate ``mission.yaml``."""
    # Long: the strict reader of mission.yaml, one key check after the other (docs/run-format.md).
    path = Path(path)
    data, lines = _yaml_with_lines(path)
    top = _Node(data if data is not None else {}, "", str(path), lines)
    top.check(
        {"format", "fleet", "start_ns", "duration_s", "robots", "comm_graph"},
        {"objects", "mocap", "simulation"},
    )
    if data["format"] != RUN_FORMAT:
        raise top._err(f"format: expected {RUN_FORMAT!r}, got {data['format']!r}", "format")
    fleet = top.get("fleet", "name")
    start_ns = top.get("start_ns", "int")
    if start_ns <= 0:
        raise top._err(f"start_ns: expected > 0, got {start_ns}", "start_ns")
    duration_s = top.get("duration_s", "float")
    if duration_s <= 0:
        raise top._err(f"duration_s: expected > 0, got {duration_s}", "duration_s")
    robots = []
    for i, item in enumerate(top.get("robots", "list")):
        n = _Node(item, f"robots[{i}]", str(path), lines)
        n.check({"id", "name"}, {"mocap_body", "T_body_marker", "T_world_odom"})
        rid = n.get("id", "int")
        if not 0 <= rid <= 65535:
            raise n._err(f"{n.key('id')}: expected 0..65535, got {rid}", n.key("id"))
        robots.append(
            RunRobot(
                rid,
                n.get("name", "name"),
                n.get("mocap_body", "str"),
                n.get("T_body_marker", "pose", np.eye(4)),
                n.get("T_world_odom", "pose"),
            )
        )
    check_robot_list(top, robots)
    objects = []
    for i, item in enumerate(top.get("objects", "list", [])):
        n = _Node(item, f"objects[{i}]", str(path), lines)
        n.check({"id"}, {"name", "mocap_body", "T_object_marker"})
        oid = n.get("id", "int")
        objects.append(
            RunObject(
                oid,
                n.get("name", "str", f"object{oid}"),
                n.get("mocap_body", "str"),
                n.get("T_object_marker", "pose", np.eye(4)),
            )
        )
    ids = {r.id for r in robots}
    edges = set()
    for i, e in enumerate(top.get("comm_graph", "list")):
        key = f"comm_graph[{i}]"
        if (
            not isinstance(e, list)
            or len(e) != 2
            or any(isinstance(x, bool) or not isinstance(x, int) for x in e)
        ):
            raise top._err(f"{key}: expected a pair of robot ids [a, b], got {e!r}", key)
        a, b = e
        if a == b or a not in ids or b not in ids:
            raise top._err(
                f"{key}: expected two different robot ids of this run ({sorted(ids)}), got {e!r}",
                key,
            )
        edges.add((min(a, b), max(a, b)))
    mocap_file = mocap_start = None
    up = "y"
    if "mocap" in data:
        m = _Node(top.get("mocap", "dict"), "mocap", str(path), lines)
        m.check({"file"}, {"start_ns", "up_axis"})
        mocap_file = m.get("file", "str")
        mocap_start = m.get("start_ns", "int")
        up = m.get("up_axis", "str", "y")
        if up not in ("y", "z"):
            raise m._err(f"mocap.up_axis: expected 'y' or 'z', got {up!r}", "mocap.up_axis")
    sim = top.get("simulation", "dict") if "simulation" in data else None
    return Mission(
        fleet,
        start_ns,
        duration_s,
        tuple(robots),
        tuple(objects),
        tuple(sorted(edges)),
        mocap_file,
        mocap_start,
        up,
        sim,
    )


#: mission.yaml's start_ns this far from the recorded stamps is an error, not a warning: a
#: replay ticking a day of empty rounds is a typo (a start_ns of 1), not a late start.
CLOCK_ERROR_S = 86_400.0


def check_mission_clock(
    m: Mission, span_ns: tuple[int, int] | None, period_s: float, path: str = "mission.yaml"
) -> list[str]:
    """Check mission.yaml's clock against the recorded stamps ``span_ns`` = (first, last).

    Raises InputError when ``start_ns`` lies after every record or more than a day before the
    first one (the replay would tick through that many empty rounds); returns warnings when it
    is off by more than two rounds (idle rounds before the first record, or records before the
    start), when the records outlast ``duration_s`` or end well before it, and when
    ``mocap.start_ns`` is more than a minute from the records (evaluation would align the
    ground truth wrongly)."""
    if span_ns is None:
        return []
    first, last = span_ns
    warn: list[str] = []
    early_s = (first - m.start_ns) * 1e-9
    if m.start_ns > last:
        raise InputError(
            f"start_ns {m.start_ns} is after every recorded stamp (records span "
            f"{first}..{last}); expected the mission start on the robots' clock",
            path=path,
        )
    if early_s > CLOCK_ERROR_S:
        raise InputError(
            f"start_ns {m.start_ns} is {early_s:.3g} s before the first recorded "
            f"stamp {first}: the replay would tick {early_s / period_s:.3g} empty "
            f"rounds; expected the mission start on the robots' clock (the first "
            f"stamp, {first})",
            path=path,
        )
    tol_s = max(2.0, 2 * period_s)
    if early_s > tol_s:
        warn.append(
            f"{path}: start_ns is {early_s:.1f} s before the first recorded stamp: the "
            f"replay runs {int(early_s / period_s)} rounds with no input first "
            f"(set start_ns: {first} if that is not intended)"
        )
    elif early_s < -tol_s:
        warn.append(
            f"{path}: start_ns is {-early_s:.1f} s after the first recorded stamp: the "
            f"records before it are all applied in the first round"
        )
    span_s = (last - m.start_ns) * 1e-9
    if span_s > m.duration_s + max(tol_s, 0.1 * m.duration_s):
        warn.append(
            f"{path}: the records run {span_s:.1f} s from start_ns, but duration_s is "
            f"{m.duration_s:g}: the replay runs {span_s:.1f} s of rounds"
        )
    elif span_s < 0.5 * m.duration_s - tol_s:
        warn.append(
            f"{path}: the records end {span_s:.1f} s after start_ns, duration_s is "
            f"{m.duration_s:g}: the rest are rounds with no new input"
        )
    if m.mocap_start_ns is not None:
        off_s = (m.mocap_start_ns - first) * 1e-9
        if abs(off_s) > 60.0:
            warn.append(
                f"{path}: mocap.start_ns is {off_s:+.3g} s from the first recorded stamp "
                f"{first}; the ground truth will not line up with the trajectories "
                f"(expected Motive's time 0 on the robots' clock; remove it to let "
                f"eval estimate the offset)"
            )
    return warn


def mission_to_yaml_dict(m: Mission) -> dict:
    """The plain-data form of ``m`` written as ``mission.yaml``."""
    robots = []
    for r in m.robots:
        d: dict[str, Any] = {"id": r.id, "name": r.name}
        if r.mocap_body:
            d["mocap_body"] = r.mocap_body
            d["T_body_marker"] = pose_to_yaml(r.T_body_marker)
        if r.T_world_odom is not None:
            d["T_world_odom"] = pose_to_yaml(r.T_world_odom)
        robots.append(d)
    objects = []
    for o in m.objects:
        d = {"id": o.id, "name": o.name}
        if o.mocap_body:
            d["mocap_body"] = o.mocap_body
            d["T_object_marker"] = pose_to_yaml(o.T_object_marker)
        objects.append(d)
    out: dict[str, Any] = {
        "format": RUN_FORMAT,
        "fleet": m.fleet,
        "start_ns": int(m.start_ns),
        "duration_s": float(m.duration_s),
        "robots": robots,
        "objects": objects,
        "comm_graph": [[int(a), int(b)] for a, b in m.comm_graph],
    }
    if m.mocap_file:
        mocap: dict[str, Any] = {"file": m.mocap_file, "up_axis": m.mocap_up_axis}
        if m.mocap_start_ns is not None:
            mocap["start_ns"] = int(m.mocap_start_ns)
        out["mocap"] = mocap
    if m.simulation:
        out["simulation"] = m.simulation
    return out


def write_yaml(path: str | Path, data: Any, header: str = "") -> None:
    import yaml

    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)
    if header:
        text = "".join(f"# {line}\n" for line in header.splitlines()) + text
    Path(path).write_text(text, encoding="utf-8")


def write_mission(run_dir: str | Path, m: Mission) -> Path:
    path = Path(run_dir) / "mission.yaml"
    write_yaml(path, mission_to_yaml_dict(m), header="dran-edge recorded run (docs/run-format.md)")
    return path


# ------------------------------------------------------------------------------ the run
@dataclass(frozen=True, eq=False)
class Run:
    """A run directory, opened: the mission and where every robot's parts are."""

    root: Path
    mission: Mission

    @property
    def calib_dir(self) -> Path:
        return self.root / "calib"

    @property
    def out_dir(self) -> Path:
        return self.root / "out"

    def robot_dir(self, name: str) -> Path:
        return self.root / "robots" / name

    def config_path(self, name: str) -> Path:
        return self.robot_dir(name) / "robot.yaml"

    def ingest_path(self, name: str) -> Path:
        return self.robot_dir(name) / "ingest.bin"

    def frames_dir(self, name: str) -> Path | None:
        d = self.robot_dir(name) / "frames"
        return d if (d / "frames.csv").exists() else None

    @property
    def mocap_path(self) -> Path | None:
        return self.root / self.mission.mocap_file if self.mission.mocap_file else None

    def read_ingest(self, name: str) -> bytes:
        path = self.ingest_path(name)
        try:
            return path.read_bytes()
        except FileNotFoundError:
            raise InputError(
                "file not found: every robot of a run needs its ingest records "
                "(docs/run-format.md)",
                path=str(path),
            ) from None

    def load_config(self, name: str):
        """The robot's config, strictly loaded; its id and name must match the mission."""
        from dran_edge.config import load_config

        path = self.config_path(name)
        if not path.exists():
            raise InputError(
                "file not found: every robot of a run needs its config", path=str(path)
            )
        cfg = load_config(path)
        r = self.mission.robot(name)
        if cfg.robot.id != r.id or cfg.robot.name != r.name:
            raise InputError(
                f"robot: expected id {r.id} name {r.name!r} (mission.yaml), got id "
                f"{cfg.robot.id} name {cfg.robot.name!r}",
                path=str(path),
            )
        return cfg


def open_run(run_dir: str | Path) -> Run:
    """Open a run directory; checks that every robot listed has its folder and ingest file."""
    root = Path(run_dir)
    if not root.is_dir():
        raise InputError("expected a run directory (docs/run-format.md)", path=str(root))
    mission = read_mission(root / "mission.yaml")
    run = Run(root, mission)
    for r in mission.robots:
        if not run.ingest_path(r.name).exists():
            raise InputError(
                f"robot {r.name!r} of mission.yaml has no ingest.bin",
                path=str(run.ingest_path(r.name)),
            )
    if run.mocap_path is not None and not run.mocap_path.exists():
        raise InputError(
            "mission.yaml names this mocap file but it does not exist", path=str(run.mocap_path)
        )
    return run
