#!/usr/bin/env python3
"""vins_bridge: forward VINS-Mono's topics to the dran-edge daemon's ingest socket.

Runs in ROS Noetic's own Python (3.8) with the standard library and rospy only; it does not
import dran_edge (the daemon has its own venv). It subscribes to

- ``/vins_estimator/odometry`` (nav_msgs/Odometry): IMU-body pose in the VIO world -> ODOMETRY
- ``/vins_estimator/keyframe_pose`` (nav_msgs/Odometry): keyframe pose -> KEYFRAME
- ``/feature_tracker/restart`` (std_msgs/Bool): VINS restarts its estimator -> RESET
- ``~loop_topic`` (default ``/pose_graph/loop_edge``, nav_msgs/Odometry), published by our small
  change to VINS-Mono's pose_graph node (docs/vins-mono.md): header.stamp = current keyframe
  time, pose = relative pose T_old_cur (translation, quaternion), twist.linear.x = old keyframe
  time (seconds, as VINS stores it), twist.linear.y = relative yaw (degrees, unused: the
  quaternion carries it), twist.angular.x = PnP inlier count -> LOOP

and, when ``~image_topic`` is set (ROS owns the camera, ``camera.source: forwarded``), camera
frames: ``sensor_msgs/Image`` colour (``bgr8``/``rgb8``) paired by stamp with the aligned depth
of ``~depth_topic`` (``16UC1``, optional) -> FRAME, in perception's raw frame layout
(docs/perception.md "Frame byte layout"; no numpy or OpenCV needed), at most ``~frame_hz``;

and writes framed records (docs/ingest.md) to the Unix stream socket ``~socket`` (default
``/run/dran-edge/ingest.sock``), reconnecting with back-off when the daemon restarts. While
disconnected, records wait in a bounded queue (oldest dropped and counted).

The record encoder below duplicates ``dran_edge.comms.ingest``'s ``pack_*`` functions;
``tests/test_vins_bridge.py`` checks that both produce identical bytes.

Usage (ROS environment sourced)::

    python3 dran_edge/ros/vins_bridge.py _socket:=/run/dran-edge/ingest.sock
"""

import collections
import socket
import struct
import threading
import time
import zlib

MAGIC = b"DRNI"
VERSION = 1
HEADER = struct.Struct("<4sBBHII")
KIND_ODOMETRY, KIND_KEYFRAME, KIND_LOOP, KIND_RESET = 1, 2, 3, 4
FLAG_COVARIANCE = 0x0001
KIND_FRAME = 5
RESET_FEATURE_TRACKER_RESTART = 1
FRAME_MAGIC = b"DRFR"
FRAME_HEADER = struct.Struct("<4sBBBBqHHIIB")
_POSE = struct.Struct("<q3d4d")
_COV = struct.Struct("<36d")
_LOOP = struct.Struct("<qq3d4dI")
_RESET = struct.Struct("<qB")
MAX_RESET_TEXT = 200


# --------------------------------------------------------------------------- record encoder
def _frame(kind, payload, flags=0):
    return HEADER.pack(MAGIC, VERSION, kind, flags, len(payload), zlib.crc32(payload)) + payload


def _floats(values, n):
    out = [float(v) for v in values]
    if len(out) != n:
        raise ValueError("expected %d numbers, got %d" % (n, len(out)))
    return out


def pack_odometry(stamp_ns, xyz, quat_xyzw, covariance=None):
    payload = _POSE.pack(int(stamp_ns), *(_floats(xyz, 3) + _floats(quat_xyzw, 4)))
    if covariance is None:
        return _frame(KIND_ODOMETRY, payload)
    return _frame(KIND_ODOMETRY, payload + _COV.pack(*_floats(covariance, 36)), FLAG_COVARIANCE)


def pack_keyframe(stamp_ns, xyz, quat_xyzw):
    return _frame(
        KIND_KEYFRAME, _POSE.pack(int(stamp_ns), *(_floats(xyz, 3) + _floats(quat_xyzw, 4)))
    )


def pack_loop(stamp_old_ns, stamp_cur_ns, xyz, quat_xyzw, inliers):
    return _frame(
        KIND_LOOP,
        _LOOP.pack(
            int(stamp_old_ns),
            int(stamp_cur_ns),
            *(_floats(xyz, 3) + _floats(quat_xyzw, 4) + [int(inliers)]),
        ),
    )


def pack_reset(stamp_ns, reason_code, reason=""):
    text = reason.encode("utf-8")[:MAX_RESET_TEXT]
    return _frame(KIND_RESET, _RESET.pack(int(stamp_ns), int(reason_code)) + text)


def pack_frame(stamp_ns, frame_bytes):
    return _frame(KIND_FRAME, struct.pack("<q", int(stamp_ns)) + bytes(frame_bytes))


def frame_bytes(stamp_ns, width, height, colour, depth=None, rgb=False, camera_id=""):
    """Perception's frame layout v1 with raw codecs: colour H*W*3 bytes, depth H*W*2 (LE)."""
    cam = camera_id.encode("utf-8")[:64]
    if len(colour) != width * height * 3:
        raise ValueError("colour: expected %d bytes, got %d" % (width * height * 3, len(colour)))
    if depth is not None and len(depth) != width * height * 2:
        raise ValueError("depth: expected %d bytes, got %d" % (width * height * 2, len(depth)))
    flags = (1 if depth is not None else 0) | (2 if rgb else 0)
    depth = b"" if depth is None else bytes(depth)
    header = FRAME_HEADER.pack(
        FRAME_MAGIC, 1, flags, 0, 0, int(stamp_ns), width, height, len(colour), len(depth), len(cam)
    )
    return b"".join((header, cam, bytes(colour), depth))


# --------------------------------------------------------------------------- message mapping
def stamp_ns_of(header):
    return int(header.stamp.secs) * 1000000000 + int(header.stamp.nsecs)


def seconds_to_ns(t):
    return int(round(float(t) * 1e9))


def _pose_parts(pose):
    p, q = pose.position, pose.orientation
    return (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)


def odometry_record(msg):
    xyz, q = _pose_parts(msg.pose.pose)
    cov = list(msg.pose.covariance)
    # VINS-Mono publishes all-zero covariances: "unknown", the daemon applies its noise model
    return pack_odometry(stamp_ns_of(msg.header), xyz, q, cov if any(cov) else None)


def keyframe_record(msg):
    xyz, q = _pose_parts(msg.pose.pose)
    return pack_keyframe(stamp_ns_of(msg.header), xyz, q)


def loop_record(msg):
    xyz, q = _pose_parts(msg.pose.pose)
    return pack_loop(
        seconds_to_ns(msg.twist.twist.linear.x),
        stamp_ns_of(msg.header),
        xyz,
        q,
        max(0, int(round(msg.twist.twist.angular.x))),
    )


def _packed_rows(msg, bytes_per_px):
    """Image data without row padding; None for big-endian 16-bit data."""
    row = msg.width * bytes_per_px
    data = bytes(msg.data)
    if bytes_per_px == 2 and msg.is_bigendian:
        return None
    if msg.step == row:
        return data[: row * msg.height]
    return b"".join(data[r * msg.step : r * msg.step + row] for r in range(msg.height))


def frame_record(colour_msg, depth_msg=None):
    """A FRAME record of a colour image (+ aligned depth), or None for unsupported encodings."""
    if colour_msg.encoding not in ("bgr8", "rgb8"):
        return None
    colour = _packed_rows(colour_msg, 3)
    depth = None
    if depth_msg is not None:
        if depth_msg.encoding not in ("16UC1", "mono16") or (depth_msg.width, depth_msg.height) != (
            colour_msg.width,
            colour_msg.height,
        ):
            return None
        depth = _packed_rows(depth_msg, 2)
        if depth is None:
            return None
    stamp = stamp_ns_of(colour_msg.header)
    return pack_frame(
        stamp,
        frame_bytes(
            stamp,
            colour_msg.width,
            colour_msg.height,
            colour,
            depth,
            colour_msg.encoding == "rgb8",
            colour_msg.header.frame_id,
        ),
    )


# --------------------------------------------------------------------------- socket client
class IngestClient:
    """Sends records to the daemon; reconnects; bounded queue while the daemon is away."""

    def __init__(self, path, max_queue=20000, log=None):
        self.path = path
        self.queue = collections.deque()
        self.max_queue = max_queue
        self.dropped = 0
        self.sent = 0
        self.log = log or (lambda msg: None)
        self._cv = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="ingest-client")
        self._thread.daemon = True

    def start(self):
        self._thread.start()

    def stop(self, flush_s=2.0):
        end = time.monotonic() + flush_s
        while self.queue and time.monotonic() < end:
            time.sleep(0.01)
        with self._cv:
            self._stop = True
            self._cv.notify()
        self._thread.join(5.0)

    def put(self, record):
        with self._cv:
            if len(self.queue) >= self.max_queue:
                self.queue.popleft()
                self.dropped += 1
            self.queue.append(record)
            self._cv.notify()

    def _connect(self):
        backoff = 0.1
        while not self._stop:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                s.connect(self.path)
                self.log("connected to %s" % self.path)
                return s
            except OSError as exc:
                s.close()
                self.log("cannot connect to %s (%s); retrying" % (self.path, exc))
                time.sleep(backoff)
                backoff = min(backoff * 2, 2.0)
        return None

    def _run(self):
        sock = None
        while True:
            with self._cv:
                while not self.queue and not self._stop:
                    self._cv.wait(0.5)
                if self._stop and not self.queue:
                    break
                batch = list(self.queue)
                self.queue.clear()
            if sock is None:
                sock = self._connect()
            try:
                if sock is None:
                    raise OSError("stopped")
                sock.sendall(b"".join(batch))
                self.sent += len(batch)
            except OSError as exc:
                with self._cv:  # back to the front of the queue, still bounded
                    self.queue.extendleft(reversed(batch))
                    while len(self.queue) > self.max_queue:
                        self.queue.popleft()
                        self.dropped += 1
                if sock is None:
                    break
                self.log("daemon connection lost (%s); reconnecting" % exc)
                sock.close()
                sock = None
        if sock is not None:
            sock.close()


# --------------------------------------------------------------------------- the node
def main():
    # Long: a standalone ROS 1 node (Python 3.8, no dran_edge imports) whose main wires the
    # subscribers; kept flat so it reads as the launch it is.
    import rospy
    from nav_msgs.msg import Odometry
    from std_msgs.msg import Bool

    rospy.init_node("dran_edge_vins_bridge")
    path = rospy.get_param("~socket", "/run/dran-edge/ingest.sock")
    loop_topic = rospy.get_param("~loop_topic", "/pose_graph/loop_edge")
    client = IngestClient(
        path,
        int(rospy.get_param("~max_queue", 20000)),
        log=lambda m: rospy.loginfo("vins_bridge: " + m),
    )
    client.start()
    last = {"stamp_ns": 0}

    def on_odometry(msg):
        last["stamp_ns"] = max(last["stamp_ns"], stamp_ns_of(msg.header))
        client.put(odometry_record(msg))

    def on_keyframe(msg):
        client.put(keyframe_record(msg))

    def on_loop(msg):
        client.put(loop_record(msg))

    def on_restart(msg):
        if msg.data:
            # std_msgs/Bool has no stamp: the new segment starts just after the last odometry
            stamp = last["stamp_ns"] + 1 if last["stamp_ns"] else rospy.Time.now().to_nsec()
            client.put(pack_reset(stamp, RESET_FEATURE_TRACKER_RESTART))

    rospy.Subscriber("/vins_estimator/odometry", Odometry, on_odometry, queue_size=200)
    rospy.Subscriber("/vins_estimator/keyframe_pose", Odometry, on_keyframe, queue_size=100)
    rospy.Subscriber("/feature_tracker/restart", Bool, on_restart, queue_size=10)
    rospy.Subscriber(loop_topic, Odometry, on_loop, queue_size=100)
    image_topic = rospy.get_param("~image_topic", "")
    if image_topic:
        from sensor_msgs.msg import Image

        depth_topic = rospy.get_param("~depth_topic", "")
        min_gap_ns = int(1e9 / float(rospy.get_param("~frame_hz", 5.0)))
        pending = collections.OrderedDict()  # stamp -> [colour, depth]
        sent_at = {"stamp_ns": 0}

        def offer(stamp, colour=None, depth=None):
            slot = pending.setdefault(stamp, [None, None])
            if colour is not None:
                slot[0] = colour
            if depth is not None:
                slot[1] = depth
            while len(pending) > 10:
                pending.popitem(last=False)
            if slot[0] is None or (depth_topic and slot[1] is None):
                return
            del pending[stamp]
            if stamp - sent_at["stamp_ns"] < min_gap_ns:
                return
            rec = frame_record(slot[0], slot[1])
            if rec is not None:
                sent_at["stamp_ns"] = stamp
                client.put(rec)

        rospy.Subscriber(
            image_topic,
            Image,
            lambda m: offer(stamp_ns_of(m.header), colour=m),
            queue_size=2,
            buff_size=2**24,
        )
        if depth_topic:
            rospy.Subscriber(
                depth_topic,
                Image,
                lambda m: offer(stamp_ns_of(m.header), depth=m),
                queue_size=2,
                buff_size=2**24,
            )
    rospy.loginfo("vins_bridge: forwarding VINS-Mono to %s (loops from %s)", path, loop_topic)

    def report(_event):
        rospy.loginfo(
            "vins_bridge: sent %d records, %d queued, %d dropped",
            client.sent,
            len(client.queue),
            client.dropped,
        )

    rospy.Timer(rospy.Duration(30.0), report)
    rospy.spin()
    client.stop()


if __name__ == "__main__":
    main()
