"""Split a pose graph into per-robot parts like the paper's Table 1 (Sec. 6.1).

"We simulate a multi-robot setting by splitting each trajectory into five segments and assigning
each segment to one robot. The physical topology is defined by inter-robot measurements, and the
communication topology follows it by exchanging separator variables between connected robots."

Vertices are taken in id order and cut into ``num_robots`` contiguous segments of (nearly) equal
length. For robot ``r``:

- ``intra_edges``: edges with both ends in its segment (``f_intra``);
- ``inter_edges``: edges with exactly one end in its segment (``f_inter``); the other end is a
  neighbour's *separator*, held fixed as an anchor during the local step (Sec. 3.1, edge-based
  decoupling). Every inter-robot edge therefore appears in two parts; the global objective counts
  it once (``Partition.global_cost_edges``).
- ``separators``: its own vertices touched by inter-robot edges (what it sends);
- ``anchors``: the neighbours' vertices its inter-robot edges touch (what it receives);
- ``neighbours``: robots sharing at least one inter-robot edge.

All indices are positions into the graph's vertex arrays (``G2oGraph.vertex_ids`` order).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dran_edge.errors import InputError


@dataclass(frozen=True, eq=False)
class RobotPart:
    """One robot's share of a partitioned graph (arrays of vertex / edge positions)."""

    robot_id: int
    vertices: np.ndarray
    """(n_r,) int64 positions of the robot's own vertices (its private trajectory x_i), sorted."""
    intra_edges: np.ndarray
    """(m_r,) int64 edge positions with both ends owned by this robot."""
    inter_edges: np.ndarray
    """(k_r,) int64 edge positions with exactly one end owned by this robot."""
    separators: np.ndarray
    """(s_r,) int64 own vertex positions touched by inter-robot edges (sent to neighbours)."""
    anchors: np.ndarray
    """(a_r,) int64 other robots' vertex positions touched by this robot's inter-robot edges."""
    neighbours: tuple[int, ...]
    """Robots sharing at least one inter-robot edge with this one, ascending."""
    separators_for: dict[int, np.ndarray]
    """neighbour id -> (s,) int64 own separator positions that neighbour needs."""


@dataclass(frozen=True, eq=False)
class Partition:
    """A graph's vertices assigned to robots, with each robot's part."""

    owner: np.ndarray
    """(n,) int64 robot id owning each vertex."""
    parts: tuple[RobotPart, ...]
    """One part per robot, indexed by robot id."""
    edges: np.ndarray
    """(m, 2) int64 the graph's edges (positions), copied for convenience."""

    @property
    def num_robots(self) -> int:
        return len(self.parts)

    def neighbour_pairs(self) -> list[tuple[int, int]]:
        """Undirected communication edges (i < j) of the measurement-induced topology."""
        return sorted(
            {(min(p.robot_id, q), max(p.robot_id, q)) for p in self.parts for q in p.neighbours}
        )


def contiguous_owner(num_vertices: int, num_robots: int) -> np.ndarray:
    """(n,) owner ids: vertices in order cut into ``num_robots`` near-equal contiguous segments."""
    if num_robots < 1:
        raise InputError(f"number of robots must be >= 1, got {num_robots}")
    if num_vertices < num_robots:
        raise InputError(
            f"cannot split {num_vertices} vertices among {num_robots} robots; "
            "expected at least one vertex per robot"
        )
    bounds = np.linspace(0, num_vertices, num_robots + 1).round().astype(np.int64)
    return np.searchsorted(bounds, np.arange(num_vertices), side="right").astype(np.int64) - 1


def partition_edges(edges: np.ndarray, owner: np.ndarray) -> Partition:
    """Build every robot's part from an edge list (m, 2) and a vertex -> robot ``owner`` map."""
    edges = np.asarray(edges, dtype=np.int64)
    owner = np.asarray(owner, dtype=np.int64)
    num_robots = int(owner.max()) + 1
    oi, oj = owner[edges[:, 0]], owner[edges[:, 1]]
    cross = oi != oj
    parts = []
    for r in range(num_robots):
        vertices = np.flatnonzero(owner == r).astype(np.int64)
        intra = np.flatnonzero((oi == r) & (oj == r)).astype(np.int64)
        inter = np.flatnonzero(cross & ((oi == r) | (oj == r))).astype(np.int64)
        e = edges[inter]
        mine_first = owner[e[:, 0]] == r
        own_end = np.where(mine_first, e[:, 0], e[:, 1])
        other_end = np.where(mine_first, e[:, 1], e[:, 0])
        other_owner = owner[other_end]
        neighbours = tuple(int(x) for x in np.unique(other_owner))
        separators_for = {
            q: np.unique(own_end[other_owner == q]).astype(np.int64) for q in neighbours
        }
        parts.append(
            RobotPart(
                robot_id=r,
                vertices=vertices,
                intra_edges=intra,
                inter_edges=inter,
                separators=np.unique(own_end).astype(np.int64),
                anchors=np.unique(other_end).astype(np.int64),
                neighbours=neighbours,
                separators_for=separators_for,
            )
        )
    return Partition(owner=owner, parts=tuple(parts), edges=edges)


def partition_contiguous(edges: np.ndarray, num_vertices: int, num_robots: int) -> Partition:
    """The paper's split: ``num_robots`` contiguous trajectory segments (Sec. 6.1)."""
    return partition_edges(edges, contiguous_owner(num_vertices, num_robots))


def interleaved_owner(num_vertices: int, num_robots: int, chunks_per_robot: int = 4) -> np.ndarray:
    """(n,) owner ids: the vertices in order cut into ``num_robots × chunks_per_robot``
    near-equal chunks dealt round-robin (chunk c to robot c mod R), so every robot drives
    several stretches of the trajectory and robots revisit each other's areas."""
    if chunks_per_robot < 1:
        raise InputError(f"chunks per robot must be >= 1, got {chunks_per_robot}")
    chunks = contiguous_owner(num_vertices, num_robots * chunks_per_robot)
    return chunks % num_robots
