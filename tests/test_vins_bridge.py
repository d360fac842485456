"""dran_edge/ros/vins_bridge.py: its duplicated encoder matches ours byte for byte, it is Python 3.8
code, and it forwards real ROS messages from a real roscore to the ingest socket."""

from __future__ import annotations

import ast
import importlib.util
import os
import shutil
import socket
import subprocess
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dran_edge import geometry as geo
from dran_edge.comms import ingest as I
from dran_edge.events import Keyframe, LoopClosure, OdometrySample, VioReset
from dran_edge.daemon.ingest_server import IngestServer

REPO = Path(__file__).resolve().parents[1]
BRIDGE = REPO / "dran_edge" / "ros" / "vins_bridge.py"
SYSTEM_PYTHON = "/usr/bin/python3"


def load_bridge():
    spec = importlib.util.spec_from_file_location("vins_bridge", BRIDGE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


bridge = load_bridge()

finite = st.floats(-1e4, 1e4, allow_nan=False)
quat = (
    st.lists(st.floats(-1, 1), min_size=4, max_size=4)
    .filter(lambda q: np.linalg.norm(q) > 0.1)
    .map(lambda q: list(np.array(q) / np.linalg.norm(q)))
)
stamp = st.integers(1, 2**62)


@settings(max_examples=80, deadline=None)
@given(
    s=stamp,
    s2=stamp,
    xyz=st.lists(finite, min_size=3, max_size=3),
    q=quat,
    cov=st.one_of(st.none(), st.lists(finite, min_size=36, max_size=36)),
    inliers=st.integers(0, 2**31),
    code=st.integers(0, 3),
)
def test_bridge_encoder_is_byte_identical(s, s2, xyz, q, cov, inliers, code):
    assert bridge.pack_odometry(s, xyz, q, cov) == I.pack_odometry(s, xyz, q, cov)
    assert bridge.pack_keyframe(s, xyz, q) == I.pack_keyframe(s, xyz, q)
    assert bridge.pack_loop(s, s2, xyz, q, inliers) == I.pack_loop(s, s2, xyz, q, inliers)
    assert bridge.pack_reset(s, code) == I.pack_reset(s, code)
    assert bridge.HEADER.format == I.HEADER.format and bridge.MAGIC == I.MAGIC


def test_bridge_is_python38_and_imports_only_stdlib_and_ros():
    tree = ast.parse(BRIDGE.read_text(), feature_version=(3, 8))
    allowed = {
        "collections",
        "socket",
        "struct",
        "threading",
        "time",
        "zlib",
        "rospy",
        "nav_msgs.msg",
        "std_msgs.msg",
        "sensor_msgs.msg",
    }
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            assert {a.name for a in node.names} <= allowed
        elif isinstance(node, ast.ImportFrom):
            assert node.module in allowed
        assert not isinstance(node, ast.NamedExpr)  # 3.8 has it, but keep the file plain


def test_bridge_frame_bytes_decode_in_perception():
    pytest.importorskip("cv2")
    from types import SimpleNamespace

    from dran_edge.perception.frame import frame_from_bytes

    rng = np.random.default_rng(0)
    colour = rng.integers(0, 256, (6, 5, 3), dtype=np.uint8)
    depth = rng.integers(0, 4000, (6, 5), dtype=np.uint16)
    header = SimpleNamespace(stamp=SimpleNamespace(secs=12, nsecs=34), frame_id="cam0")
    padded = np.zeros((6, 16), np.uint8)
    padded[:, :15] = colour.reshape(6, 15)  # ROS images may pad rows (step > width * 3)
    cmsg = SimpleNamespace(
        header=header,
        width=5,
        height=6,
        step=16,
        encoding="bgr8",
        is_bigendian=0,
        data=padded.tobytes(),
    )
    dmsg = SimpleNamespace(
        header=header,
        width=5,
        height=6,
        step=10,
        encoding="16UC1",
        is_bigendian=0,
        data=depth.astype("<u2").tobytes(),
    )
    rec = bridge.frame_record(cmsg, dmsg)
    ev = I.decode_record(rec)
    assert ev.stamp_ns == 12_000_000_034
    f = frame_from_bytes(ev.payload)
    np.testing.assert_array_equal(f.colour, colour)
    np.testing.assert_array_equal(f.depth, depth)
    assert f.camera_id == "cam0" and f.stamp_ns == 12_000_000_034
    assert bridge.frame_record(SimpleNamespace(**{**vars(cmsg), "encoding": "mono8"})) is None
    assert bridge.pack_frame(5, b"abc") == I.pack_frame(5, b"abc")


def _ros_available() -> str | None:
    if not shutil.which("roscore") or not Path(SYSTEM_PYTHON).exists():
        return "roscore not installed"
    res = subprocess.run(
        [SYSTEM_PYTHON, "-c", "import rospy, nav_msgs.msg, std_msgs.msg"], capture_output=True
    )
    return None if res.returncode == 0 else "rospy/nav_msgs not importable by /usr/bin/python3"


PUBLISHER = textwrap.dedent("""
    import sys, time, rospy
    from nav_msgs.msg import Odometry
    from std_msgs.msg import Bool
    from sensor_msgs.msg import Image
    rospy.init_node("fake_vins")
    img = rospy.Publisher("/camera/color/image_raw", Image, queue_size=2)
    odo = rospy.Publisher("/vins_estimator/odometry", Odometry, queue_size=100)
    kf = rospy.Publisher("/vins_estimator/keyframe_pose", Odometry, queue_size=100)
    rst = rospy.Publisher("/feature_tracker/restart", Bool, queue_size=10)
    loop = rospy.Publisher("/pose_graph/loop_edge", Odometry, queue_size=10)
    end = time.time() + 30
    while time.time() < end and min(p.get_num_connections()
                                    for p in (odo, kf, rst, loop, img)) < 1:
        time.sleep(0.1)
    def msg(t, x, q=(0.0, 0.0, 0.0, 1.0)):
        m = Odometry()
        m.header.stamp = rospy.Time(t)
        m.header.frame_id = "world"
        m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z = x, 2 * x, 0.5
        o = m.pose.pose.orientation
        o.x, o.y, o.z, o.w = q
        return m
    for i in range(5):
        odo.publish(msg(1700000000.0 + 0.1 * i, 0.1 * i))
        time.sleep(0.05)
    kf.publish(msg(1700000000.1, 0.1))
    kf.publish(msg(1700000000.3, 0.3))
    time.sleep(0.1)
    rst.publish(Bool(data=True))
    time.sleep(0.1)
    lp = msg(1700000000.3, 0.25, (0.0, 0.0, 0.6, 0.8))
    lp.twist.twist.linear.x = 1700000000.1   # t_old, seconds as VINS stores it
    lp.twist.twist.linear.y = 73.74          # relative yaw, degrees
    lp.twist.twist.angular.x = 41            # PnP inliers
    loop.publish(lp)
    im = Image(height=3, width=4, encoding="bgr8", step=12, data=bytes(range(36)))
    im.header.stamp = rospy.Time(1700000000.35)
    img.publish(im)
    time.sleep(1.0)
""")


def test_bridge_forwards_real_ros_messages(tmp_path):
    why = _ros_available()
    if why:
        pytest.skip(why)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(
        os.environ,
        ROS_MASTER_URI=f"http://127.0.0.1:{port}",
        ROS_HOME=str(tmp_path),
        ROS_LOG_DIR=str(tmp_path / "log"),
        ROS_HOSTNAME="127.0.0.1",
    )
    for var in ("PYTHONPATH", "VIRTUAL_ENV"):
        env.pop(var, None)
    got: list = []
    lock = threading.Lock()

    def on_record(r):
        with lock:
            got.append(r)

    frames: list = []
    server = IngestServer(tmp_path / "ingest.sock", on_record, frames.append)
    server.start()
    core = subprocess.Popen(
        ["roscore", "-p", str(port)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    procs = [core]
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            if subprocess.run(["rosnode", "list"], env=env, capture_output=True).returncode == 0:
                break
            time.sleep(0.3)
        else:
            pytest.skip("roscore did not come up")
        procs.append(
            subprocess.Popen(
                [
                    SYSTEM_PYTHON,
                    str(BRIDGE),
                    f"_socket:={server.path}",
                    "_image_topic:=/camera/color/image_raw",
                ],
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
            )
        )
        pub = subprocess.run(
            [SYSTEM_PYTHON, "-c", PUBLISHER], env=env, capture_output=True, text=True, timeout=90
        )
        assert pub.returncode == 0, pub.stderr
        end = time.monotonic() + 15
        while time.monotonic() < end and (len(got) < 9 or not frames):
            time.sleep(0.1)
    finally:
        for p in reversed(procs):
            p.terminate()
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        server.stop()
    events = [r.event for r in got]
    odo = [e for e in events if isinstance(e, OdometrySample)]
    kfs = [e for e in events if isinstance(e, Keyframe)]
    resets = [e for e in events if isinstance(e, VioReset)]
    loops = [e for e in events if isinstance(e, LoopClosure)]
    assert len(odo) == 5 and len(kfs) == 2 and len(resets) == 1 and len(loops) == 1, events
    assert server.counters.rejected == 0
    assert abs(odo[2].stamp_ns - 1_700_000_000_200_000_000) < 1000  # double-second stamps
    np.testing.assert_allclose(odo[2].T_odom_body[:3, 3], [0.2, 0.4, 0.5])
    assert odo[0].covariance is None  # all-zero ROS covariance = unknown
    assert resets[0].reason == "feature_tracker_restart"
    assert resets[0].stamp_ns > odo[-1].stamp_ns
    lp = loops[0]
    assert abs(lp.stamp_old_ns - kfs[0].stamp_ns) < 1000
    assert abs(lp.stamp_cur_ns - kfs[1].stamp_ns) < 1000
    assert lp.inliers == 41
    assert len(frames) == 1 and abs(frames[0].event.stamp_ns - 1_700_000_000_350_000_000) < 1000
    assert frames[0].event.payload[29:] == bytes(range(36))  # raw bgr8 after the frame header
    yaw = geo.so3_log(lp.T_old_cur[:3, :3])[2]
    assert np.degrees(yaw) == pytest.approx(73.74, abs=0.01)
