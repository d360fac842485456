"""The centralized reference of a run: merged.g2o solved centrally, and its SE-Sync costs.

SR_ATE needs the centralized solution and SR_cost the costs F_init, F_k and F* (paper Sec. 6.2,
docs/eval.md). When the run gives no ``out/centralized/`` trajectories, ``merged.g2o`` (the
decentralized final estimate as vertices) is solved with our centralized Schur-LM
(dran_edge.solver.centralized) and mapped back to robots and stamps by ``merged_vertices.csv``.
F_k is the SE-Sync objective at the file's vertices, F_init at the robots' initial estimate
(``<robot>_init.tum`` at the vertex stamps, each object placed by its first observation from
that trajectory: where the decentralized method starts) and F* at the centralized optimum (the
chordal start's value is kept as ``F_chordal``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import InputError
from dran_edge.formats.g2o import G2oGraph, read_g2o
from dran_edge.formats.run_outputs import read_vertex_map

if TYPE_CHECKING:
    from dran_edge.solver.centralized import SolveReport

Track = tuple[np.ndarray, np.ndarray]
"""(stamps_s, T_world_body (n, 4, 4)) of one robot's trajectory."""
VertexMap = dict[int, tuple[str, str, int]]
"""merged.g2o vertex id -> (kind "pose" / "object", robot or object name, stamp_ns)."""


def initial_objective(g: G2oGraph, vmap: VertexMap, inits: dict[str, Track]) -> float | None:
    """F (SE-Sync) of merged.g2o at the robots' initial estimate, or None if one is missing.

    Pose vertices take ``trajectory_init.tum`` interpolated at their stamps; an object vertex
    is placed by its first observation edge (earliest stamp) from that initial trajectory,
    as a robot initialises an object it has not seen before.
    """
    from dran_edge.solver.objective import sesync_objective, sesync_weights

    P0 = g.poses.copy()
    ids = [int(v) for v in g.vertex_ids]
    kind = [vmap.get(v, ("", "", 0)) for v in ids]
    for name, (s_init, T_init) in inits.items():
        sel = np.array([k for k, kd in enumerate(kind) if kd[:2] == ("pose", name)], np.int64)
        if len(sel) == 0:
            continue
        stamps_ns = np.array([kind[k][2] for k in sel], np.int64)
        P0[sel], _ = geo.se3_interpolate(np.round(s_init * 1e9).astype(np.int64), T_init, stamps_ns)
    if any(kd[0] == "pose" and kd[1] not in inits for kd in kind):
        return None
    is_obj = np.array([kd[0] == "object" for kd in kind])
    stamp = np.array(
        [kd[2] if kd[0] == "pose" else np.iinfo(np.int64).max for kd in kind], np.int64
    )
    placed = np.zeros(len(ids), bool)
    obs = [k for k, (a, b) in enumerate(g.edges.tolist()) if is_obj[b] and not is_obj[a]]
    for k in sorted(obs, key=lambda k: stamp[g.edges[k, 0]]):
        a, b = g.edges[k]
        if not placed[b]:
            P0[b] = P0[a] @ g.measurements[k]
            placed[b] = True
    if (is_obj & ~placed).any():
        return None
    kappa, tau = sesync_weights(g.dim, g.information)
    return float(sesync_objective(P0, g.edges, g.measurements, kappa, tau))


def solve_centrally(g: G2oGraph, notes: list[str]) -> tuple[SolveReport, bool]:
    """(report, started from the chordal initialisation) of the centralized solve: from the
    chordal initialisation, else (a disconnected graph) from the graph's values."""
    from dran_edge.solver.centralized import solve_g2o

    try:
        return solve_g2o(g, init="chordal"), True
    except InputError as exc:
        # e.g. a disconnected merged graph (robots that never met, each fixed by its own
        # gauge): chordal initialisation needs one component; start from the file instead.
        notes.append(
            f"centralized: chordal initialisation failed ({exc}); solved from the "
            "decentralized estimate, so F_init is not the chordal one"
        )
        return solve_g2o(g, init="file"), False


def _cost_of(rep: SolveReport, chordal: bool) -> dict[str, Any]:
    """F_k, F* (and F_chordal) of the centralized solve, and how it ended."""
    cost: dict[str, Any] = {
        "source": "merged.g2o (SE-Sync objective, objective.sesync_objective)",
        "F_k": rep.objective_input,
        "F_star": rep.objective_final,
        "centralized_status": str(getattr(rep.result.status, "value", rep.result.status)),
        "centralized_iterations": int(getattr(rep.result, "iterations", -1)),
    }
    if chordal:
        cost["F_chordal"] = rep.objective_init
    return cost


def _robot_tracks(
    g: G2oGraph, vmap: VertexMap, poses: np.ndarray, finals: dict[str, Track], cost: dict[str, Any]
) -> dict[str, Track]:
    """{robot: (stamps_s, T)} of the centralized ``poses``, by merged_vertices.csv.

    Also checks the file's vertex values against the exported final trajectory at the same
    stamps: the largest difference goes into ``cost["merged_vs_trajectory_max_m"]``.
    """
    out = {}
    ids = g.vertex_ids
    for name in finals:
        sel_list = [
            k for k, vid in enumerate(ids) if vmap.get(int(vid), ("", "", 0))[:2] == ("pose", name)
        ]
        if not sel_list:
            continue
        sel = np.array(sel_list)
        stamps = np.array([vmap[int(ids[k])][2] for k in sel], dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        out[name] = (stamps[order] * 1e-9, poses[sel[order]])
        # The file's vertex values against the exported trajectory at the same stamps.
        s_f, T_f = finals[name]
        s_ns = np.round(s_f * 1e9).astype(np.int64)
        pos = np.searchsorted(s_ns, stamps)
        hit = (pos < len(s_ns)) & (s_ns[np.minimum(pos, len(s_ns) - 1)] == stamps)
        if hit.any():
            d = np.linalg.norm(g.poses[sel[hit]][:, :3, 3] - T_f[pos[hit]][:, :3, 3], axis=1)
            worst = max(cost.get("merged_vs_trajectory_max_m", 0.0), float(d.max()))
            cost["merged_vs_trajectory_max_m"] = worst
    return out


def centralized_from_g2o(
    run_dir: Path,
    finals: dict[str, Track],
    notes: list[str],
    inits: dict[str, Track] | None = None,
) -> tuple[dict[str, Track], dict[str, Any]]:
    """Centralized trajectories {robot: (stamps_s, T)} and costs from merged.g2o.

    ``finals`` are the robots' exported final estimates: merged.g2o's vertex values must be
    the same poses (F_k is evaluated there); the largest difference is reported. ``inits``
    are the robots' initial estimates (F_init is evaluated there, see ``initial_objective``).
    What is missing or not comparable is said in ``notes``.
    """
    g2o_path = run_dir / "out" / "merged.g2o"
    if not g2o_path.exists():
        notes.append("SR_ATE / SR_cost: out/merged.g2o absent; no centralized solution")
        return {}, {}
    g = read_g2o(g2o_path)
    if g.dim != 3:
        raise InputError(
            f"expected SE(3) vertices in merged.g2o, got SE({g.dim})", path=str(g2o_path)
        )
    rep, chordal = solve_centrally(g, notes)
    cost = _cost_of(rep, chordal)
    vmap_path = run_dir / "out" / "merged_vertices.csv"
    if not vmap_path.exists():
        notes.append(
            "SR_ATE / SR_cost: out/merged_vertices.csv absent, cannot map merged.g2o "
            "vertices to robots and stamps"
        )
        return {}, cost
    vmap = read_vertex_map(vmap_path)
    F_init = initial_objective(g, vmap, inits or {})
    if F_init is None:
        notes.append(
            "SR_cost: some robot has no out/<robot>/<robot>_init.tum (or an object "
            "no observation), so F_init at the initial estimate is unknown"
        )
    else:
        cost["F_init"] = F_init
    out = _robot_tracks(g, vmap, rep.result.poses, finals, cost)
    if cost.get("merged_vs_trajectory_max_m", 0.0) > 0.01:
        notes.append(
            f"merged.g2o: its vertex values differ from out/<robot>/<robot>.tum by up to "
            f"{cost['merged_vs_trajectory_max_m']:.3f} m at the same stamps (another frame?); "
            "F_k, SR_cost and the centralized solution (SR_ATE) are then not comparable"
        )
    return out, cost
