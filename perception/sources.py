"""Frame sources: one interface, hardware libraries imported only by the source that needs them.

A source is an iterable of ``Frame`` with ``close()`` (and context-manager support):

- ``ImageFilesSource``      one image file or a folder of images (stamps = index, 1 ns apart)
- ``RecordedFramesSource``  a frames folder: ``frames.csv`` + PNG colour + 16-bit PNG depth
- ``RealSenseSource``       a live D435i via pyrealsense2: colour 640x480@30 + depth aligned to
                            colour, global-time stamps, reconnects after an unplug
- ``RealSenseRecordingSource`` a RealSense recording (.db3 from librealsense >= 2.56, .bag
                            before) played through pyrealsense2 itself, not in real time
- ``DepthAISource``         an OAK camera via depthai (colour + stereo depth aligned to colour)
- ``ForwardedFramesSource`` frames arriving as bytes (``frame.frame_from_bytes``) from the
                            daemon's ingest socket when ROS owns the camera

``open_source(spec)`` picks one from a string (CLI): an image, a folder, a frames folder, a
recording file, ``realsense[:SERIAL]`` or ``oak``.
"""

from __future__ import annotations

import csv
import logging
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np
from dran_edge.perception.frame import Frame, frame_from_bytes

from dran_edge.errors import DecodeError, DependencyError, InputError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
FRAMES_CSV = "frames.csv"
FRAMES_CSV_HEADER = ["stamp_ns", "colour", "depth", "camera_id"]


class FrameSource:
    """Base class: iterate to get frames; ``close()`` releases the device or files."""

    def __iter__(self) -> Iterator[Frame]:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _read_colour(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError("not a readable image", path=str(path))
    return img


class ImageFilesSource(FrameSource):
    """One image or every image of a folder (sorted by name); ``stamp_ns`` = index."""

    def __init__(self, path: str | Path, camera_id: str = "") -> None:
        path = Path(path)
        if path.is_dir():
            self.paths = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self.paths:
                raise InputError(
                    f"no images ({', '.join(IMAGE_SUFFIXES)}) in folder", path=str(path)
                )
        elif path.is_file():
            self.paths = [path]
        else:
            raise InputError("no such file or folder", path=str(path))
        self.camera_id = camera_id

    def __iter__(self) -> Iterator[Frame]:
        for i, p in enumerate(self.paths):
            yield Frame(i, _read_colour(p), None, self.camera_id or p.name)


class RecordedFramesSource(FrameSource):
    """A frames folder (docs/perception.md "Recorded frames"): ``frames.csv`` with the header
    ``stamp_ns,colour,depth,camera_id`` (paths relative to the folder; depth may be empty)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.csv_path = self.folder / FRAMES_CSV
        if not self.csv_path.is_file():
            raise InputError(f"expected {FRAMES_CSV} in the frames folder", path=str(self.folder))
        self.rows = self._read_rows()

    def _read_rows(self) -> list[tuple[int, str, str, str, int]]:
        rows = []
        with open(self.csv_path, newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header != FRAMES_CSV_HEADER:
                raise InputError(
                    f"expected header {','.join(FRAMES_CSV_HEADER)}, got {header}",
                    path=str(self.csv_path),
                    line=1,
                )
            last = None
            for line_no, row in enumerate(reader, start=2):
                if len(row) != 4:
                    raise InputError(
                        f"expected 4 fields, got {len(row)}", path=str(self.csv_path), line=line_no
                    )
                try:
                    stamp = int(row[0])
                except ValueError:
                    raise InputError(
                        f"stamp_ns: expected an integer, got {row[0]!r}",
                        path=str(self.csv_path),
                        line=line_no,
                    ) from None
                if last is not None and stamp <= last:
                    raise InputError(
                        f"stamp_ns must increase: {stamp} after {last}",
                        path=str(self.csv_path),
                        line=line_no,
                    )
                last = stamp
                rows.append((stamp, row[1], row[2], row[3], line_no))
        return rows

    def __iter__(self) -> Iterator[Frame]:
        import cv2

        for stamp, colour, depth, cam, line_no in self.rows:
            img = _read_colour(self.folder / colour)
            dep = None
            if depth:
                dep = cv2.imread(str(self.folder / depth), cv2.IMREAD_UNCHANGED)
                if dep is None or dep.dtype != np.uint16 or dep.shape != img.shape[:2]:
                    raise InputError(
                        f"depth {depth!r}: expected a 16-bit PNG of {img.shape[1]}x{img.shape[0]}",
                        path=str(self.csv_path),
                        line=line_no,
                    )
            yield Frame(stamp, img, dep, cam)


def write_recorded_frames(folder: str | Path, frames: Iterable[Frame]) -> int:
    """Write frames as a frames folder readable by ``RecordedFramesSource``; returns the count."""
    import cv2

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    n = 0
    with open(folder / FRAMES_CSV, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(FRAMES_CSV_HEADER)
        for n, fr in enumerate(frames, start=1):
            colour = f"colour/{fr.stamp_ns}.png"
            (folder / "colour").mkdir(exist_ok=True)
            cv2.imwrite(str(folder / colour), fr.colour)
            depth = ""
            if fr.depth is not None:
                depth = f"depth/{fr.stamp_ns}.png"
                (folder / "depth").mkdir(exist_ok=True)
                cv2.imwrite(str(folder / depth), fr.depth)
            w.writerow([fr.stamp_ns, colour, depth, fr.camera_id])
    return n


# --------------------------------------------------------------------------- RealSense
def _import_rs():
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise DependencyError(
            f"pyrealsense2 is needed for RealSense sources ({exc}); pip install "
            "'dran-edge[realsense]' (and the system libusb-1.0)"
        ) from exc
    return rs


class _RealSensePairer:
    """Pairs colour with the closest depth frame of the framesets a pipeline returns.

    A colour frame is emitted with a depth frame whose stamp is within ``tolerance_ms``, as soon
    as one with the identical stamp arrives, or when the next colour frame arrives (playback
    syncers may first hand a new colour frame with the previous depth frame).
    """

    def __init__(self, align, camera_id: str, tolerance_ms: float = 16.0) -> None:
        self.align = align
        self.camera_id = camera_id
        self.tolerance_ms = tolerance_ms
        self.pending: list | None = None  # [colour_number, stamp_ms, colour, depth, |dt|]

    def push(self, frames) -> Iterator[Frame]:
        fs = self.align.process(frames) if self.align is not None else frames
        c = fs.get_color_frame()
        if not c:
            return
        d = fs.get_depth_frame()
        number, stamp_ms = c.get_frame_number(), c.get_timestamp()
        if self.pending is not None and self.pending[0] != number:
            yield from self.flush()
        if self.pending is None:
            colour = np.asanyarray(c.get_data()).copy()
            if c.get_profile().format().name == "rgb8":
                colour = np.ascontiguousarray(colour[..., ::-1])
            self.pending = [number, stamp_ms, colour, None, np.inf]
        if d:
            dt = abs(d.get_timestamp() - stamp_ms)
            if dt <= self.tolerance_ms and dt < self.pending[4]:
                self.pending[3] = np.asanyarray(d.get_data()).copy()
                self.pending[4] = dt
        if self.pending[4] < 1e-3:
            yield from self.flush()

    def flush(self) -> Iterator[Frame]:
        if self.pending is not None:
            _, stamp_ms, colour, depth, _ = self.pending
            self.pending = None
            yield Frame(int(round(stamp_ms * 1e6)), colour, depth, self.camera_id)


class _RealSensePipelineSource(FrameSource):
    """A source owning a started ``rs.pipeline`` in ``self._pipe`` (None when stopped)."""

    _pipe = None

    def close(self) -> None:
        if self._pipe is not None:
            try:
                self._pipe.stop()
            except RuntimeError:
                pass
            self._pipe = None


class RealSenseSource(_RealSensePipelineSource):
    """A live RealSense (D435i): colour BGR + depth aligned to colour, global-time stamps.

    ``global_time_enabled`` makes librealsense map the camera's hardware clock onto the host
    clock, so ``stamp_ns`` is comparable with ROS/VINS stamps on the same host. After an unplug
    or a frame timeout the pipeline is stopped and restarted every ``reconnect_s`` until the
    camera is back; iteration continues (no daemon restart). Only one process can stream a
    RealSense endpoint: when realsense-ros owns the camera use ``ForwardedFramesSource``.
    """

    def __init__(
        self,
        serial: str | None = None,
        width: int = 640,
        height: int = 480,
        fps: int = 30,
        depth: bool = True,
        timeout_ms: int = 2000,
        reconnect_s: float = 1.0,
        max_reconnects: int | None = None,
    ) -> None:
        self.rs = _import_rs()
        self.serial, self.width, self.height, self.fps = serial, width, height, fps
        self.depth, self.timeout_ms = depth, timeout_ms
        self.reconnect_s, self.max_reconnects = reconnect_s, max_reconnects
        self.reconnects = 0
        self._pipe = None

    def _start(self):
        rs = self.rs
        cfg = rs.config()
        if self.serial:
            cfg.enable_device(self.serial)
        cfg.enable_stream(rs.stream.color, self.width, self.height, rs.format.bgr8, self.fps)
        if self.depth:
            cfg.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
        pipe = rs.pipeline()
        profile = pipe.start(cfg)
        device = profile.get_device()
        for sensor in device.query_sensors():
            if sensor.supports(rs.option.global_time_enabled):
                sensor.set_option(rs.option.global_time_enabled, 1)
        self.camera_id = device.get_info(rs.camera_info.serial_number)
        self._pipe = pipe
        log.info(
            "RealSense %s streaming %dx%d@%d (depth %s)",
            self.camera_id,
            self.width,
            self.height,
            self.fps,
            self.depth,
        )
        return _RealSensePairer(
            rs.align(rs.stream.color) if self.depth else None,
            self.camera_id,
            tolerance_ms=500.0 / self.fps,
        )

    def __iter__(self) -> Iterator[Frame]:
        pairer = None
        while True:
            try:
                if pairer is None:
                    pairer = self._start()
                frames = self._pipe.wait_for_frames(self.timeout_ms)
                yield from pairer.push(frames)
            except RuntimeError as exc:  # unplug, timeout, "No device connected"
                log.warning("RealSense: %s; reconnecting in %.1f s", exc, self.reconnect_s)
                self.close()
                pairer = None
                self.reconnects += 1
                if self.max_reconnects is not None and self.reconnects > self.max_reconnects:
                    raise DependencyError(
                        f"RealSense: gave up after {self.max_reconnects} reconnects ({exc})"
                    ) from exc
                time.sleep(self.reconnect_s)


class RealSenseRecordingSource(_RealSensePipelineSource):
    """A RealSense recording played back by pyrealsense2 (``enable_device_from_file``) with
    ``set_real_time(False)``: every frame is delivered, paced by the consumer.

    The playback device is resolved and switched to non-real-time *before* the pipeline starts
    (``pipeline.start`` reuses the config's cached resolved profile). Switching after ``start``
    loses the first frame in roughly one playback in five (measured with pyrealsense2 2.59.1:
    frame 0 missing in 3 of 15 runs), because playback has already begun in real time.
    """

    def __init__(self, path: str | Path, align: bool = True, timeout_ms: int = 1000) -> None:
        self.rs = _import_rs()
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError("no such recording", path=str(self.path))
        self.align, self.timeout_ms = align, timeout_ms
        self._pipe = None

    def __iter__(self) -> Iterator[Frame]:
        rs = self.rs
        cfg = rs.config()
        cfg.enable_device_from_file(str(self.path), repeat_playback=False)
        pipe = rs.pipeline()
        try:
            resolved = cfg.resolve(rs.pipeline_wrapper(pipe))
            resolved.get_device().as_playback().set_real_time(False)
            profile = pipe.start(cfg)
        except RuntimeError as exc:
            raise InputError(
                f"pyrealsense2 cannot play this recording: {exc}", path=str(self.path)
            ) from exc
        self._pipe = pipe
        if profile.get_device().as_playback().is_real_time():
            self.close()
            raise RuntimeError(
                "pyrealsense2 started a different playback device than it resolved;"
                " frames could be dropped"
            )
        has_depth = any(s.stream_type() == rs.stream.depth for s in profile.get_streams())
        pairer = _RealSensePairer(
            rs.align(rs.stream.color) if (self.align and has_depth) else None, self.path.name
        )
        try:
            while True:
                ok, frames = pipe.try_wait_for_frames(self.timeout_ms)
                if not ok:
                    break
                yield from pairer.push(frames)
            yield from pairer.flush()
        finally:
            self.close()


# --------------------------------------------------------------------------- OAK
class DepthAISource(FrameSource):
    """An OAK camera through depthai 2.x: the colour camera's ISP output scaled by ``isp_scale``
    (1080p sensor mode / 3 = 640x360 BGR) and, when ``depth`` is set, stereo depth aligned to the
    colour camera at the same size (mm).

    Write the camera file for that size (intrinsics: ``device.readCalibration()
    .getCameraIntrinsics(CAM_A, 640, 360)``). Stamps: ``getTimestamp()``, the device clock
    synchronised to the host's steady clock. Untested here: depthai is not installed on the
    development machine (``oak`` extra), so this follows the depthai 2.x documentation only.
    """

    def __init__(
        self, isp_scale: tuple[int, int] = (1, 3), fps: int = 30, depth: bool = True
    ) -> None:
        try:
            import depthai as dai
        except ImportError as exc:
            raise DependencyError(
                f"depthai is needed for OAK cameras ({exc}); pip install 'dran-edge[oak]'"
            ) from exc
        self.dai = dai
        self.isp_scale, self.fps, self.depth = isp_scale, fps, depth
        self._device = None

    def _pipeline(self):
        dai = self.dai
        pipeline = dai.Pipeline()
        cam = pipeline.create(dai.node.ColorCamera)
        cam.setBoardSocket(dai.CameraBoardSocket.CAM_A)
        cam.setResolution(dai.ColorCameraProperties.SensorResolution.THE_1080_P)
        cam.setIspScale(*self.isp_scale)
        cam.setFps(self.fps)
        xout = pipeline.create(dai.node.XLinkOut)
        xout.setStreamName("colour")
        cam.isp.link(xout.input)  # YUV420; getCvFrame() converts to BGR
        if self.depth:
            left = pipeline.create(dai.node.MonoCamera)
            right = pipeline.create(dai.node.MonoCamera)
            left.setBoardSocket(dai.CameraBoardSocket.CAM_B)
            right.setBoardSocket(dai.CameraBoardSocket.CAM_C)
            left.setFps(self.fps)
            right.setFps(self.fps)
            stereo = pipeline.create(dai.node.StereoDepth)
            stereo.setDepthAlign(dai.CameraBoardSocket.CAM_A)
            stereo.setOutputSize(*cam.getIspSize())
            left.out.link(stereo.left)
            right.out.link(stereo.right)
            xd = pipeline.create(dai.node.XLinkOut)
            xd.setStreamName("depth")
            stereo.depth.link(xd.input)
        return pipeline

    def __iter__(self) -> Iterator[Frame]:
        self._device = self.dai.Device(self._pipeline())
        qc = self._device.getOutputQueue("colour", maxSize=4, blocking=False)
        qd = self._device.getOutputQueue("depth", maxSize=4, blocking=False) if self.depth else None
        camera_id = self._device.getMxId()
        while True:
            c = qc.get()
            colour = np.ascontiguousarray(c.getCvFrame())
            depth = None
            d = qd.tryGet() if qd is not None else None
            if d is not None:
                dep = d.getFrame()
                if dep.shape == colour.shape[:2]:
                    depth = dep.astype(np.uint16)
            yield Frame(int(c.getTimestamp().total_seconds() * 1e9), colour, depth, camera_id)

    def close(self) -> None:
        if self._device is not None:
            self._device.close()
            self._device = None


# --------------------------------------------------------------------------- forwarded
class ForwardedFramesSource(FrameSource):
    """Frames forwarded as bytes (layout: ``frame.frame_to_bytes``) by the daemon's ingest
    socket. ``records`` is any iterable of bytes, or a zero-argument callable returning the next
    record (None = end). Undecodable records are counted in ``dropped`` and skipped."""

    def __init__(self, records: Iterable[bytes] | Callable[[], bytes | None]) -> None:
        self.records = records
        self.dropped = 0

    def _iter_records(self) -> Iterator[bytes]:
        if callable(self.records):
            while (rec := self.records()) is not None:
                yield rec
        else:
            yield from self.records

    def __iter__(self) -> Iterator[Frame]:
        for rec in self._iter_records():
            try:
                yield frame_from_bytes(rec)
            except DecodeError as exc:
                self.dropped += 1
                log.warning("forwarded frame dropped: %s", exc)


# --------------------------------------------------------------------------- by name
RECORDING_SUFFIXES = (".db3", ".bag")


def open_source(spec: str) -> FrameSource:
    """A source from a CLI string: ``realsense[:SERIAL]``, ``oak``, a recording (.db3/.bag),
    a frames folder (with frames.csv), a folder of images, or one image."""
    if spec == "realsense" or spec.startswith("realsense:"):
        return RealSenseSource(serial=spec.partition(":")[2] or None)
    if spec == "oak":
        return DepthAISource()
    path = Path(spec)
    if path.is_file() and path.suffix.lower() in RECORDING_SUFFIXES:
        return RealSenseRecordingSource(path)
    if path.is_dir() and (path / FRAMES_CSV).is_file():
        return RecordedFramesSource(path)
    return ImageFilesSource(path)
