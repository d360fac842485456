"""The exact distributed refinement (``dran_edge.dran.exact_gn``, docs/dran.md) in the object
simulation (``objects.run_objects``, docs/notes/object-simulation.md).

The scenario viewed as one partitioned pose graph: the vertices are every robot's trajectory
and one copy of every observed object; the factors are those of the centralized reference
(``objects.centralized``: odometry, the start prior, object observations), so the refinement
minimises exactly the objective F* is the minimum of. Ownership: robot r owns its poses; an
object is owned by the robot with the most observations of it (the lowest id on a tie), which
keeps the boundaries small: every other observer's viewing poses become separators and the
object an anchor of theirs. An observation by a robot that does not own the object is an
inter-robot factor, at half weight in each of the two robots' shares (as in ``exact_gn``).

The tree is a BFS spanning tree of the communication graph, not of the factor graph: two
robots coupled by an observation need not be neighbours, since every condensed system is
forwarded up to the root and every boundary value comes down from it
(``substructure.robot_tree``); relayed values are datagrams on every link they cross, and the
bus counts them. The start prior fixes the gauge (no gauge vertex). Least squares only: a
robust kernel is not split by halving a factor's weight, so runs with kernels (``--robust``,
``--outliers``) are not refined.
"""

from __future__ import annotations

import dataclasses
from typing import cast

import numpy as np
import scipy.sparse as sp

from dran_edge.dran import exact_gn
from dran_edge.dran.partition import Partition, RobotPart, partition_edges
from dran_edge.dran.substructure import robot_tree
from dran_edge.solver.factors import BetweenFactors, PriorFactors
from dran_edge.solver.graph import PoseGraph
from dran_edge.solver.linearize import block_normal_equations

B_SE3 = 6  # tangent size of one SE(3) vertex


@dataclasses.dataclass(frozen=True, eq=False)
class ObjectGraph:
    """The scenario's centralized graph over the used vertices, partitioned among the robots."""

    vertices: np.ndarray
    """(n,) positions in the centralized graph of the refined vertices (poses, observed objects)."""
    partition: Partition
    blocks: tuple
    """Per robot: its factor blocks (compact indices; inter-robot ones at half weight)."""


def object_owner(graph: PoseGraph, off: np.ndarray) -> np.ndarray:
    """(N,) owning robot of every centralized vertex: poses their robot's, objects the robot
    with most observations of them (lowest id on a tie), -1 for objects nobody observes."""
    n_x = int(off[-1])
    robot_of = np.searchsorted(off, np.arange(n_x), side="right") - 1
    owner = np.full(graph.num_variables, -1, np.int64)
    owner[:n_x] = robot_of
    R = len(off) - 1
    counts = np.zeros((graph.num_variables - n_x, R), np.int64)
    for block in graph.factors:
        v = np.asarray(block.variables)
        if v.shape[1] == 2:
            obs = v[:, 1] >= n_x
            np.add.at(counts, (v[obs, 1] - n_x, robot_of[v[obs, 0]]), 1)
    seen = counts.sum(axis=1) > 0
    owner[n_x:][seen] = np.argmax(counts[seen], axis=1)  # argmax: the lowest id on a tie
    return owner


def object_graph(graph: PoseGraph, off: np.ndarray) -> ObjectGraph:
    """Partition the centralized graph (``objects.centralized``) by ``object_owner``."""
    owner_all = object_owner(graph, off)
    vertices = np.flatnonzero(owner_all >= 0)
    compact = np.full(owner_all.size, -1, np.int64)
    compact[vertices] = np.arange(vertices.size)
    owner = owner_all[vertices]
    edges = np.concatenate(
        [
            compact[np.asarray(b.variables)]
            for b in graph.factors
            if np.asarray(b.variables).shape[1] == 2
        ]
    )
    partition = partition_edges(edges, owner)
    per_robot: list[list] = [[] for _ in partition.parts]
    for block in cast(tuple[BetweenFactors | PriorFactors, ...], graph.factors):
        var = compact[np.asarray(block.variables)]
        own = owner[var]
        for r in range(partition.num_robots):
            rows = np.flatnonzero((own == r).any(axis=1))
            if rows.size:
                half = ~(own[rows] == r).all(axis=1)
                scale = np.where(half, np.sqrt(0.5), 1.0)[:, None]
                per_robot[r].append(
                    dataclasses.replace(
                        block,
                        variables=var[rows],
                        measurements=block.measurements[rows],
                        whitening=block.whitening[rows] * scale,
                    )
                )
    return ObjectGraph(vertices, partition, tuple(tuple(b) for b in per_robot))


def refine_objects(
    graph: PoseGraph,
    off: np.ndarray,
    poses: np.ndarray,
    adjacency: list[list[int]],
    exchange,
    params: exact_gn.RefineParams,
    wire_dtype: type | None = np.float32,
) -> exact_gn.RefineResult:
    """``exact_gn.refine_shares`` on the scenario's centralized graph from ``poses`` (N, 4, 4)
    over a BFS tree of ``adjacency`` (the communication graph, per robot its neighbours).
    The result's poses are all N (unobserved objects unchanged); its F is twice the
    centralized objective (``exact_gn``'s convention)."""
    if any(b.kernel is not None for b in graph.factors):
        raise ValueError("the exact refinement of the object simulation is least squares only")
    og = object_graph(graph, off)
    n = og.vertices.size

    def share_of(
        part: RobotPart, T: np.ndarray, exact: bool
    ) -> tuple[sp.csr_matrix, np.ndarray, float, np.ndarray]:
        H, g, cost = sp.csr_matrix((n * B_SE3, n * B_SE3)), np.zeros(n * B_SE3), 0.0
        H2 = H
        for block in og.blocks[part.robot_id]:
            Hb, gb, c = block_normal_equations(block, T)
            Hs, gs = exact_gn.scatter_blocks(Hb, gb, block.variables, n, B_SE3)
            H, g, cost = H + Hs, g + gs, cost + c
            second = block.second_order(T) if exact else None  # None: geodesic residual
            if second is not None:
                H2 = H2 + exact_gn.scatter_blocks(second, gb, block.variables, n, B_SE3)[0]
        return H + H2, g, cost, H.diagonal()

    tree = robot_tree(og.partition, adjacency)
    res = exact_gn.refine_shares(
        3, n, og.partition, share_of, poses[og.vertices], exchange, params, -1, wire_dtype, tree
    )
    out = np.asarray(poses, np.float64).copy()
    out[og.vertices] = res.poses
    res.poses = out
    return res
