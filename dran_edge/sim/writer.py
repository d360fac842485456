"""Write a simulated :class:`~dran_edge.sim.mission.Mission` as a run directory (docs/run-format.md).

What each robot's folder gets is what a real robot records:

- ``ingest.bin``: the ingest records the VINS bridge would have sent (odometry, keyframes,
  loops, resets), encoded by :mod:`dran_edge.comms.ingest` itself, in stamp order; in
  ``frames="none"`` mode also OBSERVATIONS records drawn directly from the geometry.
- ``frames/``: 640 x 480 colour PNG + 16-bit depth PNG (millimetres) rendered by
  :mod:`dran_edge.perception.render` from the robot's camera at each frame stamp, with the
  tags the camera can see (facing, in range, in the image, not hidden behind another box);
  and, as the robot's daemon journals its perception output, the OBSERVATIONS records the
  perception pipeline finds in those frames go into ``ingest.bin`` (replay uses them unless
  ``--redetect``).
- ``robot.yaml``: the robot's config (recorded camera, loopback neighbour addresses).

And the run gets ``calib/`` (tag map and cameras in the perception formats), ``mocap.csv``
(Motive CSV, Y-up, written by :mod:`dran_edge.formats.motive`) and ``mission.yaml``.

Rendering is the slow part: robots are rendered in parallel worker processes (``workers``);
each robot's frames depend only on its own seed, so the output does not depend on it.
"""

from __future__ import annotations

import csv
import logging
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from dran_edge.formats import run_dir as rd
from dran_edge.sim import mission as sim
from dran_edge.errors import InputError

log = logging.getLogger(__name__)

FRAME_MODES = ("render", "none")
FLEET_NAME = "simfleet"
BASE_PORT = 47600


def _calib_files(m: sim.Mission, calib: Path) -> None:
    w = m.world
    objects = []
    for k in w.object_ids.tolist():
        tags = [
            {
                "tag_id": int(w.tag_ids[k, j]),
                "size_m": float(w.tag_size_m),
                "T_object_tag": rd.pose_to_yaml(w.T_object_tag[j]),
            }
            for j in range(sim.TAGS_PER_OBJECT)
        ]
        objects.append({"id": int(k), "name": f"box{k}", "tags": tags})
    calib.mkdir(parents=True, exist_ok=True)
    rd.write_yaml(
        calib / "tags.yaml",
        {"format": "dran-edge-tags/1", "family": "tag36h11", "objects": objects},
        header="Simulated boxes: one tag36h11 tag per vertical face (docs/calibration.md)",
    )
    (calib / "cameras").mkdir(exist_ok=True)
    K = sim.CAMERA_K
    for r in m.robots:
        rd.write_yaml(
            calib / "cameras" / f"{r.name}.yaml",
            {
                "format": "dran-edge-camera/1",
                "robot": r.name,
                "model": "simulated D435i colour",
                "width": sim.CAMERA_WIDTH,
                "height": sim.CAMERA_HEIGHT,
                "intrinsics": {
                    "fx": float(K[0, 0]),
                    "fy": float(K[1, 1]),
                    "cx": float(K[0, 2]),
                    "cy": float(K[1, 2]),
                },
                "distortion": [0.0] * 5,
                "depth_unit_m": 0.001,
                "T_body_camera": rd.pose_to_yaml(sim.T_BODY_CAMERA),
            },
        )


def _robot_config(m: sim.Mission, r: sim.RobotMission, frames: bool) -> dict:
    from dran_edge.config import config_from_dict, config_to_dict

    neighbours = [b if a == r.robot_id else a for a, b in m.comm_edges if r.robot_id in (a, b)]
    data = {
        "robot": {"id": r.robot_id, "name": r.name, "fleet": FLEET_NAME},
        "neighbours": [
            {"id": n, "name": f"dingo{n}", "address": f"127.0.0.1:{BASE_PORT + n}"}
            for n in sorted(neighbours)
        ],
        "comms": {"transport": "udp", "bind_address": "127.0.0.1", "port": BASE_PORT + r.robot_id},
        "camera": (
            {
                "source": "recorded",
                "calib_dir": "../../calib",
                "tags_file": "../../calib/tags.yaml",
                "recording": "frames",
                "width": sim.CAMERA_WIDTH,
                "height": sim.CAMERA_HEIGHT,
                "fps": max(1, int(round(m.params.frame_rate_hz))),
            }
            if frames
            else {"source": "none"}
        ),
    }
    cfg = config_from_dict(data)  # validate what we write with the daemon's own loader
    return config_to_dict(cfg)


def _ingest_bytes(
    m: sim.Mission, r: sim.RobotMission, frames_mode: str, perceived: Sequence[bytes] = ()
) -> bytes:
    """The robot's ingest records in stamp order; ``perceived``: observation records of the
    perception pipeline on its frames (placed after the bridge's records of the same stamp)."""
    from dran_edge.comms import ingest
    from dran_edge.events import (
        Keyframe,
        LoopClosure,
        ObjectObservation,
        ObservationBatch,
        OdometrySample,
        VioReset,
    )

    records: list[tuple[int, int, bytes]] = []  # (stamp, order, bytes)
    stamps = r.odom_stamps_ns.tolist()
    for i, stamp in enumerate(stamps):
        records.append((stamp, 1, ingest.encode_event(OdometrySample(stamp, r.T_odom_body[i]))))
    for i in r.keyframes.tolist():
        records.append((stamps[i], 2, ingest.encode_event(Keyframe(stamps[i], r.T_odom_body[i]))))
    kf_stamps = r.odom_stamps_ns[r.keyframes]
    for (o, c), T in zip(r.loops.tolist(), r.loop_T_old_cur):
        ev = LoopClosure(
            int(kf_stamps[o]), int(kf_stamps[c]), T, inliers=int(40 + (o * 7 + c) % 60)
        )
        records.append((int(kf_stamps[c]), 3, ingest.encode_event(ev)))
    if m.params.announce_resets:
        for stamp in r.reset_stamps_ns.tolist():
            records.append((stamp, 0, ingest.encode_event(VioReset(stamp, "estimator_failure"))))
    if frames_mode == "none":
        rng = np.random.default_rng([m.params.seed, r.robot_id, 17])
        for stamp, obs in sim.direct_observations(m, r, rng):
            batch = ObservationBatch(
                stamp, tuple(ObjectObservation(stamp, oid, T, C) for oid, T, C in obs)
            )
            records.append((stamp, 4, ingest.encode_event(batch)))
    for rec in perceived:
        records.append((_record_stamp(rec), 4, rec))
    records.sort(key=lambda x: (x[0], x[1]))
    return b"".join(rec for _, _, rec in records)


def _record_stamp(record: bytes) -> int:
    from dran_edge.comms.ingest import decode_record

    return int(decode_record(record).stamp_ns)


def render_robot_frames(
    m: sim.Mission,
    r: sim.RobotMission,
    frames_dir: Path,
    progress: Callable[[int], None] | None = None,
) -> int:
    """Render and write one robot's frames; returns the number written."""
    import cv2

    from dran_edge.perception.render import DepthModel, Lighting, TagRenderer
    from dran_edge.perception.sources import FRAMES_CSV, FRAMES_CSV_HEADER

    renderer = TagRenderer()
    (frames_dir / "colour").mkdir(parents=True, exist_ok=True)
    (frames_dir / "depth").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([m.params.seed, r.robot_id, 5])
    T_wc = r.T_world_body_frames @ sim.T_BODY_CAMERA
    colour_names, depth_names = [], []
    w = m.world
    tag_ids = w.tag_ids.reshape(-1)
    batch = 64
    for start in range(0, len(T_wc), batch):
        vis, T_ct = sim.visible_tags(w, T_wc[start : start + batch], m.params)
        for j in range(vis.shape[0]):
            frame_k = start + j
            sel = vis[j].reshape(-1)
            poses = T_ct[j].reshape(-1, 4, 4)[sel]
            light = Lighting(
                gain=float(rng.uniform(0.85, 1.1)),
                offset=float(rng.uniform(-10, 10)),
                gradient=float(rng.uniform(0, 0.25)),
                gradient_angle_rad=float(rng.uniform(-np.pi, np.pi)),
            )
            colour, depth = renderer.render(
                sim.CAMERA_K,
                sim.CAMERA_WIDTH,
                sim.CAMERA_HEIGHT,
                poses,
                tag_ids[sel].tolist(),
                w.tag_size_m,
                blur_sigma_px=float(rng.uniform(0.3, 0.9)),
                noise_sigma=1.5,
                lighting=light,
                rng=rng,
                depth=DepthModel(),
            )
            cname, dname = f"colour/{frame_k:06d}.png", f"depth/{frame_k:06d}.png"
            # The rendered scene is grey (B = G = R): an 8-bit grey PNG holds it losslessly in
            # a third of the bytes, and readers load it as BGR like any colour PNG.
            assert np.array_equal(colour[..., 0], colour[..., 2])
            cv2.imwrite(str(frames_dir / cname), colour[..., 0], [cv2.IMWRITE_PNG_COMPRESSION, 3])
            cv2.imwrite(str(frames_dir / dname), depth, [cv2.IMWRITE_PNG_COMPRESSION, 3])
            colour_names.append(cname)
            depth_names.append(dname)
            if progress is not None:
                progress(1)
    with open(frames_dir / FRAMES_CSV, "w", newline="", encoding="utf-8") as f:
        out = csv.writer(f, lineterminator="\n")
        out.writerow(FRAMES_CSV_HEADER)
        for stamp, c, d in zip(r.frame_stamps_ns.tolist(), colour_names, depth_names):
            out.writerow([stamp, c, d, r.name])
    return len(colour_names)


def _perceive(robot_dir: Path, name: str) -> list[bytes]:
    """The perception pipeline on the robot's written frames, as on the robot."""
    from dran_edge.comms.ingest import encode_event
    from dran_edge.perception.recorded import perceive_frames

    batches, _ = perceive_frames(robot_dir / "robot.yaml", robot_dir.parents[1] / "calib", name)
    return [encode_event(b) for b in batches]


def _render_job(args: tuple) -> tuple[int, list[bytes]]:
    params, robot_index, frames_dir = args
    from dran_edge.blas import set_blas_threads

    set_blas_threads(1)  # one rendering process per core already
    m = sim.generate_mission(params)
    r = m.robots[robot_index]
    n = render_robot_frames(m, r, Path(frames_dir))
    return n, _perceive(Path(frames_dir).parent, r.name)


def write_run(
    m: sim.Mission,
    out_dir: str | Path,
    *,
    frames: str = "render",
    workers: int | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> Path:
    """Write ``m`` as a run directory at ``out_dir`` (which must be empty or not exist).

    ``frames``: ``render`` (PNG frames through the renderer; replay runs the perception
    pipeline) or ``none`` (no frames; tag observations go into ``ingest.bin`` directly).
    ``progress("rendering", done, total)`` is called as frames are written.
    """
    if frames not in FRAME_MODES:
        raise InputError(f"frames: expected one of {FRAME_MODES}, got {frames!r}")
    root = Path(out_dir)
    if root.exists() and any(root.iterdir()):
        raise InputError("expected an empty or new directory for the run", path=str(root))
    root.mkdir(parents=True, exist_ok=True)
    render = frames == "render" and len(m.robots[0].frame_stamps_ns) > 0
    _calib_files(m, root / "calib")
    for r in m.robots:
        d = root / "robots" / r.name
        d.mkdir(parents=True)
        (d / "ingest.bin").write_bytes(_ingest_bytes(m, r, frames))
        rd.write_yaml(
            d / "robot.yaml",
            _robot_config(m, r, render),
            header=f"{r.name}: config used for this run (docs/config.md)",
        )
    # mocap
    from dran_edge.formats.motive_write import make_take, write_motive_csv

    take = make_take(
        m.mocap_time_s,
        sim.mocap_poses(m),
        take_name="simulated",
        frame_rate_hz=m.params.mocap_rate_hz,
    )
    write_motive_csv(root / "mocap.csv", take)
    T_om = sim._object_marker(m.world.box_size_m)
    mission = rd.Mission(
        fleet=FLEET_NAME,
        start_ns=m.params.start_ns,
        duration_s=m.params.duration_s,
        robots=tuple(
            rd.RunRobot(r.robot_id, r.name, r.name, sim.T_BODY_MARKER, r.T_world_odom[0])
            for r in m.robots
        ),
        objects=tuple(
            rd.RunObject(int(k), f"box{k}", f"box{k}", T_om) for k in m.world.object_ids.tolist()
        ),
        comm_graph=m.comm_edges,
        mocap_file="mocap.csv",
        mocap_start_ns=m.params.start_ns,
        mocap_up_axis="y",
        simulation=sim.params_to_dict(m.params) | {"frames": frames},
    )
    rd.write_mission(root, mission)
    if render:
        total = sum(len(r.frame_stamps_ns) for r in m.robots)
        jobs = [
            (m.params, i, str(root / "robots" / r.name / "frames")) for i, r in enumerate(m.robots)
        ]
        workers = workers or min(len(jobs), os.cpu_count() or 1)
        done = 0
        perceived: list[list[bytes]] = []
        if workers <= 1:
            for r, job in zip(m.robots, jobs):

                def tick(n: int) -> None:
                    nonlocal done
                    done += n
                    if progress:
                        progress("rendering", done, total)

                render_robot_frames(m, r, Path(job[2]), tick)
                perceived.append(_perceive(Path(job[2]).parent, r.name))
        else:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                for n, recs in pool.map(_render_job, jobs):
                    done += n
                    perceived.append(recs)
                    if progress:
                        progress("rendering", done, total)
        for r, recs in zip(m.robots, perceived):
            (root / "robots" / r.name / "ingest.bin").write_bytes(_ingest_bytes(m, r, frames, recs))
    log.info("wrote run %s (%d robots, %s frames)", root, len(m.robots), frames)
    return root


def truth_T_world_body(m: sim.Mission, r: sim.RobotMission, stamps_ns: np.ndarray) -> np.ndarray:
    """True body poses at ``stamps_ns`` (for tests)."""
    return r.path.poses((np.asarray(stamps_ns) - m.params.start_ns) / 1e9)
