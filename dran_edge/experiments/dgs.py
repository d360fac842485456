"""The DGS baseline: distributed Gauss–Seidel (Choudhary et al., IJRR 2017), as in Table 1.

Choudhary et al. estimate poses in two linear stages solved by distributed Gauss–Seidel: the
chordal relaxation of the rotations, then the full poses linearised once around that estimate.
The paper runs every method from the same distributed chordal initialisation (Sec. 6.1: "All
methods share the same distributed chordal initialization, with the Gauss-Seidel iterations
capped at 50 for both rotation and translation"), so here DGS is:

1. the shared initialisation (``dist_init.distributed_chordal_init``, same bytes as DRAN's);
2. one Gauss–Newton step on the full poses, linearised at the initial estimate (SE-Sync
   objective, chordal residual): ``H δ = −g`` with ``H = JᵀJ``, solved by block Gauss–Seidel
   over a greedy colouring of the robot graph, successive over-relaxation ω = 1.0 (the paper's
   setting), stopped when no robot's δ changes by more than ``tol`` or after ``max_iterations``
   (50). Robot r's update: ``δ_r ← (1 − ω) δ_r + ω H_rr⁻¹ (−g_r − H_rk δ_k)``, k its anchors.
   Separator values travel as ``InitEntry`` poses ``T_v Exp(δ_v)`` through the same codec;
3. the poses ``T_v Exp(δ_v)``.

No further nonlinear iterations: that is DGS's accuracy limit the paper's table shows.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from dran_edge import geometry as geo
from dran_edge.dran.linear_stage import greedy_colouring
from dran_edge.messages import InitEntry, InitStage


@dataclass(frozen=True)
class DGSParams:
    max_iterations: int = 50
    """Cap on Gauss–Seidel sweeps of the pose stage."""
    tol: float = 1e-3
    """Stop when no robot's δ changes by more than this (max abs entry)."""
    sor: float = 1.0
    """Successive over-relaxation ω (Choudhary et al.: 1.0)."""
    send_tol: float = 1e-5
    """A separator δ is re-sent only when it moved by more than this."""


def _expand(v: np.ndarray, b: int) -> np.ndarray:
    return (v[:, None] * b + np.arange(b)[None]).ravel()


def dgs_pose_stage(
    g, partition, poses: np.ndarray, kappa, tau, exchange, params: DGSParams, gauge: int = 0
) -> tuple[np.ndarray, int]:
    """Step 2 of the module docstring; returns (poses, sweeps)."""
    # Long: one Gauss-Seidel sweep of the DGS baseline as its paper writes it.
    from dran_edge.solver.graph import PoseGraph, kinds_array
    from dran_edge.solver.lm import build_plan, linearize
    from dran_edge.solver.objective import edge_factors

    dof = 6 if g.dim == 3 else 3
    n = g.num_vertices
    fixed = np.zeros(n, bool)
    fixed[gauge] = True
    colour = greedy_colouring(partition)
    R = partition.num_robots
    views = [np.zeros(n * dof) for _ in range(R)]
    blocks = []
    for part in partition.parts:
        e = np.concatenate([part.intra_edges, part.inter_edges])
        block = edge_factors(
            g.dim, g.edges[e], g.measurements[e], g.information[e], "chordal", "sesync"
        )
        # frozen factor dataclasses against Factor's settable attributes (solver/factors.py)
        graph = PoseGraph(g.dim, kinds_array(n, fixed=fixed), (block,))  # type: ignore[arg-type]
        plan = build_plan(graph)
        lin = linearize(graph, plan, poses)
        slot = np.full(n, -1)
        slot[plan.private_vars] = np.arange(plan.private_vars.size)
        own = part.vertices[part.vertices != gauge]
        known = part.anchors
        ro, rk = _expand(slot[own], dof), _expand(slot[known[known != gauge]], dof)
        H = lin.A.tocsr()
        lu = spla.splu(
            sp.csc_matrix(H[ro][:, ro]),
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
        blocks.append(
            {
                "own": own,
                "known": known[known != gauge],
                "lu": lu,
                "H_rk": H[ro][:, rk].tocsr(),
                "g": lin.g_x[ro],
                "delta": np.zeros(ro.size),
            }
        )
    last_sent: dict = {}
    sweeps = 0
    for it in range(params.max_iterations):
        sweeps = it + 1
        max_change = 0.0
        for c in np.unique(colour):
            outgoing = {}
            for r in np.flatnonzero(colour == c).tolist():
                b, view = blocks[r], views[r]
                rhs = -b["g"] - b["H_rk"] @ view[_expand(b["known"], dof)]
                new = (1 - params.sor) * b["delta"] + params.sor * b["lu"].solve(rhs)
                max_change = max(max_change, float(np.max(np.abs(new - b["delta"]), initial=0.0)))
                b["delta"] = new
                view[_expand(b["own"], dof)] = new
                sends = []
                for q in partition.parts[r].neighbours:
                    vs = partition.parts[r].separators_for[q]
                    vs = vs[vs != gauge]
                    D = view.reshape(n, dof)[vs]
                    prev = last_sent.setdefault((r, q), np.full_like(D, np.nan))
                    changed = ~(np.max(np.abs(D - prev), axis=1) <= params.send_tol)
                    prev[changed] = D[changed]
                    T: np.ndarray | list[np.ndarray] = (
                        geo.retract(poses[vs[changed]], D[changed]) if changed.any() else []
                    )
                    entries = [
                        InitEntry(InitStage.TRANSLATION, r, int(v), T[k])
                        for k, v in enumerate(vs[changed].tolist())
                    ]
                    if entries:
                        sends.append((q, entries))
                outgoing[r] = sends
            for r, entries in exchange(InitStage.TRANSLATION, it, outgoing).items():
                for e in entries:
                    v = int(e.keyframe_id)
                    delta = geo.log(geo.inverse(poses[v]) @ np.asarray(e.value, float))
                    views[r][v * dof : (v + 1) * dof] = delta
        if max_change < params.tol:
            break
    out = poses.copy()
    for r, part in enumerate(partition.parts):
        own = blocks[r]["own"]
        out[own] = geo.retract(poses[own], views[r].reshape(n, dof)[own])
    return out, sweeps


def run_g2o_dgs(
    g,
    num_robots: int,
    params: DGSParams = DGSParams(),
    init_params=None,
    links=None,
    partitions=(),
    delta_every: int = 0,
    initial_poses: np.ndarray | None = None,
    partition=None,
) -> dict:
    """DGS on a g2o graph split like Table 1; same bus and byte accounting as ``run_g2o_dran``
    (``links``: the bus's ``BusParams``, default lossless; ``delta_every``: the delta layout,
    see ``Fleet``; ``initial_poses`` (diagnostics): run the pose stage from these instead of
    the distributed init, no init rounds or bytes; ``partition``: this split instead of the
    contiguous one)."""
    from dran_edge.experiments.fleet import split_and_init
    from dran_edge.solver.objective import sesync_objective

    t0 = time.perf_counter()
    kappa, tau, part, fleet, start = split_and_init(
        g, num_robots, partition, links, partitions, delta_every, initial_poses, init_params
    )
    init_rounds, init_bytes = fleet.round, fleet.traffic.bytes_total
    poses, sweeps = dgs_pose_stage(g, part, start, kappa, tau, fleet.init_exchange, params)

    def F(T):
        return sesync_objective(T, g.edges, g.measurements, kappa, tau)

    return {
        "poses": poses,
        "rounds": fleet.round - init_rounds,
        "init_rounds": init_rounds,
        "rounds_total": fleet.round,
        "pose_stage_sweeps": sweeps,
        "bytes_init": init_bytes,
        "bytes_total": fleet.traffic.bytes_total,
        "datagrams": fleet.traffic.datagrams,
        "objective_init": F(start),
        "objective_final": F(poses),
        "local_step_ms_median": None,
        "wall_s": time.perf_counter() - t0,
    }
