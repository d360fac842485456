"""One camera frame, and its compact byte layout for the daemon's ingest socket.

Documented in docs/perception.md ("Frame byte layout").

A ``Frame`` is ``(stamp_ns, colour BGR uint8 (H, W, 3), depth uint16 (H, W) in the camera's depth
unit (mm for RealSense) aligned to colour, or None, camera_id)``.

Byte layout, version 1, all little-endian (``FRAME_HEADER``)::

    offset size field
    0      4    magic b"DRFR"
    4      1    version (1)
    5      1    flags: bit0 depth present, bit1 colour bytes are RGB (not BGR)
    6      1    colour codec: 0 raw (H*W*3 bytes, row-major), 1 PNG, 2 JPEG
    7      1    depth codec: 0 raw (H*W*2 bytes, uint16 little-endian), 1 PNG (16-bit grey)
    8      8    stamp_ns (int64)
    16     2    width (uint16)
    18     2    height (uint16)
    20     4    colour_len (uint32)
    24     4    depth_len (uint32; 0 when no depth)
    28     1    camera_id_len (uint8, <= 64)
    29     ...  camera_id (UTF-8), colour bytes, depth bytes — nothing after

Raw codecs let a Python 3.8 ROS bridge forward ``sensor_msgs/Image`` data (``bgr8``/``rgb8`` and
``16UC1``) without numpy or OpenCV. Decoding is strict: every length and size is checked against
the header and the bytes that actually arrived.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from dran_edge.errors import DecodeError, InputError

MAGIC = b"DRFR"
VERSION = 1
FRAME_HEADER = struct.Struct("<4sBBBBqHHIIB")
COLOUR_CODECS = {"raw": 0, "png": 1, "jpeg": 2}
DEPTH_CODECS = {"raw": 0, "png": 1}
MAX_CAMERA_ID_BYTES = 64
MAX_SIDE_PX = 8192


@dataclass(frozen=True, eq=False)
class Frame:
    """One camera frame: ``stamp_ns`` in the VIO clock domain, BGR colour, aligned depth or None."""

    stamp_ns: int
    colour: np.ndarray
    depth: np.ndarray | None
    camera_id: str = ""

    def __post_init__(self) -> None:
        c = self.colour
        if not (
            isinstance(c, np.ndarray) and c.dtype == np.uint8 and c.ndim == 3 and c.shape[2] == 3
        ):
            raise InputError(
                f"frame colour: expected uint8 (H, W, 3), got "
                f"{getattr(c, 'dtype', type(c))} {getattr(c, 'shape', '')}"
            )
        d = self.depth
        if d is not None and not (
            isinstance(d, np.ndarray) and d.dtype == np.uint16 and d.shape == c.shape[:2]
        ):
            raise InputError(
                f"frame depth: expected uint16 {c.shape[:2]}, got "
                f"{getattr(d, 'dtype', type(d))} {getattr(d, 'shape', '')}"
            )


def frame_to_bytes(
    frame: Frame, colour_codec: str = "png", depth_codec: str = "png", jpeg_quality: int = 95
) -> bytes:
    """Encode a frame (layout in the module docstring)."""
    import cv2

    if colour_codec not in COLOUR_CODECS or depth_codec not in DEPTH_CODECS:
        raise InputError(
            f"frame codecs: expected colour in {list(COLOUR_CODECS)} and depth in "
            f"{list(DEPTH_CODECS)}, got {colour_codec!r}, {depth_codec!r}"
        )
    h, w = frame.colour.shape[:2]
    cam = frame.camera_id.encode()
    if len(cam) > MAX_CAMERA_ID_BYTES:
        raise InputError(f"camera id: expected <= {MAX_CAMERA_ID_BYTES} bytes, got {len(cam)}")
    if colour_codec == "raw":
        colour = np.ascontiguousarray(frame.colour).tobytes()
    else:
        ext = ".png" if colour_codec == "png" else ".jpg"
        opts = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if colour_codec == "jpeg" else []
        ok, buf = cv2.imencode(ext, frame.colour, opts)
        if not ok:
            raise InputError(f"frame colour: OpenCV could not encode {colour_codec}")
        colour = buf.tobytes()
    depth = b""
    if frame.depth is not None:
        if depth_codec == "raw":
            depth = np.ascontiguousarray(frame.depth, dtype="<u2").tobytes()
        else:
            ok, buf = cv2.imencode(".png", frame.depth)
            if not ok:
                raise InputError("frame depth: OpenCV could not encode PNG")
            depth = buf.tobytes()
    header = FRAME_HEADER.pack(
        MAGIC,
        VERSION,
        1 if frame.depth is not None else 0,
        COLOUR_CODECS[colour_codec],
        DEPTH_CODECS[depth_codec],
        int(frame.stamp_ns),
        w,
        h,
        len(colour),
        len(depth),
        len(cam),
    )
    return b"".join((header, cam, colour, depth))


def frame_from_bytes(data: bytes) -> Frame:
    """Decode and validate a frame; raises ``DecodeError`` saying what was expected."""
    import cv2

    data = bytes(data)
    if len(data) < FRAME_HEADER.size:
        raise DecodeError(f"frame: expected >= {FRAME_HEADER.size} header bytes, got {len(data)}")
    (magic, version, flags, ccodec, dcodec, stamp_ns, w, h, clen, dlen, idlen) = (
        FRAME_HEADER.unpack_from(data)
    )
    if magic != MAGIC:
        raise DecodeError(f"frame: expected magic {MAGIC!r}, got {magic!r}")
    if version != VERSION:
        raise DecodeError(f"frame: expected version {VERSION}, got {version}")
    if flags & ~0b11:
        raise DecodeError(f"frame: unknown flag bits in {flags:#04x}")
    if ccodec not in COLOUR_CODECS.values() or dcodec not in DEPTH_CODECS.values():
        raise DecodeError(f"frame: unknown codec colour={ccodec} depth={dcodec}")
    if not (1 <= w <= MAX_SIDE_PX and 1 <= h <= MAX_SIDE_PX):
        raise DecodeError(f"frame: expected 1..{MAX_SIDE_PX} px sides, got {w}x{h}")
    if idlen > MAX_CAMERA_ID_BYTES:
        raise DecodeError(f"frame: camera id of {idlen} bytes (max {MAX_CAMERA_ID_BYTES})")
    has_depth = bool(flags & 1)
    if not has_depth and dlen:
        raise DecodeError(f"frame: no-depth flag but depth_len={dlen}")
    expected = FRAME_HEADER.size + idlen + clen + dlen
    if len(data) != expected:
        raise DecodeError(f"frame: header says {expected} bytes in all, got {len(data)}")
    o = FRAME_HEADER.size
    try:
        camera_id = data[o : o + idlen].decode()
    except UnicodeDecodeError as exc:
        raise DecodeError("frame: camera id is not UTF-8") from exc
    o += idlen
    cbytes, dbytes = data[o : o + clen], data[o + clen :]
    if ccodec == 0:
        if clen != w * h * 3:
            raise DecodeError(f"frame: raw colour needs {w * h * 3} bytes, got {clen}")
        colour = np.frombuffer(cbytes, np.uint8).reshape(h, w, 3).copy()
    else:
        colour = cv2.imdecode(np.frombuffer(cbytes, np.uint8), cv2.IMREAD_COLOR)
        if colour is None or colour.shape != (h, w, 3):
            raise DecodeError(f"frame: colour does not decode to {w}x{h} BGR")
    if flags & 2:
        colour = np.ascontiguousarray(colour[..., ::-1])
    depth = None
    if has_depth:
        if dcodec == 0:
            if dlen != w * h * 2:
                raise DecodeError(f"frame: raw depth needs {w * h * 2} bytes, got {dlen}")
            depth = np.frombuffer(dbytes, "<u2").reshape(h, w).astype(np.uint16)
        else:
            depth = cv2.imdecode(np.frombuffer(dbytes, np.uint8), cv2.IMREAD_UNCHANGED)
            if depth is None or depth.dtype != np.uint16 or depth.shape != (h, w):
                raise DecodeError(f"frame: depth does not decode to {w}x{h} uint16")
    return Frame(int(stamp_ns), colour, depth, camera_id)
