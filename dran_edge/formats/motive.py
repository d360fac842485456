"""OptiTrack Motive CSV: read rigid-body tracks (written by :mod:`dran_edge.formats.motive_write`).

Layout of a Motive CSV export with header (format versions 1.2x; docs/motive.md has the details)::

    Format Version,1.23,Take Name,run01,...,Rotation Type,Quaternion,Length Units,Meters,Coordinate Space,Global
    <blank>
    ,Type,Rigid Body,Rigid Body,...,Rigid Body Marker,...,Marker,...
    ,Name,dingo1,dingo1,...,dingo1:Marker1,...
    ,ID,1,1,...
    ,,Rotation,Rotation,Rotation,Rotation,Position,Position,Position,Mean Marker Error,...
    Frame,Time (Seconds),X,Y,Z,W,X,Y,Z,,...
    0,0.000000,...

The columns are found by these header rows, never by position: only ``Rigid Body`` columns are
read (rigid-body markers, markers, skeleton bones are skipped). Rotations are quaternions
(X, Y, Z, W) or Euler angles in degrees whose order the ``Rotation Type`` key names; Motive's
Euler angles are relative (intrinsic): ``XYZ`` means about X, then the new Y, then the new Z,
so ``R = Rx(a) Ry(b) Rz(c)`` (NaturalPoint knowledge base, "Changes in Motive's reported Euler
angles"). Lengths are converted to metres. An occluded body has blank cells in its frame.

Motive's global frame is right-handed and Y-up; ours is Z-up. The reader maps Motive's world
into ours with the fixed rotation ``R_zup_yup`` (x' = x, y' = −z, z' = y, a +90° turn about X),
applied on the left of every pose: ``T_world_marker = R_zup_yup · T_motive_marker``. The rigid
body's own axes are left as Motive defined them; the offset from the mocap rigid body to the
robot or object body frame, ``T_body_marker``, belongs to the mission (docs/eval.md).

This is a pure core module (numpy, scipy, stdlib).
"""

from __future__ import annotations

import csv
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from dran_edge import geometry as geo
from dran_edge.errors import InputError

log = logging.getLogger(__name__)

#: Rotation taking Motive's Y-up world coordinates into our Z-up world (x'=x, y'=−z, z'=y).
R_ZUP_YUP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

#: Metres per unit for the ``Length Units`` values Motive writes.
LENGTH_UNITS_M = {"Meters": 1.0, "Centimeters": 0.01, "Millimeters": 0.001}

#: The ``Rotation Type`` values: a quaternion or one of the six intrinsic Euler orders.
EULER_ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")
ROTATION_TYPES = ("Quaternion",) + EULER_ORDERS

#: Motive's axis names, in column order.
AXES = "XYZ"


@dataclass(frozen=True)
class MotiveBody:
    """One rigid body's track, in our Z-up world frame and metres."""

    name: str
    """The rigid body's name in Motive (``Name`` header row)."""
    body_id: str
    """Motive's ID of the body (``ID`` header row): an integer or a GUID, kept as text."""
    T_world_marker: np.ndarray = field(repr=False)
    """Poses ``(n, 4, 4)`` of the mocap rigid body in the Z-up world; NaN where occluded."""
    valid: np.ndarray = field(repr=False)
    """``(n,)`` bool: True where the body was tracked in that frame."""
    mean_marker_error_m: np.ndarray = field(repr=False)
    """``(n,)`` Motive's mean marker error in metres; NaN where absent or occluded."""


@dataclass(frozen=True)
class MotiveTake:
    """A Motive take: frame numbers, times and the rigid bodies, plus the header's metadata."""

    frame: np.ndarray = field(repr=False)
    """``(n,)`` int64 frame numbers as exported."""
    time_s: np.ndarray = field(repr=False)
    """``(n,)`` seconds since the start of the take (Motive's ``Time (Seconds)`` column)."""
    bodies: dict[str, MotiveBody]
    """Rigid bodies by name."""
    take_name: str = ""
    """``Take Name`` from the header."""
    format_version: str = "1.23"
    """``Format Version`` from the header."""
    capture_frame_rate_hz: float = float("nan")
    """``Capture Frame Rate`` (Hz)."""
    export_frame_rate_hz: float = float("nan")
    """``Export Frame Rate`` (Hz): the rate of the rows in this file."""
    capture_start_time: str = ""
    """``Capture Start Time`` as written by Motive (local time of the Motive PC, no zone)."""
    rotation_type: str = "Quaternion"
    """``Rotation Type`` the file was written with."""
    length_units: str = "Meters"
    """``Length Units`` the file was written with (poses here are always in metres)."""
    path: str | None = None
    """File the take was read from, for messages."""

    def body(self, name: str) -> MotiveBody:
        """The rigid body called ``name``; InputError listing the available names otherwise."""
        try:
            return self.bodies[name]
        except KeyError:
            raise InputError(
                f"no rigid body named {name!r} in the Motive take; it has: "
                + (", ".join(sorted(self.bodies)) or "(none)"),
                path=self.path,
            ) from None


# --------------------------------------------------------------------------------------------
# reading


def up_rotation(up_axis: str) -> np.ndarray:
    """Rotation taking coordinates of the ``up_axis``-up world into our Z-up world."""
    if up_axis == "y":
        return R_ZUP_YUP
    if up_axis == "z":
        return np.eye(3)
    raise ValueError(f"up_axis must be 'y' (Motive's default) or 'z', got {up_axis!r}")


def _metadata(cells: list[str]) -> dict[str, str]:
    """The first row's key,value pairs."""
    meta = {}
    for i in range(0, len(cells) - 1, 2):
        key = cells[i].strip()
        if key:
            meta[key] = cells[i + 1].strip()
    return meta


def _float_or_nan(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return float("nan")


def _euler_to_rotmat(angles_deg_xyz: np.ndarray, order: str) -> np.ndarray:
    """Rotation matrices from angles about X, Y, Z (degrees, columns by axis) in Motive's
    relative (intrinsic) ``order``."""
    by_order = np.stack([angles_deg_xyz[:, AXES.index(a)] for a in order], axis=-1)
    return Rotation.from_euler(order, by_order, degrees=True).as_matrix()


def _parse_table(
    lines: list[str], width: int, first_line: int, path: str, column_names: list[str]
) -> tuple[np.ndarray, np.ndarray]:
    """Parse the data rows: (values ``(n, width)``, blank mask ``(n, width)``).

    One C-level pass (``np.fromstring``) over the text with blank cells spelled ``nan``; when
    that fails, a per-cell pass finds the first bad cell and raises InputError with its line.
    """
    n = len(lines)
    for r, line in enumerate(lines):
        if line.count(",") != width - 1:
            raise InputError(
                f"expected {width} cells like the header, got {line.count(',') + 1} (truncated "
                "or malformed row)",
                path=path,
                line=first_line + r,
            )
    if n == 0:
        return np.zeros((0, width)), np.zeros((0, width), bool)
    body = "\n".join(lines) + "\n"
    # Blank cells -> "nan" (two passes cover runs of blanks), also at line ends and starts.
    body = body.replace(",,", ",nan,").replace(",,", ",nan,")
    body = body.replace(",\n", ",nan\n").replace("\n,", "\nnan,")
    if body.startswith(","):
        body = "nan" + body
    try:
        values = np.fromstring(body[:-1].replace("\n", ","), sep=",")
    except ValueError:
        values = np.zeros(0)
    if values.size != n * width:
        for r, line in enumerate(lines):
            for c, cell in enumerate(line.split(",")):
                if cell.strip() and math.isnan(_float_or_nan(cell)):
                    raise InputError(
                        f"expected a number or a blank cell in column {c + 1} "
                        f"({column_names[c]}), got {cell!r}",
                        path=path,
                        line=first_line + r,
                    )
        raise InputError("could not parse the data rows as numbers", path=path, line=first_line)
    values = values.reshape(n, width)
    blank = np.isnan(values)
    bad = np.isinf(values)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise InputError(
            f"expected a finite number in column {c + 1} ({column_names[c]}), got {values[r, c]}",
            path=path,
            line=first_line + int(r),
        )
    return values, blank


def _read_text(path: str) -> str:
    try:
        return Path(path).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError("Motive CSV file not found", path=path) from None
    except UnicodeDecodeError as exc:
        raise InputError(
            f"expected a text (UTF-8) Motive CSV, got undecodable bytes: {exc}", path=path
        ) from None


def _check_metadata(rows: list[list[str]], path: str) -> dict[str, str]:
    """The first row's key/value metadata, checked: format 1.2x (newer: a warning), a known
    rotation type and length unit, global coordinates."""
    if not rows or not rows[0] or rows[0][0].strip() != "Format Version":
        got = ",".join(rows[0])[:60] if rows else "an empty file"
        raise InputError(
            f"expected a Motive CSV whose first row starts with 'Format Version' (export with "
            f"the header enabled), got {got!r}",
            path=path,
            line=1,
        )
    meta = _metadata(rows[0])
    version = meta.get("Format Version", "")
    if not version.startswith("1.2"):
        try:
            newer = float(version) > 1.2
        except ValueError:
            newer = False
        if not newer:
            raise InputError(
                f"expected Motive CSV format version 1.2x, got {version!r}", path=path, line=1
            )
        log.warning(
            "%s: Motive CSV format version %s is newer than 1.2x; reading it as 1.2x", path, version
        )
    rotation_type = meta.setdefault("Rotation Type", "Quaternion")
    if rotation_type not in ROTATION_TYPES:
        raise InputError(
            f"expected Rotation Type one of {', '.join(ROTATION_TYPES)}, got {rotation_type!r}",
            path=path,
            line=1,
        )
    units = meta.setdefault("Length Units", "Meters")
    if units not in LENGTH_UNITS_M:
        raise InputError(
            f"expected Length Units one of {', '.join(LENGTH_UNITS_M)}, got {units!r}",
            path=path,
            line=1,
        )
    space = meta.get("Coordinate Space", "Global")
    if space != "Global":
        raise InputError(
            f"expected Coordinate Space 'Global' (world poses), got {space!r}", path=path, line=1
        )
    return meta


@dataclass
class _Header:
    """The header rows of a Motive CSV: cells of the Type / Name / ID / component rows and the
    axis row, by column; 0-based row indices of the Name, ID and axis rows."""

    cells: dict[str, list[str]]
    axis: list[str]
    i_name: int
    i_id: int
    i_axis: int

    @property
    def width(self) -> int:
        return len(self.axis)


def _find_header(rows: list[list[str]], path: str) -> _Header:
    """Header rows by content: Type / Name / ID (second cell), then the component row, then the
    axis row that starts with "Frame". Line numbers in messages are 1-based."""
    find = {}
    i_axis = None
    for i, row in enumerate(rows[1:40], start=1):
        if row and row[0].strip() == "Frame":
            i_axis = i
            break
        if len(row) > 1 and row[0].strip() == "" and row[1].strip() in ("Type", "Name", "ID"):
            find[row[1].strip()] = i
    if i_axis is None or "Type" not in find or "Name" not in find:
        raise InputError(
            "expected the header rows ',Type,...', ',Name,...' and 'Frame,Time (Seconds),...' "
            "within the first 40 lines; got none (was the CSV exported with headers?)",
            path=path,
        )
    width = len(rows[i_axis])
    header_rows = {"Type": find["Type"], "Name": find["Name"], "component": i_axis - 1}
    if "ID" in find:
        header_rows["ID"] = find["ID"]
    cells = {}
    for key, i in header_rows.items():
        row = rows[i]
        if len(row) != width:
            raise InputError(
                f"header row {key!r} has {len(row)} cells, expected {width} like the "
                f"'Frame,Time (Seconds),...' row",
                path=path,
                line=i + 1,
            )
        cells[key] = [c.strip() for c in row]
    axis = [c.strip() for c in rows[i_axis]]
    if width < 2 or not axis[1].startswith("Time"):
        raise InputError(
            f"expected 'Frame,Time (Seconds)' to start the axis row, got {','.join(axis[:2])!r}",
            path=path,
            line=i_axis + 1,
        )
    return _Header(cells, axis, find["Name"], find.get("ID", find["Name"]), i_axis)


def _rigid_body_columns(
    h: _Header, path: str
) -> tuple[dict[str, dict[tuple[str, str], int]], dict[str, str]]:
    """Rigid-body columns grouped by name: ``{name: {(component, axis): column}}``, and each
    body's Motive ID."""
    layout: dict[str, dict[tuple[str, str], int]] = {}
    ids: dict[str, str] = {}
    for c in range(2, h.width):
        if h.cells["Type"][c] != "Rigid Body":
            continue
        name = h.cells["Name"][c]
        if not name:
            raise InputError(f"rigid body column {c + 1} has no name", path=path, line=h.i_name + 1)
        bid = h.cells["ID"][c] if "ID" in h.cells else ""
        if ids.setdefault(name, bid) != bid:
            raise InputError(
                f"two rigid bodies are named {name!r} (IDs {ids[name]!r} and "
                f"{bid!r}); names must be unique",
                path=path,
                line=h.i_id + 1,
            )
        key = (h.cells["component"][c], h.axis[c])
        if key in layout.setdefault(name, {}):
            raise InputError(
                f"rigid body {name!r} has two '{key[0]} {key[1]}' columns",
                path=path,
                line=h.i_axis + 1,
            )
        layout[name][key] = c
    return layout, ids


def _frames_and_times(table: np.ndarray, blank_all: np.ndarray, first: int, path: str):
    """The Frame and Time columns: every row has both, times strictly increase."""
    fr_t, blank = table[:, :2], blank_all[:, :2]
    if blank.any():
        r = int(np.argwhere(blank)[0][0])
        raise InputError(
            "expected a frame number and a time in every data row, got a blank",
            path=path,
            line=first + r + 1,
        )
    frame = fr_t[:, 0].astype(np.int64)
    time_s = fr_t[:, 1]
    back = np.flatnonzero(np.diff(time_s) <= 0)
    if back.size:
        r = int(back[0]) + 1
        raise InputError(
            f"expected increasing times, got {time_s[r]:.6f} s after {time_s[r - 1]:.6f} s",
            path=path,
            line=first + r + 1,
        )
    return frame, time_s


def _rigid_body(
    name: str,
    cols: dict,
    table: np.ndarray,
    blank_all: np.ndarray,
    rotation_type: str,
    scale_m: float,
    R_up: np.ndarray,
    first: int,
    i_axis: int,
    path: str,
    body_id: str,
) -> MotiveBody:
    """One rigid body's track: all its rotation/position cells blank (occluded) or none."""
    rot_axes = "XYZW" if rotation_type == "Quaternion" else "XYZ"
    need = [("Rotation", a) for a in rot_axes] + [("Position", a) for a in AXES]
    missing = [f"{c} {a}" for c, a in need if (c, a) not in cols]
    if missing:
        raise InputError(
            f"rigid body {name!r} lacks the columns {', '.join(missing)} needed for "
            f"Rotation Type {rotation_type}",
            path=path,
            line=i_axis + 1,
        )
    sel = [cols[k] for k in need]
    values, blank = table[:, sel], blank_all[:, sel]
    occluded = blank.all(axis=1)
    partial = blank.any(axis=1) & ~occluded
    if partial.any():
        r = int(np.flatnonzero(partial)[0])
        raise InputError(
            f"rigid body {name!r}: some rotation/position cells are blank "
            "and some are not (expected all blank when occluded)",
            path=path,
            line=first + r + 1,
        )
    n = table.shape[0]
    valid = np.asarray(~occluded, dtype=bool)
    nr = len(rot_axes)
    rot = values[:, :nr]
    pos_m = values[:, nr:] * scale_m
    R = np.full((n, 3, 3), np.nan)
    if valid.any():
        if rotation_type == "Quaternion":
            q = rot[valid]
            norm = np.linalg.norm(q, axis=-1)
            off = np.flatnonzero(np.abs(norm - 1.0) > 1e-3)
            if off.size:
                r = int(np.flatnonzero(valid)[off[0]])
                raise InputError(
                    f"rigid body {name!r}: expected a unit quaternion, got norm {norm[off[0]]:.6f}",
                    path=path,
                    line=first + r + 1,
                )
            R[valid] = geo.rotmat_from_quat_xyzw(q)
        else:
            R[valid] = _euler_to_rotmat(rot[valid], rotation_type)
    T = geo.se3_from_rt(R_up @ R, pos_m @ R_up.T)
    T[~valid] = np.nan
    mme = np.full(n, np.nan)
    if ("Mean Marker Error", "") in cols:
        c = cols[("Mean Marker Error", "")]
        mme = np.where(blank_all[:, c] | ~valid, np.nan, table[:, c] * scale_m)
    return MotiveBody(name, body_id, T, valid, mme)


def read_motive_csv(path: str | Path, *, up_axis: str = "y") -> MotiveTake:
    """Read a Motive CSV export (with header rows) into a :class:`MotiveTake`.

    ``up_axis`` is the export's vertical axis: ``"y"`` (Motive's default; converted to our
    Z-up) or ``"z"`` (the export already used a Z-up axis convention; kept as is).
    Raises InputError (with the line number) for anything that is not a Motive 1.2x rigid-body
    export: missing header rows, unknown rotation type or units, malformed or partial cells.
    """
    path = str(path)
    R_up = up_rotation(up_axis)
    lines = _read_text(path).splitlines()
    rows = list(csv.reader(lines[:40]))
    meta = _check_metadata(rows, path)
    rotation_type, units = meta["Rotation Type"], meta["Length Units"]
    h = _find_header(rows, path)
    layout, ids = _rigid_body_columns(h, path)
    # Data rows: every line after the axis row (trailing blank lines ignored).
    first = h.i_axis + 1
    data_lines = lines[first:]
    while data_lines and not data_lines[-1].strip(","):
        data_lines.pop()
    column_names = ["Frame", "Time"] + [
        f"{h.cells['Name'][c]} {h.cells['component'][c]} {h.axis[c]}".strip()
        for c in range(2, h.width)
    ]
    table, blank_all = _parse_table(data_lines, h.width, first + 1, path, column_names)
    frame, time_s = _frames_and_times(table, blank_all, first, path)
    bodies = {
        name: _rigid_body(
            name,
            cols,
            table,
            blank_all,
            rotation_type,
            LENGTH_UNITS_M[units],
            R_up,
            first,
            h.i_axis,
            path,
            ids.get(name, ""),
        )
        for name, cols in layout.items()
    }
    if not bodies:
        log.warning("%s: no rigid-body columns (only markers?)", path)
    return MotiveTake(
        frame=frame,
        time_s=time_s,
        bodies=bodies,
        take_name=meta.get("Take Name", ""),
        format_version=meta.get("Format Version", ""),
        capture_frame_rate_hz=_float_or_nan(meta.get("Capture Frame Rate", "nan")),
        export_frame_rate_hz=_float_or_nan(meta.get("Export Frame Rate", "nan")),
        capture_start_time=meta.get("Capture Start Time", ""),
        rotation_type=rotation_type,
        length_units=units,
        path=path,
    )
