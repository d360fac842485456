"""``merged.g2o`` + ``merged_vertices.csv``: every robot's local graph as one g2o file.

Vertices: robot ``r``'s keyframe ``j`` is ``r * 1_000_000 + j`` (by stamp order), object ``k``
is ``1_000_000_000 + k`` (shared by every robot that observed it). Edges: every odometry, loop
and observation factor with information ``Σ⁻¹``; a robot's gauge prior fixes its node (FIX);
the bounded graph's marginalisation prior is not exported. Values: the final decentralized
estimate (each robot's agent, world frame; an object takes the chordal mean of the robots'
copies). ``merged_vertices.csv`` maps each vertex back to its robot and stamp
(docs/run-format.md); the evaluation solves this file centrally (SR_ATE, SR_cost).
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dran_edge import geometry as geo
from dran_edge.formats import run_dir as rd
from dran_edge.formats.g2o import G2oGraph, write_g2o

if TYPE_CHECKING:
    from dran_edge.replay.robots import RobotResult

log = logging.getLogger(__name__)

#: A unary prior at most this tight (variance, m² / rad²) is a gauge: FIX in merged.g2o.
GAUGE_VARIANCE_MAX = 1e-6
#: Vertex id of robot r's keyframe j: r * ROBOT_VERTEX_STRIDE + j.
ROBOT_VERTEX_STRIDE = 1_000_000
#: Vertex id of object k: OBJECT_VERTEX_BASE + k.
OBJECT_VERTEX_BASE = 1_000_000_000


@dataclass
class _MergedGraph:
    """The merged graph as it is collected, robot by robot."""

    vid: list[int] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    rows: list[tuple[int, str, str, int]] = field(default_factory=list)
    """merged_vertices.csv: (vertex_id, kind, name, stamp_ns)."""
    edges: list[tuple[int, int]] = field(default_factory=list)
    meas: list[np.ndarray] = field(default_factory=list)
    info: list[np.ndarray] = field(default_factory=list)
    fixed_ids: set[int] = field(default_factory=set)
    object_copies: dict[int, list[np.ndarray]] = field(default_factory=dict)
    """Object id -> the T_world_object of every robot (so far) that has it."""


def _add_robot_poses(m: _MergedGraph, rid: int, r: RobotResult) -> dict[int, int]:
    """Adds the robot's final keyframes (those still in its graph) and object copies;
    returns its graph key -> vertex id."""
    assert r.graph is not None and r.last is not None
    keys, stamps = r.graph["keys"], r.graph["stamps"]
    final = {int(s): T for s, T in zip(r.last.keyframe_stamps_ns.tolist(), r.last.T_world_body)}
    keep = np.array([int(s) in final for s in stamps.tolist()], bool)
    keys, stamps = keys[keep], stamps[keep]
    order = np.argsort(stamps, kind="stable")
    key_vid = {}
    for j, i in enumerate(order.tolist()):
        v = rid * ROBOT_VERTEX_STRIDE + j
        key_vid[int(keys[i])] = v
        m.vid.append(v)
        m.poses.append(final[int(stamps[i])])
        m.rows.append((v, "pose", r.name, int(stamps[i])))
    for oid, T in zip(r.last.object_ids, r.last.T_world_object):
        m.object_copies.setdefault(int(oid), []).append(T)
    return key_vid


def _add_robot_factors(m: _MergedGraph, r: RobotResult, key_vid: dict[int, int]) -> None:
    """Adds the robot's factors between exported vertices; its gauge prior becomes a FIX."""
    assert r.graph is not None
    fa, obj_base = r.graph["factors"], r.graph["obj_base"]

    def vertex(key: int) -> int | None:
        if key >= obj_base:
            oid = int(key - obj_base)
            return OBJECT_VERTEX_BASE + oid if oid in m.object_copies else None
        return key_vid.get(int(key))

    for p, q, Z, S in zip(fa["p"].tolist(), fa["q"].tolist(), fa["Z"], fa["S"]):
        vq = vertex(q)
        if p < 0:
            # the gauge prior (sub-millimetre) fixes its node; weaker unary priors have no
            # g2o form and are left out
            if vq is not None and np.max(np.diag(S)) <= GAUGE_VARIANCE_MAX:
                m.fixed_ids.add(vq)
            continue
        vp = vertex(p)
        if vp is None or vq is None:
            continue
        m.edges.append((vp, vq))
        m.meas.append(Z)
        m.info.append(np.linalg.inv(S))


def _add_objects(m: _MergedGraph) -> None:
    """One vertex per object at the chordal mean of the robots' copies."""
    for oid in sorted(m.object_copies):
        v = OBJECT_VERTEX_BASE + oid
        m.vid.append(v)
        copies = np.stack(m.object_copies[oid])
        m.poses.append(
            geo.se3_from_rt(
                geo.so3_project(copies[:, :3, :3].mean(axis=0)), copies[:, :3, 3].mean(axis=0)
            )
        )
        m.rows.append((v, "object", str(oid), 0))


def _to_g2o_graph(m: _MergedGraph) -> G2oGraph:
    """The collected graph with vertices sorted by id and symmetric information."""
    vid_arr = np.asarray(m.vid, np.int64)
    order = np.argsort(vid_arr)
    pos = {int(v): k for k, v in enumerate(vid_arr[order].tolist())}
    e = np.array([[pos[a], pos[b]] for a, b in m.edges], np.int64).reshape(-1, 2)
    info_arr = np.stack(m.info) if m.info else np.zeros((0, 6, 6))
    info_arr = 0.5 * (info_arr + np.swapaxes(info_arr, -1, -2))
    return G2oGraph(
        dim=3,
        vertex_ids=vid_arr[order],
        poses=np.stack(m.poses)[order],
        has_pose=np.ones(len(m.vid), bool),
        edges=e,
        measurements=np.stack(m.meas) if m.meas else np.zeros((0, 4, 4)),
        information=info_arr,
        fixed=np.isin(vid_arr[order], sorted(m.fixed_ids)),
        edge_lines=np.zeros(len(m.edges), np.int64),
    )


def _write_vertex_map(path: Path, rows: list[tuple[int, str, str, int]]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["vertex_id", "kind", "name", "stamp_ns"])
        for row in sorted(rows):
            w.writerow(row)


@dataclass(frozen=True)
class MergedGraph:
    """The merged graph of every robot's local graph, as written to merged.g2o."""

    graph: G2oGraph
    """Vertices sorted by id, values the robots' current estimates (see the module docstring)."""
    vertex_map: dict[int, tuple[str, str, int]]
    """merged_vertices.csv: vertex id -> (kind "pose" / "object", robot or object name,
    stamp_ns); the form :func:`dran_edge.formats.run_outputs.read_vertex_map` reads back."""


def merged_graph(results: dict[int, RobotResult]) -> MergedGraph | None:
    """Every robot's local graph (if it has one) as one graph, with the robots' estimates as
    values (the module docstring); None when no robot exposes its graph. The replay builds it
    at the end (merged.g2o) and at the rounds whose costs it samples (round_costs.py)."""
    m = _MergedGraph()
    for rid in sorted(results):
        r = results[rid]
        if r.graph is None or r.last is None:
            continue
        key_vid = _add_robot_poses(m, rid, r)
        _add_robot_factors(m, r, key_vid)
    if not m.vid:
        return None
    _add_objects(m)
    return MergedGraph(_to_g2o_graph(m), {v: (kind, name, st) for v, kind, name, st in m.rows})


def write_merged_g2o(run: rd.Run, results: dict[int, RobotResult]) -> bool:
    """``merged.g2o`` + ``merged_vertices.csv`` from every robot's local graph (if it has one);
    False (and neither file) when no robot exposes its graph. See the module docstring."""
    merged = merged_graph(results)
    if merged is None:
        log.warning("no robot exposes its local graph: merged.g2o not written")
        for f in ("merged.g2o", "merged_vertices.csv"):
            (run.out_dir / f).unlink(missing_ok=True)
        return False
    write_g2o(run.out_dir / "merged.g2o", merged.graph)
    _write_vertex_map(
        run.out_dir / "merged_vertices.csv", [(v, *row) for v, row in merged.vertex_map.items()]
    )
    return True
