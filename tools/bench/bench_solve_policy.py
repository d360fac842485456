"""Benchmark: the centralised solver's Newton damping before/after, with GTSAM as a reference.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python tools/bench/bench_solve_policy.py [--quick]
        [--table1 [DATA_DIR]] [--no-gtsam] [FILE.g2o ...]

For each graph, in one process and from the same chordal initialisation: our Schur-LM with the
exact Hessian (chordal residual, SE-Sync weights, cost_tol 1e-8, max 100 iterations — what
``dran-edge solve`` runs) with ``newton_damping='shared'`` (one μ for the Newton and the
Gauss-Newton model, the policy before) and ``'separate'`` (now), side by side: iterations,
damped solves, seconds, F and the ratio of times; then GTSAM's LM (defaults, relative error tol
1e-5, geodesic BetweenFactorPose2/3 with the same isotropic weights) as a reference.

Graphs: generated long street-grid trajectories (``dran_edge.sim.graphgen.city_graph``: 15 000
poses, 3 % loop closures, σ 0.1 m / 0.08 rad, and a noisier 0.2 m / 0.15 rad one; ``--quick``:
2000 poses), the paper's six graphs with ``--table1``, and any g2o files given.
gtsam is a benchmark-only dependency (the project's 'bench' extra).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_g2o import DATASETS, _gtsam_problem, _gtsam_run  # noqa: E402

from dran_edge.formats.g2o import read_g2o  # noqa: E402
from dran_edge.sim.graphgen import city_graph  # noqa: E402
from dran_edge.solver.lm import LMParams, solve  # noqa: E402
from dran_edge.solver.objective import sesync_objective, sesync_weights  # noqa: E402
from dran_edge.solver.centralized import initial_poses, pose_graph  # noqa: E402


def _generated(n: int):
    for st, sr in ((0.1, 0.08), (0.2, 0.15)):
        g, _ = city_graph(n, loop_fraction=0.03, sigma_t_m=st, sigma_r_rad=sr, seed=1)
        yield f"city{n}_s{st:g}_{sr:g}", g


def _ours(graph, T0, policy):
    t = time.perf_counter()
    res = solve(
        graph,
        T0,
        LMParams(hessian="exact", cost_tol=1e-8, linear_solver="auto", newton_damping=policy),
    )
    return time.perf_counter() - t, res


def main(argv: list[str] | None = None) -> int:
    default = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "g2o"
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="*", help="extra g2o files")
    ap.add_argument("--quick", action="store_true", help="2000-pose generated graphs")
    ap.add_argument(
        "--table1",
        nargs="?",
        const=str(default),
        metavar="DATA_DIR",
        help="also the paper's six graphs (default ../shared/data/g2o)",
    )
    ap.add_argument("--no-generated", action="store_true", help="skip the generated graphs")
    ap.add_argument("--no-gtsam", action="store_true")
    args = ap.parse_args(argv)
    gtsam = None
    if not args.no_gtsam:
        try:
            import gtsam
        except ImportError:
            print("gtsam is not installed (pip install gtsam); use --no-gtsam", file=sys.stderr)
            return 3
    graphs = []
    if not args.no_generated:
        graphs += list(_generated(2000 if args.quick else 15000))
    if args.table1:
        graphs += [(name, Path(args.table1) / f) for name, (f, _) in DATASETS.items()]
    graphs += [(Path(f).stem, Path(f)) for f in args.files]
    print(f"# cpu: {os.cpu_count()} cores; exact Hessian, cost_tol 1e-8, max 100 iterations")
    print(
        "| graph | n / m | F_init | before (shared μ): it / solves / s / F | after (separate "
        "μ_N): it / solves / s / F | time after/before | GTSAM: it / s / F |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, g in graphs:
        if isinstance(g, Path):
            g = read_g2o(g)
        kappa, tau = sesync_weights(g.dim, g.information)

        def F(T, g=g, kappa=kappa, tau=tau):
            return sesync_objective(T, g.edges, g.measurements, kappa, tau)

        T0 = initial_poses(g, "chordal")
        graph = pose_graph(g, "chordal", "sesync")
        cols = []
        times = []
        for policy in ("shared", "separate"):
            dt, res = _ours(graph, T0, policy)
            times.append(dt)
            cap = "*" if res.status.value == "max_iterations" else ""
            cols.append(f"{res.iterations}{cap} / {res.trials} / {dt:.2f} / {F(res.poses):.8g}")
        gt = "—"
        if gtsam is not None:
            fg, values = _gtsam_problem(gtsam, g, T0, kappa, tau)
            dt_g, it_g, T_g = _gtsam_run(gtsam, fg, values, g)
            gt = f"{it_g} / {dt_g:.2f} / {F(T_g):.8g}"
        print(
            f"| {name} | {g.num_vertices} / {g.num_edges} | {F(T0):.6g} | {cols[0]} | "
            f"{cols[1]} | {times[1] / times[0]:.2f} | {gt} |",
            flush=True,
        )
    print("\n'*' = stopped at the 100-iteration cap. solves = damped factorisations (trials).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
