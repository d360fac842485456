"""ROS 2 bridge (Humble, Jazzy): VIO topics -> the daemon's ingest socket; estimates -> ROS.

Run it with ``python3 -m dran_edge.ros.bridge2 --ros-args -p socket:=... `` (docs/ros2.md has
the launch lines). It subscribes to

- ``odometry`` (nav_msgs/Odometry), ``keyframes`` (nav_msgs/Odometry, optional),
- ``loop_topic`` (nav_msgs/Odometry in the form of docs/vins-mono.md) or ``loop_old`` +
  ``loop_cur`` (geometry_msgs/PoseWithCovarianceStamped pairs, docs/bags.md),
- ``reset`` (std_msgs/Bool, optional), ``image`` + ``depth`` (sensor_msgs/Image, optional:
  forwarded as FRAME records when the daemon's ``camera.source`` is ``forwarded``),

converts each message with :mod:`dran_edge.formats.ros_msgs` — the same code as
``dran-edge import-bag`` — and sends the records to the daemon's ingest socket. Every
``publish_period_s`` it reads the daemon's status socket and publishes the estimate: the
keyframe path as nav_msgs/Path, the object map as visualization_msgs/MarkerArray (cubes and
id labels) and TF ``world -> <robot>/base_link`` at the newest keyframe.

:class:`BridgeCore` holds everything but rclpy (tested with rosbags-deserialised ROS 2
messages in tests/test_ros2_bridge.py); :func:`main` wires it to an rclpy node.
"""

from __future__ import annotations

import collections
from collections.abc import Callable
from typing import Any

import numpy as np

from dran_edge.formats import ros_msgs as rm

DEFAULTS = {
    "socket": "/run/dran-edge/ingest.sock",
    "status_socket": "/run/dran-edge/status.sock",
    "odometry": "/vins_estimator/odometry",
    "keyframes": "/vins_estimator/keyframe_pose",
    "loop_topic": "/pose_graph/loop_edge",
    "loop_old": "",
    "loop_cur": "",
    "reset": "/feature_tracker/restart",
    "image": "",
    "depth": "",
    "frame_hz": 5.0,
    "world_frame": "world",
    "robot_frame": "base_link",
    "publish_period_s": 1.0,
    "max_queue": 20000,
}


class BridgeCore:
    """Message handling without rclpy: ``send(record_bytes)`` receives every record."""

    def __init__(
        self, send: Callable[[bytes], None], frame_hz: float = 5.0, with_depth: bool = False
    ):
        self.send = send
        self.last_odometry_ns = 0
        self.skipped: collections.Counter = collections.Counter()
        self._old: collections.deque = collections.deque(maxlen=100)
        self._cur: collections.deque = collections.deque(maxlen=100)
        self._min_gap_ns = int(1e9 / frame_hz) if frame_hz > 0 else 0
        self._sent_frame_ns = 0
        self._with_depth = with_depth
        self._pending: collections.OrderedDict = collections.OrderedDict()

    def _guard(self, fn: Callable[[], rm.Item | None]) -> None:
        try:
            item = fn()
        except rm.MessageError as exc:
            self.skipped[exc.reason] += 1
            return
        if item is not None:
            self.send(item.data)

    def on_odometry(self, msg: Any) -> None:
        def f():
            it = rm.odometry_record(msg)
            if it.stamp_ns <= self.last_odometry_ns:
                raise rm.MessageError("non_monotonic", "odometry stamp went backwards")
            self.last_odometry_ns = it.stamp_ns
            return it

        self._guard(f)

    def on_keyframe(self, msg: Any) -> None:
        self._guard(lambda: rm.keyframe_record(msg))

    def on_loop(self, msg: Any) -> None:
        self._guard(lambda: rm.vins_loop_record(msg))

    def on_loop_old(self, msg: Any) -> None:
        self._old.append(msg)
        self._pair()

    def on_loop_cur(self, msg: Any) -> None:
        self._cur.append(msg)
        self._pair()

    def _pair(self) -> None:
        while self._old and self._cur:
            o, c = self._old.popleft(), self._cur.popleft()
            self._guard(lambda: rm.pose_pair_loop_record(o, c))

    def on_reset(self, msg: Any) -> None:
        self._guard(lambda: rm.reset_record(msg, self.last_odometry_ns))

    def on_image(self, msg: Any, depth: bool = False) -> None:
        """Colour (and, when configured, the depth image with the same stamp) -> FRAME."""
        s = rm.stamp_ns(msg.header)
        slot = self._pending.setdefault(s, [None, None])
        slot[1 if depth else 0] = msg
        while len(self._pending) > 10:
            self._pending.popitem(last=False)
            self.skipped["frame_unpaired"] += 1
        if slot[0] is None or (self._with_depth and slot[1] is None):
            return
        del self._pending[s]
        if s - self._sent_frame_ns < self._min_gap_ns:
            return
        self._guard(lambda: self._frame(s, slot[0], slot[1]))

    def _frame(self, s: int, colour_msg: Any, depth_msg: Any) -> rm.Item:
        from dran_edge.comms import ingest
        from dran_edge.perception.frame import Frame, frame_to_bytes

        colour, depth = rm.decode_image(colour_msg), None
        if colour.ndim == 2:
            colour = np.repeat(colour[:, :, None], 3, axis=2)
        if depth_msg is not None:
            depth = rm.decode_image(depth_msg, depth=True)
        frame = Frame(s, np.ascontiguousarray(colour), depth, str(colour_msg.header.frame_id))
        self._sent_frame_ns = s
        return rm.Item(s, ingest.KIND_FRAME, ingest.pack_frame(s, frame_to_bytes(frame)))


def estimate_from_status(status: dict) -> dict | None:
    """The ``estimate`` section of the daemon's status document, as arrays (None if absent)."""
    est = status.get("estimate") if isinstance(status, dict) else None
    if not est or not est.get("keyframes"):
        return None
    kf = np.asarray(est["keyframes"], dtype=np.float64).reshape(-1, 8)
    objs = np.asarray(est.get("objects") or np.zeros((0, 8)), dtype=np.float64).reshape(-1, 8)
    return {
        "stamps_ns": kf[:, 0].astype(np.int64),
        "poses": kf[:, 1:],
        "object_ids": objs[:, 0].astype(np.int64),
        "object_poses": objs[:, 1:],
    }


def _subscribe(node, core: BridgeCore, p: dict) -> None:  # pragma: no cover - needs rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from rclpy.qos import qos_profile_sensor_data
    from std_msgs.msg import Bool

    node.create_subscription(Odometry, p["odometry"], core.on_odometry, 200)
    if p["keyframes"]:
        node.create_subscription(Odometry, p["keyframes"], core.on_keyframe, 100)
    if p["loop_old"] and p["loop_cur"]:
        node.create_subscription(PoseWithCovarianceStamped, p["loop_old"], core.on_loop_old, 100)
        node.create_subscription(PoseWithCovarianceStamped, p["loop_cur"], core.on_loop_cur, 100)
    elif p["loop_topic"]:
        node.create_subscription(Odometry, p["loop_topic"], core.on_loop, 100)
    if p["reset"]:
        node.create_subscription(Bool, p["reset"], core.on_reset, 10)
    if p["image"]:
        from sensor_msgs.msg import Image

        node.create_subscription(Image, p["image"], core.on_image, qos_profile_sensor_data)
        if p["depth"]:
            node.create_subscription(
                Image, p["depth"], lambda m: core.on_image(m, True), qos_profile_sensor_data
            )


def _pose_msg(v):  # pragma: no cover - needs rclpy
    from geometry_msgs.msg import Point, Pose, Quaternion

    return Pose(
        position=Point(x=float(v[0]), y=float(v[1]), z=float(v[2])),
        orientation=Quaternion(x=float(v[3]), y=float(v[4]), z=float(v[5]), w=float(v[6])),
    )


def _publisher(node, p: dict) -> Callable[[], None]:  # pragma: no cover - needs rclpy
    """The timer callback: status socket -> Path, MarkerArray, TF."""
    from geometry_msgs.msg import PoseStamped, TransformStamped
    from nav_msgs.msg import Path
    from tf2_ros import TransformBroadcaster
    from visualization_msgs.msg import Marker, MarkerArray

    from dran_edge.daemon.status import query_status
    from dran_edge.errors import DranError

    path_pub = node.create_publisher(Path, "~/path", 1)
    marker_pub = node.create_publisher(MarkerArray, "~/objects", 1)
    tf = TransformBroadcaster(node)
    world = p["world_frame"]

    def publish() -> None:
        try:
            est = estimate_from_status(query_status(p["status_socket"], timeout_s=0.5))
        except DranError as exc:
            node.get_logger().warn(str(exc), throttle_duration_sec=30.0)
            return
        if est is None:
            return
        now = node.get_clock().now().to_msg()
        path = Path()
        path.header.frame_id, path.header.stamp = world, now
        for s, v in zip(est["stamps_ns"].tolist(), est["poses"]):
            ps = PoseStamped(pose=_pose_msg(v))
            ps.header.frame_id = world
            ps.header.stamp.sec, ps.header.stamp.nanosec = divmod(int(s), 1_000_000_000)
            path.poses.append(ps)
        path_pub.publish(path)
        arr = MarkerArray()
        for oid, v in zip(est["object_ids"].tolist(), est["object_poses"]):
            for kind, mid in ((Marker.CUBE, 2 * oid), (Marker.TEXT_VIEW_FACING, 2 * oid + 1)):
                m = Marker(type=kind, id=int(mid), action=Marker.ADD, pose=_pose_msg(v))
                m.header.frame_id, m.header.stamp, m.ns = world, now, "dran_edge_objects"
                m.scale.x = m.scale.y = m.scale.z = 0.4 if kind == Marker.CUBE else 0.2
                m.color.r, m.color.g, m.color.b, m.color.a = 0.2, 0.6, 1.0, 0.8
                m.text = f"object {oid}"
                arr.markers.append(m)
        marker_pub.publish(arr)
        t = TransformStamped()
        t.header.frame_id, t.header.stamp = world, now
        t.child_frame_id = p["robot_frame"]
        v = [float(x) for x in est["poses"][-1]]
        t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = v[:3]
        q = t.transform.rotation
        q.x, q.y, q.z, q.w = v[3:]
        tf.sendTransform(t)

    return publish


def main(argv: list[str] | None = None) -> int:  # pragma: no cover - needs rclpy
    import rclpy
    from rclpy.node import Node

    from dran_edge.ros.ingest_client import IngestClient

    rclpy.init(args=argv)
    node = Node("dran_edge_bridge")
    p = {k: node.declare_parameter(k, v).value for k, v in DEFAULTS.items()}
    client = IngestClient(p["socket"], int(p["max_queue"]), log=lambda m: node.get_logger().info(m))
    client.start()
    core = BridgeCore(client.put, float(p["frame_hz"]), bool(p["depth"]))
    _subscribe(node, core, p)
    node.create_timer(float(p["publish_period_s"]), _publisher(node, p))
    node.get_logger().info(f"dran-edge bridge: {p['odometry']} ... -> {p['socket']}")
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        client.stop()
        node.destroy_node()
        rclpy.shutdown()
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
