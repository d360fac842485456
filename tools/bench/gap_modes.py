"""Where is DRAN's remaining gap after N rounds of a Table 1 run? (diagnostic)

Usage: .venv/bin/python tools/bench/gap_modes.py DATASET.g2o F_STAR [--rounds 200] [--chunk 40]

Runs the Table 1 setup (``multiagent.table1_setup``) for ``--rounds`` rounds with both stopping
tests off, then asks two questions of the merged estimate:

1. Would a coarse correction help? The best rigid motion per robot (and, separately, per chunk
   of ``--chunk`` consecutive poses) is fitted to the edges between robots (chunks) by
   ``scipy.optimize.least_squares``; F before and after is printed. A two-level method (block
   iteration + coarse solve) pays only if this removes a large part of the gap.
2. What does the error look like? Positions are aligned to the centralized optimum
   (``pgo.solve_g2o``) by the best rotation + translation; the mean error per robot
   (separators / interior) and along the trajectory (20 bins) is printed, in metres.
3. Is the gap a different basin, or a biased fixed point? The centralized LM is run from the
   distributed init (same basin if it reaches F*), and DRAN is started at the centralized
   optimum for ``--rounds`` rounds (a fixed point if F stays at F*: quantisation, send threshold
   and stale anchors do not pull it away).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import dataclasses

import numpy as np
from scipy.optimize import least_squares

from dran_edge import geometry as geo
from dran_edge.formats.g2o import read_g2o
from dran_edge.solver.lm import LMParams, solve
from dran_edge.experiments.fleet import run_g2o_dran, table1_setup
from dran_edge.solver.objective import sesync_objective, sesync_weights
from dran_edge.dran.partition import partition_contiguous
from dran_edge.solver.centralized import pose_graph, solve_g2o


def rigid_corrected(g, poses, group, kappa, tau):
    """F after the best rigid motion T_g (world frame, T ← T_g T) per group label."""
    d = g.dim
    dof = 3 if d == 2 else 6
    n_groups = int(group.max()) + 1
    cross = group[g.edges[:, 0]] != group[g.edges[:, 1]]
    E, M = g.edges[cross], g.measurements[cross]
    sk, st = np.sqrt(kappa[cross])[:, None, None], np.sqrt(tau[cross])[:, None]

    def moved(params):
        T = geo.exp(params.reshape(n_groups, dof))  # (groups, D, D)
        return T[group] @ poses

    def residual(params):
        Q = moved(params)
        Pi, Pj = Q[E[:, 0]], Q[E[:, 1]]
        rot = (Pj[:, :d, :d] - Pi[:, :d, :d] @ M[:, :d, :d]) * sk
        trans = (Pj[:, :d, d] - Pi[:, :d, d] - (Pi[:, :d, :d] @ M[:, :d, d, None])[:, :, 0]) * st
        return np.concatenate([rot.ravel(), trans.ravel()])

    sol = least_squares(residual, np.zeros(n_groups * dof), method="trf", x_scale="jac")
    return sesync_objective(moved(sol.x), g.edges, g.measurements, kappa, tau)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("f_star", type=float, help="the centralized optimum (docs/benchmarks.md)")
    ap.add_argument("--robots", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=200)
    ap.add_argument("--chunk", type=int, default=40, help="poses per rigid chunk")
    args = ap.parse_args(argv)
    g = read_g2o(args.dataset)
    d = g.dim
    kappa, tau = sesync_weights(d, g.information)
    part = partition_contiguous(g.edges, g.num_vertices, args.robots)
    owner = np.zeros(g.num_vertices, np.int64)
    for r, p in enumerate(part.parts):
        owner[p.vertices] = r
    cfg, kw = table1_setup(d)
    cfg = dataclasses.replace(cfg, eps_u=0.0, eps_cost_rel=0.0)
    final = {}

    def callback(k, fleet):
        if k == 1:
            final["after_init"] = merged(fleet)
        if k == args.rounds:
            final["poses"] = merged(fleet)

    def merged(fleet):
        poses = np.zeros((g.num_vertices, d + 1, d + 1))
        for r, p in enumerate(part.parts):
            poses[p.vertices] = fleet.agents[r].x
        return poses

    run_g2o_dran(g, args.robots, cfg, max_rounds=args.rounds, callback=callback, **kw)
    poses = final["poses"]

    def gap(F):
        return f"{F:.6f} ({100 * (F / args.f_star - 1):.3f} %)"

    F = sesync_objective(poses, g.edges, g.measurements, kappa, tau)
    print(f"round {args.rounds}: F {gap(F)}")
    print(f"  best rigid motion per robot: F {gap(rigid_corrected(g, poses, owner, kappa, tau))}")
    chunks = np.arange(g.num_vertices) // args.chunk
    print(f"  best rigid motion per {args.chunk}-pose chunk ({chunks.max() + 1} chunks): "
          f"F {gap(rigid_corrected(g, poses, chunks, kappa, tau))}")

    opt = solve_g2o(g).result.poses
    a, b = poses[:, :d, d], opt[:, :d, d]
    U, _, Vt = np.linalg.svd((b - b.mean(0)).T @ (a - a.mean(0)))
    S = np.eye(d)
    S[-1, -1] = np.sign(np.linalg.det(U @ Vt))
    R = U @ S @ Vt
    err = np.linalg.norm((a - a.mean(0)) @ R.T + b.mean(0) - b, axis=1)
    cross = owner[g.edges[:, 0]] != owner[g.edges[:, 1]]
    sep = np.zeros(g.num_vertices, bool)
    sep[g.edges[cross].ravel()] = True
    print(f"position error against the centralized optimum (extent {np.ptp(b, axis=0).round(1)} m):")
    for r in range(args.robots):
        m = owner == r
        interior = f"{err[m & ~sep].mean():.3f}" if (m & ~sep).any() else "-"
        print(f"  robot {r}: {m.sum()} poses, {(m & sep).sum()} separators; mean {err[m].mean():.3f}"
              f" m (separators {err[m & sep].mean():.3f}, interior {interior}), max {err[m].max():.3f}")
    bins = np.array_split(np.arange(g.num_vertices), 20)
    print("  along the trajectory (20 bins):", " ".join(f"{err[i].mean():.2f}" for i in bins))

    lm = solve(pose_graph(g, "chordal", "sesync"), final["after_init"],
               LMParams(hessian="exact", cost_tol=1e-10))
    F_lm = sesync_objective(lm.poses, g.edges, g.measurements, kappa, tau)
    print(f"centralized LM from the distributed init (+1 DRAN round): F {gap(F_lm)} after "
          f"{lm.iterations} iterations")
    res = run_g2o_dran(g, args.robots, cfg, max_rounds=args.rounds, initial_poses=opt, **kw)
    print(f"DRAN started at the centralized optimum, after {res['rounds']} rounds: "
          f"F {gap(res['objective_final'])}, {res['bytes_total'] / 1e6:.3f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
