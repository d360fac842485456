"""Centralised pose-graph optimisation of a g2o graph: initialise, build factors, run Schur–LM.

The library behind ``dran-edge solve``, the demo and the g2o benchmark. Gauge: the vertices named
by FIX lines are fixed; without FIX lines the first vertex (lowest id) is fixed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dran_edge import geometry as geo
from dran_edge.solver.chordal import chordal_initialization
from dran_edge.errors import InputError
from dran_edge.solver.graph import PoseGraph, kinds_array
from dran_edge.solver.choices import Hessian
from dran_edge.solver.lm import LMParams, LMResult, solve
from dran_edge.solver.objective import (
    WEIGHTS,
    edge_factors,
    sesync_objective,
    sesync_weights,
    weight_problems,
)

if TYPE_CHECKING:  # the solver only reads a G2oGraph's arrays; the format layer builds it
    from dran_edge.formats.g2o import G2oGraph

INITS = ("chordal", "file", "odometry")


def gauge_fixed(g: G2oGraph) -> np.ndarray:
    """(n,) bool: the FIX vertices, or the first vertex when the file fixes none."""
    fixed: np.ndarray = g.fixed.copy()
    if not fixed.any():
        fixed[0] = True
    return fixed


def odometry_initialization(g: G2oGraph, anchor: int, T_anchor: np.ndarray) -> np.ndarray:
    """Poses composed along a breadth-first spanning tree of the edges from ``anchor``
    (for a trajectory, the odometry chain i → i+1 when it is complete)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import breadth_first_order

    n = g.num_vertices
    i, j = g.edges[:, 0], g.edges[:, 1]
    # Prefer consecutive-id edges (odometry) by giving the tree search only those first.
    consecutive = np.abs(g.vertex_ids[j] - g.vertex_ids[i]) == 1
    order_edges = np.concatenate([np.flatnonzero(consecutive), np.flatnonzero(~consecutive)])
    T: np.ndarray = np.broadcast_to(np.eye(g.dim + 1), (n, g.dim + 1, g.dim + 1)).copy()
    done = np.zeros(n, dtype=bool)
    T[anchor], done[anchor] = T_anchor, True
    for subset in (order_edges[: int(consecutive.sum())], order_edges):
        adj = sp.coo_matrix(
            (np.arange(1, subset.size + 1), (i[subset], j[subset])), shape=(n, n)
        ).tocsr()
        adj = adj + adj.T.multiply(-1)  # sign tells the direction of the stored edge
        roots = np.flatnonzero(done)
        for root in roots:
            order, pred = breadth_first_order(abs(adj), root, directed=False)
            for v in order[1:]:
                if done[v]:
                    continue
                p = pred[v]
                code = adj[p, v]
                e = subset[abs(int(code)) - 1]
                Z = g.measurements[e]
                T[v] = T[p] @ (Z if code > 0 else geo.inverse(Z))
                done[v] = True
        if done.all():
            break
    if not done.all():
        raise InputError(
            f"{int((~done).sum())} vertices are not connected to vertex {int(g.vertex_ids[anchor])}; "
            "odometry initialisation needs a connected graph"
        )
    return T


def initial_poses(g: G2oGraph, init: str) -> np.ndarray:
    """Initial values by 'chordal', 'file' (the VERTEX lines) or 'odometry' (composition)."""
    fixed = gauge_fixed(g)
    anchor = int(np.flatnonzero(fixed)[0])
    T_anchor = g.poses[anchor]
    if init == "file":
        if not g.has_pose.all():
            missing = g.vertex_ids[~g.has_pose]
            raise InputError(
                f"--init file needs a VERTEX line for every vertex; {missing.size} have none "
                f"(e.g. id {int(missing[0])}); use --init chordal or odometry"
            )
        poses: np.ndarray = g.poses.copy()
        return poses
    if init == "odometry":
        T = odometry_initialization(g, anchor, T_anchor)
    elif init == "chordal":
        kappa, tau = sesync_weights(g.dim, g.information)
        T = T_anchor @ chordal_initialization(
            g.num_vertices, g.edges, g.measurements, kappa, tau, anchor
        )
    else:
        raise ValueError(f"init must be one of {INITS}, got {init!r}")
    T[fixed] = g.poses[fixed]  # other FIX vertices keep the file's values
    return T


def pose_graph(g: G2oGraph, residual: str, weights: str) -> PoseGraph:
    """The PoseGraph of a g2o graph: every vertex private except the gauge-fixed ones.

    Raises InputError naming the first edge (ids and line) whose information the chosen
    ``weights`` cannot use (see :func:`dran_edge.solver.objective.weight_problems`)."""
    problems = weight_problems(g.dim, g.information, weights) if weights in WEIGHTS else []
    if problems:
        k, why = problems[0]
        i, j = (int(g.vertex_ids[v]) for v in g.edges[k])
        more = f" ({len(problems) - 1} more edges like it)" if len(problems) > 1 else ""
        raise InputError(f"edge {i} {j} on line {int(g.edge_lines[k])}: {why}{more}")
    block = edge_factors(g.dim, g.edges, g.measurements, g.information, residual, weights)
    return PoseGraph(
        dim=g.dim, kinds=kinds_array(g.num_vertices, fixed=gauge_fixed(g)), factors=(block,)
    )


@dataclass(frozen=True, eq=False)
class SolveReport:
    result: LMResult
    poses_init: np.ndarray
    objective_input: float | None
    """F at the file's vertices (None when some vertex has no VERTEX line)."""
    objective_init: float
    objective_final: float
    init_s: float
    solve_s: float


def solve_g2o(
    g: G2oGraph,
    init: str = "chordal",
    residual: str = "chordal",
    weights: str = "sesync",
    params: LMParams | None = None,
    callback: Callable[[int, float, float], None] | None = None,
) -> SolveReport:
    """Initialise and optimise ``g``; objectives in the SE-Sync convention (see objective.py).
    ``params`` default: exact Hessian (Newton on the chordal cost), cost_tol 1e-8."""
    if params is None:
        params = LMParams(hessian=Hessian.EXACT, cost_tol=1e-8)
    kappa, tau = sesync_weights(g.dim, g.information)

    def F(T: np.ndarray) -> float:
        return sesync_objective(T, g.edges, g.measurements, kappa, tau)

    graph = pose_graph(g, residual, weights)
    t0 = time.perf_counter()
    T0 = initial_poses(g, init)
    t1 = time.perf_counter()
    result = solve(graph, T0, params, callback=callback)
    t2 = time.perf_counter()
    return SolveReport(
        result=result,
        poses_init=T0,
        objective_input=F(g.poses) if g.has_pose.all() else None,
        objective_init=F(T0),
        objective_final=F(result.poses),
        init_s=t1 - t0,
        solve_s=t2 - t1,
    )
