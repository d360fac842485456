#!/usr/bin/env python3
"""Could an iterative interface solve replace the refinement's dense gathers? A probe.

    .venv/bin/python tools/interface_pcg_probe.py ../shared/data/g2o/sphere2500.g2o
    .venv/bin/python tools/interface_pcg_probe.py G.g2o --robots 5 --steps 4 --mu 1e-6

The exact refinement (``dran_edge.dran.exact_gn``) gathers every robot's dense condensed system
S_r at the root, which on sphere2500 costs more than the whole byte budget DRAN is measured
against (docs/notes/generalisation.md, "Frozen-Hessian (chord) refinement"). The alternative
asked for there: conjugate gradients on the interface system ``S δ_B = g_B`` (S = Σ_r S_r), where
one iteration costs one boundary vector down the robot tree and one up (robot r applies S_r
with its own interior factor), preconditioned by something the root can hold after a cheap
gather. This probe measures, centrally and in float64, how many such iterations a step needs.

It splits the graph contiguously (as ``dran-edge bench g2o``), starts from the centralized
chordal initialisation and takes ``--steps`` exact damped Newton steps (the exact-Hessian model
of ``exact_gn``, Marquardt damping ``--mu``, each step solved exactly). At every step it forms
S and g_B densely and runs PCG to relative residuals 1e-1, 1e-2 and 1e-4 with each
preconditioner M, printing the iterations, the floats M costs to gather and the extreme
eigenvalues of M⁻¹S (PCG needs ~√(λmax/λmin) iterations for a fixed residual reduction):

- ``bj``: the 6×6 (3×3 in 2D) diagonal blocks of S;
- ``dropTOL``: each S_r without its off-diagonal blocks weaker than TOL relative to their
  diagonal blocks, the dropped norm added to both diagonal blocks (M ⪰ S);
- ``lrK``: each S_r as ``H_BB − C_K`` with C_K the K largest eigenpairs of ``C = H_BI H_II⁻¹ H_IB``
  (M ⪰ S, K·|B_r|·dof floats plus H_BB's blocks);
- ``bj+defl K``: ``bj`` with the K eigenvectors of the smallest eigenvalues of ``bj⁻¹S``
  deflated exactly (an oracle: how large a coarse space of global modes would have to be);
- ``none``: plain CG.

Floats per CG iteration (printed): every robot's boundary values, down and up. A development
tool, central and dense (minutes on sphere2500); not part of make test.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from dran_edge import geometry as geo
from dran_edge.dran import exact_gn, substructure
from dran_edge.dran.partition import partition_contiguous
from dran_edge.formats.g2o import read_g2o
from dran_edge.solver.chordal import chordal_initialization
from dran_edge.solver.factors import isotropic_whitening
from dran_edge.solver.objective import sesync_objective, sesync_weights

GAUGE = 0


def robot_systems(g, part, W, T: np.ndarray, mu: float, b: int) -> list[dict]:
    """Per robot: its damped exact-Hessian share condensed onto its boundary by
    ``substructure.condense`` (what the refinement would gather), with S_r and its H_BB dense."""
    out = []
    for p in part.parts:
        H, gr, _, D = exact_gn.share(p, g.num_vertices, g.dim, g.edges, g.measurements, W, T, True)
        loc = substructure.condense(
            p, part, H + mu * sp.diags(D), -gr[:, None], b, GAUGE, np.zeros((b, 1))
        )
        m = loc.B.size * b
        H_BB = np.zeros((m, m))
        for (i, j), blk in zip(loc.st.pairs.tolist(), loc.Q_BB):
            H_BB[i * b : (i + 1) * b, j * b : (j + 1) * b] = blk
            H_BB[j * b : (j + 1) * b, i * b : (i + 1) * b] = blk.T
        S = H_BB.copy()
        for (_, N), P in zip(loc.st.comps, loc.pieces):
            rn = substructure.expand(N, b)
            S[np.ix_(rn, rn)] += P
        out.append(dict(B=loc.B, S=S, H_BB=H_BB, g_B=loc.g[:, 0], loc=loc))
    return out


def assemble(systems: list[dict], blocks: list[np.ndarray], where: dict, b: int) -> np.ndarray:
    """Σ_r of per-robot boundary matrices ``blocks`` on the interface."""
    n = len(where) * b
    M = np.zeros((n, n))
    for s, blk in zip(systems, blocks):
        idx = substructure.expand(np.array([where[v] for v in s["B"]], np.int64), b)
        M[np.ix_(idx, idx)] += blk
    return M


def interface_rhs(systems: list[dict], where: dict, b: int) -> np.ndarray:
    rhs = np.zeros(len(where) * b)
    for s in systems:
        rhs[substructure.expand(np.array([where[v] for v in s["B"]], np.int64), b)] += s["g_B"]
    return rhs


def block_diagonal(S: np.ndarray, b: int) -> np.ndarray:
    out = np.zeros_like(S)
    for i in range(0, S.shape[0], b):
        out[i : i + b, i : i + b] = S[i : i + b, i : i + b]
    return out


def dropped(S: np.ndarray, b: int, tol: float) -> tuple[np.ndarray, int]:
    """S without its weak off-diagonal blocks, compensated on the diagonal; floats kept."""
    S = S.copy()
    m = S.shape[0] // b
    blk = S.reshape(m, b, m, b).transpose(0, 2, 1, 3)
    norm = np.linalg.norm(blk, 2, axis=(2, 3))
    kept = 0
    for i in range(m):
        for j in range(i + 1, m):
            if norm[i, j] <= tol * np.sqrt(norm[i, i] * norm[j, j]):
                S[i * b : (i + 1) * b, j * b : (j + 1) * b] = 0
                S[j * b : (j + 1) * b, i * b : (i + 1) * b] = 0
                for k in (i, j):
                    S[k * b : (k + 1) * b, k * b : (k + 1) * b] += norm[i, j] * np.eye(b)
            else:
                kept += 1
    return S, kept * b * b + m * b * (b + 1) // 2


def low_rank(s: dict, b: int, k: int) -> tuple[np.ndarray, int]:
    """H_BB − (the k largest eigenpairs of C = H_BB − S_r): an upper bound of S_r; floats."""
    C = s["H_BB"] - s["S"]
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    k = min(k, w.size)
    w, V = w[::-1][:k], V[:, ::-1][:, :k]
    m = s["H_BB"].shape[0] // b
    nonzero_blocks = np.count_nonzero(np.abs(s["H_BB"]).reshape(m, b, m, b).sum(axis=(1, 3)))
    return s["H_BB"] - (V * w) @ V.T, k * (C.shape[0] + 1) + nonzero_blocks * b * b


def pcg(S: np.ndarray, rhs: np.ndarray, apply_Minv, eta: float, max_iter: int) -> str:
    """Iterations of preconditioned CG from 0 to ‖r‖ ≤ eta ‖rhs‖ ("N+" at the cap)."""
    x, r = np.zeros_like(rhs), rhs.copy()
    z = apply_Minv(r)
    p, rz, r0 = z.copy(), r @ z, np.linalg.norm(rhs)
    for k in range(1, max_iter + 1):
        q = S @ p
        alpha = rz / (p @ q)
        x += alpha * p
        r -= alpha * q
        if np.linalg.norm(r) <= eta * r0:
            return str(k)
        z = apply_Minv(r)
        rz, rz_old = r @ z, rz
        p = z + (rz / rz_old) * p
    return f"{max_iter}+"


def spd_inverse(M: np.ndarray):
    c = sla.cho_factor(M)
    return lambda v: sla.cho_solve(c, v)


def deflated(M: np.ndarray, S: np.ndarray, k: int):
    """M⁻¹ with the k slowest modes of M⁻¹S solved exactly (balancing-style two-level)."""
    L = np.linalg.cholesky(M)
    A = sla.solve_triangular(L, sla.solve_triangular(L, S, lower=True).T, lower=True)
    _, V = np.linalg.eigh(0.5 * (A + A.T))
    Z = sla.solve_triangular(L.T, V[:, :k], lower=False)  # the modes in S's coordinates
    E = Z.T @ S @ Z
    Minv = spd_inverse(M)

    def apply(r: np.ndarray) -> np.ndarray:
        c = Z @ np.linalg.solve(E, Z.T @ r)
        rr = r - S @ c
        return c + (Minv(rr) - Z @ np.linalg.solve(E, Z.T @ (S @ Minv(rr))))

    return apply


def extreme_eigenvalues(M: np.ndarray, S: np.ndarray) -> tuple[float, float]:
    w = sla.eigh(S, M, eigvals_only=True)
    return float(w.min()), float(w.max())


def back_substitute(g, part, systems, where, dB: np.ndarray, b: int, T: np.ndarray):
    delta = np.zeros((g.num_vertices, b))
    for p, s in zip(part.parts, systems):
        idx = np.array([where[v] for v in s["B"]], np.int64)
        x_B = dB[substructure.expand(idx, b)]
        loc = s["loc"]
        if loc.I.size:
            delta[loc.I] = loc.back_substitute(x_B[:, None]).reshape(-1, b)
        own = np.isin(s["B"], p.vertices)
        delta[s["B"][own]] = x_B.reshape(-1, b)[own]
    return geo.retract(T, delta)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("graph", type=Path, help="a g2o pose graph")
    ap.add_argument("--robots", type=int, default=5, help="contiguous split (default 5)")
    ap.add_argument("--steps", type=int, default=4, help="Newton steps probed (default 4)")
    ap.add_argument("--mu", type=float, default=1e-6, help="Marquardt damping (default 1e-6)")
    ap.add_argument("--max-iter", type=int, default=500, help="CG iteration cap (default 500)")
    args = ap.parse_args(argv)

    g = read_g2o(args.graph)
    b = geo.dof(g.dim)
    kappa, tau = sesync_weights(g.dim, g.information)
    part = partition_contiguous(g.edges, g.num_vertices, args.robots)
    W = isotropic_whitening(kappa, tau, "chordal", g.dim)
    interface = np.unique(np.concatenate([substructure.boundary(p, GAUGE) for p in part.parts]))
    where = {int(v): k for k, v in enumerate(interface)}
    sizes = [substructure.boundary(p, GAUGE).size for p in part.parts]
    per_iteration = 2 * sum(sizes) * b
    print(
        f"{args.graph.name}: {g.num_vertices} poses, {args.robots} robots, interface "
        f"{interface.size} poses ({interface.size * b} unknowns), boundaries {sizes}; one CG "
        f"iteration {per_iteration} floats ({per_iteration * 4 / 1e6:.3f} MB as float32)"
    )
    T = chordal_initialization(g.num_vertices, g.edges, g.measurements, kappa, tau)
    F0 = sesync_objective(T, g.edges, g.measurements, kappa, tau)
    for step in range(args.steps):
        t0 = time.perf_counter()
        systems = robot_systems(g, part, W, T, args.mu, b)
        S = assemble(systems, [s["S"] for s in systems], where, b)
        rhs = interface_rhs(systems, where, b)
        F = sesync_objective(T, g.edges, g.measurements, kappa, tau)
        print(
            f"\nstep {step}: F/F_init {F / F0:.10f}, |g_B| {np.linalg.norm(rhs):.3e}, interiors "
            f"positive definite {all(s['loc'].positive_definite for s in systems)}"
        )
        bj = block_diagonal(S, b)
        candidates: dict[str, tuple[np.ndarray, int]] = {"bj": (bj, sum(sizes) * b * (b + 1) // 2)}
        for tol in (0.03, 0.3):
            pieces = [dropped(s["S"], b, tol) for s in systems]
            candidates[f"drop{tol:g}"] = (
                assemble(systems, [m for m, _ in pieces], where, b),
                sum(f for _, f in pieces),
            )
        for k in (20, 150):
            pieces = [low_rank(s, b, k) for s in systems]
            candidates[f"lr{k}"] = (
                assemble(systems, [m for m, _ in pieces], where, b),
                sum(f for _, f in pieces),
            )
        etas = (1e-1, 1e-2, 1e-4)
        print(f"  {'M':<12} {'floats':>9}  iterations to η = {' / '.join(f'{e:g}' for e in etas)}")
        for name, (M, floats) in candidates.items():
            lo, hi = extreme_eigenvalues(M, S)
            its = [pcg(S, rhs, spd_inverse(M), e, args.max_iter) for e in etas]
            print(f"  {name:<12} {floats:>9}  {' / '.join(its):<16} eig(M⁻¹S) [{lo:.1e}, {hi:.1e}]")
        for k in (10, 50, 200):
            apply = deflated(bj, S, k)
            its = [pcg(S, rhs, apply, e, args.max_iter) for e in etas]
            print(f"  {f'bj+defl {k}':<12} {'oracle':>9}  {' / '.join(its)}")
        its = [pcg(S, rhs, lambda v: v, e, args.max_iter) for e in etas]
        print(f"  {'none':<12} {0:>9}  {' / '.join(its)}  ({time.perf_counter() - t0:.0f} s)")
        T = back_substitute(g, part, systems, where, np.linalg.solve(S, rhs), b, T)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
