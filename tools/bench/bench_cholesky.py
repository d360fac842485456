"""Benchmark: our supernodal Cholesky vs SuperLU on the damped normal matrices A + μI of the six
g2o graphs (the tier-3 cost of one LM trial).

    .venv/bin/python tools/bench/bench_cholesky.py [DATA_DIR] [--repeat N]

For each graph: A = JᵀJ of the geodesic residual with SE-Sync weights at the chordal
initialisation (vertex 0 fixed), μ = 1e-6·max diag(A). Times (best of --repeat) of
SuperLU (``splu``, MMD on AᵀA+A, symmetric mode, as lm.py's 'superlu' option) and of our
numeric factorisation, plus our one-off analysis and one solve with 1 right-hand side each;
the relative residual ‖(A+μI)x − b‖∞/‖b‖∞ checks both.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # see bench_g2o.py

import numpy as np
import scipy.sparse as sp

from dran_edge.g2o import read_g2o
from dran_edge.lm import _factorize, build_plan, linearize
from dran_edge.pgo import initial_poses, pose_graph
from dran_edge.sparse_cholesky import SymbolicCholesky

FILES = {
    "parking-garage": "parking-garage.g2o",
    "sphere2500": "sphere2500.g2o",
    "torus3D": "torus3D.g2o",
    "CSAIL": "CSAIL.g2o",
    "intel": "input_INTEL_g2o.g2o",
    "manhattan": "input_M3500_g2o.g2o",
}


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
    t_lu, lu = _best(lambda: _factorize(A_mu), repeat)
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


def main(argv: list[str] | None = None) -> int:
    default = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "g2o"
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_dir", nargs="?", default=str(default) if default.exists() else None)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    if args.data_dir is None:
        ap.error("no DATA_DIR given and ../shared/data/g2o does not exist")
    print(f"# best of {args.repeat}; times in ms")
    print(
        f"{'dataset':15s} {'n':>6s} {'nnz(A)':>8s} | {'superlu':>8s} {'solve':>6s} {'resid':>7s} | "
        f"{'analyse':>8s} {'chol':>7s} {'solve':>6s} {'resid':>7s} | {'speed-up':>8s}"
    )
    for name, fname in FILES.items():
        print(_one(name, Path(args.data_dir) / fname, args.repeat), flush=True)
    print("speed-up = SuperLU factorisation time / our numeric factorisation time (same matrix)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
