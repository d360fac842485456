"""Frame -> ``ObservationBatch``: detect, tag poses with covariance, objects in the body frame.

    pipeline = ObservationPipeline(load_calibration("calib", "dingo1"))
    batch = pipeline.process(frame)      # events.ObservationBatch, stamp = frame.stamp_ns

Timing note for the graph engineer: the batch carries the frame's own timestamp. Frames are not
synchronous with VIO keyframes, so the robot's graph must attach an observation to the body pose
at ``stamp_ns`` by interpolating odometry (``geometry.se3_interpolate`` between the bracketing
samples), not by nearest keyframe. The frame source stamps frames in the VIO's clock domain
(RealSense global time = host clock; docs/perception.md).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from dran_edge.perception.calib import Calibration
from dran_edge.perception.detector import DetectorParams, TagDetections, TagDetector, to_gray
from dran_edge.perception.frame import Frame
from dran_edge.perception.objects import ObjectPoses, fuse_objects
from dran_edge.perception.tagpose import TagPoseParams, TagPoses, estimate_tag_poses

from dran_edge.events import ObjectObservation, ObservationBatch

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineParams:
    """All perception parameters."""

    detector: DetectorParams = field(default_factory=DetectorParams)
    """AprilTag detector (family, threads, decimation, ...)."""
    tag_pose: TagPoseParams = field(default_factory=TagPoseParams)
    """Rejection, ambiguity and corner-noise parameters."""
    use_depth: bool = True
    """Use the aligned depth image (when a frame has one) to resolve ambiguous tags."""
    fuse_iterations: int = 1
    """Gauss-Newton steps of the joint fit of a multi-tag object."""
    default_tag_size_m: float | None = None
    """Size assumed for tags missing from the tag map (they get a pose but no object); None =
    such tags get no pose (rejected as ``unknown_tag``)."""


@dataclass(frozen=True, eq=False)
class FrameResult:
    """Everything computed for one frame (the CLI and tests look inside)."""

    detections: TagDetections
    map_pos: np.ndarray
    tag_poses: TagPoses
    objects: ObjectPoses
    batch: ObservationBatch


class ObservationPipeline:
    """One camera's perception. Holds a C detector: one pipeline per thread."""

    def __init__(self, calib: Calibration, params: PipelineParams | None = None) -> None:
        self.calib = calib
        self.params = params or PipelineParams()
        if calib.tags.family != self.params.detector.family:
            log.warning(
                "tag map family %s differs from detector family %s",
                calib.tags.family,
                self.params.detector.family,
            )
        self.detector = TagDetector(self.params.detector)
        cam = calib.camera
        self._undistort = bool(np.any(cam.distortion != 0))
        depth_mm_per_unit = cam.depth_unit_m / 1e-3
        self._depth_scale = None if abs(depth_mm_per_unit - 1.0) < 1e-12 else depth_mm_per_unit
        log.info(
            "perception for %s: %dx%d, K=%s, tags=%d, objects=%d, params=%s",
            cam.robot,
            cam.width,
            cam.height,
            cam.K.tolist(),
            calib.tags.tag_id.size,
            len(calib.tags.object_names),
            self.params,
        )

    def process(self, frame: Frame) -> ObservationBatch:
        """The observation batch of one frame (see the module docstring)."""
        return self.process_detailed(frame).batch

    def process_detailed(self, frame: Frame) -> FrameResult:
        cam, tags, p = self.calib.camera, self.calib.tags, self.params
        h, w = frame.colour.shape[:2]
        if (w, h) != (cam.width, cam.height):
            from dran_edge.errors import InputError

            raise InputError(
                f"frame {frame.stamp_ns}: expected {cam.width}x{cam.height} "
                f"(calibration of {cam.robot}), got {w}x{h}"
            )
        det = self.detector.detect(to_gray(frame.colour))
        corners = det.corners
        if self._undistort and len(det):
            corners = self._undistorted(corners)
            det = TagDetections(det.tag_id, det.hamming, det.decision_margin, corners)
        map_pos = tags.lookup(det.tag_id)
        fallback = np.nan if p.default_tag_size_m is None else p.default_tag_size_m
        if tags.size_m.size:
            size = tags.size_m[map_pos]  # -1 picks the last entry; replaced just below
            size[map_pos < 0] = fallback
        else:
            size = np.full(len(det), fallback)
        depth = frame.depth if p.use_depth else None
        if depth is not None and self._depth_scale is not None:
            depth = np.clip(depth * self._depth_scale, 0, 65535).astype(np.uint16)
        tp = estimate_tag_poses(det, cam.K, size, (w, h), depth, p.tag_pose)
        objs = fuse_objects(
            cam.K,
            cam.T_body_camera,
            corners,
            tp,
            map_pos,
            tags.object_id,
            tags.T_tag_object,
            tags.adjoint_object_tag,
            tags.corners_object,
            p.tag_pose.max_reproj_px,
            p.fuse_iterations,
            p.tag_pose.inflate_by_residual,
        )
        batch = ObservationBatch(
            stamp_ns=int(frame.stamp_ns),
            observations=tuple(
                ObjectObservation(
                    int(frame.stamp_ns),
                    int(objs.object_id[i]),
                    objs.T_body_object[i],
                    objs.covariance[i],
                )
                for i in range(objs.object_id.size)
            ),
        )
        return FrameResult(det, map_pos, tp, objs, batch)

    def _undistorted(self, corners: np.ndarray) -> np.ndarray:
        import cv2

        cam = self.calib.camera
        pts = (corners.reshape(-1, 1, 2) - 0.5).astype(np.float64)
        und = cv2.undistortPoints(pts, cam.K, cam.distortion, P=cam.K)
        return und.reshape(corners.shape) + 0.5


# --------------------------------------------------------------------------- daemon adapter
def _camera_file(cfg) -> Path:
    """The camera file named by ``camera.calib_dir``: a file, ``<path>.yaml``, or a directory
    holding ``<robot name>.yaml``."""
    from dran_edge.errors import ConfigError

    base = cfg.resolve(cfg.camera.calib_dir)
    if base is None:
        raise ConfigError(
            "camera.calib_dir: expected the robot's camera file or its directory, got nothing",
            path=cfg.source_path or None,
        )
    for candidate in (base, Path(str(base) + ".yaml"), base / f"{cfg.robot.name}.yaml"):
        if candidate.is_file():
            return candidate
    raise ConfigError(
        f"camera.calib_dir: no camera file at {base}, {base}.yaml or {base}/{cfg.robot.name}.yaml",
        path=cfg.source_path or None,
    )


def calibration_from_config(cfg) -> Calibration:
    """Camera and tag map named by a robot config's ``camera`` section (docs/config.md).

    ``tags_file`` "" falls back to ``tags.yaml`` next to the ``cameras/`` directory.
    """
    from dran_edge.perception.calib import load_camera, load_tag_map

    from dran_edge.errors import ConfigError

    camera_path = _camera_file(cfg)
    camera = load_camera(camera_path)
    if (camera.width, camera.height) != (cfg.camera.width, cfg.camera.height):
        raise ConfigError(
            f"camera.width/height: {cfg.camera.width}x{cfg.camera.height}, but "
            f"{camera_path} is calibrated for {camera.width}x{camera.height}",
            path=cfg.source_path or None,
        )
    tags_path = cfg.resolve(cfg.camera.tags_file) or camera_path.parent.parent / "tags.yaml"
    return Calibration(camera=camera, tags=load_tag_map(tags_path))


def make_observation_source(cfg, frames=None, params: PipelineParams | None = None):
    """The daemon's perception producer: a callable returning the next ``ObservationBatch``.

    ``cfg`` is the robot's ``RobotConfig``; ``camera.source`` selects the frames:
    ``realsense`` (``RealSenseSource``: serial, width, height, fps), ``oak`` (``DepthAISource``),
    ``recorded`` (``camera.recording``: a frames folder or a RealSense recording), or
    ``forwarded``: ingest records taken from ``frames`` (a queue with ``get(timeout_s)``; items
    are ingest ``Record``s whose ``event`` has ``stamp_ns`` and ``payload`` = ``frame_to_bytes``
    bytes; the record's stamp is authoritative). The callable blocks for the next frame (0.5 s
    at most for ``forwarded``), returns None when there is nothing to hand over (no frame, or no
    object seen), and raises ``StopIteration`` when a finite source ends. Frame errors propagate
    (the daemon's worker counts them and continues). Runs in one thread.
    """
    from dran_edge.perception import sources

    from dran_edge.errors import ConfigError

    pipeline = ObservationPipeline(calibration_from_config(cfg), params)
    cam = cfg.camera
    if cam.source == "forwarded":
        if frames is None:
            raise ConfigError("camera.source forwarded needs the ingest frame queue")
        from dran_edge.perception.frame import frame_from_bytes

        def produce_forwarded():
            item = frames.get(0.5)
            if item is None:
                return None
            event = getattr(item, "event", item)
            frame = frame_from_bytes(event.payload)
            frame = Frame(int(event.stamp_ns), frame.colour, frame.depth, frame.camera_id)
            batch = pipeline.process(frame)
            return batch if batch.observations else None

        return produce_forwarded
    if cam.source == "realsense":
        source = sources.RealSenseSource(
            serial=cam.serial or None, width=cam.width, height=cam.height, fps=cam.fps
        )
    elif cam.source == "oak":
        source = sources.DepthAISource(fps=cam.fps)
    elif cam.source == "recorded":
        path = cfg.resolve(cam.recording)
        if path is None:
            raise ConfigError("camera.recording: expected a frames folder or a recording")
        source = sources.open_source(str(path))
    else:
        raise ConfigError(f"camera.source: no frame source for {cam.source!r}")
    iterator = iter(source)

    def produce():
        batch = pipeline.process(next(iterator))
        return batch if batch.observations else None

    produce.source = source  # so the caller can close() it
    return produce
