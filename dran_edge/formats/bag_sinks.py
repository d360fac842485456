"""Per-robot and mocap sinks of the bag importer (dran_edge/formats/bags.py, docs/bags.md).

:class:`RobotSink` turns one robot's messages into ingest records written in stamp order
(within the mapping's reorder window), frames and the camera file, counting what it skips;
:class:`MocapSink` collects the rigid bodies' poses and writes them as a Motive-like CSV.
"""

from __future__ import annotations

import bisect
import csv
import heapq
import struct
from collections import Counter, OrderedDict, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge.errors import InputError
from dran_edge.formats import ros_msgs as rm
from dran_edge.formats.bag_map import BagMapping, ImageMap, RobotMap

#: Record order at equal stamps (the simulator's): reset, odometry, keyframe, loop.
_KIND_ORDER = {4: 0, 1: 1, 2: 2, 3: 3}
_KIND_NAME = {1: "odometry", 2: "keyframes", 3: "loops", 4: "resets"}
_PENDING_IMAGES = 30


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
        self._frames_file: Any = None
        self._frames_csv: Any = None  # csv writer of frames/frames.csv, once a frame came
        self._frame_n = 0
        self._last_frame_ns = 0
        self._last_keep_ns = 0
        self._decided: OrderedDict[int, bool] = OrderedDict()
        self.camera: dict | None = None
        self.frame_size: tuple[int, int] | None = None

    @property
    def _image_map(self) -> ImageMap:
        """The robot's image mapping: image roles are routed only to a robot that has one."""
        assert self.r.image is not None
        return self.r.image

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
            _first_note(
                self, f"non_monotonic:{stream}", f"stamp {s} ns after {last} ns on {stream}"
            )
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
            if (
                self.r.keyframes is None
                and (self.counts["odometry"] - 1) % self.r.keyframe_every == 0
            ):
                self._emit(rm.keyframe_from_odometry(it))
        elif role == "keyframes":
            it = rm.keyframe_record(msg, off, stamp)
            if recv:
                self._kf_header.append(rm.stamp_ns(msg.header))
                self._kf_receive.append(it.stamp_ns)
            if self._monotonic("keyframes", it.stamp_ns):
                self._emit(it)
        elif role == "reset":
            reset = rm.reset_record(msg, self._last_odom_ns, off, stamp)
            if reset is not None:
                self._emit(reset)
        elif role == "loops":
            old, cur, v, inl = rm.vins_loop_parts(msg)
            self._loop(old, cur, v, inl)
        elif role in ("loop_old", "loop_cur"):
            (self._pair_old if role == "loop_old" else self._pair_cur).append(msg)
            if self._pair_old and self._pair_cur:
                o, c = self._pair_old.popleft(), self._pair_cur.popleft()
                self._loop(
                    rm.stamp_ns(o.header), rm.stamp_ns(c.header), rm.pose_vector(rm._pose_of(c)), 0
                )
        elif role in ("image", "depth"):
            self._image(role, msg, receive_ns + off if recv else rm.stamp_ns(msg.header) + off)
        elif role == "camera_info":
            if self.camera is None:
                im = self._image_map
                if im.T_body_camera is None:
                    raise InputError(
                        f"robots: {self.r.name}.image: T_body_camera is needed to "
                        "build the camera file from camera_info (or give calib with "
                        f"cameras/{self.r.name}.yaml)",
                        path=self.mapping.path,
                    )
                self.camera = rm.camera_file(msg, self.r.name, im.T_body_camera, im.depth_unit_m)

    def _loop(self, old: int, cur: int, v: tuple, inliers: int) -> None:
        """A loop between two keyframes given by their header stamps (robot clock)."""
        if self.mapping.clock == "receive":
            old_r, cur_r = self._receive_of(old), self._receive_of(cur)
            if old_r is None or cur_r is None:
                self.skipped["loop_unknown_keyframe"] += 1
                return
            old, cur = old_r, cur_r
        off = self.r.clock_offset_ns
        self._emit(rm.loop_record(old + off, cur + off, v, inliers))

    def _receive_of(self, header_ns: int) -> int | None:
        """Receive-clock stamp of the keyframe whose header stamp is within 1 ms of
        ``header_ns``."""
        i = bisect.bisect_left(self._kf_header, header_ns)
        best = min(
            (j for j in (i - 1, i) if 0 <= j < len(self._kf_header)),
            key=lambda j: abs(self._kf_header[j] - header_ns),
            default=None,
        )
        if best is None or abs(self._kf_header[best] - header_ns) > 1_000_000:
            return None
        return self._kf_receive[best] - self.r.clock_offset_ns

    def keep_frame(self, role: str, s: int) -> bool:
        """Whether the frame at ``s`` passes ``max_rate_hz``: decided once per stamp (by the
        first of its colour/depth images to arrive), so a pair is kept or dropped together,
        before any pixel is decoded."""
        if s in self._decided:
            return self._decided[s]
        rate = self._image_map.max_rate_hz
        keep = (
            not rate or not self._last_keep_ns or s - self._last_keep_ns >= int(1e9 / rate) - 1000
        )
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
        img = rm.image_file(msg, depth=role == "depth", encode=self._image_map.encode)
        slot = self._pending.setdefault(s, _Pending())
        if role == "image":
            slot.colour = img
        else:
            slot.depth = img
        want_depth = self._image_map.depth is not None
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
        colour = slot.colour
        assert colour is not None  # _image writes a frame once its colour image came
        if s <= self._last_frame_ns:
            self.skipped["non_monotonic:frames"] += 1
            return
        fdir = self.dir / "frames"
        if self._frames_csv is None:
            (fdir / "colour").mkdir(parents=True, exist_ok=True)
            if self._image_map.depth:
                (fdir / "depth").mkdir(parents=True, exist_ok=True)
            self._frames_file = open(fdir / "frames.csv", "w", newline="", encoding="utf-8")
            self._frames_csv = csv.writer(self._frames_file, lineterminator="\n")
            from dran_edge.perception.sources import FRAMES_CSV_HEADER

            self._frames_csv.writerow(FRAMES_CSV_HEADER)
        cname = f"colour/{self._frame_n:06d}{colour.suffix}"
        (fdir / cname).write_bytes(colour.data)
        dname = ""
        if slot.depth is not None:
            dname = f"depth/{self._frame_n:06d}{slot.depth.suffix}"
            (fdir / dname).write_bytes(slot.depth.data)
        self._frames_csv.writerow([s, cname, dname, self.r.name])
        if colour.width and colour.height is not None and self.frame_size is None:
            self.frame_size = (colour.width, colour.height)
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
            if slot.colour is not None and self._image_map.depth is None:
                continue
            self.skipped["colour_without_depth" if slot.colour else "depth_without_colour"] += 1


class MocapSink:
    """The mocap bodies' poses, written at the end as one Motive-like CSV."""

    def __init__(self, offset_ns: int):
        self.offset_ns = offset_ns
        self.stamps: dict[str, list[int]] = {}
        self.poses: dict[str, list[tuple[float, ...]]] = {}
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
        from dran_edge.formats.motive import up_rotation
        from dran_edge.formats.motive_write import make_take, write_motive_csv

        bodies = [b for b in order if self.stamps.get(b)]
        if not bodies:
            return None
        all_s = np.unique(np.concatenate([np.asarray(self.stamps[b], np.int64) for b in bodies]))
        # one row per distinct stamp; stamps closer than 0.1 ms share a row
        keep = np.r_[True, np.diff(all_s) > 100_000]
        rows = all_s[keep]
        t0 = int(rows[0])
        R_up = np.eye(4)
        R_up[:3, :3] = up_rotation(up_axis)
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
