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

import bisect
import csv
import heapq
import json
import shutil
import struct
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge.formats import run_dir as rd
from dran_edge.errors import DependencyError, InputError
from dran_edge.formats import ros_msgs as rm
from dran_edge.formats.bag_map import BagMapping, RobotMap

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
#: Record order at equal stamps (the simulator's): reset, odometry, keyframe, loop.
_KIND_ORDER = {4: 0, 1: 1, 2: 2, 3: 3}
_KIND_NAME = {1: "odometry", 2: "keyframes", 3: "loops", 4: "resets"}
_BASE_PORT = 47600
_PENDING_IMAGES = 30


ProgressFn = Callable[[str, int, int], None]
"""progress(stage, messages_done, messages_total), stage = "import-bag: <bag file name>"."""


def open_bag(path: str | Path):
    """A ``rosbags`` AnyReader (not yet opened) for a ROS 1 .bag or a ROS 2 bag directory/file."""
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise DependencyError("reading bags needs the 'rosbags' package: "
                              "pip install 'dran-edge[bags]'") from None
    p = Path(path)
    if not p.exists():
        raise InputError("bag not found", path=str(p))
    if p.is_file() and p.suffix in (".db3", ".mcap"):
        if not (p.parent / "metadata.yaml").exists():
            raise InputError("a ROS 2 bag file needs its folder's metadata.yaml next to it "
                             "(ros2 bag reindex writes one)", path=str(p))
        p = p.parent
    elif p.is_file() and p.suffix != ".bag":
        raise InputError("expected a ROS 1 .bag file, or a ROS 2 bag folder (or its .db3/.mcap)",
                         path=str(p))
    elif p.is_dir() and not (p / "metadata.yaml").exists():
        raise InputError("expected a ROS 2 bag folder with metadata.yaml", path=str(p))
    return AnyReader([p]), p


def bag_size_bytes(p: Path) -> int:
    return p.stat().st_size if p.is_file() else sum(f.stat().st_size for f in p.iterdir()
                                                     if f.is_file())


@dataclass
class _Pending:
    colour: rm.EncodedImage | None = None
    depth: rm.EncodedImage | None = None


class RobotSink:
    """One robot's output: ordered ingest records, frames, camera file; counts what it skips."""

    def __init__(self, robot: RobotMap, root: Path, mapping: BagMapping):
        self.r, self.mapping = robot, mapping
        self.dir = root / "robots" / robot.name
        self.dir.mkdir(parents=True, exist_ok=True)
        self._out = open(self.dir / "ingest.bin", "wb")
        self._heap: list[tuple[int, int, int, bytes]] = []
        self._seq = 0
        self._window_ns = int(mapping.reorder_window_s * 1e9)
        self._high_ns = 0
        self._written_ns = 0
        self.counts: Counter = Counter()
        self.skipped: Counter = Counter()
        self.first_ns: int | None = None
        self.last_ns: int | None = None
        self._last_odom_ns = 0
        self._last_stream_ns: dict[str, int] = {}
        self._kf_header: list[int] = []  # receive clock: keyframe header stamps, in order
        self._kf_receive: list[int] = []
        self._pair_old: deque = deque()
        self._pair_cur: deque = deque()
        self._pending: OrderedDict[int, _Pending] = OrderedDict()
        self._frames_csv = None
        self._frame_n = 0
        self._last_frame_ns = 0
        self._last_keep_ns = 0
        self._decided: OrderedDict[int, bool] = OrderedDict()
        self.camera: dict | None = None
        self.frame_size: tuple[int, int] | None = None

    # -------------------------------------------------------------- records
    def _emit(self, item: rm.Item) -> None:
        kind = _KIND_NAME[item.kind]
        self.counts[kind] += 1
        if item.stamp_ns < self._written_ns:
            self.counts["late_records"] += 1
        heapq.heappush(self._heap, (item.stamp_ns, _KIND_ORDER[item.kind], self._seq, item.data))
        self._seq += 1
        self._high_ns = max(self._high_ns, item.stamp_ns)
        self._flush(self._high_ns - self._window_ns)

    def _flush(self, upto_ns: int | None) -> None:
        while self._heap and (upto_ns is None or self._heap[0][0] <= upto_ns):
            s, _, _, data = heapq.heappop(self._heap)
            self._out.write(data)
            self._written_ns = max(self._written_ns, s)

    def _monotonic(self, stream: str, s: int) -> bool:
        last = self._last_stream_ns.get(stream, 0)
        if s <= last:
            self.skipped[f"non_monotonic:{stream}"] += 1
            _first_note(self, f"non_monotonic:{stream}",
                        f"stamp {s} ns after {last} ns on {stream}")
            return False
        self._last_stream_ns[stream] = s
        return True

    # -------------------------------------------------------------- handlers
    def handle(self, role: str, msg: Any, receive_ns: int) -> None:
        """One message of ``role``; raises MessageError for a message to skip."""
        off = self.r.clock_offset_ns
        recv = self.mapping.clock == "receive"
        stamp = receive_ns if recv else None
        if role == "odometry":
            it = rm.odometry_record(msg, off, stamp)
            if not self._monotonic("odometry", it.stamp_ns):
                return
            self._last_odom_ns = it.stamp_ns
            self.first_ns = it.stamp_ns if self.first_ns is None else self.first_ns
            self.last_ns = it.stamp_ns
            self._emit(it)
            if self.r.keyframes is None and (self.counts["odometry"] - 1) \
                    % self.r.keyframe_every == 0:
                self._emit(rm.keyframe_from_odometry(it))
        elif role == "keyframes":
            it = rm.keyframe_record(msg, off, stamp)
            if recv:
                self._kf_header.append(rm.stamp_ns(msg.header))
                self._kf_receive.append(it.stamp_ns)
            if self._monotonic("keyframes", it.stamp_ns):
                self._emit(it)
        elif role == "reset":
            it = rm.reset_record(msg, self._last_odom_ns, off, stamp)
            if it is not None:
                self._emit(it)
        elif role == "loops":
            old, cur, v, inl = rm.vins_loop_parts(msg)
            self._loop(old, cur, v, inl)
        elif role in ("loop_old", "loop_cur"):
            (self._pair_old if role == "loop_old" else self._pair_cur).append(msg)
            if self._pair_old and self._pair_cur:
                o, c = self._pair_old.popleft(), self._pair_cur.popleft()
                self._loop(rm.stamp_ns(o.header), rm.stamp_ns(c.header),
                           rm.pose_vector(rm._pose_of(c)), 0)
        elif role in ("image", "depth"):
            self._image(role, msg, receive_ns + off if recv else rm.stamp_ns(msg.header) + off)
        elif role == "camera_info":
            if self.camera is None:
                im = self.r.image
                if im.T_body_camera is None:
                    raise InputError(f"robots: {self.r.name}.image: T_body_camera is needed to "
                                     "build the camera file from camera_info (or give calib with "
                                     f"cameras/{self.r.name}.yaml)", path=self.mapping.path)
                self.camera = rm.camera_file(msg, self.r.name, im.T_body_camera, im.depth_unit_m)

    def _loop(self, old: int, cur: int, v: tuple, inliers: int) -> None:
        """A loop between two keyframes given by their header stamps (robot clock)."""
        if self.mapping.clock == "receive":
            old, cur = self._receive_of(old), self._receive_of(cur)
            if old is None or cur is None:
                self.skipped["loop_unknown_keyframe"] += 1
                return
        off = self.r.clock_offset_ns
        self._emit(rm.loop_record(old + off, cur + off, v, inliers))

    def _receive_of(self, header_ns: int) -> int | None:
        """Receive-clock stamp of the keyframe whose header stamp is within 1 ms of ``header_ns``."""
        i = bisect.bisect_left(self._kf_header, header_ns)
        best = min((j for j in (i - 1, i) if 0 <= j < len(self._kf_header)),
                   key=lambda j: abs(self._kf_header[j] - header_ns), default=None)
        if best is None or abs(self._kf_header[best] - header_ns) > 1_000_000:
            return None
        return self._kf_receive[best] - self.r.clock_offset_ns

    def keep_frame(self, role: str, s: int) -> bool:
        """Whether the frame at ``s`` passes ``max_rate_hz``: decided once per stamp (by the
        first of its colour/depth images to arrive), so a pair is kept or dropped together,
        before any pixel is decoded."""
        if s in self._decided:
            return self._decided[s]
        rate = self.r.image.max_rate_hz
        keep = not rate or not self._last_keep_ns or \
            s - self._last_keep_ns >= int(1e9 / rate) - 1000
        if keep:
            self._last_keep_ns = s
        self._decided[s] = keep
        while len(self._decided) > 256:
            self._decided.popitem(last=False)
        if not keep:  # counted once per frame (colour + depth), at its first image
            self.counts["frames_dropped_by_rate"] += 1
        return keep

    def _image(self, role: str, msg: Any, s: int) -> None:
        if not self._monotonic(role, s) or not self.keep_frame(role, s):
            return
        img = rm.image_file(msg, depth=role == "depth", encode=self.r.image.encode)
        slot = self._pending.setdefault(s, _Pending())
        if role == "image":
            slot.colour = img
        else:
            slot.depth = img
        want_depth = self.r.image.depth is not None
        while len(self._pending) > _PENDING_IMAGES:
            old_s, old = self._pending.popitem(last=False)
            if old.colour is not None:
                self.skipped["colour_without_depth"] += 1
            else:
                self.skipped["depth_without_colour"] += 1
        if slot.colour is not None and (slot.depth is not None or not want_depth):
            del self._pending[s]
            self._write_frame(s, slot)

    def _write_frame(self, s: int, slot: _Pending) -> None:
        if s <= self._last_frame_ns:
            self.skipped["non_monotonic:frames"] += 1
            return
        fdir = self.dir / "frames"
        if self._frames_csv is None:
            (fdir / "colour").mkdir(parents=True, exist_ok=True)
            if self.r.image.depth:
                (fdir / "depth").mkdir(parents=True, exist_ok=True)
            self._frames_file = open(fdir / "frames.csv", "w", newline="", encoding="utf-8")
            self._frames_csv = csv.writer(self._frames_file, lineterminator="\n")
            from dran_edge.perception.sources import FRAMES_CSV_HEADER

            self._frames_csv.writerow(FRAMES_CSV_HEADER)
        cname = f"colour/{self._frame_n:06d}{slot.colour.suffix}"
        (fdir / cname).write_bytes(slot.colour.data)
        dname = ""
        if slot.depth is not None:
            dname = f"depth/{self._frame_n:06d}{slot.depth.suffix}"
            (fdir / dname).write_bytes(slot.depth.data)
        self._frames_csv.writerow([s, cname, dname, self.r.name])
        if slot.colour.width and self.frame_size is None:
            self.frame_size = (slot.colour.width, slot.colour.height)
        self._frame_n += 1
        self._last_frame_ns = s
        self.counts["frames"] += 1

    def close(self) -> None:
        self._flush(None)
        self._out.close()
        if self._frames_csv is not None:
            self._frames_file.close()
        left = len(self._pair_old) + len(self._pair_cur)
        if left:
            self.skipped["loop_unpaired"] += left
        for slot in self._pending.values():
            if slot.colour is not None and self.r.image.depth is None:
                continue
            self.skipped["colour_without_depth" if slot.colour else "depth_without_colour"] += 1


class MocapSink:
    """The mocap bodies' poses, written at the end as one Motive-like CSV."""

    def __init__(self, offset_ns: int):
        self.offset_ns = offset_ns
        self.stamps: dict[str, list[int]] = {}
        self.poses: dict[str, list[np.ndarray]] = {}
        self.skipped: Counter = Counter()

    def handle(self, body: str, msg: Any) -> None:
        s, v = rm.mocap_pose(msg, self.offset_ns)
        st = self.stamps.setdefault(body, [])
        if st and s <= st[-1]:
            self.skipped[f"non_monotonic:mocap:{body}"] += 1
            return
        st.append(s)
        self.poses.setdefault(body, []).append(v)

    def write(self, path: Path, up_axis: str, order: list[str]) -> int | None:
        """Write the CSV (bodies in ``order``); returns the stamp of its time 0 (None: no pose)."""
        from dran_edge import geometry as geo
        from dran_edge.formats.motive import _up_rotation, make_take, write_motive_csv

        bodies = [b for b in order if self.stamps.get(b)]
        if not bodies:
            return None
        all_s = np.unique(np.concatenate([np.asarray(self.stamps[b], np.int64) for b in bodies]))
        # one row per distinct stamp; stamps closer than 0.1 ms share a row
        keep = np.r_[True, np.diff(all_s) > 100_000]
        rows = all_s[keep]
        t0 = int(rows[0])
        R_up = np.eye(4)
        R_up[:3, :3] = _up_rotation(up_axis)
        poses = {}
        for b in bodies:
            s = np.asarray(self.stamps[b], np.int64)
            idx = np.searchsorted(rows, s, side="right") - 1
            T = np.full((len(rows), 4, 4), np.nan)
            T[idx] = R_up @ geo.se3_from_xyz_quat_xyzw(np.asarray(self.poses[b]))
            poses[b] = T
        dt = np.diff(rows)
        rate = 1e9 / float(np.median(dt)) if len(dt) else 120.0
        take = make_take((rows - t0) / 1e9, poses, take_name="bag import", frame_rate_hz=rate)
        write_motive_csv(path, take, up_axis=up_axis)
        return t0


def _select(reader, bag_name: str, wanted: dict[str, tuple[str, str]]) -> dict[str, Any]:
    """topic -> connection for the mapped topics in this bag; checks the message types."""
    out = {}
    for c in reader.connections:
        if c.topic not in wanted:
            continue
        owner, role = wanted[c.topic]
        allowed = ROLE_TYPES[role]
        if c.msgtype not in allowed:
            raise InputError(f"topic {c.topic} ({owner} {role}) has message type {c.msgtype}; "
                             f"expected {' or '.join(allowed)} (docs/bags.md)", path=bag_name)
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
            raise InputError(f"{owner}: bag {bag_sel!r} is not among the bags given "
                             f"({', '.join(b.name for b in bags)})", path=mapping.path)
        for i in idx:
            if topic in per_bag[i] and per_bag[i][topic] != (owner, role):
                raise InputError(f"topic {topic} is mapped to {per_bag[i][topic][0]} and "
                                 f"{owner}; name each robot's bag with 'bag:'", path=mapping.path)
            per_bag[i][topic] = (owner, role)
    return per_bag


def import_bags(bag_paths: list[str | Path], mapping: BagMapping, out_dir: str | Path, *,
                progress: ProgressFn | None = None) -> dict:
    """Import ``bag_paths`` as a run directory at ``out_dir`` (new or empty); returns the summary."""
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
        for conn, receive_ns, raw in (reader.messages(connections=sel) if sel else ()):
            done += 1
            owner, role = wanted[conn.topic]
            found.add((conn.topic, str(path)))
            target = sinks.get(owner)
            if role in ("image", "depth") and target.r.image.max_rate_hz \
                    and target.mapping.clock == "header":
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
        stats["bags"].append({"path": str(path), "messages": done, "bytes": size,
                              "seconds": round(time.monotonic() - t_start, 3)})
    finally:
        reader.close()


def peek_header_stamp_ns(raw: bytes | memoryview, ros2: bool) -> int | None:
    """header.stamp of a serialised message that starts with a std_msgs/Header, without
    deserialising it: ROS 1 ``seq u32, secs u32, nsecs u32``; ROS 2 CDR ``4-byte
    encapsulation, sec i32, nanosec u32`` (little- or big-endian). None if too short."""
    if ros2:
        if len(raw) < 12:
            return None
        fmt = "<iI" if raw[1] & 1 else ">iI"
        sec, nsec = struct.unpack_from(fmt, raw, 4)
    else:
        if len(raw) < 12:
            return None
        sec, nsec = struct.unpack_from("<II", raw, 4)
    return sec * 1_000_000_000 + nsec


def _first_note(sink, reason: str, text: str) -> None:
    notes = sink.__dict__.setdefault("notes", {})
    notes.setdefault(reason, text)


def _check_found(per_bag, found, bags, mapping) -> None:
    """Every mapped topic must be in (at least one of) its bags."""
    topics_in: dict[str, set[str]] = {}
    for wanted, b in zip(per_bag, bags):
        for t, (owner, role) in wanted.items():
            topics_in.setdefault((t, owner, role), set()).add(str(b))
    for (t, owner, role), where in topics_in.items():
        if not any((t, w) in found for w in where):
            raise InputError(f"topic {t} ({owner} {role}) has no messages in "
                             f"{', '.join(sorted(where))} (mapping {mapping.path}; "
                             "'dran-edge import-bag --list BAG' lists a bag's topics)")


def _finish(root: Path, mapping: BagMapping, sinks: dict[str, RobotSink], mocap, stats) -> dict:
    calib_src = mapping.resolve(mapping.calib) if mapping.calib else None
    tags = False
    if calib_src is not None:
        if not (calib_src / "tags.yaml").exists():
            raise InputError("calib: expected a folder with tags.yaml (docs/calibration.md)",
                             path=str(calib_src))
        (root / "calib" / "cameras").mkdir(parents=True, exist_ok=True)
        shutil.copyfile(calib_src / "tags.yaml", root / "calib" / "tags.yaml")
        tags = True
    for r in mapping.robots:
        s = sinks[r.name]
        if s.first_ns is None:
            raise InputError(f"robot {r.name}: no usable odometry on {r.odometry}",
                             path=mapping.path)
        cam_dst = root / "calib" / "cameras" / f"{r.name}.yaml"
        if r.image is not None:
            given = calib_src / "cameras" / f"{r.name}.yaml" if calib_src else None
            cam_dst.parent.mkdir(parents=True, exist_ok=True)
            if given is not None and given.exists():
                shutil.copyfile(given, cam_dst)
            elif s.camera is not None:
                rd.write_yaml(cam_dst, s.camera, header=f"{r.name}: from camera_info")
            elif s.counts["frames"]:
                raise InputError(f"robot {r.name}: no camera_info message and no "
                                 f"cameras/{r.name}.yaml in calib", path=mapping.path)
    start = mapping.start_ns or min(s.first_ns for s in sinks.values())
    end = max(s.last_ns for s in sinks.values())
    duration = mapping.duration_s or max((end - start) / 1e9, 1e-3)
    mocap_start = None
    if mocap is not None:
        mocap_start = mocap.write(root / "mocap.csv", mapping.mocap.up_axis,
                                  list(mapping.mocap.bodies))
    mission = rd.Mission(
        fleet=mapping.fleet, start_ns=int(start), duration_s=float(duration),
        robots=tuple(rd.RunRobot(r.id, r.name, r.mocap_body, r.T_body_marker, r.T_world_odom)
                     for r in mapping.robots),
        objects=mapping.objects, comm_graph=mapping.comm_graph,
        mocap_file="mocap.csv" if mocap_start is not None else None,
        mocap_start_ns=mocap_start, mocap_up_axis=mapping.mocap.up_axis if mapping.mocap else "y")
    for r in mapping.robots:
        _write_config(root, mapping, mission, r, sinks[r.name], tags)
    rd.write_mission(root, mission)
    summary = {
        "format": "dran-edge-import/1",
        "bags": stats["bags"],
        "messages": stats["messages"],
        "undecodable": dict(stats["undecodable"]),
        "robots": {n: {"written": dict(s.counts), "skipped": dict(s.skipped),
                       "first_skip": getattr(s, "notes", {})} for n, s in sinks.items()},
        "mocap": ({"bodies": {b: len(v) for b, v in mocap.stamps.items()},
                   "skipped": dict(mocap.skipped)} if mocap else None),
        "start_ns": int(start), "duration_s": float(duration),
    }
    (root / "import.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    return summary


def _write_config(root: Path, mapping: BagMapping, mission: rd.Mission, r: RobotMap,
                  sink: RobotSink, tags: bool) -> None:
    from dran_edge.config import config_from_dict, config_to_dict

    dst = root / "robots" / r.name / "robot.yaml"
    if r.config:
        shutil.copyfile(mapping.resolve(r.config), dst)
        return
    nb = mission.neighbours(r.id)
    names = {x.id: x.name for x in mission.robots}
    camera: dict = {"source": "none"}
    if sink.counts["frames"] and tags:
        camera = {"source": "recorded", "calib_dir": "../../calib",
                  "tags_file": "../../calib/tags.yaml", "recording": "frames"}
        cam = rd._yaml_with_lines(root / "calib" / "cameras" / f"{r.name}.yaml")[0]
        camera |= {"width": int(cam["width"]), "height": int(cam["height"])}
        span = (sink._last_frame_ns - int(mission.start_ns)) / 1e9
        if span > 0:
            camera["fps"] = max(1, int(round(sink.counts["frames"] / max(span, 1e-3))))
    cfg = config_from_dict({
        "robot": {"id": r.id, "name": r.name, "fleet": mapping.fleet},
        "neighbours": [{"id": n, "name": names[n], "address": f"127.0.0.1:{_BASE_PORT + n}"}
                       for n in nb],
        "comms": {"transport": "udp", "bind_address": "127.0.0.1", "port": _BASE_PORT + r.id},
        "camera": camera,
    })
    rd.write_yaml(dst, config_to_dict(cfg),
                  header=f"{r.name}: generated by dran-edge import-bag (docs/bags.md)")


def list_topics(path: str | Path) -> list[tuple[str, str, int]]:
    """(topic, message type, count) of a bag, for ``import-bag --list``."""
    from rosbags.highlevel import AnyReaderError

    reader, p = open_bag(path)
    try:
        with reader:
            return sorted((t, i.msgtype or "?", i.msgcount) for t, i in reader.topics.items())
    except AnyReaderError as exc:
        raise InputError(f"cannot open the bag: {exc}", path=str(p)) from None
