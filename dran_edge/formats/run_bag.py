"""Write a run directory as ROS bags (the inverse of :mod:`dran_edge.formats.bags`).

What a lab's recording of the run would hold, with the topics VINS-Mono, a RealSense driver
and vrpn_client_ros publish, written by the ``rosbags`` writers (ROS 1 .bag, ROS 2 sqlite3
or MCAP), plus the mapping file (docs/bags.md) that imports it back. Used by the import tests
(the replay of the re-imported run must equal the replay of the original), by
``tools/bench/bench_bags.py`` and for trying ``import-bag`` without a robot.

Per robot (``/<name>`` prefix when all robots share one bag):

=====================================  ============================  ===========================
topic                                  type                          from
=====================================  ============================  ===========================
vins_estimator/odometry                nav_msgs/Odometry             ODOMETRY records
vins_estimator/keyframe_pose           nav_msgs/Odometry             KEYFRAME records
pose_graph/loop_edge                   nav_msgs/Odometry (vins form) LOOP records
feature_tracker/restart                std_msgs/Header (stamped)     RESET records
camera/color/image_raw[/compressed]    Image mono8 / CompressedImage frames/colour
camera/aligned_depth_to_color/...      Image 16UC1 / compressedDepth frames/depth
camera/color/camera_info               sensor_msgs/CameraInfo        calib/cameras/<name>.yaml
=====================================  ============================  ===========================

and ``/vrpn_client_node/<body>/pose`` (geometry_msgs/PoseStamped in the mocap system's own
world, Y-up for Motive, as vrpn_client_ros streams it) per mocap body.
Receive times are the stamps plus a latency per topic (loops arrive late, as from VINS).
"""

from __future__ import annotations

import csv
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.formats import run_dir as rd
from dran_edge.errors import InputError

FORMATS = ("ros1", "sqlite3", "mcap")
#: Receive-time latency per role (ns): what a recorder on the robot sees.
LATENCY_NS = {
    "odometry": 3_000_000,
    "keyframes": 40_000_000,
    "loops": 350_000_000,
    "reset": 1_000_000,
    "image": 25_000_000,
    "depth": 26_000_000,
    "camera_info": 25_000_000,
    "mocap": 2_000_000,
}
_POSE = struct.Struct("<q7d")
_LOOP = struct.Struct("<qq7dI")
_HDR = 16


def _typestore(fmt: str):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)


class _Msgs:
    """Message constructors for one typestore."""

    def __init__(self, ts):
        self.ts = ts
        T = ts.types
        self.Time, self.Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
        self.is1 = "seq" in self.Header.__dataclass_fields__

    def header(self, stamp_ns: int, frame: str = "world"):
        t = self.Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))
        return (
            self.Header(seq=0, stamp=t, frame_id=frame)
            if self.is1
            else self.Header(stamp=t, frame_id=frame)
        )

    def pose(self, v):
        T = self.ts.types
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=v[0], y=v[1], z=v[2]),
            orientation=T["geometry_msgs/msg/Quaternion"](x=v[3], y=v[4], z=v[5], w=v[6]),
        )

    def odometry(self, stamp_ns, v, twist=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0), cov=None):
        T = self.ts.types
        V3 = T["geometry_msgs/msg/Vector3"]
        cov = np.zeros(36) if cov is None else np.asarray(cov, np.float64).reshape(36)
        return T["nav_msgs/msg/Odometry"](
            header=self.header(stamp_ns),
            child_frame_id="body",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(v), covariance=cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](
                    linear=V3(x=twist[0], y=twist[1], z=twist[2]),
                    angular=V3(x=twist[3], y=twist[4], z=twist[5]),
                ),
                covariance=np.zeros(36),
            ),
        )

    def pose_stamped(self, stamp_ns, v):
        return self.ts.types["geometry_msgs/msg/PoseStamped"](
            header=self.header(stamp_ns), pose=self.pose(v)
        )

    def image(self, stamp_ns, array: np.ndarray, encoding: str):
        a = np.ascontiguousarray(array)
        h, w = a.shape[:2]
        return self.ts.types["sensor_msgs/msg/Image"](
            header=self.header(stamp_ns, "camera"),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=a.strides[0],
            data=a.reshape(-1).view(np.uint8),
        )

    def compressed(self, stamp_ns, data: bytes, fmt: str):
        return self.ts.types["sensor_msgs/msg/CompressedImage"](
            header=self.header(stamp_ns, "camera"),
            format=fmt,
            data=np.frombuffer(data, dtype=np.uint8),
        )

    def camera_info(self, stamp_ns, cam: dict):
        i = cam["intrinsics"]
        K = np.array([i["fx"], 0, i["cx"], 0, i["fy"], i["cy"], 0, 0, 1], np.float64)
        P = np.array([i["fx"], 0, i["cx"], 0, 0, i["fy"], i["cy"], 0, 0, 0, 1, 0], np.float64)
        T = self.ts.types
        roi = T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        names = T["sensor_msgs/msg/CameraInfo"].__dataclass_fields__
        kw = {
            "header": self.header(stamp_ns, "camera"),
            "height": cam["height"],
            "width": cam["width"],
            "distortion_model": "plumb_bob",
            "binning_x": 0,
            "binning_y": 0,
            "roi": roi,
        }
        upper = "K" in names
        kw["D" if upper else "d"] = np.asarray(cam.get("distortion", [0.0] * 5), np.float64)
        kw["K" if upper else "k"] = K
        kw["R" if upper else "r"] = np.eye(3).reshape(9)
        kw["P" if upper else "p"] = P
        return T["sensor_msgs/msg/CameraInfo"](**kw)


def _robot_messages(
    run: rd.Run, name: str, msgs: _Msgs, raw_images: bool
) -> Iterator[tuple[str, int, int, object]]:
    """(role, stamp_ns, receive_ns, message) of one robot, unordered."""
    from dran_edge.comms import ingest

    has_frames = run.frames_dir(name) is not None
    for rec in ingest.iter_records(run.read_ingest(name)):
        if isinstance(rec, Exception):
            raise InputError(
                f"robot {name}: ingest.bin does not decode: {rec}", path=str(run.ingest_path(name))
            )
        p = rec.raw[_HDR:]
        if rec.kind in (ingest.KIND_ODOMETRY, ingest.KIND_KEYFRAME):
            s, *v = _POSE.unpack_from(p)
            cov = rec.event.covariance if rec.kind == ingest.KIND_ODOMETRY else None
            role = "odometry" if rec.kind == ingest.KIND_ODOMETRY else "keyframes"
            yield role, s, s, msgs.odometry(s, v, cov=cov)
        elif rec.kind == ingest.KIND_LOOP:
            so, sc, *rest = _LOOP.unpack_from(p)
            v, inliers = rest[:7], rest[7]
            yield (
                "loops",
                sc,
                sc,
                msgs.odometry(sc, v, twist=(so / 1e9, 0.0, 0.0, float(inliers), 0.0, 0.0)),
            )
        elif rec.kind == ingest.KIND_RESET:
            s = rec.event.stamp_ns
            yield "reset", s, s, msgs.header(s)
        elif rec.kind == ingest.KIND_OBSERVATIONS and has_frames:
            continue  # the robot's own perception output: an import derives it from the frames
        else:
            raise InputError(
                f"robot {name}: ingest record kind {rec.kind} has no ROS topic in "
                "this exporter (a run's observations are exported as the frames they came from)",
                path=str(run.ingest_path(name)),
            )
    fdir = run.frames_dir(name)
    if fdir is None:
        return
    cam = rd._yaml_with_lines(run.calib_dir / "cameras" / f"{name}.yaml")[0]
    with open(fdir / "frames.csv", newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))[1:]
    for k, (stamp, colour, depth, _cam) in enumerate(rows):
        s = int(stamp)
        if k == 0:
            yield "camera_info", s, s, msgs.camera_info(s, cam)
        cbytes = (fdir / colour).read_bytes()
        dbytes = (fdir / depth).read_bytes() if depth else None
        if raw_images:
            import cv2

            c = cv2.imdecode(np.frombuffer(cbytes, np.uint8), cv2.IMREAD_UNCHANGED)
            if c is None:
                raise InputError("cannot decode the image", path=str(fdir / colour))
            yield "image", s, s, msgs.image(s, c, "mono8" if c.ndim == 2 else "bgr8")
            if dbytes is not None:
                d = cv2.imdecode(np.frombuffer(dbytes, np.uint8), cv2.IMREAD_UNCHANGED)
                if d is None:
                    raise InputError("cannot decode the depth image", path=str(fdir / depth))
                yield "depth", s, s, msgs.image(s, d, "16UC1")
        else:
            yield "image", s, s, msgs.compressed(s, cbytes, "mono8; png compressed")
            if dbytes is not None:
                from dran_edge.formats.ros_msgs import compressed_depth_header

                yield (
                    "depth",
                    s,
                    s,
                    msgs.compressed(
                        s, compressed_depth_header() + dbytes, "16UC1; compressedDepth png"
                    ),
                )


ROBOT_TOPICS = {
    "odometry": ("vins_estimator/odometry", "nav_msgs/msg/Odometry"),
    "keyframes": ("vins_estimator/keyframe_pose", "nav_msgs/msg/Odometry"),
    "loops": ("pose_graph/loop_edge", "nav_msgs/msg/Odometry"),
    "reset": ("feature_tracker/restart", "std_msgs/msg/Header"),
    "camera_info": ("camera/color/camera_info", "sensor_msgs/msg/CameraInfo"),
}


def _image_topics(raw: bool) -> dict[str, tuple[str, str]]:
    if raw:
        return {
            "image": ("camera/color/image_raw", "sensor_msgs/msg/Image"),
            "depth": ("camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image"),
        }
    return {
        "image": ("camera/color/image_raw/compressed", "sensor_msgs/msg/CompressedImage"),
        "depth": (
            "camera/aligned_depth_to_color/image_raw/compressedDepth",
            "sensor_msgs/msg/CompressedImage",
        ),
    }


class _BagOut:
    def __init__(self, path: Path, fmt: str, ts: Any):
        self.fmt, self.ts = fmt, ts
        self.w: Any
        if fmt == "ros1":
            from rosbags.rosbag1 import Writer as Ros1Writer

            self.w = Ros1Writer(path)
        else:
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as Ros2Writer

            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self.w = Ros2Writer(path, version=9, storage_plugin=plugin)
        self.w.open()
        self.conns: dict[str, Any] = {}

    def write(self, topic: str, msgtype: str, receive_ns: int, msg: Any) -> None:
        if topic not in self.conns:
            self.conns[topic] = self.w.add_connection(topic, msgtype, typestore=self.ts)
        data = (
            self.ts.serialize_ros1(msg, msgtype)
            if self.fmt == "ros1"
            else self.ts.serialize_cdr(msg, msgtype)
        )
        self.w.write(self.conns[topic], receive_ns, data)

    def close(self) -> None:
        self.w.close()


def write_run_bags(
    run_dir: str | Path,
    out_dir: str | Path,
    fmt: str,
    *,
    per_robot: bool = False,
    raw_images: bool = False,
) -> tuple[list[Path], dict]:
    """Write ``run_dir`` as bags in ``out_dir``; returns (bag paths, mapping as a dict).

    ``per_robot``: one bag per robot (topics without a namespace) plus ``mocap`` bag; else
    one bag with ``/<name>/...`` topics. ``raw_images``: sensor_msgs/Image (mono8/bgr8,
    16UC1) instead of CompressedImage.
    """
    if fmt not in FORMATS:
        raise InputError(f"bag format: expected one of {FORMATS}, got {fmt!r}")
    run = rd.open_run(run_dir)
    ts = _typestore(fmt)
    msgs = _Msgs(ts)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ext = ".bag" if fmt == "ros1" else ""
    topics = ROBOT_TOPICS | _image_topics(raw_images)
    paths, robots_map = [], []
    single = None if per_robot else _BagOut(out / f"run{ext}", fmt, ts)
    for r in run.mission.robots:
        bag = single if single is not None else _BagOut(out / f"{r.name}{ext}", fmt, ts)
        prefix = "" if per_robot else f"/{r.name}"
        rows = sorted(
            _robot_messages(run, r.name, msgs, raw_images),
            key=lambda x: (x[2] + LATENCY_NS[x[0]], x[1]),
        )
        used = set()
        for role, _s, recv, msg in rows:
            topic, typ = topics[role]
            bag.write(f"{prefix}/{topic}", typ, recv + LATENCY_NS[role], msg)
            used.add(role)
        if per_robot:
            bag.close()
            paths.append(out / f"{r.name}{ext}")
        robots_map.append(_robot_mapping(run, r, prefix, topics, used, per_robot, ext))
    mapping: dict[str, Any] = {
        "format": "dran-edge-bag-map/1",
        "fleet": run.mission.fleet,
        "start_ns": run.mission.start_ns,
        "duration_s": run.mission.duration_s,
        "calib": str((run.calib_dir).resolve()) if (run.calib_dir / "tags.yaml").exists() else None,
        "comm_graph": [list(e) for e in run.mission.comm_graph],
        "robots": robots_map,
    }
    if mapping["calib"] is None:
        del mapping["calib"]
    if run.mocap_path is not None:
        mbag = single if single is not None else _BagOut(out / f"mocap{ext}", fmt, ts)
        bodies = _write_mocap(run, run.mocap_path, mbag, msgs)
        if per_robot:
            mbag.close()
            paths.append(out / f"mocap{ext}")
        mapping["mocap"] = {"bodies": bodies, "up_axis": run.mission.mocap_up_axis}
        if per_robot:
            mapping["mocap"]["bag"] = f"mocap{ext}"
        mapping["objects"] = [
            {
                "id": o.id,
                "name": o.name,
                "mocap_body": o.mocap_body,
                "T_object_marker": rd.pose_to_yaml(o.T_object_marker),
            }
            for o in run.mission.objects
        ]
    if single is not None:
        single.close()
        paths.append(out / f"run{ext}")
    return paths, mapping


def _robot_mapping(run, r, prefix, topics, used, per_robot, ext) -> dict:
    d: dict = {"id": r.id, "name": r.name, "odometry": f"{prefix}/{topics['odometry'][0]}"}
    if per_robot:
        d["bag"] = f"{r.name}{ext}"
    if "keyframes" in used:
        d["keyframes"] = f"{prefix}/{topics['keyframes'][0]}"
    if "reset" in used:
        d["reset"] = f"{prefix}/{topics['reset'][0]}"
    if "loops" in used:
        d["loops"] = {"form": "vins", "topic": f"{prefix}/{topics['loops'][0]}"}
    if "image" in used:
        cam = rd._yaml_with_lines(run.calib_dir / "cameras" / f"{r.name}.yaml")[0]
        d["image"] = {
            "topic": f"{prefix}/{topics['image'][0]}",
            "camera_info": f"{prefix}/{topics['camera_info'][0]}",
            "T_body_camera": cam["T_body_camera"],
            "depth_unit_m": cam.get("depth_unit_m", 0.001),
        }
        if "depth" in used:
            d["image"]["depth"] = f"{prefix}/{topics['depth'][0]}"
    if r.mocap_body:
        d["mocap_body"] = r.mocap_body
        d["T_body_marker"] = rd.pose_to_yaml(r.T_body_marker)
    if r.T_world_odom is not None:
        d["T_world_odom"] = rd.pose_to_yaml(r.T_world_odom)
    return d


def _write_mocap(run: rd.Run, mocap_path: Path, bag: _BagOut, msgs: _Msgs) -> dict[str, str]:
    from dran_edge.formats.motive import read_motive_csv, up_rotation

    take = read_motive_csv(mocap_path, up_axis=run.mission.mocap_up_axis)
    R_motive_world = np.eye(4)
    R_motive_world[:3, :3] = up_rotation(run.mission.mocap_up_axis).T
    start = run.mission.mocap_start_ns or run.mission.start_ns
    stamps = start + np.round(take.time_s * 1e9).astype(np.int64)
    bodies = {}
    rows = []
    for name, body in take.bodies.items():
        topic = f"/vrpn_client_node/{name}/pose"
        bodies[name] = topic
        # the poses as the mocap system streams them: in its own world (Motive: Y-up)
        v = geo.se3_to_xyz_quat_xyzw(
            R_motive_world @ np.where(body.valid[:, None, None], body.T_world_marker, np.eye(4))
        )
        for k in np.flatnonzero(body.valid).tolist():
            rows.append((int(stamps[k]), topic, v[k]))
    rows.sort(key=lambda x: (x[0], x[1]))
    for s, topic, v in rows:
        bag.write(
            topic, "geometry_msgs/msg/PoseStamped", s + LATENCY_NS["mocap"], msgs.pose_stamped(s, v)
        )
    return bodies
