"""TUM trajectory files (``stamp_s x y z qx qy qz qw``, one pose per line), read strictly.

The format evo and the TUM RGB-D benchmark read: whitespace-separated, ``#`` comments, exactly
eight numbers per line, quaternion X, Y, Z, W. Pure core module (numpy, stdlib).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import InputError

#: How far from 1 a quaternion's norm may be before the line is rejected (6-decimal writers).
QUAT_NORM_TOL = 1e-3


def read_tum(path: str | Path, *, require_increasing: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(stamps_s ``(n,)``, T ``(n, 4, 4)``) from a TUM file.

    Raises InputError naming the line for a line that is not eight finite numbers, a quaternion
    that is not unit within ``QUAT_NORM_TOL``, stamps that do not increase (unless
    ``require_increasing`` is False), and for a file with no poses.
    """
    path = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("TUM trajectory file not found", path=path) from None
    rows, lines = [], []
    for n, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        cells = s.replace(",", " ").split()
        if len(cells) != 8:
            raise InputError(
                f"expected 8 numbers 'stamp_s x y z qx qy qz qw', got {len(cells)} fields",
                path=path,
                line=n,
            )
        try:
            vals = [float(c) for c in cells]
        except ValueError:
            raise InputError(f"expected 8 numbers, got {s[:80]!r}", path=path, line=n) from None
        rows.append(vals)
        lines.append(n)
    if not rows:
        raise InputError("expected at least one pose line, got none", path=path)
    a = np.array(rows)
    line_of = np.array(lines)
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise InputError(
            "expected finite numbers, got NaN or inf", path=path, line=int(line_of[bad][0])
        )
    norm = np.linalg.norm(a[:, 4:8], axis=1)
    off = np.abs(norm - 1.0) > QUAT_NORM_TOL
    if off.any():
        k = int(np.flatnonzero(off)[0])
        raise InputError(
            f"expected a unit quaternion, got norm {norm[k]:.6f}", path=path, line=int(line_of[k])
        )
    if require_increasing:
        back = np.flatnonzero(np.diff(a[:, 0]) <= 0)
        if back.size:
            k = int(back[0]) + 1
            raise InputError(
                f"expected increasing stamps, got {a[k, 0]:.9f} after {a[k - 1, 0]:.9f}",
                path=path,
                line=int(line_of[k]),
            )
    return geo.se3_from_tum_rows(a)


def write_tum(path: str | Path, stamps_s: np.ndarray, T: np.ndarray, *, header: str = "") -> None:
    """Write poses ``(n, 4, 4)`` at ``stamps_s`` as TUM lines (ns-resolution stamps)."""
    rows = geo.se3_to_tum_rows(np.asarray(stamps_s, dtype=np.float64), T)
    with open(path, "w", encoding="utf-8") as f:
        if header:
            for line in header.splitlines():
                f.write(f"# {line}\n")
        np.savetxt(f, rows, fmt=["%.9f"] + ["%.10f"] * 7)
