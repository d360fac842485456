"""The ROS 2 bridge: its conversion on rosbags-serialised ROS 2 messages, through a real daemon's
ingest and status sockets; the rclpy node itself where rclpy exists."""

from __future__ import annotations

import socket
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the bridge tests build ROS 2 messages with rosbags")

from dran_edge.comms import ingest  # noqa: E402
from dran_edge.formats import run_bag  # noqa: E402
from dran_edge.ros.bridge2 import BridgeCore, estimate_from_status  # noqa: E402

T0 = 1_767_225_600_000_000_000
HUMBLE = "sqlite3"  # run_bag's ROS 2 typestore (Humble message definitions)


def _ros2(msgs, msg, typ):
    """A message as a ROS 2 subscriber gets it: CDR-serialised and deserialised by rosbags."""
    ts = msgs.ts
    return ts.deserialize_cdr(ts.serialize_cdr(msg, typ), typ)


def _events(records: list[bytes]):
    out = []
    for rec in ingest.iter_records(b"".join(records)):
        assert not isinstance(rec, Exception), rec
        out.append(rec)
    return out


def test_conversion_of_ros2_messages(tmp_path):
    from dran_edge.perception.frame import frame_from_bytes

    msgs = run_bag._Msgs(run_bag._typestore(HUMBLE))
    sent: list[bytes] = []
    core = BridgeCore(sent.append, frame_hz=5.0, with_depth=True)
    ODOM = "nav_msgs/msg/Odometry"
    for k in range(10):
        s = T0 + k * 100_000_000
        core.on_odometry(_ros2(msgs, msgs.odometry(s, (0.1 * k, 0, 0, 0, 0, 0, 1)), ODOM))
    core.on_odometry(_ros2(msgs, msgs.odometry(T0, (0, 0, 0, 0, 0, 0, 1)), ODOM))  # backwards
    core.on_keyframe(_ros2(msgs, msgs.odometry(T0 + 500_000_000, (0.5, 0, 0, 0, 0, 0, 1)), ODOM))
    core.on_loop(
        _ros2(
            msgs,
            msgs.odometry(
                T0 + 900_000_000,
                (0.2, 0, 0, 0, 0, 0.6, 0.8),
                twist=((T0 + 100_000_000) / 1e9, 0, 0, 33, 0, 0),
            ),
            ODOM,
        )
    )
    core.on_reset(_ros2(msgs, msgs.ts.types["std_msgs/msg/Bool"](data=True), "std_msgs/msg/Bool"))
    bad = msgs.odometry(T0 + 2_000_000_000, (0, 0, 0, 0, 0, 0, 2.0))  # not a unit quaternion
    core.on_odometry(_ros2(msgs, bad, ODOM))
    s = T0 + 950_000_000
    colour = np.arange(16 * 24, dtype=np.uint8).reshape(16, 24)
    depth = (np.arange(16 * 24, dtype=np.uint16) * 7).reshape(16, 24)
    core.on_image(_ros2(msgs, msgs.image(s, depth, "16UC1"), "sensor_msgs/msg/Image"), True)
    assert len(sent) == 13  # the depth image waits for its colour image
    core.on_image(_ros2(msgs, msgs.image(s, colour, "mono8"), "sensor_msgs/msg/Image"))
    yuv = msgs.image(s + 300_000_000, np.zeros((16, 48), np.uint8), "yuv422")
    core.on_image(_ros2(msgs, yuv, "sensor_msgs/msg/Image"))
    core.on_image(
        _ros2(msgs, msgs.image(s + 300_000_000, depth, "16UC1"), "sensor_msgs/msg/Image"), True
    )
    recs = _events(sent)
    kinds = [r.kind for r in recs]
    assert kinds == [1] * 10 + [2, 3, 4, 5]
    assert core.skipped == {"non_monotonic": 1, "bad_quaternion": 1, "unsupported_encoding": 1}
    assert [r.event.stamp_ns for r in recs[:10]] == [T0 + k * 100_000_000 for k in range(10)]
    assert np.allclose(recs[9].event.T_odom_body[:3, 3], [0.9, 0, 0])
    loop = recs[11].event
    assert loop.stamp_cur_ns == T0 + 900_000_000 and loop.inliers == 33
    assert abs(loop.stamp_old_ns - (T0 + 100_000_000)) < 1000
    assert recs[12].event.stamp_ns == T0 + 900_000_001  # 1 ns after the last odometry
    frame = frame_from_bytes(recs[13].event.payload)
    assert frame.stamp_ns == s and np.array_equal(frame.colour[..., 0], colour)
    assert np.array_equal(frame.depth, depth)


def test_bridge_into_a_real_daemon_and_its_estimate_back(tmp_path):
    """Records through the bridge's socket client into a running daemon; the daemon's status
    carries the estimate the node publishes as Path / markers / TF."""
    from daemon_helpers import write_config
    from test_daemon import RecordingNotifier

    from dran_edge.daemon.status import query_status
    from dran_edge.config import load_config
    from dran_edge.daemon.service import Daemon
    from dran_edge.ros.ingest_client import IngestClient
    from dran_edge.sim.vio import vio_mission

    cfg = load_config(write_config(tmp_path, comms={"period_s": 0.05}))
    d = Daemon(cfg, notifier=RecordingNotifier(), environ={})
    d.start()
    client = IngestClient(str(d.ingest.path))
    client.start()
    msgs = run_bag._Msgs(run_bag._typestore(HUMBLE))
    core = BridgeCore(client.put)
    m = vio_mission(15, seed=2)
    n = 0
    from dran_edge.geometry import se3_to_xyz_quat_xyzw

    for e in m.events:  # the VIO events as the ROS 2 topics carry them
        name = type(e).__name__
        if name in ("OdometrySample", "Keyframe"):
            msg = _ros2(
                msgs,
                msgs.odometry(e.stamp_ns, se3_to_xyz_quat_xyzw(e.T_odom_body)),
                "nav_msgs/msg/Odometry",
            )
            (core.on_odometry if name == "OdometrySample" else core.on_keyframe)(msg)
            n += 1
    assert client.flush(5.0)
    for _ in range(300):
        d.tick()
        if (
            d.ingest.counters.records >= n
            and d.journal.pending_count == 0
            and d.last_estimate is not None
        ):
            break
    try:
        st = query_status(d.runtime_dir / "status.sock")
    finally:
        client.stop()
        d.shutdown()
    assert d.ingest.counters.records == n and core.skipped == {}
    est = estimate_from_status(st)
    assert est is not None and len(est["stamps_ns"]) > 3
    assert np.all(np.diff(est["stamps_ns"]) > 0)
    assert np.allclose(np.linalg.norm(est["poses"][:, 3:], axis=1), 1.0, atol=1e-6)


def test_the_rclpy_node_forwards_odometry(tmp_path):
    rclpy = pytest.importorskip(
        "rclpy",
        reason="rclpy exists only in a ROS 2 installation (Humble/Jazzy: source "
        "/opt/ros/<distro>/setup.bash); the node's conversion is tested above without it",
    )
    from nav_msgs.msg import Odometry

    path = tmp_path / "ingest.sock"
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(str(path))
    srv.listen(1)
    srv.settimeout(20.0)
    node_proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "dran_edge.ros.bridge2",
            "--ros-args",
            "-p",
            f"socket:={path}",
            "-p",
            "odometry:=/test_odom",
            "-p",
            "keyframes:=",
            "-p",
            "reset:=",
            "-p",
            "loop_topic:=",
        ]
    )
    try:
        rclpy.init()
        pub_node = rclpy.create_node("dran_edge_test_pub")
        pub = pub_node.create_publisher(Odometry, "/test_odom", 10)
        deadline = time.monotonic() + 20.0
        conn = None
        while conn is None and time.monotonic() < deadline:
            msg = Odometry()
            msg.header.stamp.sec, msg.pose.pose.orientation.w = 1767225600, 1.0
            pub.publish(msg)
            rclpy.spin_once(pub_node, timeout_sec=0.2)
            try:
                srv.settimeout(0.2)
                conn, _ = srv.accept()
            except socket.timeout:
                pass
        assert conn is not None, "the node never connected to the ingest socket"
        data = conn.recv(4096)
        rec = next(r for r in ingest.iter_records(data) if not isinstance(r, Exception))
        assert rec.kind == ingest.KIND_ODOMETRY and rec.event.stamp_ns == 1767225600 * 10**9
    finally:
        node_proc.terminate()
        node_proc.wait(timeout=10)
        srv.close()
