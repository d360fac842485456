"""Import ROS 1 / ROS 2 bags into a run directory (docs/bags.md, docs/run-format.md).

``import_bags(bags, mapping, out)`` streams each bag once with the pure-Python ``rosbags``
reader (no ROS installation), hands every mapped message to the conversion layer
(:mod:`dran_edge.formats.ros_msgs`) and writes, per robot, ``ingest.bin`` (the records the
daemon would have journalled), ``frames/`` and ``robot.yaml``; for the run ``calib/``,
``mocap.csv`` (Motive-like CSV) and ``mission.yaml``; and ``import.json`` (what was read,
written and skipped, by reason).

Memory stays bounded by the reorder window (records are written in stamp order, held at most
``reorder_window_s`` of stamps), a few pending images, and the mocap poses (64 bytes each;
they are written as one table at the end). Bad input never raises a traceback: a problem with
the bags or the mapping as a whole is an :class:`~dran_edge.errors.InputError`; a single bad
message is skipped and counted by reason.
"""

from __future__ import annotations

import json
import shutil
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any


from dran_edge.formats import run_dir as rd
from dran_edge.errors import DependencyError, InputError
from dran_edge.formats import ros_msgs as rm
from dran_edge.formats.bag_map import BagMapping, RobotMap
from dran_edge.formats.bag_sinks import MocapSink, RobotSink, _first_note, peek_header_stamp_ns

_ODOM = "nav_msgs/msg/Odometry"
_PS = "geometry_msgs/msg/PoseStamped"
_PWCS = "geometry_msgs/msg/PoseWithCovarianceStamped"
_IMAGES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
#: Message types accepted per role.
ROLE_TYPES: dict[str, tuple[str, ...]] = {
    "odometry": (_ODOM,),
    "keyframes": (_ODOM, _PS, _PWCS),
    "reset": ("std_msgs/msg/Bool", "std_msgs/msg/Header"),
    "loops": (_ODOM,),
    "loop_old": (_PWCS, _PS),
    "loop_cur": (_PWCS, _PS),
    "image": _IMAGES,
    "depth": _IMAGES,
    "camera_info": ("sensor_msgs/msg/CameraInfo",),
    "mocap": (_PS, _PWCS),
}
_BASE_PORT = 47600


ProgressFn = Callable[[str, int, int], None]
"""progress(stage, messages_done, messages_total), stage = "import-bag: <bag file name>"."""


def open_bag(path: str | Path):
    """A ``rosbags`` AnyReader (not yet opened) for a ROS 1 .bag or a ROS 2 bag directory/file."""
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise DependencyError(
            "reading bags needs the 'rosbags' package: pip install 'dran-edge[bags]'"
        ) from None
    p = Path(path)
    if not p.exists():
        raise InputError("bag not found", path=str(p))
    if p.is_file() and p.suffix in (".db3", ".mcap"):
        if not (p.parent / "metadata.yaml").exists():
            raise InputError(
                "a ROS 2 bag file needs its folder's metadata.yaml next to it "
                "(ros2 bag reindex writes one)",
                path=str(p),
            )
        p = p.parent
    elif p.is_file() and p.suffix != ".bag":
        raise InputError(
            "expected a ROS 1 .bag file, or a ROS 2 bag folder (or its .db3/.mcap)", path=str(p)
        )
    elif p.is_dir() and not (p / "metadata.yaml").exists():
        raise InputError("expected a ROS 2 bag folder with metadata.yaml", path=str(p))
    return AnyReader([p]), p


def bag_size_bytes(p: Path) -> int:
    return (
        p.stat().st_size
        if p.is_file()
        else sum(f.stat().st_size for f in p.iterdir() if f.is_file())
    )


def _select(reader, bag_name: str, wanted: dict[str, tuple[str, str]]) -> dict[str, Any]:
    """topic -> connection for the mapped topics in this bag; checks the message types."""
    out: dict[str, Any] = {}
    for c in reader.connections:
        if c.topic not in wanted:
            continue
        owner, role = wanted[c.topic]
        allowed = ROLE_TYPES[role]
        if c.msgtype not in allowed:
            raise InputError(
                f"topic {c.topic} ({owner} {role}) has message type {c.msgtype}; "
                f"expected {' or '.join(allowed)} (docs/bags.md)",
                path=bag_name,
            )
        out.setdefault(c.topic, []).append(c)
    return out


def _bag_key(p: Path) -> set[str]:
    return {p.name, p.stem, str(p)}


def _assign(bags: list[Path], mapping: BagMapping) -> list[dict[str, tuple[str, str]]]:
    """Per bag: topic -> (owner, role) (owner = robot name or 'mocap:<body>')."""
    per_bag: list[dict[str, tuple[str, str]]] = [{} for _ in bags]
    wants: list[tuple[str | None, str, str, str]] = []
    for r in mapping.robots:
        for role, t in r.topics().items():
            wants.append((r.bag, t, r.name, role))
    if mapping.mocap is not None:
        for body, t in mapping.mocap.bodies.items():
            wants.append((mapping.mocap.bag, t, f"mocap:{body}", "mocap"))
    for bag_sel, topic, owner, role in wants:
        idx = [i for i, b in enumerate(bags) if bag_sel is None or bag_sel in _bag_key(b)]
        if bag_sel is not None and not idx:
            raise InputError(
                f"{owner}: bag {bag_sel!r} is not among the bags given "
                f"({', '.join(b.name for b in bags)})",
                path=mapping.path,
            )
        for i in idx:
            if topic in per_bag[i] and per_bag[i][topic] != (owner, role):
                raise InputError(
                    f"topic {topic} is mapped to {per_bag[i][topic][0]} and "
                    f"{owner}; name each robot's bag with 'bag:'",
                    path=mapping.path,
                )
            per_bag[i][topic] = (owner, role)
    return per_bag


def import_bags(
    bag_paths: list[str | Path],
    mapping: BagMapping,
    out_dir: str | Path,
    *,
    progress: ProgressFn | None = None,
) -> dict:
    """Import ``bag_paths`` as a run directory at ``out_dir`` (new or empty); returns the
    summary (also written as ``import.json``)."""
    root = Path(out_dir)
    if root.exists() and any(root.iterdir()):
        raise InputError("expected an empty or new directory for the run", path=str(root))
    readers = [open_bag(p) for p in bag_paths]
    bags = [p for _, p in readers]
    per_bag = _assign(bags, mapping)
    root.mkdir(parents=True, exist_ok=True)
    sinks = {r.name: RobotSink(r, root, mapping) for r in mapping.robots}
    mocap = MocapSink(mapping.mocap.clock_offset_ns) if mapping.mocap else None
    found: set[tuple[str, str]] = set()
    stats = {"bags": [], "messages": 0, "undecodable": Counter()}
    try:
        for (reader, path), wanted in zip(readers, per_bag):
            _read_one(reader, path, wanted, sinks, mocap, found, stats, progress)
    finally:
        for s in sinks.values():
            s.close()
    _check_found(per_bag, found, bags, mapping)
    return _finish(root, mapping, sinks, mocap, stats)


def _read_one(reader, path: Path, wanted, sinks, mocap, found, stats, progress) -> None:
    from rosbags.highlevel import AnyReaderError

    t_start = time.monotonic()
    size = bag_size_bytes(path)
    try:
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as exc:
        raise InputError(f"cannot open the bag: {exc}", path=str(path)) from None
    try:
        conns = _select(reader, str(path), wanted)
        total = sum(c.msgcount for cs in conns.values() for c in cs)
        done = 0
        sel = [c for cs in conns.values() for c in cs]
        for conn, receive_ns, raw in reader.messages(connections=sel) if sel else ():
            done += 1
            owner, role = wanted[conn.topic]
            found.add((conn.topic, str(path)))
            target = sinks.get(owner)
            if (
                role in ("image", "depth")
                and target.r.image.max_rate_hz
                and target.mapping.clock == "header"
            ):
                s = peek_header_stamp_ns(raw, reader.is2)
                if s is not None and not target.keep_frame(role, s + target.r.clock_offset_ns):
                    continue  # dropped by max_rate_hz: never deserialised
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception:  # rosbags raises several types for a damaged message
                stats["undecodable"][conn.topic] += 1
                continue
            try:
                if target is not None:
                    target.handle(role, msg, receive_ns)
                else:
                    mocap.handle(owner.split(":", 1)[1], msg)
            except rm.MessageError as exc:
                sink = target if target is not None else mocap
                sink.skipped[exc.reason] += 1
                _first_note(sink, exc.reason, f"{conn.topic}: {exc}")
            if progress and (done % 2000 == 0 or done == total):
                progress(f"import-bag: {path.name}", done, total)
        stats["messages"] += done
        stats["bags"].append(
            {
                "path": str(path),
                "messages": done,
                "bytes": size,
                "seconds": round(time.monotonic() - t_start, 3),
            }
        )
    finally:
        reader.close()


def _check_found(per_bag, found, bags, mapping) -> None:
    """Every mapped topic must be in (at least one of) its bags."""
    topics_in: dict[tuple[str, str, str], set[str]] = {}
    for wanted, b in zip(per_bag, bags):
        for t, (owner, role) in wanted.items():
            topics_in.setdefault((t, owner, role), set()).add(str(b))
    for (t, owner, role), where in topics_in.items():
        if not any((t, w) in found for w in where):
            raise InputError(
                f"topic {t} ({owner} {role}) has no messages in "
                f"{', '.join(sorted(where))} (mapping {mapping.path}; "
                "'dran-edge import-bag --list BAG' lists a bag's topics)"
            )


def _finish(root: Path, mapping: BagMapping, sinks: dict[str, RobotSink], mocap, stats) -> dict:
    calib_src = mapping.resolve(mapping.calib) if mapping.calib else None
    tags = False
    if calib_src is not None:
        if not (calib_src / "tags.yaml").exists():
            raise InputError(
                "calib: expected a folder with tags.yaml (docs/calibration.md)", path=str(calib_src)
            )
        (root / "calib" / "cameras").mkdir(parents=True, exist_ok=True)
        shutil.copyfile(calib_src / "tags.yaml", root / "calib" / "tags.yaml")
        tags = True
    for r in mapping.robots:
        s = sinks[r.name]
        if s.first_ns is None:
            raise InputError(
                f"robot {r.name}: no usable odometry on {r.odometry}", path=mapping.path
            )
        cam_dst = root / "calib" / "cameras" / f"{r.name}.yaml"
        if r.image is not None:
            given = calib_src / "cameras" / f"{r.name}.yaml" if calib_src else None
            cam_dst.parent.mkdir(parents=True, exist_ok=True)
            if given is not None and given.exists():
                shutil.copyfile(given, cam_dst)
            elif s.camera is not None:
                rd.write_yaml(cam_dst, s.camera, header=f"{r.name}: from camera_info")
            elif s.counts["frames"]:
                raise InputError(
                    f"robot {r.name}: no camera_info message and no cameras/{r.name}.yaml in calib",
                    path=mapping.path,
                )
    # every robot has a first (and so a last) stamp: checked above
    start = mapping.start_ns or min(s.first_ns for s in sinks.values() if s.first_ns is not None)
    end = max(s.last_ns for s in sinks.values() if s.last_ns is not None)
    duration = mapping.duration_s or max((end - start) / 1e9, 1e-3)
    mocap_start = None
    if mocap is not None:
        assert mapping.mocap is not None  # a mocap sink exists only for a mocap mapping
        mocap_start = mocap.write(
            root / "mocap.csv", mapping.mocap.up_axis, list(mapping.mocap.bodies)
        )
    mission = rd.Mission(
        fleet=mapping.fleet,
        start_ns=int(start),
        duration_s=float(duration),
        robots=tuple(
            rd.RunRobot(r.id, r.name, r.mocap_body, r.T_body_marker, r.T_world_odom)
            for r in mapping.robots
        ),
        objects=mapping.objects,
        comm_graph=mapping.comm_graph,
        mocap_file="mocap.csv" if mocap_start is not None else None,
        mocap_start_ns=mocap_start,
        mocap_up_axis=mapping.mocap.up_axis if mapping.mocap else "y",
    )
    for r in mapping.robots:
        _write_config(root, mapping, mission, r, sinks[r.name], tags)
    rd.write_mission(root, mission)
    summary = {
        "format": "dran-edge-import/1",
        "bags": stats["bags"],
        "messages": stats["messages"],
        "undecodable": dict(stats["undecodable"]),
        "robots": {
            n: {
                "written": dict(s.counts),
                "skipped": dict(s.skipped),
                "first_skip": getattr(s, "notes", {}),
            }
            for n, s in sinks.items()
        },
        "mocap": (
            {"bodies": {b: len(v) for b, v in mocap.stamps.items()}, "skipped": dict(mocap.skipped)}
            if mocap
            else None
        ),
        "start_ns": int(start),
        "duration_s": float(duration),
    }
    (root / "import.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    return summary


def _write_config(
    root: Path, mapping: BagMapping, mission: rd.Mission, r: RobotMap, sink: RobotSink, tags: bool
) -> None:
    from dran_edge.config import config_from_dict, config_to_dict

    dst = root / "robots" / r.name / "robot.yaml"
    if r.config:
        shutil.copyfile(mapping.resolve(r.config), dst)
        return
    nb = mission.neighbours(r.id)
    names = {x.id: x.name for x in mission.robots}
    camera: dict = {"source": "none"}
    if sink.counts["frames"] and tags:
        camera = {
            "source": "recorded",
            "calib_dir": "../../calib",
            "tags_file": "../../calib/tags.yaml",
            "recording": "frames",
        }
        cam = rd._yaml_with_lines(root / "calib" / "cameras" / f"{r.name}.yaml")[0]
        camera |= {"width": int(cam["width"]), "height": int(cam["height"])}
        span = (sink._last_frame_ns - int(mission.start_ns)) / 1e9
        if span > 0:
            camera["fps"] = max(1, int(round(sink.counts["frames"] / max(span, 1e-3))))
    cfg = config_from_dict(
        {
            "robot": {"id": r.id, "name": r.name, "fleet": mapping.fleet},
            "neighbours": [
                {"id": n, "name": names[n], "address": f"127.0.0.1:{_BASE_PORT + n}"} for n in nb
            ],
            "comms": {"transport": "udp", "bind_address": "127.0.0.1", "port": _BASE_PORT + r.id},
            "camera": camera,
        }
    )
    rd.write_yaml(
        dst,
        config_to_dict(cfg),
        header=f"{r.name}: generated by dran-edge import-bag (docs/bags.md)",
    )


def list_topics(path: str | Path) -> list[tuple[str, str, int]]:
    """(topic, message type, count) of a bag, for ``import-bag --list``."""
    from rosbags.highlevel import AnyReaderError

    reader, p = open_bag(path)
    try:
        with reader:
            return sorted((t, i.msgtype or "?", i.msgcount) for t, i in reader.topics.items())
    except AnyReaderError as exc:
        raise InputError(f"cannot open the bag: {exc}", path=str(p)) from None
