"""Would a Krylov method beat block SOR on a Table 1 split? A centralized check (diagnostic)

Usage:
  .venv/bin/python tools/bench/block_solvers.py DATASET.g2o F_STAR [--system gn|rotation]
      [--iterations 200] [--gn-steps 2] [--omega 1.0 1.9 1.97]

Builds, in one process, a linear system whose distributed solution costs DRAN or the init its
rounds, splits the unknowns like Table 1 (contiguous segments, 5 robots), factorises each robot's
diagonal block (what a robot's local solve does) and compares, iteration by iteration:

- block SOR in robot order with over-relaxation ω, the first sweep plain as in the init (a
  DRAN round schedule visits every robot once per sweep);
- block-Jacobi preconditioned conjugate gradients (BJ-PCG: one exchange per iteration plus two
  network-wide sums);
- symmetric block SOR (ω = 1) preconditioned CG (BSSOR-PCG: a forward and a backward sweep per
  iteration plus two sums).

``--system gn``: the Gauss–Newton system of the chordal cost (SE-Sync weights, one gauge vertex
fixed) at the centralized chordal initialisation, then ``--gn-steps − 1`` more times at the
exact Gauss–Newton iterate. Printed per iteration count: energy-norm error of the step
relative to the exact step / gap of F(x ⊕ step) to F*, in percent.
``--system rotation``: the init's first stage, the relaxed rotation least squares of
``dran_edge.solver.chordal`` from zero; printed: max abs error of the relaxed rotations / gap to F* of
the poses they give (projected, translations solved exactly).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from dran_edge.solver.chordal import chordal_translations, relaxed_rotation_system, relaxed_to_rotations
from dran_edge.formats.g2o import read_g2o
from dran_edge.solver.lm import build_plan, linearize, retract
from dran_edge.solver.objective import sesync_objective, sesync_weights
from dran_edge.dran.partition import contiguous_owner
from dran_edge.solver.centralized import gauge_fixed, initial_poses, pose_graph

MARKS = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)


class BlockSystem:
    """``A X = B`` with the unknowns split into robot blocks, each block factorised once."""

    def __init__(self, A: sp.spmatrix, B: np.ndarray, owner: np.ndarray, robots: int):
        self.A, self.B = A.tocsr(), B
        self.blocks = [np.flatnonzero(owner == r) for r in range(robots)]
        self.lu = [spla.splu(sp.csc_matrix(self.A[b][:, b])) for b in self.blocks]

    def sweep(self, X: np.ndarray, omega: float, order) -> np.ndarray:
        for r in order:
            b = self.blocks[r]
            X[b] += omega * self.lu[r].solve(self.B[b] - self.A[b] @ X)
        return X

    def block_jacobi(self, R: np.ndarray) -> np.ndarray:
        Z = np.zeros_like(R)
        for r, b in enumerate(self.blocks):
            Z[b] = self.lu[r].solve(R[b])
        return Z

    def block_ssor(self, R: np.ndarray) -> np.ndarray:
        Z = np.zeros_like(R)
        for r in [*range(len(self.blocks)), *reversed(range(len(self.blocks)))]:
            b = self.blocks[r]
            Z[b] += self.lu[r].solve(R[b] - self.A[b] @ Z)
        return Z


def run_methods(system: BlockSystem, iterations: int, omegas, report) -> None:
    """Print ``report(X)`` at the MARKS for every method (columns of B solved together)."""
    for omega in omegas:
        X, out = np.zeros_like(system.B), []
        for k in range(1, iterations + 1):
            X = system.sweep(X, omega if k > 1 else 1.0, range(len(system.blocks)))
            if k in MARKS:
                out.append(f"{k}:{report(X)}")
        print(f"  block SOR ω={omega}: " + " ".join(out), flush=True)
    for name, prec in (("BJ-PCG", system.block_jacobi), ("BSSOR-PCG", system.block_ssor)):
        X, R = np.zeros_like(system.B), system.B.copy()
        Z = prec(R)
        P, rz, out = Z.copy(), np.sum(R * Z, axis=0), []
        for k in range(1, iterations + 1):
            AP = system.A @ P
            a = rz / np.sum(P * AP, axis=0)
            X += a * P
            R -= a * AP
            Z = prec(R)
            rz_new = np.sum(R * Z, axis=0)
            P, rz = Z + (rz_new / rz) * P, rz_new
            if k in MARKS:
                out.append(f"{k}:{report(X)}")
        print(f"  {name}: " + " ".join(out), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("f_star", type=float, help="the centralized optimum (docs/benchmarks.md)")
    ap.add_argument("--system", choices=("gn", "rotation"), default="gn")
    ap.add_argument("--robots", type=int, default=5)
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--gn-steps", type=int, default=2)
    ap.add_argument("--omega", type=float, nargs="+", default=[1.0, 1.9, 1.97])
    args = ap.parse_args(argv)
    g = read_g2o(args.dataset)
    d, n = g.dim, g.num_vertices
    kappa, tau = sesync_weights(d, g.information)
    owner_v = contiguous_owner(n, args.robots)

    def gap(T):
        F = sesync_objective(T, g.edges, g.measurements, kappa, tau)
        return f"{100 * (F / args.f_star - 1):.3f}"

    if args.system == "gn":
        graph = pose_graph(g, "chordal", "sesync")
        plan = build_plan(graph)
        owner = np.repeat(owner_v[plan.private_vars], plan.dof)
        x = initial_poses(g, "chordal")
        print(f"centralized chordal init: gap {gap(x)} %")
        for step in range(args.gn_steps):
            lin = linearize(graph, plan, x)
            system = BlockSystem(lin.A, -lin.g_x[:, None], owner, args.robots)
            exact = spla.spsolve(sp.csc_matrix(lin.A), -lin.g_x)[:, None]
            energy = float(exact[:, 0] @ (system.A @ exact[:, 0]))
            x_next = retract(plan, x, exact[:, 0], np.zeros(0))
            print(f"Gauss–Newton step {step}: exact step -> gap {gap(x_next)} % "
                  "(columns: iterations:relative energy error/gap %)")

            def report(X, x=x, exact=exact, energy=energy):
                e = (X - exact)[:, 0]
                rel = np.sqrt(max(float(e @ (system.A @ e)), 0.0) / energy)
                return f"{rel:.1e}/{gap(retract(plan, x, X[:, 0], np.zeros(0)))}"

            run_methods(system, args.iterations, args.omega, report)
            x = x_next
        return 0

    # the init's first stage: the relaxed rotation least squares of dran_edge.solver.chordal
    anchor = int(np.flatnonzero(gauge_fixed(g))[0])
    T_anchor = g.poses[anchor]
    A, B, free = relaxed_rotation_system(n, g.edges, g.measurements[:, :d, :d], kappa, anchor)
    system = BlockSystem(A, B, np.repeat(owner_v, d)[free], args.robots)
    exact = spla.spsolve(sp.csc_matrix(A), B)

    def poses_of(Xf):
        R = relaxed_to_rotations(Xf, free)
        t = chordal_translations(n, g.edges, R, g.measurements[:, :d, d], tau, anchor)
        T = np.tile(np.eye(d + 1), (n, 1, 1))
        T[:, :d, :d], T[:, :d, d] = R, t
        return T_anchor @ T

    print(f"relaxed rotations solved exactly -> gap {gap(poses_of(exact))} % "
          "(columns: iterations:max abs error/gap %)")
    run_methods(system, args.iterations, args.omega,
                lambda X: f"{np.max(np.abs(X - exact)):.1e}/{gap(poses_of(X))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
