"""Readers of the files ``dran-edge replay`` writes under a run's ``out/`` (docs/run-format.md)
besides the TUM trajectories (dran_edge.formats.tum) and the g2o graph (dran_edge.formats.g2o).

Strict: every malformed line raises InputError naming the file and the line. Pure core module
(numpy, stdlib).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import InputError


#: Per-robot trajectory files under ``out/`` by kind: the name replay writes (it carries the
#: robot, so evo's legends say which robot) and the name older runs have.
TRAJECTORY_NAMES = {
    "final": ("{robot}.tum", "trajectory.tum"),
    "init": ("{robot}_init.tum", "trajectory_init.tum"),
}


def trajectory_file(out_dir: Path, robot: str, kind: str = "final") -> Path | None:
    """``out/<robot>/<robot>.tum`` (``final``), ``<robot>_init.tum`` (``init``) or
    ``out/centralized/<robot>/<robot>.tum`` (``centralized``); the older ``trajectory.tum`` /
    ``trajectory_init.tum`` names are read too. None when absent."""
    folder = Path(out_dir) / ("centralized" if kind == "centralized" else "") / robot
    for name in TRAJECTORY_NAMES["init" if kind == "init" else "final"]:
        p = folder / name.format(robot=robot)
        if p.exists():
            return p
    return None


def read_objects_csv(path: Path) -> dict[int, np.ndarray]:
    """``object_id,x,y,z,qx,qy,qz,qw`` rows (header line optional) -> {id: T_world_object}."""
    out: dict[int, np.ndarray] = {}
    with open(path, newline="", encoding="utf-8") as f:
        for n, row in enumerate(csv.reader(f), start=1):
            if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
                continue
            if n == 1 and row[0].strip() == "object_id":
                continue
            if len(row) != 8:
                raise InputError(
                    f"expected 8 fields object_id,x,y,z,qx,qy,qz,qw, got {len(row)}",
                    path=str(path),
                    line=n,
                )
            try:
                oid = int(row[0])
                v = np.array([float(c) for c in row[1:]])
            except ValueError:
                raise InputError(
                    f"expected an integer id and 7 numbers, got {','.join(row)!r}",
                    path=str(path),
                    line=n,
                ) from None
            if not np.isfinite(v).all() or abs(np.linalg.norm(v[3:]) - 1) > 1e-3:
                raise InputError(
                    "expected finite numbers and a unit quaternion", path=str(path), line=n
                )
            if oid in out:
                raise InputError(f"object {oid} appears twice", path=str(path), line=n)
            out[oid] = geo.se3_from_xyz_quat_xyzw(v)
    return out


def read_rounds_csv(path: Path) -> dict[str, np.ndarray]:
    """``rounds.csv`` -> {column: values}; needs a header with ``round``; numbers or blanks."""
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    if not rows or "round" not in [c.strip() for c in rows[0]]:
        raise InputError(
            "expected a header line naming the columns, with 'round' among them",
            path=str(path),
            line=1,
        )
    head = [c.strip() for c in rows[0]]
    cols: dict[str, list[float]] = {h: [] for h in head}
    for n, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != len(head):
            raise InputError(
                f"expected {len(head)} fields like the header, got {len(row)}",
                path=str(path),
                line=n,
            )
        for h, c in zip(head, row):
            try:
                cols[h].append(float(c) if c.strip() else math.nan)
            except ValueError:
                raise InputError(
                    f"column {h!r}: expected a number, got {c!r}", path=str(path), line=n
                ) from None
    return {h: np.array(v) for h, v in cols.items()}


def read_vertex_map(path: Path) -> dict[int, tuple[str, str, int]]:
    """``merged_vertices.csv`` (``vertex_id,kind,name,stamp_ns``; kind ``pose`` or ``object``)
    -> {vertex_id: (kind, robot name or object id, stamp_ns)}."""
    out = {}
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    if not rows or [c.strip() for c in rows[0]] != ["vertex_id", "kind", "name", "stamp_ns"]:
        raise InputError("expected the header vertex_id,kind,name,stamp_ns", path=str(path), line=1)
    for n, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        try:
            vid, kind, name, stamp = int(row[0]), row[1].strip(), row[2].strip(), int(row[3])
        except (ValueError, IndexError):
            raise InputError(
                f"expected vertex_id,kind,name,stamp_ns, got {','.join(row)!r}",
                path=str(path),
                line=n,
            ) from None
        if kind not in ("pose", "object"):
            raise InputError(
                f"kind: expected 'pose' or 'object', got {kind!r}", path=str(path), line=n
            )
        out[vid] = (kind, name, stamp)
    return out
