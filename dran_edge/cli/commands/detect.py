"""``dran-edge detect SOURCE``: AprilTag detections (and poses, objects) of images or a camera."""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import numpy as np

HELP = "detect AprilTags in an image, folder, recording or live camera"

DESCRIPTION = """\
Detect AprilTags and print one line per detection.

SOURCE is one of: an image file; a folder of images; a frames folder (frames.csv + PNGs,
docs/perception.md); a RealSense recording (.db3, or .bag from librealsense < 2.56);
'realsense' or 'realsense:SERIAL' (live D435i); 'oak' (live OAK camera).

Each line has tag_id, corners (4x2 pixels, the library's order, origin at the top-left corner
of the top-left pixel), hamming and decision_margin. With intrinsics (--calib DIR --robot NAME,
or --intrinsics) and a tag size (tag map, or --tag-size) it also has T_camera_tag (4x4, metres)
and, for tags in the map, object_id and T_body_object. A summary (frames, rate, pooled corner
noise estimate for calibrating corner_sigma_px) goes to stderr at the end.
"""


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog, description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "source", metavar="SOURCE", help="image, folder, recording, realsense[:SERIAL] or oak"
    )
    p.add_argument("--calib", metavar="DIR", help="calibration folder (tags.yaml, cameras/)")
    p.add_argument(
        "--robot", default="dingo1", help="camera file cameras/ROBOT.yaml (default: dingo1)"
    )
    p.add_argument(
        "--intrinsics",
        metavar="FX,FY,CX,CY",
        help="pinhole intrinsics in pixels (instead of --calib)",
    )
    p.add_argument(
        "--tag-size",
        type=float,
        metavar="M",
        help="tag size (black square edge, metres) for tags not in the tag map",
    )
    p.add_argument("--family", default="tag36h11", help="tag family (exactly one)")
    p.add_argument("--decimate", type=float, default=2.0, help="quad decimation (default 2)")
    p.add_argument("--threads", type=int, default=1, help="detector threads (default 1)")
    p.add_argument("--no-depth", action="store_true", help="ignore depth images")
    p.add_argument("--max-frames", type=int, default=None, help="stop after N frames")
    p.add_argument("--json", action="store_true", help="JSON lines (default: readable lines)")
    p.add_argument(
        "--show-fps", action="store_true", help="print the frame rate to stderr every second"
    )
    return p


def _calibration(args, width: int, height: int):
    from dran_edge.errors import InputError
    from dran_edge.perception.calib import Calibration, CameraCalib, TagMap, load_calibration

    if args.calib:
        return load_calibration(args.calib, args.robot)
    try:
        fx, fy, cx, cy = (float(v) for v in args.intrinsics.split(","))
    except ValueError:
        raise InputError(f"--intrinsics: expected FX,FY,CX,CY, got {args.intrinsics!r}") from None
    cam = CameraCalib(
        "cli",
        width,
        height,
        np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]),
        np.zeros(5),
        np.eye(4),
    )
    empty = TagMap(
        args.family,
        np.zeros(0, np.int64),
        np.zeros(0, np.int64),
        np.zeros((0, 4, 4)),
        np.zeros(0),
        {},
    )
    return Calibration(cam, empty)


def _record(frame: Any, index: int, res: Any, i: int, tags: Any) -> dict[str, Any]:
    det = res.detections
    rec = {
        "frame": index,
        "stamp_ns": int(frame.stamp_ns),
        "camera_id": frame.camera_id,
        "tag_id": int(det.tag_id[i]),
        "corners": np.round(det.corners[i], 3).tolist(),
        "hamming": int(det.hamming[i]),
        "decision_margin": round(float(det.decision_margin[i]), 2),
    }
    tp = getattr(res, "tag_poses", None)
    if tp is not None:
        T = tp.T_camera_tag[i]
        if np.all(np.isfinite(T)):
            rec["T_camera_tag"] = np.round(T, 6).tolist()
            rec["reprojection_rms_px"] = round(float(tp.rms_px[i]), 4)
            rec["pose_method"] = tp.method[i]
        rec["accepted"] = bool(tp.accepted[i])
        if tp.reject[i]:
            rec["reject"] = tp.reject[i]
        pos = int(res.map_pos[i])
        if pos >= 0:
            oid = int(tags.object_id[pos])
            rec["object_id"] = oid
            hit = np.flatnonzero(res.objects.object_id == oid)
            if hit.size and tp.accepted[i]:
                rec["T_body_object"] = np.round(res.objects.T_body_object[hit[0]], 6).tolist()
    return rec


def run(args: argparse.Namespace) -> int:
    from dran_edge.perception.covariance import corner_sigma_from_residuals
    from dran_edge.perception.detector import DetectorParams, TagDetections, TagDetector, to_gray
    from dran_edge.perception.pipeline import ObservationPipeline, PipelineParams
    from dran_edge.perception.sources import open_source

    det_params = DetectorParams(
        family=args.family, nthreads=args.threads, quad_decimate=args.decimate
    )
    with_pose = bool(args.calib or args.intrinsics)
    params = PipelineParams(
        detector=det_params, use_depth=not args.no_depth, default_tag_size_m=args.tag_size
    )
    pipeline = None
    detector = TagDetector(det_params) if not with_pose else None
    n_frames = n_det = 0
    sq_sum, n_pts = [], []
    t0 = last_report = time.perf_counter()
    frames_since = 0
    out = sys.stdout
    source = open_source(args.source)
    try:
        for index, frame in enumerate(source):
            if args.max_frames is not None and index >= args.max_frames:
                break
            if with_pose:
                if pipeline is None:
                    h, w = frame.colour.shape[:2]
                    pipeline = ObservationPipeline(_calibration(args, w, h), params)
                res = pipeline.process_detailed(frame)
                tags = pipeline.calib.tags
                tp = res.tag_poses
                ok = tp.accepted
                ref = params.tag_pose.corner_sigma_ref_edge_px
                sq_sum.extend((tp.rms_px[ok] ** 2 * 4 * tp.min_edge_px[ok] / ref).tolist())
                n_pts.extend([4] * int(ok.sum()))
            else:
                assert detector is not None  # made above when there is no pose to compute
                dets: TagDetections = detector.detect(to_gray(frame.colour))
                res = type("R", (), {"detections": dets})()
                tags = None
            for i in range(len(res.detections)):
                rec = _record(frame, index, res, i, tags)
                if args.json:
                    out.write(json.dumps(rec) + "\n")
                else:
                    extra = f" object={rec['object_id']}" if "object_id" in rec else ""
                    if "T_camera_tag" in rec:
                        t = np.asarray(rec["T_camera_tag"])[:3, 3]
                        extra += f" t_camera_tag=[{t[0]:.3f} {t[1]:.3f} {t[2]:.3f}] m"
                    if rec.get("reject"):
                        extra += f" rejected={rec['reject']}"
                    out.write(
                        f"frame {index} tag {rec['tag_id']} hamming={rec['hamming']} "
                        f"margin={rec['decision_margin']:.1f}{extra}\n"
                    )
                n_det += 1
            n_frames += 1
            frames_since += 1
            now = time.perf_counter()
            if args.show_fps and now - last_report >= 1.0:
                print(f"fps {frames_since / (now - last_report):.1f}", file=sys.stderr)
                last_report, frames_since = now, 0
    finally:
        source.close()
    wall = time.perf_counter() - t0
    summary = {
        "frames": n_frames,
        "detections": n_det,
        "fps": round(n_frames / wall, 2) if wall > 0 else None,
    }
    if n_pts:
        summary["corner_sigma_px"] = round(
            corner_sigma_from_residuals(np.array(sq_sum), np.array(n_pts)), 4
        )
    print("summary " + json.dumps(summary), file=sys.stderr)
    return 0
