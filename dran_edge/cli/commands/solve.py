"""``dran-edge solve``: optimise a g2o pose graph with the centralised Schur–LM solver."""

from __future__ import annotations

import argparse
import json
import os
import time

from dran_edge.config import Residual
from dran_edge.solver.choices import Hessian, LinearSolver

HELP = "optimise a g2o pose graph (centralised Schur-LM)"


def build_parser(prog: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description=(
            "Read a g2o pose graph (VERTEX_SE2/EDGE_SE2 or VERTEX_SE3:QUAT/EDGE_SE3:QUAT, FIX), "
            "initialise it, optimise it with Levenberg-Marquardt and write the optimised vertices. "
            "Objectives are reported in the SE-Sync convention F (no 1/2; docs/g2o.md)."
        ),
    )
    parser.add_argument("input", metavar="IN.g2o", help="the pose graph to optimise")
    parser.add_argument(
        "-o",
        "--out",
        metavar="OUT.g2o",
        required=True,
        help="where to write the optimised graph (same format as the input)",
    )
    parser.add_argument(
        "--init",
        choices=("chordal", "file", "odometry"),
        default="chordal",
        help="initial values: chordal relaxation (default), the file's VERTEX lines, "
        "or odometry composed along a spanning tree",
    )
    parser.add_argument(
        "--residual",
        choices=sorted(m.value for m in Residual),
        default="chordal",
        help="edge residual (paper eq. 2); chordal with sesync weights minimises "
        "F exactly (default)",
    )
    parser.add_argument(
        "--weights",
        choices=("sesync", "information"),
        default="sesync",
        help="edge weights: SE-Sync's isotropic kappa/tau (default) or the full "
        "information matrices (geodesic residual only)",
    )
    parser.add_argument(
        "--max-iterations",
        type=int,
        default=100,
        metavar="N",
        help="cap on accepted LM steps (default 100)",
    )
    parser.add_argument(
        "--cost-tol",
        type=float,
        default=1e-8,
        metavar="REL",
        help="stop when a step lowers the cost by less than REL relative (default 1e-8)",
    )
    parser.add_argument(
        "--hessian",
        choices=sorted(m.value for m in Hessian),
        default="exact",
        help="LM model: exact (adds the chordal residual's second-order terms, "
        "Gauss-Newton where that is indefinite; default) or gauss_newton (J'J)",
    )
    parser.add_argument(
        "--linear-solver",
        choices=sorted(m.value for m in LinearSolver),
        default="auto",
        help="sparse factorisation of the damped normal equations: supernodal "
        "cholesky, superlu, or auto (cholesky for large 3D graphs; default)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    return parser


def run(args: argparse.Namespace) -> int:
    # The supernodal Cholesky makes many small BLAS calls: one BLAS thread (only effective when
    # numpy is not loaded yet, i.e. from the command line).
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from dran_edge.cli.progress import note
    from dran_edge.errors import InputError
    from dran_edge.formats.g2o import read_g2o, write_g2o
    from dran_edge.solver.lm import LMParams, LMStatus
    from dran_edge.solver.centralized import solve_g2o

    if args.weights == "information" and args.residual == "chordal":
        raise InputError(
            "--weights information needs --residual geodesic; the chordal residual "
            "is weighted isotropically (--weights sesync)"
        )
    if args.max_iterations < 1 or not args.cost_tol > 0:
        raise InputError("--max-iterations must be ≥ 1 and --cost-tol > 0")
    t0 = time.perf_counter()
    graph = read_g2o(args.input)

    def progress(iteration: int, cost: float, mu: float) -> None:
        note(f"  iteration {iteration:3d}  F = {2 * cost:.10g}  mu = {mu:.3g}")

    note(
        f"{args.input}: {graph.num_vertices} vertices, {graph.num_edges} edges, "
        f"SE({graph.dim}); init {args.init}, residual {args.residual}, weights {args.weights}"
    )
    params = LMParams(
        max_iterations=args.max_iterations,
        cost_tol=args.cost_tol,
        linear_solver=args.linear_solver,
        hessian=args.hessian,
    )
    try:
        report = solve_g2o(graph, args.init, args.residual, args.weights, params, progress)
    except InputError as exc:
        if exc.path is not None:
            raise
        raise InputError(str(exc), path=args.input) from None
    write_g2o(args.out, graph, report.result.poses)
    wall_s = time.perf_counter() - t0
    result = report.result
    out = {
        "input": args.input,
        "output": args.out,
        "dim": graph.dim,
        "vertices": graph.num_vertices,
        "edges": graph.num_edges,
        "init": args.init,
        "residual": args.residual,
        "weights": args.weights,
        "objective_input": report.objective_input,
        "objective_init": report.objective_init,
        "objective_final": report.objective_final,
        "cost_final": result.cost,
        "iterations": result.iterations,
        "trials": result.trials,
        "status": result.status.value,
        "reason": result.reason,
        "init_s": report.init_s,
        "solve_s": report.solve_s,
        "wall_s": wall_s,
    }
    if args.json:
        print(json.dumps(out))
    else:
        f_in = "n/a" if report.objective_input is None else f"{report.objective_input:.10g}"
        print(
            f"F input {f_in}  init {report.objective_init:.10g}  final "
            f"{report.objective_final:.10g}"
        )
        print(
            f"{result.status.value} after {result.iterations} iterations ({result.reason}); "
            f"{wall_s:.2f} s; wrote {args.out}"
        )
    return 0 if result.status in (LMStatus.CONVERGED, LMStatus.MAX_ITERATIONS) else 1
