"""ROS messages -> dran-edge ingest events, frames, camera files and mocap poses.

One conversion layer for every path a ROS message takes into dran-edge: the bag importer
(:mod:`dran_edge.formats.bags`), the ROS 2 bridge node (:mod:`dran_edge.ros.bridge2`) and, by
construction, the ROS 1 bridge (``dran_edge/ros/vins_bridge.py``, a standard-library copy whose bytes
``tests/test_vins_bridge.py`` compares with :mod:`dran_edge.comms.ingest`).

Messages are duck-typed: anything with the ROS field names works — ``rosbags``' dataclasses
(ROS 1 and ROS 2), ``rclpy`` and ``rospy`` messages. Stamps are read from ``header.stamp`` as
``sec``/``nanosec`` (ROS 2, rosbags) or ``secs``/``nsecs`` (rospy). Which message carries what:

===================  ==============================  =========================================
role                 message                         meaning (docs/bags.md, docs/vins-mono.md)
===================  ==============================  =========================================
odometry             nav_msgs/Odometry               ``T_odom_body`` at header.stamp; a non-zero
                                                     pose covariance is kept (6x6, [t, r])
keyframe             nav_msgs/Odometry (or any       the keyframe's VIO pose at header.stamp
                     PoseStamped-like message)
loop, ``vins``       nav_msgs/Odometry               pose = ``T_old_cur``; header.stamp = current
                                                     keyframe; twist.linear.x = old keyframe's
                                                     stamp in seconds; twist.angular.x = inliers
loop, ``pose_pair``  geometry_msgs/                  two topics, paired message by message: the
                     PoseWithCovarianceStamped x 2   ``old`` message's stamp is the old keyframe,
                                                     the ``cur`` message carries ``T_old_cur``
reset                std_msgs/Bool (data true) or    a new VIO segment; a Bool has no stamp, so
                     any message with a header       it is stamped 1 ns after the last odometry
image / depth        sensor_msgs/Image or            a frame of ``frames/`` (PNG/JPEG bytes)
                     CompressedImage
camera_info          sensor_msgs/CameraInfo          ``calib/cameras/<robot>.yaml``
mocap                geometry_msgs/PoseStamped       one rigid body's pose in the mocap world
===================  ==============================  =========================================

Pure: numpy, the event types and :mod:`dran_edge.comms.ingest`; OpenCV only to encode raw
images as PNG (imported when the first raw image arrives).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from dran_edge.errors import DranError
from dran_edge.comms import ingest

#: Raw sensor_msgs/Image encodings a frame may have (colour / grey, and depth).
COLOUR_ENCODINGS = ("mono8", "8UC1", "bgr8", "rgb8", "bgra8", "rgba8")
DEPTH_ENCODINGS = ("16UC1", "mono16")
#: ROS ``compressed_depth_image_transport`` puts this many bytes before its PNG.
COMPRESSED_DEPTH_HEADER = 12
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8\xff"


class MessageError(DranError):
    """A message that cannot become a record; ``reason`` is the short name it is counted by."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


# ------------------------------------------------------------------------------ fields
def stamp_ns(header: Any) -> int:
    """``header.stamp`` in nanoseconds (ROS 2 ``sec``/``nanosec`` or ROS 1 ``secs``/``nsecs``)."""
    st = header.stamp
    if hasattr(st, "nanosec"):
        return int(st.sec) * 1_000_000_000 + int(st.nanosec)
    return int(st.secs) * 1_000_000_000 + int(st.nsecs)


def seconds_to_ns(t: float) -> int:
    """A stamp given as float seconds (VINS-Mono's ``double``) in nanoseconds."""
    return int(round(float(t) * 1e9))


def pose_vector(pose: Any) -> tuple[float, ...]:
    """geometry_msgs/Pose -> (x, y, z, qx, qy, qz, qw), exactly as in the message.

    MessageError for a non-finite pose or a quaternion whose norm is off 1 by more than 1e-3
    (the ingest decoder's rule, docs/ingest.md; the decoder renormalises, so the record keeps
    the message's bits).
    """
    p, q = pose.position, pose.orientation
    v = (float(p.x), float(p.y), float(p.z), float(q.x), float(q.y), float(q.z), float(q.w))
    if not all(map(math.isfinite, v)):
        raise MessageError("non_finite", "pose with NaN or inf")
    n = math.sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5] + v[6] * v[6])
    if abs(n - 1.0) > 1e-3:
        raise MessageError("bad_quaternion", f"quaternion norm {n:.6g}, expected 1")
    return v


def matrix_from_vector(v: tuple[float, ...]) -> np.ndarray:
    """(x, y, z, qx, qy, qz, qw) -> 4x4, the quaternion normalised (scalar code: one message)."""
    n = math.sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5] + v[6] * v[6])
    x, y, z, w = v[3] / n, v[4] / n, v[5] / n, v[6] / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w), v[0]],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w), v[1]],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y), v[2]],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def pose_matrix(pose: Any) -> np.ndarray:
    """geometry_msgs/Pose -> 4x4 ``T`` (validated like :func:`pose_vector`)."""
    return matrix_from_vector(pose_vector(pose))


def _pose_of(msg: Any) -> Any:
    """The geometry_msgs/Pose inside Odometry, PoseStamped or PoseWithCovarianceStamped."""
    pose = msg.pose
    return pose.pose if hasattr(pose, "pose") else pose


# ------------------------------------------------------------------------------ ingest records
@dataclass(frozen=True)
class Item:
    """One ingest record made from a message: its stamp, kind and exact bytes (docs/ingest.md)."""

    stamp_ns: int
    """The record's stamp (for a loop: the current keyframe's)."""
    kind: int
    data: bytes
    pose: tuple[float, ...] | None = None
    """xyz + quat_xyzw of an odometry/keyframe record (to derive keyframes from odometry)."""


def _check_stamp(s: int, what: str) -> int:
    if s <= 0:
        raise MessageError("bad_stamp", f"{what}: stamp {s} ns is not > 0")
    return s


def odometry_record(msg: Any, offset_ns: int = 0, stamp: int | None = None) -> Item:
    """nav_msgs/Odometry -> ODOMETRY; an all-zero pose covariance means 'unknown' (none sent)."""
    s = _check_stamp((stamp_ns(msg.header) if stamp is None else stamp) + offset_ns, "odometry")
    v = pose_vector(_pose_of(msg))
    cov_in = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(36)
    cov: np.ndarray | None = cov_in
    if not cov_in.any():
        cov = None
    elif not np.isfinite(cov_in).all():
        raise MessageError("non_finite", "odometry covariance with NaN or inf")
    try:
        data = ingest.pack_odometry(s, v[:3], v[3:], cov)
    except ValueError as exc:
        raise MessageError("bad_covariance", f"odometry: {exc}") from None
    return Item(s, ingest.KIND_ODOMETRY, data, v)


def keyframe_record(msg: Any, offset_ns: int = 0, stamp: int | None = None) -> Item:
    """A keyframe message (Odometry, PoseStamped, PoseWithCovarianceStamped) -> KEYFRAME."""
    s = _check_stamp((stamp_ns(msg.header) if stamp is None else stamp) + offset_ns, "keyframe")
    v = pose_vector(_pose_of(msg))
    return Item(s, ingest.KIND_KEYFRAME, ingest.pack_keyframe(s, v[:3], v[3:]), v)


def keyframe_from_odometry(item: Item) -> Item:
    """A KEYFRAME at an odometry record's stamp and pose (no keyframe topic in the bag)."""
    v = item.pose
    if v is None:
        raise ValueError("keyframe_from_odometry: the record has no pose")
    return Item(
        item.stamp_ns, ingest.KIND_KEYFRAME, ingest.pack_keyframe(item.stamp_ns, v[:3], v[3:]), v
    )


def loop_record(
    stamp_old_ns: int, stamp_cur_ns: int, v: tuple[float, ...], inliers: int = 0
) -> Item:
    """A LOOP record (``v`` = xyz + quat_xyzw of ``T_old_cur``)."""
    _check_stamp(stamp_old_ns, "loop (old keyframe)")
    _check_stamp(stamp_cur_ns, "loop (current keyframe)")
    if stamp_old_ns == stamp_cur_ns:
        raise MessageError("bad_stamp", "loop: old and current keyframe stamps are equal")
    return Item(
        stamp_cur_ns,
        ingest.KIND_LOOP,
        ingest.pack_loop(stamp_old_ns, stamp_cur_ns, v[:3], v[3:], inliers),
        v,
    )


def vins_loop_parts(msg: Any) -> tuple[int, int, tuple[float, ...], int]:
    """docs/vins-mono.md's loop edge (nav_msgs/Odometry) -> (old_ns, cur_ns, T_old_cur, inliers)."""
    old_s = float(msg.twist.twist.linear.x)
    if not math.isfinite(old_s) or old_s <= 0:
        raise MessageError(
            "bad_stamp", f"loop edge: twist.linear.x (old keyframe stamp, s) is {old_s!r}"
        )
    inl = float(msg.twist.twist.angular.x)
    inl = min(int(round(inl)), 2**32 - 1) if math.isfinite(inl) and inl > 0 else 0
    return seconds_to_ns(old_s), stamp_ns(msg.header), pose_vector(_pose_of(msg)), inl


def vins_loop_record(msg: Any, offset_ns: int = 0) -> Item:
    """The loop edge of docs/vins-mono.md's pose_graph change -> LOOP."""
    old, cur, v, inl = vins_loop_parts(msg)
    return loop_record(old + offset_ns, cur + offset_ns, v, inl)


def pose_pair_loop_record(old_msg: Any, cur_msg: Any, offset_ns: int = 0) -> Item:
    """Two PoseWithCovarianceStamped: old's stamp = old keyframe; cur carries ``T_old_cur``."""
    return loop_record(
        stamp_ns(old_msg.header) + offset_ns,
        stamp_ns(cur_msg.header) + offset_ns,
        pose_vector(_pose_of(cur_msg)),
        0,
    )


def reset_record(
    msg: Any, last_odometry_ns: int, offset_ns: int = 0, stamp: int | None = None
) -> Item | None:
    """A reset: std_msgs/Bool (true: 1 ns after the last odometry) or a stamped message.

    ``stamp`` (receive-clock mode) replaces the header stamp of a stamped message.
    """
    if hasattr(msg, "header"):
        s = stamp_ns(msg.header) if stamp is None else stamp
    elif hasattr(msg, "stamp") and hasattr(msg, "frame_id"):  # std_msgs/Header itself
        s = stamp_ns(msg) if stamp is None else stamp
    elif not bool(getattr(msg, "data", True)):
        return None
    elif last_odometry_ns <= 0:
        raise MessageError(
            "reset_before_odometry",
            "reset (std_msgs/Bool) before any odometry: no stamp to give it",
        )
    else:
        return Item(
            last_odometry_ns + 1,
            ingest.KIND_RESET,
            ingest.pack_reset(last_odometry_ns + 1, ingest.RESET_FEATURE_TRACKER_RESTART),
        )
    s = _check_stamp(s + offset_ns, "reset")
    return Item(s, ingest.KIND_RESET, ingest.pack_reset(s, ingest.RESET_FEATURE_TRACKER_RESTART))


def mocap_pose(msg: Any, offset_ns: int = 0) -> tuple[int, tuple[float, ...]]:
    """geometry_msgs/PoseStamped (or with covariance) -> (stamp_ns, xyz + quat_xyzw of
    ``T_mocap_marker``)."""
    return stamp_ns(msg.header) + offset_ns, pose_vector(_pose_of(msg))


# ------------------------------------------------------------------------------ images
@dataclass(frozen=True)
class EncodedImage:
    """An image as it goes into ``frames/``: the file bytes and the file suffix."""

    data: bytes
    suffix: str  # ".png" or ".jpg"
    width: int | None = None
    height: int | None = None


def _packed(msg: Any, bytes_per_px: int) -> np.ndarray:
    """The image's rows without padding as a uint8 array (height, width * bytes_per_px)."""
    row = int(msg.width) * bytes_per_px
    h, step = int(msg.height), int(msg.step)
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if step < row or len(data) < step * (h - 1) + row:
        raise MessageError(
            "bad_image",
            f"image data of {len(data)} bytes is too short for {msg.width}x{h} with step {step}",
        )
    if step == row:
        return data[: row * h].reshape(h, row)
    return np.stack([data[r * step : r * step + row] for r in range(h)])


def _png(array: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", array, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:  # pragma: no cover - OpenCV fails only on absurd shapes
        raise MessageError("bad_image", "OpenCV could not encode the image as PNG")
    return buf.tobytes()


def _pnm(array: np.ndarray) -> bytes:
    """Binary PGM (grey, 8 or 16 bit) or PPM (colour): lossless, no compression, fast."""
    h, w = array.shape[:2]
    if array.ndim == 3:  # BGR -> the RGB order of PPM
        return b"P6\n%d %d\n255\n" % (w, h) + np.ascontiguousarray(array[..., ::-1]).tobytes()
    if array.dtype == np.uint16:
        return b"P5\n%d %d\n65535\n" % (w, h) + array.astype(">u2").tobytes()
    return b"P5\n%d %d\n255\n" % (w, h) + array.tobytes()


def decode_image(msg: Any, depth: bool = False) -> np.ndarray:
    """sensor_msgs/Image -> array: colour BGR (H, W, 3) or grey (H, W) uint8; depth uint16."""
    enc = str(msg.encoding)
    w, h = int(msg.width), int(msg.height)
    allowed = DEPTH_ENCODINGS if depth else COLOUR_ENCODINGS
    if enc not in allowed:
        raise MessageError(
            "unsupported_encoding",
            f"{'depth' if depth else 'colour'} image encoding {enc!r} is not "
            f"supported (expected one of {', '.join(allowed)})",
        )
    if depth:
        rows = _packed(msg, 2)
        return rows.view(">u2" if msg.is_bigendian else "<u2").reshape(h, w).astype(np.uint16)
    channels = {"mono8": 1, "8UC1": 1, "bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4}[enc]
    arr = _packed(msg, channels).reshape((h, w, channels) if channels > 1 else (h, w))
    if enc.startswith("rgb"):
        arr = arr[..., [2, 1, 0]]
    elif channels == 4:
        arr = arr[..., :3]
    return np.ascontiguousarray(arr)


def raw_image(msg: Any, depth: bool = False, encode: str = "png") -> EncodedImage:
    """sensor_msgs/Image -> a lossless image file. Colour: mono8/bgr8/rgb8(+alpha); depth:
    16UC1/mono16. ``encode``: ``png`` (compressed, ~50-100 ms for 640x480 on a small CPU) or
    ``pnm`` (PGM/PPM, uncompressed, a memory copy)."""
    arr = decode_image(msg, depth)
    return _encoded(arr, encode, int(msg.width), int(msg.height))


def _encoded(arr: np.ndarray, encode: str, w: int, h: int) -> EncodedImage:
    if encode == "pnm":
        return EncodedImage(_pnm(arr), ".ppm" if arr.ndim == 3 else ".pgm", w, h)
    return EncodedImage(_png(arr), ".png", w, h)


def compressed_image(msg: Any, depth: bool = False) -> EncodedImage:
    """sensor_msgs/CompressedImage -> its PNG/JPEG bytes as they are (no re-encoding).

    Colour: ``format`` names png or jpeg (``"png"``, ``"bgr8; jpeg compressed bgr8"``, ...);
    depth: ``compressedDepth`` PNG (its 12-byte header is dropped) or a plain 16-bit PNG.
    The bytes' magic number decides, and must agree with the format string.
    """
    fmt = str(msg.format).lower()
    data = bytes(msg.data)
    if depth and "compresseddepth" in fmt:
        if "rvl" in fmt:
            raise MessageError(
                "unsupported_encoding",
                f"compressed depth format {msg.format!r}: only PNG compressedDepth is supported",
            )
        data = data[COMPRESSED_DEPTH_HEADER:]
    if data.startswith(PNG_MAGIC) and ("png" in fmt or not fmt):
        return EncodedImage(data, ".png")
    if not depth and data.startswith(JPEG_MAGIC) and ("jpeg" in fmt or "jpg" in fmt or not fmt):
        return EncodedImage(data, ".jpg")
    raise MessageError(
        "unsupported_encoding",
        f"compressed {'depth ' if depth else ''}image format {msg.format!r} is "
        "not supported (expected PNG" + ("" if depth else " or JPEG") + " data)",
    )


def image_file(msg: Any, depth: bool = False, encode: str = "png") -> EncodedImage:
    """Image or CompressedImage -> the bytes of a frames/ file (``encode``: raw images only)."""
    if hasattr(msg, "format") and not hasattr(msg, "encoding"):
        return compressed_image(msg, depth)
    return raw_image(msg, depth, encode)


# ------------------------------------------------------------------------------ camera info
def camera_file(
    msg: Any, robot: str, T_body_camera: np.ndarray, depth_unit_m: float = 0.001
) -> dict:
    """sensor_msgs/CameraInfo -> the ``cameras/<robot>.yaml`` mapping (docs/calibration.md)."""
    K = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), dtype=np.float64).reshape(-1)
    D = np.asarray(getattr(msg, "d", getattr(msg, "D", [])), dtype=np.float64).reshape(-1)
    model = str(getattr(msg, "distortion_model", "plumb_bob") or "plumb_bob")
    if K.shape != (9,) or K[0] <= 0 or K[4] <= 0:
        raise MessageError(
            "bad_camera_info",
            f"camera_info K is {K.tolist()}: expected a 3x3 matrix with positive focal lengths",
        )
    if model not in ("plumb_bob", "rational_polynomial") or np.any(D[5:]):
        raise MessageError(
            "bad_camera_info",
            f"camera_info distortion {model!r} with {len(D)} coefficients: expected plumb_bob (5)",
        )
    dist = np.zeros(5)
    dist[: min(5, len(D))] = D[:5]
    from dran_edge.formats.run_dir import pose_to_yaml

    return {
        "format": "dran-edge-camera/1",
        "robot": robot,
        "model": "from camera_info",
        "width": int(msg.width),
        "height": int(msg.height),
        "intrinsics": {"fx": float(K[0]), "fy": float(K[4]), "cx": float(K[2]), "cy": float(K[5])},
        "distortion": [float(x) for x in dist],
        "depth_unit_m": float(depth_unit_m),
        "T_body_camera": pose_to_yaml(T_body_camera),
    }


def compressed_depth_header() -> bytes:
    """The 12-byte ``compressedDepth`` config header (PNG: format 0, no depth quantisation)."""
    return struct.pack("<iff", 0, 0.0, 0.0)
