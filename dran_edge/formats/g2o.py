"""Read and write the g2o pose-graph subset dran-edge uses (format described in docs/g2o.md).

Records: ``VERTEX_SE2 id x y θ``, ``EDGE_SE2 i j dx dy dθ`` + 6 numbers (upper triangle of the 3×3
information in the order [x y | θ]), ``VERTEX_SE3:QUAT id x y z qx qy qz qw``,
``EDGE_SE3:QUAT i j dx dy dz dqx dqy dqz dqw`` + 21 numbers (upper triangle of the 6×6 information in
the order [x y z | qx qy qz]), ``FIX id``. Lines starting with ``#`` and blank lines are ignored.
The measurement of edge (i, j) is the pose of j in the frame of i: ``T_w_j = T_w_i T̃_ij``.

Every malformed line raises :class:`InputError` naming the file, the line number and the problem;
nothing is skipped silently. Files without VERTEX lines (CSAIL) are accepted: the poses of the
vertices named only by edges are unknown (``has_pose`` false) and need an initial guess.

Information matrices need not be positive definite: an edge is rejected only when no weighting
can use it (SE-Sync's κ or τ not finite and positive); edges usable only with SE-Sync's weights
are counted in one warning (see ``_check_information``).

The information's rotation block is kept as is, in our tangent order [ρ, φ] (translation first),
i.e. it is treated as the information of the rotation tangent φ — the reading of SE-Sync's and
GTSAM's g2o loaders.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import InputError
from dran_edge.solver.objective import not_positive_definite, weight_problems

log = logging.getLogger(__name__)

_VERTEX = {"VERTEX_SE2": 2, "VERTEX_SE3:QUAT": 3}
_EDGE = {"EDGE_SE2": 2, "EDGE_SE3:QUAT": 3}
_VERTEX_NUMBERS = {2: 3, 3: 7}
_EDGE_NUMBERS = {2: 3 + 6, 3: 7 + 21}
_QUAT_NORM_TOL = 1e-3


@dataclass(frozen=True, eq=False)
class G2oGraph:
    """A pose graph as read from a g2o file; arrays index vertices by position, not by id."""

    dim: int
    """2 (SE(2)) or 3 (SE(3))."""
    vertex_ids: np.ndarray
    """(n,) int64, the g2o vertex ids, sorted ascending."""
    poses: np.ndarray
    """(n, d+1, d+1) float64 ``T_world_vertex``; identity where ``has_pose`` is false."""
    has_pose: np.ndarray
    """(n,) bool, whether the file had a VERTEX line for the vertex."""
    edges: np.ndarray
    """(m, 2) int64 positions (into ``vertex_ids``) of each edge's (i, j)."""
    measurements: np.ndarray
    """(m, d+1, d+1) float64 ``T_i_j`` measured."""
    information: np.ndarray
    """(m, r, r) float64 information in [translation, rotation] order (r = 3 or 6)."""
    fixed: np.ndarray
    """(n,) bool, vertices named by FIX lines."""
    edge_lines: np.ndarray
    """(m,) int64 1-based line number of each edge in its file (for messages)."""

    @property
    def num_vertices(self) -> int:
        return int(self.vertex_ids.shape[0])

    @property
    def num_edges(self) -> int:
        return int(self.edges.shape[0])


def _parse_floats(tokens: list[str], path: str, lineno: int, what: str) -> list[float]:
    out = []
    for k, tok in enumerate(tokens):
        try:
            value = float(tok)
        except ValueError:
            raise InputError(
                f"{what}: field {k + 1} is {tok!r}, expected a number", path=path, line=lineno
            ) from None
        if not math.isfinite(value):
            raise InputError(
                f"{what}: field {k + 1} is {tok!r}, expected a finite number",
                path=path,
                line=lineno,
            )
        out.append(value)
    return out


def _parse_id(tok: str, path: str, lineno: int, what: str) -> int:
    try:
        value = int(tok)
    except ValueError:
        raise InputError(f"{what}: id {tok!r} is not an integer", path=path, line=lineno) from None
    if value < 0:
        raise InputError(f"{what}: id {value} is negative", path=path, line=lineno)
    return value


def _upper_to_full(upper: np.ndarray, r: int) -> np.ndarray:
    """(m, r(r+1)/2) row-major upper triangles -> (m, r, r) symmetric matrices."""
    iu = np.triu_indices(r)
    full = np.zeros((upper.shape[0], r, r))
    full[:, iu[0], iu[1]] = upper
    full[:, iu[1], iu[0]] = upper
    return full


def _rotation_from_quat_xyzw(q: np.ndarray, lines: np.ndarray, path: str, what: str) -> np.ndarray:
    norms = np.linalg.norm(q, axis=-1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > _QUAT_NORM_TOL)
    if bad.size:
        k = bad[0]
        raise InputError(
            f"{what}: quaternion norm is {norms[k]:.6g}, expected 1 (±{_QUAT_NORM_TOL:g})",
            path=path,
            line=int(lines[k]),
        )
    return geo.rotmat_from_quat_xyzw(q / norms[:, None])


def _check_information(
    tag: str, ij: np.ndarray, information: np.ndarray, lines: np.ndarray, path: str, dim: int
) -> None:
    """Reject the edges no weighting can use; warn once about those only SE-Sync's can use.

    Every solver path weights edges by SE-Sync's κ, τ (computed from the blocks alone) unless
    ``--weights information`` asks for Ω itself. An edge whose κ or τ is not finite and positive
    is unusable either way (a positive definite Ω always gives positive ones): InputError. An
    indefinite Ω with positive κ, τ (published 3D benchmarks have them) is usable with SE-Sync
    weights: one warning with the count; ``--weights information`` rejects it later, by line
    (:func:`dran_edge.solver.centralized.pose_graph`).
    """
    problems = weight_problems(dim, information, "sesync")
    if problems:
        k, why = problems[0]
        more = f" ({len(problems) - 1} more edges like it)" if len(problems) > 1 else ""
        raise InputError(
            f"{tag} {int(ij[k, 0])} {int(ij[k, 1])}: information matrix cannot be used: "
            f"{why}{more}",
            path=path,
            line=int(lines[k]),
        )
    bad, lam_min = not_positive_definite(information)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        log.warning(
            "%s: %d of %d edges have an information matrix that is not positive definite "
            "(first: %s %d %d on line %d, smallest eigenvalue %.6g); their SE-Sync weights "
            "kappa, tau are positive and are used (--weights information would reject them)",
            path,
            int(bad.sum()),
            bad.size,
            tag,
            int(ij[k, 0]),
            int(ij[k, 1]),
            int(lines[k]),
            lam_min[k],
        )


def _read_text(path: str) -> str:
    try:
        with open(path, encoding="utf-8") as fh:
            return fh.read()
    except OSError as exc:
        raise InputError(f"cannot read the file: {exc.strerror}", path=path) from None
    except UnicodeDecodeError:
        raise InputError(
            "the file is not UTF-8 text, expected a g2o text file", path=path
        ) from None


@dataclass
class _Records:
    """The records of a g2o file as parsed, line by line (numbers not yet converted to poses)."""

    path: str
    dim: int | None = None
    vertex_rows: dict[int, tuple[list[float], int]] = field(default_factory=dict)
    """Vertex id -> (pose numbers, line)."""
    edge_ids: list[tuple[int, int]] = field(default_factory=list)
    edge_nums: list[list[float]] = field(default_factory=list)
    edge_lines: list[int] = field(default_factory=list)
    fix_ids: list[tuple[int, int]] = field(default_factory=list)
    """(vertex id, line) of every id named by a FIX line."""

    def set_dim(self, d: int, tag: str, lineno: int) -> None:
        if self.dim is None:
            self.dim = d
        elif self.dim != d:
            raise InputError(
                f"{tag} mixes {d}D records into a {self.dim}D graph", path=self.path, line=lineno
            )

    def add_vertex(self, tag: str, tokens: list[str], lineno: int) -> None:
        path = self.path
        d = _VERTEX[tag]
        self.set_dim(d, tag, lineno)
        expected = 1 + _VERTEX_NUMBERS[d]
        if len(tokens) - 1 != expected:
            raise InputError(
                f"{tag} has {len(tokens) - 1} fields, expected {expected} (id and pose)",
                path=path,
                line=lineno,
            )
        vid = _parse_id(tokens[1], path, lineno, tag)
        if vid in self.vertex_rows:
            raise InputError(
                f"{tag}: vertex {vid} is defined twice (first on line {self.vertex_rows[vid][1]})",
                path=path,
                line=lineno,
            )
        self.vertex_rows[vid] = (_parse_floats(tokens[2:], path, lineno, tag), lineno)

    def add_edge(self, tag: str, tokens: list[str], lineno: int) -> None:
        path = self.path
        d = _EDGE[tag]
        self.set_dim(d, tag, lineno)
        expected = 2 + _EDGE_NUMBERS[d]
        if len(tokens) - 1 != expected:
            raise InputError(
                f"{tag} has {len(tokens) - 1} fields, expected {expected} "
                "(two ids, measurement, upper-triangular information)",
                path=path,
                line=lineno,
            )
        i = _parse_id(tokens[1], path, lineno, tag)
        j = _parse_id(tokens[2], path, lineno, tag)
        if i == j:
            raise InputError(f"{tag}: edge connects vertex {i} to itself", path=path, line=lineno)
        self.edge_ids.append((i, j))
        self.edge_nums.append(_parse_floats(tokens[3:], path, lineno, tag))
        self.edge_lines.append(lineno)

    def add_fix(self, tokens: list[str], lineno: int) -> None:
        if len(tokens) < 2:
            raise InputError("FIX names no vertex id", path=self.path, line=lineno)
        for tok in tokens[1:]:
            self.fix_ids.append((_parse_id(tok, self.path, lineno, "FIX"), lineno))


def _parse_records(text: str, path: str) -> _Records:
    """Every record of the file, checked field by field (InputError naming the line)."""
    rec = _Records(path)
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tokens = line.split()
        tag = tokens[0]
        if tag in _VERTEX:
            rec.add_vertex(tag, tokens, lineno)
        elif tag in _EDGE:
            rec.add_edge(tag, tokens, lineno)
        elif tag == "FIX":
            rec.add_fix(tokens, lineno)
        else:
            raise InputError(
                f"unsupported record {tag!r}; expected one of "
                "VERTEX_SE2, EDGE_SE2, VERTEX_SE3:QUAT, EDGE_SE3:QUAT, FIX",
                path=path,
                line=lineno,
            )
    if rec.dim is None or not rec.edge_ids:
        raise InputError(
            "no edges found, expected at least one EDGE_SE2 or EDGE_SE3:QUAT line", path=path
        )
    return rec


def _vertex_poses(rec: _Records, dim: int, vertex_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(poses, has_pose) of every vertex: the VERTEX line's pose, else the identity."""
    n, D = vertex_ids.shape[0], dim + 1
    poses = np.broadcast_to(np.eye(D), (n, D, D)).copy()
    has_pose = np.zeros(n, dtype=bool)
    if rec.vertex_rows:
        vids = np.fromiter(rec.vertex_rows.keys(), np.int64, len(rec.vertex_rows))
        rows = np.asarray([v[0] for v in rec.vertex_rows.values()])
        vlines = np.asarray([v[1] for v in rec.vertex_rows.values()])
        pos = np.searchsorted(vertex_ids, vids)
        if dim == 2:
            poses[pos] = geo.se2_from_xy_theta(rows)
        else:
            R = _rotation_from_quat_xyzw(rows[:, 3:7], vlines, rec.path, "VERTEX_SE3:QUAT")
            poses[pos] = geo.se3_from_rt(R, rows[:, :3])
        has_pose[pos] = True
    return poses, has_pose


def _edge_arrays(
    rec: _Records, dim: int, ij: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(measurements, information, lines) of the edges; the information checked."""
    nums = np.asarray(rec.edge_nums)
    lines = np.asarray(rec.edge_lines, dtype=np.int64)
    if dim == 2:
        measurements = geo.se2_from_xy_theta(nums[:, :3])
        information = _upper_to_full(nums[:, 3:], 3)
        tag = "EDGE_SE2"
    else:
        R = _rotation_from_quat_xyzw(nums[:, 3:7], lines, rec.path, "EDGE_SE3:QUAT")
        measurements = geo.se3_from_rt(R, nums[:, :3])
        information = _upper_to_full(nums[:, 7:], 6)
        tag = "EDGE_SE3:QUAT"
    _check_information(tag, ij, information, lines, rec.path, dim)
    return measurements, information, lines


def _fixed_vertices(rec: _Records, vertex_ids: np.ndarray) -> np.ndarray:
    """(n,) bool of the vertices named by FIX lines (each must be a vertex of the graph)."""
    n = vertex_ids.shape[0]
    fixed = np.zeros(n, dtype=bool)
    for vid, lineno in rec.fix_ids:
        k = int(np.searchsorted(vertex_ids, vid))
        if k >= n or vertex_ids[k] != vid:
            raise InputError(
                f"FIX names vertex {vid}, which no VERTEX or EDGE line defines",
                path=rec.path,
                line=lineno,
            )
        fixed[k] = True
    return fixed


def read_g2o(path: str | Path) -> G2oGraph:
    """Parse a g2o file (see module docstring); raises InputError on any malformed line."""
    path = str(path)
    rec = _parse_records(_read_text(path), path)
    dim = rec.dim
    assert dim is not None  # _parse_records raises without records
    ij = np.asarray(rec.edge_ids, dtype=np.int64)
    vertex_ids = np.union1d(
        np.fromiter(rec.vertex_rows.keys(), np.int64, len(rec.vertex_rows)), ij.ravel()
    )
    poses, has_pose = _vertex_poses(rec, dim, vertex_ids)
    measurements, information, lines = _edge_arrays(rec, dim, ij)
    fixed = _fixed_vertices(rec, vertex_ids)
    return G2oGraph(
        dim=dim,
        vertex_ids=vertex_ids,
        poses=poses,
        has_pose=has_pose,
        edges=np.searchsorted(vertex_ids, ij),
        measurements=measurements,
        information=information,
        fixed=fixed,
        edge_lines=lines,
    )


def _fmt(rows: np.ndarray) -> list[str]:
    """Shortest round-trip text of each row of floats."""
    return [" ".join(repr(float(x)) for x in row) for row in rows]


def write_g2o(path: str | Path, graph: G2oGraph, poses: np.ndarray | None = None) -> None:
    """Write ``graph`` (with ``poses`` in place of ``graph.poses`` when given) as a g2o file.

    Every vertex gets a VERTEX line, then every edge, then one FIX line per fixed vertex; numbers
    are written with full precision so that ``read_g2o(write_g2o(g))`` reproduces ``g``.
    """
    poses = graph.poses if poses is None else np.asarray(poses, dtype=np.float64)
    if poses.shape != graph.poses.shape:
        raise ValueError(f"poses have shape {poses.shape}, expected {graph.poses.shape}")
    r = graph.information.shape[-1]
    iu = np.triu_indices(r)
    upper = graph.information[:, iu[0], iu[1]]
    ids = graph.vertex_ids
    if graph.dim == 2:
        vtag, etag = "VERTEX_SE2", "EDGE_SE2"
        vrows = geo.se2_to_xy_theta(poses)
        erows = geo.se2_to_xy_theta(graph.measurements)
    else:
        vtag, etag = "VERTEX_SE3:QUAT", "EDGE_SE3:QUAT"
        vrows = geo.se3_to_xyz_quat_xyzw(poses)
        erows = geo.se3_to_xyz_quat_xyzw(graph.measurements)
    out = [f"{vtag} {vid} {txt}" for vid, txt in zip(ids.tolist(), _fmt(vrows))]
    ei, ej = ids[graph.edges[:, 0]].tolist(), ids[graph.edges[:, 1]].tolist()
    out += [f"{etag} {i} {j} {m} {inf}" for i, j, m, inf in zip(ei, ej, _fmt(erows), _fmt(upper))]
    out += [f"FIX {vid}" for vid in ids[graph.fixed].tolist()]
    try:
        Path(path).write_text("\n".join(out) + "\n", encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot write the file: {exc.strerror}", path=str(path)) from None
