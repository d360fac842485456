"""The DGS baseline: distributed Gauss–Seidel (Choudhary et al., IJRR 2017), as in Table 1.

Two linear stages over the same robot split and the same wire codec as DRAN
(``dran_edge.dist_init``): (1) the chordal relaxation of the rotations, projected to SO(d);
(2) the translations with those rotations fixed. Each stage runs block Gauss–Seidel over a greedy
colouring of the robot graph (robots of one colour update together with the newest values),
with successive over-relaxation ω = 1.0 as the paper sets it, and stops when no robot's estimate
changes by more than ``tol`` or after ``max_iterations``. Unlike DRAN's initialisation there is
no segment-alignment warm start (``frame_iterations = 0``): DGS starts every pose at the
identity as in the original method. Choudhary et al.'s optional second pass (one Gauss–Newton
step on the full poses linearised at the stage-2 estimate) is not implemented: the stage-2
estimate is DGS's answer here.
"""

from __future__ import annotations

import time

import numpy as np

from dran_edge.dist_init import InitParams, distributed_chordal_init


def dgs_params(max_iterations: int = 1000, tol: float = 1e-2) -> InitParams:
    """DGS settings: Gauss–Seidel over a colouring, SOR 1.0, no warm start."""
    return InitParams(max_iterations=max_iterations, rotation_tol=tol, translation_tol=tol,
                      send_tol=1e-4, sor=1.0, gauss_seidel=True, frame_iterations=0)


def run_g2o_dgs(g, num_robots: int, params: InitParams | None = None, links=None, seed: int = 0
                ) -> dict:
    """DGS on a g2o graph split like Table 1; same byte accounting as ``run_g2o_dran``."""
    from dran_edge.multiagent import Fleet, LinkModel, adjacency_from_pairs
    from dran_edge.objective import sesync_objective, sesync_weights
    from dran_edge.partition import partition_contiguous

    t0 = time.perf_counter()
    kappa, tau = sesync_weights(g.dim, g.information)
    part = partition_contiguous(g.edges, g.num_vertices, num_robots)
    A = adjacency_from_pairs(num_robots, part.neighbour_pairs())
    fleet = Fleet([], A, links or LinkModel(), seed=seed)
    steps: list[float] = []
    res = distributed_chordal_init(g.dim, g.num_vertices, g.edges, g.measurements, kappa, tau,
                                   part, fleet.init_exchange, params or dgs_params())
    F = sesync_objective(res.poses, g.edges, g.measurements, kappa, tau)
    return {
        "poses": res.poses,
        "rounds": fleet.round,
        "rotation_iterations": res.rotation_iterations,
        "translation_iterations": res.translation_iterations,
        "bytes_total": fleet.traffic.bytes_total,
        "datagrams": fleet.traffic.datagrams,
        "objective_init": float("nan"),
        "objective_final": F,
        "local_step_ms_median": float(np.median(steps)) if steps else float("nan"),
        "wall_s": time.perf_counter() - t0,
    }
