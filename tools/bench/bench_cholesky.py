"""Benchmark: our supernodal Cholesky vs SuperLU on the damped normal matrices A + μI of the six
g2o graphs (the tier-3 cost of one LM trial).

    .venv/bin/python tools/bench/bench_cholesky.py [DATA_DIR] [--repeat N] [--baseline FILE]
    .venv/bin/python tools/bench/bench_cholesky.py --quick   # two small generated graphs, seconds

For each graph: A = JᵀJ of the geodesic residual with SE-Sync weights at the chordal
initialisation (vertex 0 fixed), μ = 1e-6·max diag(A). Times (best of --repeat) of
SuperLU (``splu``, MMD on AᵀA+A, symmetric mode, as lm.py's 'superlu' option) and of our
numeric factorisation, plus our one-off analysis and one solve with 1 right-hand side each;
the relative residual ‖(A+μI)x − b‖∞/‖b‖∞ checks both.

``--baseline FILE`` (another version of dran_edge/solver/sparse_cholesky.py, e.g. from
``git show REV:dran_edge/solver/sparse_cholesky.py > /tmp/base.py``) adds an A/B table on the SE(3)
graphs: analysis, factorisation and solve of both versions on the same matrix, and whole LM solves
(lm.solve with linear_solver='cholesky': chordal residual with the exact Hessian to 1e-8 as the
CLI, and geodesic Gauss–Newton to 1e-5) with each version swapped into dran_edge.solver.schur, interleaved,
best of --repeat. These times are CPU seconds of this process (time.process_time), which a
shared, oversubscribed machine disturbs far less than wall time; F of both results is compared.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
import time
from pathlib import Path

import _common  # one BLAS thread, before numpy (see bench_g2o.py)
import numpy as np
import scipy.sparse as sp

import dran_edge.solver.sparse_cholesky as ours
from dran_edge.formats.g2o import read_g2o
from dran_edge.solver import lm, schur
from dran_edge.solver.centralized import initial_poses, pose_graph
from dran_edge.solver.lm import LMParams, build_plan, linearize, superlu_factorize
from dran_edge.solver.objective import sesync_objective, sesync_weights
from dran_edge.solver.sparse_cholesky import SymbolicCholesky

FILES = {name: fname for name, (fname, _) in _common.G2O_GRAPHS.items()}


def _best(fn, repeat):
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def _one(name: str, path: Path, repeat: int) -> str:
    g = read_g2o(path)
    graph = pose_graph(g, "geodesic", "sesync")
    plan = build_plan(graph)
    lin = linearize(graph, plan, initial_poses(g, "chordal"))
    A = lin.A
    mu = 1e-6 * float(A.diagonal().max())
    A_mu = sp.csc_matrix(A + mu * sp.identity(plan.n_u, format="csc"))
    b = np.random.default_rng(0).normal(size=plan.n_u)
    t_lu, lu = _best(lambda: superlu_factorize(A_mu), repeat)
    t_lus, x1 = _best(lambda: lu.solve(b), repeat)
    t_an, sym = _best(
        lambda: SymbolicCholesky(plan.A_indptr, plan.A_indices, plan.n_u, plan.dof),
        max(1, repeat // 2),
    )
    t_ch, ch = _best(lambda: sym.factorize(A.data, mu), repeat)
    t_chs, x2 = _best(lambda: ch.solve(b), repeat)

    def res(x):
        return np.abs(A_mu @ x - b).max() / np.abs(b).max()

    return (
        f"{name:15s} {plan.n_u:6d} {A.nnz:8d} | {1e3 * t_lu:8.1f} {1e3 * t_lus:6.1f} "
        f"{res(x1):7.0e} | {1e3 * t_an:8.1f} {1e3 * t_ch:7.1f} {1e3 * t_chs:6.1f} "
        f"{res(x2):7.0e} | {t_lu / t_ch:7.2f}x"
    )


def _cpu_best(fn, repeat):
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.process_time()
        out = fn()
        best = min(best, time.process_time() - t)
    return best, out


def _load_baseline(path: str):
    spec = importlib.util.spec_from_file_location("sparse_cholesky_baseline", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def _ab(name: str, path: Path, base, repeat: int) -> list[str]:
    """A/B of our module against ``base`` on one graph (CPU ms / s, best of ``repeat``)."""
    g = read_g2o(path)
    T0 = initial_poses(g, "chordal")
    graph = pose_graph(g, "geodesic", "sesync")
    plan = build_plan(graph)
    A = linearize(graph, plan, T0).A
    mu = 1e-6 * float(A.diagonal().max())
    b = np.random.default_rng(0).normal(size=plan.n_u)
    row = {}
    args = (plan.A_indptr, plan.A_indices, plan.n_u, plan.dof)
    for label, mod in (("base", base), ("ours", ours)):
        t_an, sym = _cpu_best(lambda mod=mod: mod.SymbolicCholesky(*args), repeat)
        t_ch, ch = _cpu_best(lambda sym=sym: sym.factorize(A.data, mu), repeat)
        t_s, x = _cpu_best(lambda ch=ch: ch.solve(b), repeat)
        row[label] = (t_an, t_ch, t_s, x, sym.num_supernodes)
    dx = np.abs(row["ours"][3] - row["base"][3]).max() / np.abs(row["base"][3]).max()
    kappa, tau = sesync_weights(g.dim, g.information)
    runs = {}
    cases = (("chordal", 1e-8, "exact"), ("geodesic", 1e-5, "gauss_newton"))
    saved = schur.SymbolicCholesky, schur.NotPositiveDefinite
    try:
        for _ in range(repeat):
            for label, mod in (("base", base), ("ours", ours)):
                schur.SymbolicCholesky, schur.NotPositiveDefinite = (
                    mod.SymbolicCholesky,
                    mod.NotPositiveDefinite,
                )
                for residual, tol, hessian in cases:
                    gr = pose_graph(g, residual, "sesync")
                    params = LMParams(cost_tol=tol, linear_solver="cholesky", hessian=hessian)
                    t = time.process_time()
                    res = lm.solve(gr, T0, params)
                    dt = time.process_time() - t
                    F = sesync_objective(res.poses, g.edges, g.measurements, kappa, tau)
                    prev = runs.get((label, residual), (float("inf"), F))
                    runs[(label, residual)] = (min(prev[0], dt), F)
    finally:
        schur.SymbolicCholesky, schur.NotPositiveDefinite = saved
    out = []
    (ba, bc, bs, _, bn), (oa, oc, os_, _, on) = row["base"], row["ours"]
    out.append(
        f"{name:15s} {bn:5d} {on:5d} | {1e3 * ba:6.1f} {1e3 * oa:6.1f} | {1e3 * bc:6.1f} "
        f"{1e3 * oc:6.1f} {bc / oc:5.2f}x | {1e3 * bs:5.1f} {1e3 * os_:5.1f} | {dx:7.0e}"
    )
    for residual, _, _ in cases:
        (tb, Fb), (to, Fo) = runs[("base", residual)], runs[("ours", residual)]
        out.append(
            f"{'':15s} LM {residual:8s}: base {tb:6.3f} s, ours {to:6.3f} s, ours/base "
            f"{to / tb:5.3f}; F {Fo:.10g}, |ΔF|/F {abs(Fo - Fb) / Fb:.0e}"
        )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_dir", nargs="?", default=_common.default_g2o_dir())
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--baseline", help="another sparse_cholesky.py to compare against (A/B)")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="two small generated graphs, one run each: checks the script, not speed",
    )
    args = ap.parse_args(argv)
    if args.quick:
        with tempfile.TemporaryDirectory() as tmp:
            files = {k: f for k, (f, _) in _common.quick_g2o_graphs(tmp).items()}
            return _run(args, tmp, files, ["quick-se3"], 1)
    if args.data_dir is None:
        ap.error("no DATA_DIR given and ../shared/data/g2o does not exist")
    return _run(
        args, args.data_dir, FILES, ["parking-garage", "sphere2500", "torus3D"], args.repeat
    )


def _run(args, data_dir: str, files: dict[str, str], ab_names: list[str], repeat: int) -> int:
    print(f"# best of {repeat}; times in ms")
    print(
        f"{'dataset':15s} {'n':>6s} {'nnz(A)':>8s} | {'superlu':>8s} {'solve':>6s} {'resid':>7s} | "
        f"{'analyse':>8s} {'chol':>7s} {'solve':>6s} {'resid':>7s} | {'speed-up':>8s}"
    )
    for name, fname in files.items():
        print(_one(name, Path(data_dir) / fname, repeat), flush=True)
    print("speed-up = SuperLU factorisation time / our numeric factorisation time (same matrix)")
    if args.baseline:
        base = _load_baseline(args.baseline)
        print(f"\n# A/B against {args.baseline}: CPU time (process_time), best of {repeat}")
        print(
            f"{'dataset':15s} {'sn b':>5s} {'sn o':>5s} | {'analyse b/o ms':>13s} | "
            f"{'factor b/o ms':>13s} {'b/o':>6s} | {'solve b/o':>11s} | {'Δx':>7s}"
        )
        for name in ab_names:
            for line in _ab(name, Path(data_dir) / files[name], base, repeat):
                print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
