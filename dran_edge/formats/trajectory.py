"""Trajectory files the way evo users have them: TUM, EuRoC/ASL CSV, KITTI poses (read, write,
detect), and the run's mocap exported in them (docs/trajectory-formats.md).

The quaternion order is never guessed. It comes from the format (TUM: x y z w; EuRoC/ASL
and VINS-Mono CSV: w x y z), from a header naming the columns (``q_RS_w``, ``qw``,
``orientation.w`` ...), or from the caller (``quat_order``). A file that could be either —
comma-separated, eight columns, no header, stamps in seconds — is an error asking for
``--quat-order`` or ``--format``, never silently scored as TUM. Pure (numpy, stdlib).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import InputError

FORMATS = ("tum", "euroc", "kitti")
QUAT_ORDERS = ("xyzw", "wxyz")
QUAT_NORM_TOL = 1e-3
#: Stamps above this are nanoseconds (1e12 s is 31700 years; 1e12 ns is 16 minutes).
NS_THRESHOLD = 1e12
EUROC_HEADER = (
    "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"
)
_QUAT_NAME = re.compile(
    r"(?:^|[._ ])(?:q|quat|quaternion|orientation|rot)[a-z0-9_.]*?[._]?([wxyz])$"
)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Poses read from a file, with how they were read."""

    stamps_s: np.ndarray
    T: np.ndarray
    format: str
    quat_order: str | None
    """``xyzw`` / ``wxyz``; None for KITTI (rotation matrices)."""
    how: str
    """How the format and quaternion order were decided (for messages and reports)."""
    path: str = ""
    has_stamps: bool = True
    """False for KITTI poses without a times file (stamps are index / rate)."""

    @property
    def positions_only(self) -> bool:
        """Every rotation is the identity: the file carries positions, not orientations."""
        R = self.T[:, :3, :3]
        return bool(np.all(np.abs(R - np.eye(3)) < 1e-12))


def _header_order(tokens: list[str]) -> tuple[str, int] | None:
    """(quat order, column of the first quaternion component) from column names, if named."""
    found: dict[str, int] = {}
    for i, tok in enumerate(tokens):
        t = re.sub(r"\s*\[.*?\]\s*", "", tok.strip().lower())
        m = _QUAT_NAME.search(t) or (re.fullmatch(r"q([wxyz])", t))
        if m and m.group(1) not in found:
            found[m.group(1)] = i
    if set(found) != set("wxyz"):
        return None
    return ("wxyz" if found["w"] < found["x"] else "xyzw"), min(found.values())


def _rows(path: str) -> tuple[list[str], list[tuple[int, str]]]:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("trajectory file not found", path=path) from None
    except UnicodeDecodeError:
        raise InputError("not a text trajectory file", path=path) from None
    header: list[str] = []
    data: list[tuple[int, str]] = []
    for n, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if not s:
            continue
        if s[0] in "#%" or (not data and not re.match(r"^[-+0-9.]", s)):
            if not data:
                header = (
                    [c for c in re.split(r"[,\s]+", s.lstrip("#% ")) if c]
                    if "," not in s
                    else [c for c in s.lstrip("#% ").split(",")]
                )
            continue
        data.append((n, s))
    if not data:
        raise InputError("expected at least one pose line, got none", path=path)
    return header, data


def detect(
    path: str | Path, fmt: str = "auto", quat_order: str | None = None
) -> tuple[str, str | None, str]:
    """(format, quaternion order, how it was decided) of a trajectory file."""
    path = str(path)
    if fmt not in FORMATS + ("auto",):
        raise InputError(f"format: expected one of {FORMATS + ('auto',)}, got {fmt!r}")
    if quat_order is not None and quat_order not in QUAT_ORDERS:
        raise InputError(f"quaternion order: expected one of {QUAT_ORDERS}, got {quat_order!r}")
    header, data = _rows(path)
    n, first = data[0]
    comma = "," in first
    cells = [c for c in (first.split(",") if comma else first.split()) if c.strip()]
    named = _header_order(header) if header else None
    if fmt == "kitti" or (fmt == "auto" and not comma and len(cells) == 12):
        return "kitti", None, "12 numbers per line: KITTI poses" if fmt == "auto" else "given"
    if fmt != "auto":
        order = quat_order or ("xyzw" if fmt == "tum" else "wxyz")
        how = "given" + (
            f", quaternion {order} given"
            if quat_order
            else f", quaternion {order} by the format's definition"
        )
        if named and named[0] != order:
            raise InputError(
                f"the header names the quaternion columns in {named[0]} order but "
                f"{order} was asked for",
                path=path,
                line=1,
            )
        return fmt, order, how
    if named:
        f = "euroc" if comma else "tum"
        if quat_order and quat_order != named[0]:
            raise InputError(
                f"the header names the quaternion columns in {named[0]} order but "
                f"--quat-order {quat_order} was given",
                path=path,
                line=1,
            )
        return f, named[0], f"header names the quaternion columns ({named[0]})"
    try:
        stamp = float(cells[0])
    except ValueError:
        raise InputError(
            f"expected a number as the first column, got {cells[0]!r}", path=path, line=n
        ) from None
    if quat_order:
        return ("euroc" if comma else "tum"), quat_order, f"quaternion {quat_order} given"
    if not comma and len(cells) == 8 and stamp < NS_THRESHOLD:
        return "tum", "xyzw", "8 space-separated numbers, stamps in seconds: TUM (x y z w)"
    if comma and len(cells) >= 8 and stamp >= NS_THRESHOLD:
        return (
            "euroc",
            "wxyz",
            ("comma-separated, stamps in nanoseconds: EuRoC/ASL or VINS-Mono CSV (w x y z)"),
        )
    raise InputError(
        f"cannot tell the quaternion order: {len(cells)} {'comma' if comma else 'space'}-"
        f"separated columns, stamps in {'ns' if stamp >= NS_THRESHOLD else 's'}, no header "
        "naming the columns. TUM is 'stamp_s x y z qx qy qz qw' (space-separated); EuRoC/ASL "
        "and VINS-Mono CSV are 'stamp_ns, x, y, z, qw, qx, qy, qz'. Give --quat-order "
        "xyzw|wxyz or --format tum|euroc|kitti",
        path=path,
        line=n,
    )


def read_trajectory(
    path: str | Path,
    fmt: str = "auto",
    *,
    quat_order: str | None = None,
    kitti_times: str | Path | None = None,
    kitti_rate_hz: float = 10.0,
    require_increasing: bool = True,
) -> Trajectory:
    """Read a trajectory file (any of FORMATS); errors name the file and the line."""
    path = str(path)
    fmt, order, how = detect(path, fmt, quat_order)
    _, data = _rows(path)
    rows, lines = [], []
    for n, s in data:
        cells = [c for c in (s.split(",") if "," in s else s.split()) if c.strip()]
        need = 12 if fmt == "kitti" else 8
        if len(cells) < need or (fmt != "euroc" and len(cells) != need):
            raise InputError(
                f"expected {need} numbers per line ({fmt}), got {len(cells)}", path=path, line=n
            )
        try:
            rows.append([float(c) for c in cells[:need]])
        except ValueError:
            raise InputError(f"expected numbers, got {s[:80]!r}", path=path, line=n) from None
        lines.append(n)
    a = np.asarray(rows)
    line_of = np.asarray(lines)
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise InputError(
            "expected finite numbers, got NaN or inf", path=path, line=int(line_of[bad][0])
        )
    if fmt == "kitti":
        T = np.tile(np.eye(4), (len(a), 1, 1))
        T[:, :3, :] = a.reshape(-1, 3, 4)
        stamps, has = _kitti_stamps(len(a), kitti_times, kitti_rate_hz, path)
        return Trajectory(stamps, T, "kitti", None, how, path, has)
    stamps = a[:, 0] * (1e-9 if a[0, 0] >= NS_THRESHOLD else 1.0)  # ns or s by magnitude
    q = a[:, 4:8]
    norm = np.linalg.norm(q, axis=1)
    off = np.abs(norm - 1.0) > QUAT_NORM_TOL
    if off.any():
        k = int(np.flatnonzero(off)[0])
        raise InputError(
            f"expected a unit quaternion ({order}), got norm {norm[k]:.6f}",
            path=path,
            line=int(line_of[k]),
        )
    q = q / norm[:, None]
    xyzw = q if order == "xyzw" else q[:, [1, 2, 3, 0]]
    if require_increasing:
        back = np.flatnonzero(np.diff(stamps) <= 0)
        if back.size:
            k = int(back[0]) + 1
            raise InputError(
                f"expected increasing stamps, got {a[k, 0]!r} after {a[k - 1, 0]!r}",
                path=path,
                line=int(line_of[k]),
            )
    T = geo.se3_from_xyz_quat_xyzw(np.concatenate([a[:, 1:4], xyzw], axis=1))
    return Trajectory(stamps, T, fmt, order, how, path)


def _kitti_stamps(
    n: int, times: str | Path | None, rate_hz: float, path: str
) -> tuple[np.ndarray, bool]:
    if times is None:
        return np.arange(n) / rate_hz, False
    try:
        t = np.loadtxt(times, dtype=np.float64, ndmin=1)
    except (OSError, ValueError) as exc:
        raise InputError(f"KITTI times file: {exc}", path=str(times)) from None
    if t.shape != (n,):
        raise InputError(
            f"expected {n} stamps (one per pose of {path}), got {t.size}", path=str(times)
        )
    return t, True


def write_trajectory(
    path: str | Path, stamps_s: np.ndarray, T: np.ndarray, fmt: str = "tum", *, header: str = ""
) -> None:
    """Write poses in ``fmt``: TUM (s, x y z qx qy qz qw), EuRoC CSV (ns, w-first), KITTI."""
    stamps_s = np.asarray(stamps_s, dtype=np.float64)
    T = np.asarray(T, dtype=np.float64)
    if fmt == "tum":
        from dran_edge.formats.tum import write_tum

        write_tum(path, stamps_s, T, header=header)
    elif fmt == "euroc":
        wxyz = geo.se3_to_xyz_quat_wxyz(T)
        with open(path, "w", encoding="utf-8") as f:
            f.write(EUROC_HEADER + "\n")
            for s, v in zip(np.round(stamps_s * 1e9).astype(np.int64).tolist(), wxyz):
                f.write(f"{s}," + ",".join(f"{x:.10f}" for x in v) + "\n")
    elif fmt == "kitti":
        np.savetxt(path, T[:, :3, :].reshape(-1, 12), fmt="%.10e")
        np.savetxt(Path(path).with_suffix(".times.txt"), stamps_s, fmt="%.9f")
    else:
        raise InputError(f"format: expected one of {FORMATS}, got {fmt!r}")


SUFFIX = {"tum": ".tum", "euroc": ".csv", "kitti": ".kitti"}
BAG_POSE_TYPES = (
    "nav_msgs/msg/Odometry",
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
)


def read_bag_trajectory(path: str | Path, topic: str) -> Trajectory:
    """The poses of one topic of a ROS 1 / ROS 2 bag (Odometry, PoseStamped or
    PoseWithCovarianceStamped), at their header stamps; a stamp not after the previous one
    is dropped (the count is in ``how``)."""
    from dran_edge.formats import ros_msgs as rm
    from dran_edge.formats.bags import open_bag

    reader, p = open_bag(path)
    topic = topic if topic.startswith("/") else "/" + topic
    stamps: list[int] = []
    rows: list[Any] = []
    dropped = 0
    try:
        with reader:
            conns = [c for c in reader.connections if c.topic == topic]
            if not conns:
                have = ", ".join(sorted({c.topic for c in reader.connections}))
                raise InputError(f"no topic {topic} in the bag; it has: {have}", path=str(p))
            if conns[0].msgtype not in BAG_POSE_TYPES:
                raise InputError(
                    f"topic {topic} is {conns[0].msgtype}; expected one of "
                    f"{', '.join(BAG_POSE_TYPES)}",
                    path=str(p),
                )
            for c, _t, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, c.msgtype)
                try:
                    s, v = rm.mocap_pose(msg)
                except rm.MessageError:
                    dropped += 1
                    continue
                if stamps and s <= stamps[-1]:
                    dropped += 1
                    continue
                stamps.append(s)
                rows.append(v)
    except InputError:
        raise
    except Exception as exc:  # rosbags' errors for a damaged bag
        raise InputError(f"cannot read the bag: {exc}", path=str(p)) from None
    if not rows:
        raise InputError(f"topic {topic}: no usable pose", path=str(p))
    a = np.asarray(rows, dtype=np.float64)
    a[:, 3:] /= np.linalg.norm(a[:, 3:], axis=1, keepdims=True)
    how = f"bag topic {topic} ({conns[0].msgtype})" + (f", {dropped} dropped" if dropped else "")
    return Trajectory(
        np.asarray(stamps, np.int64) * 1e-9,
        geo.se3_from_xyz_quat_xyzw(a),
        "bag",
        "xyzw",
        how,
        str(p),
    )


def export_mocap(
    run_dir: str | Path,
    fmt: str = "tum",
    out_dir: str | Path | None = None,
    *,
    marker: bool = False,
) -> list[Path]:
    """Each mocap body of a run as a trajectory file; returns the paths written.

    Stamps are in the robot clock (``mocap.start_ns`` of mission.yaml; without it the Motive
    times are written as they are, with a warning line in the header). Robots' bodies are
    written in the robot body frame (``T_world_marker · T_body_marker⁻¹``) and objects in the
    object frame, unless ``marker``; occluded frames are left out.
    """
    from dran_edge.formats import run_dir as rd
    from dran_edge.formats.motive import read_motive_csv

    run = rd.open_run(run_dir)
    if run.mocap_path is None:
        raise InputError(
            "the run has no mocap (mission.yaml: mocap.file)", path=str(run.root / "mission.yaml")
        )
    m = run.mission
    take = read_motive_csv(run.mocap_path, up_axis=m.mocap_up_axis)
    out = Path(out_dir) if out_dir else run.root / "export" / "mocap"
    out.mkdir(parents=True, exist_ok=True)
    offset_s = m.mocap_start_ns * 1e-9 if m.mocap_start_ns is not None else 0.0
    pivots = {r.mocap_body: (r.T_body_marker, f"robot {r.name}") for r in m.robots if r.mocap_body}
    pivots |= {
        o.mocap_body: (o.T_object_marker, f"object {o.name}") for o in m.objects if o.mocap_body
    }
    paths = []
    for name, body in take.bodies.items():
        T = body.T_world_marker[body.valid]
        what = "rigid body (marker frame)"
        if not marker and name in pivots:
            T = T @ geo.se3_inverse(pivots[name][0])
            what = pivots[name][1] + " body frame"
        p = out / f"{name}{SUFFIX[fmt]}"
        hdr = (
            f"mocap body {name}: {what}, world frame (Z-up), stamps in the robot clock "
            f"(mission.yaml mocap.start_ns)"
            if m.mocap_start_ns is not None
            else f"mocap body {name}: stamps are Motive's take time (no mocap.start_ns)"
        )
        write_trajectory(
            p, take.time_s[body.valid] + offset_s, T, fmt, header=hdr if fmt == "tum" else ""
        )
        paths.append(p)
    return paths
