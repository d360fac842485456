#!/usr/bin/env python3
"""Build (or extend) a dran-edge run directory from VINS-Mono outputs and an image folder.

One robot per invocation; run it once per robot with the same OUT_DIR to build a fleet::

    dran-edge import-vins run01 --name dingo1 --id 1 \\
        --no-loop-csv out1/vins_result_no_loop.csv [--loop-csv out1/vins_result_loop.csv] \\
        [--pose-graph out1/pose_graph.txt] [--images cam0/data --calib calib/] \\
        [--neighbours 2,3] [--mocap take.csv --mocap-body dingo1]

What it reads (docs/vins-mono.md; docs/replay.md "Converting VINS-Mono outputs"):

- ``vins_result_no_loop.csv`` (required): the estimator's odometry, one line per processed
  image: ``t_ns, px, py, pz, qw, qx, qy, qz, vx, vy, vz,`` — nanosecond stamps, w-first
  quaternion, a trailing comma, no header. Becomes ODOMETRY records. A stamp gap longer than
  ``--gap-s`` (VINS restarts after a 1 s image gap) or a stamp going backwards starts a new
  segment: a RESET record is written before the first sample after it.
- ``vins_result_loop.csv`` (optional): the pose graph's keyframes ``t_ns, px, py, pz, qw, qx,
  qy, qz,``. Its stamps become KEYFRAME records; the keyframe pose is the VIO pose (the
  odometry at that stamp, interpolated), not the loop-corrected one: dran-edge does its own
  loop correction. Without it, keyframes are taken every ``--keyframe-every`` odometry samples.
- ``pose_graph.txt`` (optional, written by pose_graph's ``savePoseGraph``): ``index time_stamp
  vioT(3) pgT(3) vioQ(wxyz) pgQ(wxyz) loop_index loop_info(8) n_keypoints``. Each line with
  ``loop_index >= 0`` becomes a LOOP record between the keyframes at the two stamps with
  ``T_old_cur`` = (relative_t, relative_q w-first) of ``loop_info`` — the only place VINS-Mono
  writes loop constraints to disk. Stamps there are seconds; they are matched to keyframe
  stamps within 1 ms.
- an image folder (optional): files named by their stamp in nanoseconds (EuRoC
  ``cam0/data/<t_ns>.png``) or in seconds with a decimal point; copied into ``frames/`` with a
  ``frames.csv``; replay runs the AprilTag pipeline on them when ``--calib`` gives the camera
  and tag map (``calib/tags.yaml`` + ``calib/cameras/<name>.yaml``, docs/calibration.md).

Everything malformed is an error naming the file and line. Standard library + numpy + the
dran_edge package (run it with the project's venv).
"""

from __future__ import annotations

import argparse
import logging
import re
import shutil
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.formats import run_dir as rd
from dran_edge.errors import InputError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".bmp")


def _stamp_ns(text: str, path: str, line: int, unit: str = "ns") -> int:
    t = text.strip()
    try:
        d = Decimal(t)
    except InvalidOperation:
        raise InputError(
            f"expected a timestamp in {unit}, got {t!r}", path=path, line=line
        ) from None
    if not d.is_finite() or d <= 0:
        raise InputError(f"expected a positive timestamp, got {t!r}", path=path, line=line)
    return int(d * (1 if unit == "ns" else 1_000_000_000))


def read_vins_csv(path: str | Path, min_fields: int) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_ns (n,), T_odom_body (n, 4, 4)) from a VINS-Mono result CSV.

    Lines are ``t_ns, px, py, pz, qw, qx, qy, qz[, ...],``: at least ``min_fields`` numbers, an
    optional trailing comma; blank lines are skipped. Quaternions must be unit within 1e-3.
    """
    path = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    stamps, rows = [], []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        cells = [c.strip() for c in line.split(",")]
        if cells and cells[-1] == "":
            cells = cells[:-1]
        if len(cells) < min_fields:
            raise InputError(
                f"expected at least {min_fields} comma-separated fields "
                f"(t_ns, p xyz, q wxyz ...), got {len(cells)}",
                path=path,
                line=lineno,
            )
        stamp = _stamp_ns(cells[0], path, lineno)
        try:
            vals = [float(c) for c in cells[1:8]]
        except ValueError:
            raise InputError(
                f"expected numbers, got {','.join(cells[1:8])!r}", path=path, line=lineno
            ) from None
        if not all(np.isfinite(vals)):
            raise InputError("expected finite numbers", path=path, line=lineno)
        q = np.array(vals[3:7])
        if abs(np.linalg.norm(q) - 1.0) > 1e-3:
            raise InputError(
                f"expected a unit quaternion (w, x, y, z), got norm {np.linalg.norm(q):.6g}",
                path=path,
                line=lineno,
            )
        stamps.append(stamp)
        rows.append(vals[:3] + list(q / np.linalg.norm(q)))
    if not stamps:
        raise InputError("no poses in the file", path=path)
    return np.asarray(stamps, np.int64), geo.se3_from_xyz_quat_wxyz(np.asarray(rows))


def read_pose_graph_loops(path: str | Path) -> list[tuple[int, int, np.ndarray]]:
    """Loops (stamp_old_ns, stamp_cur_ns, T_old_cur) of a VINS-Mono ``pose_graph.txt``."""
    path = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    index_stamp: dict[int, int] = {}
    pending = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        f = raw.split()
        if not f:
            continue
        if len(f) != 26:
            raise InputError(
                f"expected 26 fields (index time vioT pgT vioQ pgQ loop_index "
                f"loop_info n_keypoints), got {len(f)}",
                path=path,
                line=lineno,
            )
        try:
            index, loop_index = int(f[0]), int(f[16])
            info = [float(x) for x in f[17:25]]
        except ValueError:
            raise InputError(
                "expected integer index/loop_index and numeric loop_info", path=path, line=lineno
            ) from None
        index_stamp[index] = _stamp_ns(f[1], path, lineno, unit="s")
        if loop_index >= 0:
            q = np.array(info[3:7])
            if not np.all(np.isfinite(info)) or abs(np.linalg.norm(q) - 1) > 1e-3:
                raise InputError(
                    "loop_info: expected finite t and a unit quaternion (w, x, y, z)",
                    path=path,
                    line=lineno,
                )
            T = geo.se3_from_xyz_quat_wxyz(np.r_[info[:3], q / np.linalg.norm(q)])
            pending.append((loop_index, index, T, lineno))
    loops = []
    for old, cur, T, lineno in pending:
        if old not in index_stamp:
            raise InputError(
                f"loop_index {old} names no keyframe of the file", path=path, line=lineno
            )
        loops.append((index_stamp[old], index_stamp[cur], T))
    return loops


def image_stamps(folder: str | Path) -> list[tuple[int, Path]]:
    """(stamp_ns, path) of the images of a folder, stamps from the file names."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("expected a folder of images", path=str(folder))
    out = []
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        stem = p.stem
        if re.fullmatch(r"\d{10,20}", stem):
            out.append((int(stem), p))
        elif re.fullmatch(r"\d+\.\d+", stem):
            out.append((_stamp_ns(stem, str(p), 0, unit="s"), p))
        else:
            raise InputError(
                "expected an image named by its stamp (<t_ns>.png or <t_s>.png)", path=str(p)
            )
    out.sort()
    for (a, pa), (b, pb) in zip(out, out[1:]):
        if a == b:
            raise InputError(
                f"two images with the stamp {a}: {pa.name}, {pb.name}", path=str(folder)
            )
    if not out:
        raise InputError("no images (.png, .jpg, .pgm, .bmp) in the folder", path=str(folder))
    return out


def build_ingest(
    stamps: np.ndarray,
    T: np.ndarray,
    kf_stamps: np.ndarray,
    loops: list[tuple[int, int, np.ndarray]],
    gap_ns: int,
) -> tuple[bytes, dict]:
    """Ingest records (docs/ingest.md) for one robot, in stamp order."""
    from dran_edge.comms import ingest

    from dran_edge.events import Keyframe, LoopClosure, OdometrySample, VioReset

    order = np.argsort(stamps, kind="stable")
    if np.any(np.diff(stamps) <= 0):
        # VINS appends; a stamp going backwards is a restart in the input. Keep file order.
        order = np.arange(len(stamps))
    recs: list[tuple[int, int, bytes]] = []
    resets = 0
    for n, i in enumerate(order.tolist()):
        s = int(stamps[i])
        if n > 0:
            prev = int(stamps[order[n - 1]])
            if s - prev > gap_ns or s <= prev:
                recs.append(
                    (s, 0, ingest.encode_event(VioReset(s, "gap in vins_result_no_loop.csv")))
                )
                resets += 1
        recs.append((s, 1, ingest.encode_event(OdometrySample(s, T[i]))))
    mono = np.all(np.diff(stamps) > 0)
    kf_used = 0
    for s in np.asarray(kf_stamps, np.int64).tolist():
        if not mono:
            j = int(np.argmin(np.abs(stamps - s)))
            if abs(int(stamps[j]) - s) > 1_000_000:
                continue
            Tk = T[j]
        else:
            Tq, valid = geo.se3_interpolate(stamps, T, np.array([s]))
            if not valid[0]:
                continue
            Tk = Tq[0]
        recs.append((s, 2, ingest.encode_event(Keyframe(s, Tk))))
        kf_used += 1
    kf_set = np.asarray(sorted(set(np.asarray(kf_stamps, np.int64).tolist())), np.int64)
    loops_used = 0
    for s_old, s_cur, T_oc in loops:
        pair = []
        for s in (s_old, s_cur):
            j = int(np.clip(np.searchsorted(kf_set, s), 0, max(len(kf_set) - 1, 0)))
            cand = [k for k in (j - 1, j) if 0 <= k < len(kf_set)]
            best = min(cand, key=lambda k: abs(int(kf_set[k]) - s)) if cand else None
            if best is None or abs(int(kf_set[best]) - s) > 1_000_000:
                break
            pair.append(int(kf_set[best]))
        if len(pair) == 2 and pair[0] != pair[1]:
            recs.append((pair[1], 3, ingest.encode_event(LoopClosure(pair[0], pair[1], T_oc))))
            loops_used += 1
    if mono:
        recs.sort(key=lambda x: (x[0], x[1]))
    return b"".join(r for _, _, r in recs), {
        "odometry": len(stamps),
        "keyframes": kf_used,
        "loops": loops_used,
        "resets": resets,
    }


def _copy_frames(args: argparse.Namespace, robot_dir: Path) -> int:
    """The images of ``--images`` as the robot's recorded colour frames (copied, or linked
    with ``--symlink``) with their frames.csv; returns the frame count."""
    imgs = image_stamps(args.images)
    fdir = robot_dir / "frames"
    (fdir / "colour").mkdir(parents=True, exist_ok=True)
    lines = ["stamp_ns,colour,depth,camera_id"]
    for s, p in imgs:
        dest = fdir / "colour" / f"{s}{p.suffix.lower()}"
        if args.symlink:
            dest.unlink(missing_ok=True)
            dest.symlink_to(p.resolve())
        else:
            shutil.copyfile(p, dest)
        lines.append(f"{s},colour/{dest.name},,{args.name}")
    (fdir / "frames.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return len(imgs)


def _copy_calibration(args: argparse.Namespace, out: Path, frames: int) -> dict[str, str]:
    """The calibration of ``--calib`` into the run's calib/; returns the robot's camera
    config section (recorded frames when there are frames and a calibration)."""
    camera = {"source": "none"}
    if not args.calib:
        return camera
    src = Path(args.calib)
    if not (src / "tags.yaml").exists() or not (src / "cameras" / f"{args.name}.yaml").exists():
        raise InputError(
            f"expected tags.yaml and cameras/{args.name}.yaml in the calibration "
            "folder (docs/calibration.md)",
            path=str(src),
        )
    (out / "calib" / "cameras").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src / "tags.yaml", out / "calib" / "tags.yaml")
    shutil.copyfile(
        src / "cameras" / f"{args.name}.yaml", out / "calib" / "cameras" / f"{args.name}.yaml"
    )
    if frames:
        camera = {
            "source": "recorded",
            "calib_dir": "../../calib",
            "tags_file": "../../calib/tags.yaml",
            "recording": "frames",
        }
    return camera


def _update_mission(args: argparse.Namespace, out: Path, stamps: np.ndarray) -> rd.Mission:
    """Creates or extends the run's mission.yaml with this robot, its links and its span."""
    mpath = out / "mission.yaml"
    start = int(stamps.min())
    end = int(stamps.max())
    robots: list[rd.RunRobot]
    edges: set[tuple[int, int]]
    if mpath.exists():
        m = rd.read_mission(mpath)
        robots = [r for r in m.robots if r.name != args.name]
        start_ns = min(m.start_ns, start)
        end_ns = max(m.start_ns + int(m.duration_s * 1e9), end)
        edges = set(m.comm_graph)
        objects, fleet, mocap_file, mocap_start = m.objects, m.fleet, m.mocap_file, m.mocap_start_ns
    else:
        robots, start_ns, end_ns, edges = [], start, end, set()
        objects, fleet, mocap_file, mocap_start = (), args.fleet, None, None
    if any(r.id == args.id for r in robots):
        raise InputError(
            f"robot id {args.id} is already used by another robot of the run", path=str(mpath)
        )
    robots.append(rd.RunRobot(args.id, args.name, args.mocap_body))
    ids = {r.id for r in robots}
    for n in args.neighbours:
        edges.add((min(n, args.id), max(n, args.id)))
    if args.mocap:
        shutil.copyfile(args.mocap, out / "mocap.csv")
        mocap_file = "mocap.csv"
    pending = {e for e in edges if not set(e) <= ids}
    edges = {e for e in edges if set(e) <= ids}
    for a, b in sorted(pending):
        log.warning(
            "link %d-%d names a robot not yet in the run; give --neighbours %d when converting it",
            a,
            b,
            args.id,
        )
    m = rd.Mission(
        fleet,
        start_ns,
        (end_ns - start_ns) / 1e9,
        tuple(sorted(robots, key=lambda r: r.id)),
        objects,
        tuple(sorted(edges)),
        mocap_file,
        mocap_start,
        "y",
        None,
    )
    rd.write_mission(out, m)
    return m


def _write_robot_config(
    args: argparse.Namespace, robot_dir: Path, m: rd.Mission, camera: dict[str, str]
) -> None:
    """The robot's robot.yaml: its id, fleet, neighbours on loopback and camera section."""
    from dran_edge.config import config_from_dict, config_to_dict

    nb = sorted(b if a == args.id else a for a, b in m.comm_graph if args.id in (a, b))
    cfg = config_from_dict(
        {
            "robot": {"id": args.id, "name": args.name, "fleet": m.fleet},
            "neighbours": [{"id": n, "address": f"127.0.0.1:{47600 + n}"} for n in nb],
            "comms": {"bind_address": "127.0.0.1", "port": 47600 + args.id},
            "camera": camera,
        }
    )
    rd.write_yaml(
        robot_dir / "robot.yaml",
        config_to_dict(cfg),
        header=f"{args.name}: generated by dran-edge import-vins (docs/config.md)",
    )


def convert(args: argparse.Namespace) -> dict[str, Any]:
    """One robot's VINS-Mono CSVs (and images, calibration, mocap) into the run ``args.out``;
    returns the record counts."""
    out = Path(args.out)
    stamps, T = read_vins_csv(args.no_loop_csv, 11 if not args.lenient else 8)
    if args.loop_csv:
        kf_stamps, _ = read_vins_csv(args.loop_csv, 8)
    else:
        kf_stamps = stamps[:: max(1, args.keyframe_every)]
    loops = read_pose_graph_loops(args.pose_graph) if args.pose_graph else []
    data, counts = build_ingest(stamps, T, kf_stamps, loops, int(args.gap_s * 1e9))
    robot_dir = out / "robots" / args.name
    if (robot_dir / "ingest.bin").exists() and not args.force:
        raise InputError(
            f"robot {args.name} already exists in the run (use --force to replace)",
            path=str(robot_dir),
        )
    robot_dir.mkdir(parents=True, exist_ok=True)
    (robot_dir / "ingest.bin").write_bytes(data)
    frames = _copy_frames(args, robot_dir) if args.images else 0
    camera = _copy_calibration(args, out, frames)
    m = _update_mission(args, out, stamps)
    _write_robot_config(args, robot_dir, m, camera)
    return {**counts, "frames": frames, "robot": args.name, "run": str(out)}
