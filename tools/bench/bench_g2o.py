"""Benchmark: our centralised Schur-LM vs GTSAM's Levenberg-Marquardt on the paper's six g2o graphs.

    .venv/bin/python tools/bench/bench_g2o.py [DATA_DIR] [--only NAME ...] [--repeat N]
    .venv/bin/python tools/bench/bench_g2o.py --quick     # two small generated graphs, seconds

DATA_DIR defaults to ../shared/data/g2o when it exists. GTSAM's arm runs when gtsam is installed
(``--no-gtsam`` skips it; ``--quick`` skips it when it is missing). For every graph, in the same process:
read it, compute the chordal initialisation once, then time (best of --repeat runs)

Our linear solver is 'auto' (supernodal Cholesky on the 3D graphs, SuperLU on the 2D ones).

- ours, geodesic residual, SE-Sync isotropic weights, Gauss-Newton model (M = JᵀJ + μI), stopping
  at a relative cost decrease < 1e-5 (GTSAM's default relativeErrorTol), the same rule as GTSAM;
- ours, chordal residual, SE-Sync weights, exact Hessian (damped Newton), stopping at 1e-8 (the
  CLI default): the minimiser of the SE-Sync objective F itself (paper Table 1);
- GTSAM LM (default parameters: lambda0 1e-5, factor 10, relative/absolute error tol 1e-5) with
  BetweenFactorPose{2,3} and the same isotropic weights (precision τ on translation, 2κ on
  rotation, which equals SE-Sync's F to first order), from the same initial values, vertex 0 fixed
  by a constrained prior.

Times are the optimiser only (ours: solve() including its structure plan; GTSAM: optimize()),
not file reading, initialisation or graph building. F is the SE-Sync objective of each result.
gtsam is a benchmark-only dependency (pip install gtsam, or the project's 'bench' extra).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

# Our frontal matrices are small: one BLAS thread per process (threaded OpenBLAS oversubscribes
# a busy 2-core machine badly). _common sets it; it must come before numpy. GTSAM is not affected.
import _common
import numpy as np

from dran_edge.formats.g2o import read_g2o
from dran_edge.solver.centralized import initial_poses, pose_graph
from dran_edge.solver.lm import LMParams, solve
from dran_edge.solver.objective import sesync_objective, sesync_weights

# F* of the data README (exact LM, ‖grad‖ ≤ 2e-4); the paper prints them rounded.
DATASETS = _common.G2O_GRAPHS


def _gtsam_problem(gtsam, g, T0, kappa, tau):
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    if g.dim == 3:
        for k in range(g.num_vertices):
            values.insert(k, gtsam.Pose3(T0[k]))
        for e in range(g.num_edges):
            i, j = (int(x) for x in g.edges[e])
            noise = gtsam.noiseModel.Diagonal.Precisions(np.r_[[2 * kappa[e]] * 3, [tau[e]] * 3])
            graph.add(gtsam.BetweenFactorPose3(i, j, gtsam.Pose3(g.measurements[e]), noise))
        graph.add(
            gtsam.PriorFactorPose3(0, gtsam.Pose3(T0[0]), gtsam.noiseModel.Constrained.All(6))
        )
    else:

        def pose2(T):
            return gtsam.Pose2(T[0, 2], T[1, 2], np.arctan2(T[1, 0], T[0, 0]))

        for k in range(g.num_vertices):
            values.insert(k, pose2(T0[k]))
        for e in range(g.num_edges):
            i, j = (int(x) for x in g.edges[e])
            noise = gtsam.noiseModel.Diagonal.Precisions(np.r_[[tau[e]] * 2, [2 * kappa[e]]])
            graph.add(gtsam.BetweenFactorPose2(i, j, pose2(g.measurements[e]), noise))
        graph.add(gtsam.PriorFactorPose2(0, pose2(T0[0]), gtsam.noiseModel.Constrained.All(3)))
    return graph, values


def _gtsam_run(gtsam, graph, values, g):
    params = gtsam.LevenbergMarquardtParams()
    t = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    res = opt.optimize()
    dt = time.perf_counter() - t
    get = res.atPose3 if g.dim == 3 else res.atPose2
    T = np.array([get(k).matrix() for k in range(g.num_vertices)])
    return dt, opt.iterations(), T


def _ours(g, T0, residual, cost_tol, hessian):
    graph = pose_graph(g, residual, "sesync")
    t = time.perf_counter()
    res = solve(graph, T0, LMParams(cost_tol=cost_tol, linear_solver="auto", hessian=hessian))
    return time.perf_counter() - t, res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_dir", nargs="?", default=_common.default_g2o_dir())
    ap.add_argument("--only", nargs="+", choices=list(DATASETS), help="a subset of the graphs")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs per solver (best is kept)")
    ap.add_argument("--no-gtsam", action="store_true", help="skip GTSAM")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="two small generated graphs, one run each: checks the script, not speed",
    )
    args = ap.parse_args(argv)
    if args.quick:
        with tempfile.TemporaryDirectory() as tmp:
            return _run(args, tmp, _common.quick_g2o_graphs(tmp), 1, gtsam_required=False)
    if args.data_dir is None:
        ap.error("no DATA_DIR given and ../shared/data/g2o does not exist")
    graphs = {k: DATASETS[k] for k in args.only or DATASETS}
    return _run(args, args.data_dir, graphs, args.repeat, gtsam_required=True)


def _run(
    args, data_dir: str, graphs: dict[str, tuple[str, float]], repeat: int, gtsam_required: bool
) -> int:
    gtsam = None
    if not args.no_gtsam:
        try:
            import gtsam
        except ImportError:
            if gtsam_required:
                print("gtsam is not installed (pip install gtsam); use --no-gtsam", file=sys.stderr)
                return 3
            print("# gtsam is not installed: its columns stay empty")
    print(f"# cpu: {os.cpu_count()} cores; numpy {np.__version__}; best of {repeat} runs")
    head = (
        f"{'dataset':15s} {'n':>5s} {'m':>5s} {'F_init':>11s} | {'geo s':>6s} {'it':>3s} "
        f"{'F geo':>12s} {'relF*':>8s} | {'gtsam s':>7s} {'it':>3s} {'F gtsam':>12s} "
        f"{'relF*':>8s} | {'ratio':>5s} | {'chord s':>7s} {'it':>3s} {'F chordal':>12s} {'relF*':>8s} "
        f"{'ratio':>5s}"
    )
    print(head)
    print("-" * len(head))
    for name, (fname, F_star) in graphs.items():
        g = read_g2o(Path(data_dir) / fname)
        kappa, tau = sesync_weights(g.dim, g.information)

        def F(T, g=g, kappa=kappa, tau=tau):
            return sesync_objective(T, g.edges, g.measurements, kappa, tau)

        T0 = initial_poses(g, "chordal")
        geo_runs = [_ours(g, T0, "geodesic", 1e-5, "gauss_newton") for _ in range(repeat)]
        t_geo = min(r[0] for r in geo_runs)
        res_geo = geo_runs[0][1]
        cho_runs = [_ours(g, T0, "chordal", 1e-8, "exact") for _ in range(repeat)]
        t_cho = min(r[0] for r in cho_runs)
        res_cho = cho_runs[0][1]
        if gtsam is not None:
            graph, values = _gtsam_problem(gtsam, g, T0, kappa, tau)
            gt_runs = [_gtsam_run(gtsam, graph, values, g) for _ in range(repeat)]
            t_gt = min(r[0] for r in gt_runs)
            it_gt, F_gt = gt_runs[0][1], F(gt_runs[0][2])
            gt_txt = f"{t_gt:7.3f} {it_gt:3d} {F_gt:12.6f} {(F_gt - F_star) / F_star:8.1e} | {t_geo / t_gt:5.2f}"
            cho_ratio = f"{t_cho / t_gt:5.2f}"
        else:
            gt_txt = f"{'-':>7s} {'-':>3s} {'-':>12s} {'-':>8s} | {'-':>5s}"
            cho_ratio = f"{'-':>5s}"
        F_geo, F_cho = F(res_geo.poses), F(res_cho.poses)
        print(
            f"{name:15s} {g.num_vertices:5d} {g.num_edges:5d} {F(T0):11.4f} | {t_geo:6.3f} "
            f"{res_geo.iterations:3d} {F_geo:12.6f} {(F_geo - F_star) / F_star:8.1e} | {gt_txt} | "
            f"{t_cho:7.3f} {res_cho.iterations:3d} {F_cho:12.6f} {(F_cho - F_star) / F_star:8.1e} "
            f"{cho_ratio}",
            flush=True,
        )
    print(
        "ratio = our wall time / GTSAM's (optimiser only; geodesic and chordal columns each "
        "against the same GTSAM run); relF* = (F - F*) / F*"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
