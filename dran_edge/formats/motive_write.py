"""Write ground truth as an OptiTrack Motive CSV export (the format :mod:`.motive` reads).

:func:`make_take` builds a :class:`~dran_edge.formats.motive.MotiveTake` from poses in our Z-up
world (what the mission simulator and the bag importer have); :func:`write_motive_csv` writes
it as Motive exports it (format 1.23, header rows, Y-up world, the chosen units and rotation
type; docs/motive.md).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from dran_edge import geometry as geo
from dran_edge.formats.motive import (
    AXES,
    LENGTH_UNITS_M,
    ROTATION_TYPES,
    MotiveBody,
    MotiveTake,
    up_rotation,
)


def make_take(
    time_s: np.ndarray,
    T_world_marker: Mapping[str, np.ndarray],
    *,
    take_name: str = "dran-edge",
    frame_rate_hz: float | None = None,
    body_ids: Mapping[str, str] | None = None,
    capture_start_time: str = "2026-01-01 12.00.00.000 PM",
) -> MotiveTake:
    """A take from poses in our Z-up world (what the mission simulator has), ready to write.

    ``T_world_marker[name]`` is ``(n, 4, 4)``; a pose holding NaN marks an occluded frame.
    """
    time_s = np.asarray(time_s, dtype=np.float64).reshape(-1)
    n = len(time_s)
    if frame_rate_hz is None:
        frame_rate_hz = 1.0 / float(np.median(np.diff(time_s))) if n > 1 else 120.0
    bodies = {}
    for k, (name, T) in enumerate(T_world_marker.items()):
        T = np.asarray(T, dtype=np.float64)
        if T.shape != (n, 4, 4):
            raise ValueError(f"body {name!r}: expected poses ({n}, 4, 4), got {T.shape}")
        valid = np.all(np.isfinite(T), axis=(-1, -2))
        bid = str(body_ids[name]) if body_ids and name in body_ids else str(k + 1)
        bodies[name] = MotiveBody(name, bid, T, valid, np.full(n, np.nan))
    return MotiveTake(
        frame=np.arange(n, dtype=np.int64),
        time_s=time_s,
        bodies=bodies,
        take_name=take_name,
        capture_frame_rate_hz=float(frame_rate_hz),
        export_frame_rate_hz=float(frame_rate_hz),
        capture_start_time=capture_start_time,
    )


def _rotmat_to_euler(R: np.ndarray, order: str) -> np.ndarray:
    """Angles about X, Y, Z (degrees, columns by axis) of ``R`` in the intrinsic ``order``."""
    by_order = Rotation.from_matrix(R).as_euler(order, degrees=True)
    out = np.empty_like(by_order)
    for k, a in enumerate(order):
        out[:, AXES.index(a)] = by_order[:, k]
    return out


def write_motive_csv(
    path: str | Path,
    take: MotiveTake,
    *,
    rotation_type: str = "Quaternion",
    length_units: str = "Meters",
    up_axis: str = "y",
    line_terminator: str = "\r\n",
) -> None:
    """Write ``take`` as Motive exports it (format 1.23, rigid bodies, header rows included).

    Poses in ``take`` are in our Z-up world and metres; the file gets Motive's Y-up world
    (``up_axis="y"``), the chosen units and rotation type. Occluded frames become blank cells.
    Motive runs on Windows, so lines end in CRLF by default.
    """
    if rotation_type not in ROTATION_TYPES:
        raise ValueError(f"rotation_type must be one of {ROTATION_TYPES}, got {rotation_type!r}")
    if length_units not in LENGTH_UNITS_M:
        raise ValueError(f"length_units must be one of {tuple(LENGTH_UNITS_M)}")
    R_up = up_rotation(up_axis)
    scale = 1.0 / LENGTH_UNITS_M[length_units]
    n = len(take.time_s)
    rot_axes = "XYZW" if rotation_type == "Quaternion" else "XYZ"
    per_body = len(rot_axes) + 4

    meta = [
        ("Format Version", "1.23"),
        ("Take Name", take.take_name),
        ("Take Notes", ""),
        ("Capture Frame Rate", f"{take.capture_frame_rate_hz:.6f}"),
        ("Export Frame Rate", f"{take.export_frame_rate_hz:.6f}"),
        ("Capture Start Time", take.capture_start_time),
        ("Capture Start Frame", str(int(take.frame[0]) if n else 0)),
        ("Total Frames in Take", str(n)),
        ("Total Exported Frames", str(n)),
        ("Rotation Type", rotation_type),
        ("Length Units", length_units),
        ("Coordinate Space", "Global"),
    ]
    names = ["", "Name"]
    types = ["", "Type"]
    ids_ = ["", "ID"]
    comps = ["", ""]
    axes = ["Frame", "Time (Seconds)"]
    blocks = [
        take.frame.astype(np.int64).astype(str)[:, None],
        np.char.mod("%.6f", take.time_s)[:, None],
    ]
    for body in take.bodies.values():
        types += ["Rigid Body"] * per_body
        names += [body.name] * per_body
        ids_ += [body.body_id] * per_body
        comps += ["Rotation"] * len(rot_axes) + ["Position"] * 3 + ["Mean Marker Error"]
        axes += list(rot_axes) + list(AXES) + [""]
        valid = body.valid & np.all(np.isfinite(body.T_world_marker), axis=(-1, -2))
        T = np.where(valid[:, None, None], body.T_world_marker, np.eye(4))
        R = R_up.T @ T[:, :3, :3]
        pos = (T[:, :3, 3] @ R_up) * scale
        if rotation_type == "Quaternion":
            rot = geo.quat_xyzw_from_rotmat(R)
        else:
            rot = _rotmat_to_euler(R, rotation_type)
        mme = np.where(np.isfinite(body.mean_marker_error_m), body.mean_marker_error_m, 0.0)
        num = np.concatenate([rot, pos, (mme * scale)[:, None]], axis=1)
        txt = np.char.mod("%.6f", num)
        txt[~valid] = ""
        blocks.append(txt)
    table = np.concatenate(blocks, axis=1) if n else np.empty((0, len(axes)), dtype=str)

    out = io.StringIO(newline="")
    w = csv.writer(out, lineterminator=line_terminator)
    w.writerow([c for kv in meta for c in kv])
    w.writerow([])
    for row in (types, names, ids_, comps, axes):
        w.writerow(row)
    w.writerows(table.tolist())
    Path(path).write_text(out.getvalue(), encoding="utf-8", newline="")
