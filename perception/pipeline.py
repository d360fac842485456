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
            log.warning("tag map family %s differs from detector family %s",
                        calib.tags.family, self.params.detector.family)
        self.detector = TagDetector(self.params.detector)
        cam = calib.camera
        self._undistort = bool(np.any(cam.distortion != 0))
        depth_mm_per_unit = cam.depth_unit_m / 1e-3
        self._depth_scale = None if abs(depth_mm_per_unit - 1.0) < 1e-12 else depth_mm_per_unit
        log.info("perception for %s: %dx%d, K=%s, tags=%d, objects=%d, params=%s", cam.robot,
                 cam.width, cam.height, cam.K.tolist(), calib.tags.tag_id.size,
                 len(calib.tags.object_names), self.params)

    def process(self, frame: Frame) -> ObservationBatch:
        """The observation batch of one frame (see the module docstring)."""
        return self.process_detailed(frame).batch

    def process_detailed(self, frame: Frame) -> FrameResult:
        cam, tags, p = self.calib.camera, self.calib.tags, self.params
        h, w = frame.colour.shape[:2]
        if (w, h) != (cam.width, cam.height):
            from dran_edge.errors import InputError

            raise InputError(f"frame {frame.stamp_ns}: expected {cam.width}x{cam.height} "
                             f"(calibration of {cam.robot}), got {w}x{h}")
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
        objs = fuse_objects(cam.K, cam.T_body_camera, corners, tp, map_pos, tags.object_id,
                            tags.T_tag_object, tags.adjoint_object_tag, tags.corners_object,
                            p.tag_pose.max_reproj_px, p.fuse_iterations)
        batch = ObservationBatch(
            stamp_ns=int(frame.stamp_ns),
            observations=tuple(
                ObjectObservation(int(frame.stamp_ns), int(objs.object_id[i]),
                                  objs.T_body_object[i], objs.covariance[i])
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
