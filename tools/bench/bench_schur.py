"""Table 2 ablation: one DRAN local step with and without the Schur complement, same problems.

Usage: .venv/bin/python tools/bench/bench_schur.py [--steps 300] [--seed 0]
       .venv/bin/python tools/bench/bench_schur.py --quick     # 5 steps per variant

The problem is the size of one robot of the paper's real-world run: 112 trajectory poses, 165
edges (111 odometry + 54 object observations), 9 objects, each object also tied to 2 neighbours'
copies by the eq. 6 consensus term. One local step = linearise (A, B, C, g_x, g_y) + damped solve
+ retraction. Variants, timed side by side in this process on identical linearisations:

- ``schur``: eliminate the private poses (supernodal Cholesky of A + μI, reused for [g_x, C]), dense Ĥ on
  the 9 objects (eqs. 8, 11, 12) — ``lm.schur_step``;
- ``full-dense``: solve the whole damped system M ξ = −g densely (the unreduced step);
- ``full-sparse``: the whole system as one sparse Cholesky (objects treated as private).

Then each variant runs 30 LM steps from the same start and the final local costs are printed.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: see docs/benchmarks.md

import argparse
import time

import numpy as np
import scipy.linalg

from dran_edge import geometry as geo
from dran_edge.dran.consensus import ConsensusFactors
from dran_edge.solver.factors import BetweenFactors, PriorFactors
from dran_edge.solver.graph import PoseGraph, kinds_array
from dran_edge.solver.lm import (
    build_plan,
    cholesky_factorizer,
    evaluate_cost,
    linearize,
    retract,
    schur_step,
)


def _raw(seed: int = 0) -> dict:
    """The measurements of the benchmark robot (shared by the factor-level and agent variants)."""
    rng = np.random.default_rng(seed)
    n, n_obj, n_obs, n_nbr = 112, 9, 54, 2
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False) * 1.5
    xyz = np.column_stack([2.0 * np.cos(ang), 2.0 * np.sin(ang), np.zeros(n)])
    T_gt = geo.se3_from_rt(geo.so3_exp(np.column_stack([np.zeros((n, 2)), ang + np.pi / 2])), xyz)
    obj = geo.se3_from_rt(
        geo.so3_exp(rng.normal(0, 1, (n_obj, 3))),
        np.column_stack(
            [
                3.0 * np.cos(np.arange(n_obj)),
                3.0 * np.sin(np.arange(n_obj)),
                rng.normal(0, 0.2, n_obj),
            ]
        ),
    )
    noise = lambda m, s: geo.se3_exp(rng.normal(0, s, (m, 6)))
    odo = geo.se3_between(T_gt[:-1], T_gt[1:]) @ noise(n - 1, 0.01)
    pi = np.sort(rng.choice(n, n_obs, replace=False))
    oi = rng.integers(0, n_obj, n_obs)
    obs = geo.se3_between(T_gt[pi], obj[oi]) @ noise(n_obs, 0.01)
    nbr = obj[np.repeat(np.arange(n_obj), n_nbr)] @ noise(n_obj * n_nbr, 0.02)
    return {
        "n": n,
        "n_obj": n_obj,
        "n_obs": n_obs,
        "n_nbr": n_nbr,
        "T_gt": T_gt,
        "odo": odo,
        "pi": pi,
        "oi": oi,
        "obs": obs,
        "nbr": nbr,
    }


def problem(seed: int = 0):
    d = _raw(seed)
    n, n_obj, n_obs, n_nbr = d["n"], d["n_obj"], d["n_obs"], d["n_nbr"]
    T_gt, odo, pi, oi, obs, nbr = d["T_gt"], d["odo"], d["pi"], d["oi"], d["obs"], d["nbr"]
    N = n + n_obj + n_obj * n_nbr
    o_base, c_base = n, n + n_obj
    W = np.ones(6)
    blocks = (
        BetweenFactors(
            np.column_stack([np.arange(n - 1), np.arange(1, n)]), odo, np.tile(W, (n - 1, 1))
        ),
        BetweenFactors(
            np.column_stack([pi, o_base + oi]), obs, np.tile(W, (n_obs, 1)), label="object"
        ),
        PriorFactors(np.array([[0]]), T_gt[:1], np.full((1, 6), 100.0)),
        ConsensusFactors(
            np.column_stack(
                [o_base + np.repeat(np.arange(n_obj), n_nbr), c_base + np.arange(n_obj * n_nbr)]
            ),
            np.full(n_obj * n_nbr, 1 / 3),
            np.zeros((n_obj * n_nbr, 6)),
            1.0,
        ),
    )
    x0 = [T_gt[0]]
    for Z in odo:
        x0.append(x0[-1] @ Z)
    y0 = np.stack([np.stack(x0)[pi[oi == k][0]] @ obs[oi == k][0] for k in range(n_obj)])
    poses = np.concatenate([np.stack(x0), y0, nbr])
    kinds = kinds_array(N, public=np.arange(o_base, c_base), fixed=np.arange(c_base, N))
    kinds_flat = kinds_array(N, fixed=np.arange(c_base, N))
    return PoseGraph(3, kinds, blocks), PoseGraph(3, kinds_flat, blocks), poses


def agent_round_ms(seed: int, rounds: int) -> tuple[float, float]:
    """The same robot as a real ``Agent`` (paper defaults, no robust kernel): its 9 objects'
    copies from 2 neighbours arrive as ``NeighbourData``; one ``Tick`` = one DRAN round (dual
    update, the local step with its acceptance test, outputs). Returns (median ms, p90 ms)."""
    from dran_edge.config import AgentConfig
    from dran_edge.dran.agent import Agent
    from dran_edge.dran.problem import LocalProblem
    from dran_edge.events import NeighbourData, Tick
    from dran_edge.messages import NeighbourMessage, ObjectEntry

    d = _raw(seed)
    n, n_obj, n_nbr = d["n"], d["n_obj"], d["n_nbr"]
    z = np.zeros(0, np.int64)
    x0 = [d["T_gt"][0]]
    for Z in d["odo"]:
        x0.append(x0[-1] @ Z)
    W = np.ones(6)
    prob = LocalProblem(
        dim=3,
        residual="geodesic",
        pose_ids=np.arange(n),
        pose_stamps_ns=np.arange(n),
        x0=np.stack(x0),
        between=np.column_stack([np.arange(n - 1), np.arange(1, n)]),
        between_T=d["odo"],
        between_W=np.tile(W, (n - 1, 1)),
        between_robust=np.zeros(n - 1, bool),
        inter_own=z,
        inter_owner=z,
        inter_anchor_id=z,
        inter_own_is_p=np.zeros(0, bool),
        inter_T=np.zeros((0, 4, 4)),
        inter_W=np.zeros((0, 6)),
        inter_robust=np.zeros(0, bool),
        prior_own=np.array([0]),
        prior_T=d["T_gt"][:1],
        prior_W=np.full((1, 6), 100.0),
        obs_own=d["pi"],
        obs_object=d["oi"],
        obs_T=d["obs"],
        obs_W=np.tile(W, (d["pi"].size, 1)),
    )
    nbrs = tuple(range(1, n_nbr + 1))
    agent = Agent(
        AgentConfig(robust_kernel="none", neighbours=nbrs, eps_u=0.0),
        prob,
        weights={q: 1 / 3 for q in nbrs},
    )
    times = []
    for k in range(1, rounds + 1):
        for j, q in enumerate(nbrs):
            entries = tuple(ObjectEntry(o, d["nbr"][o * n_nbr + j], q, 0) for o in range(n_obj))
            agent.handle(NeighbourData(0, NeighbourMessage(q, k, 0, objects=entries)))
        t0 = time.perf_counter()
        agent.handle(Tick(k))
        times.append(1e3 * (time.perf_counter() - t0))
    times = times[5:] or times  # the first rounds build the structure plan and the analysis
    return float(np.median(times)), float(np.percentile(times, 90))


def full_dense_step(lin, mu):
    A = lin.A.toarray()
    C = lin.C.toarray()
    M = np.block([[A, C], [C.T, lin.B]]) + mu * np.eye(A.shape[0] + lin.B.shape[0])
    g = np.concatenate([lin.g_x, lin.g_y])
    xi = -scipy.linalg.cho_solve(scipy.linalg.cho_factor(M), g)
    return xi[: A.shape[0]], xi[A.shape[0] :]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--quick",
        action="store_true",
        help="5 timed steps per variant, 10 to compare costs: checks the script only",
    )
    args = ap.parse_args(argv)
    if args.quick:
        args.steps = min(args.steps, 5)
    conv_steps = 10 if args.quick else 30  # LM steps per variant before the costs are compared
    g_red, g_flat, poses = problem(args.seed)
    p_red, p_flat = build_plan(g_red), build_plan(g_flat)
    # both sparse variants factorise with the supernodal Cholesky the agent uses (analysed once)
    f_red, f_flat = cholesky_factorizer(p_red), cholesky_factorizer(p_flat)
    print(f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}")
    print(
        f"problem: 112 poses, 9 objects, {sum(b.variables.shape[0] for b in g_red.factors[:2])} edges "
        f"+ prior + {g_red.factors[3].variables.shape[0]} consensus terms"
    )
    mu = 1e-3
    # correctness: the reduced step equals the full dense step
    lin = linearize(g_red, p_red, poses)
    u, v = schur_step(lin.A, lin.B, lin.C, lin.g_x, lin.g_y, mu)
    u2, v2 = full_dense_step(lin, mu)
    print(
        f"max |reduced - full dense| step difference: {max(np.abs(u - u2).max(), np.abs(v - v2).max()):.2e}"
    )
    times = {"schur": [], "full-dense": [], "full-sparse": []}
    chunk = min(25, args.steps)  # variants alternate in chunks: they share the load, not caches
    for _ in range(max(args.steps // chunk, 1)):
        for name in times:
            for _ in range(chunk):
                t0 = time.perf_counter()
                if name == "full-sparse":
                    lin = linearize(g_flat, p_flat, poses)
                    u, v = schur_step(lin.A, lin.B, lin.C, lin.g_x, lin.g_y, mu, f_flat)
                    new = retract(p_flat, poses, u, v)
                else:
                    lin = linearize(g_red, p_red, poses)
                    u, v = (
                        schur_step(lin.A, lin.B, lin.C, lin.g_x, lin.g_y, mu, f_red)
                        if name == "schur"
                        else full_dense_step(lin, mu)
                    )
                    new = retract(p_red, poses, u, v)
                times[name].append(1e3 * (time.perf_counter() - t0))
                del new
    base = np.median(times["schur"])
    for name, ts in times.items():
        print(
            f"{name:<12} local step median {np.median(ts):7.3f} ms  (p90 {np.percentile(ts, 90):7.3f})"
            f"  ratio to schur {np.median(ts) / base:5.2f}"
        )
    ts = []
    for _ in range(args.steps):
        t0 = time.perf_counter()
        evaluate_cost(g_red, poses)
        ts.append(1e3 * (time.perf_counter() - t0))
    print(
        f"{'acceptance':<12} the LM step's cost evaluation at the new poses: median "
        f"{np.median(ts):7.3f} ms (add it to a local step)"
    )
    med, p90 = agent_round_ms(args.seed, args.steps)
    print(
        f"{'agent round':<12} one Tick of a real Agent (local step + acceptance + duals + outputs) "
        f"median {med:7.3f} ms  (p90 {p90:7.3f})"
    )
    for name, graph, plan, fac in (
        ("schur", g_red, p_red, f_red),
        ("full-dense", g_red, p_red, None),
        ("full-sparse", g_flat, p_flat, f_flat),
    ):
        P = poses.copy()
        for _ in range(conv_steps):
            lin = linearize(graph, plan, P)
            u, v = (
                full_dense_step(lin, mu)
                if name == "full-dense"
                else schur_step(lin.A, lin.B, lin.C, lin.g_x, lin.g_y, mu, fac)
            )
            P = retract(plan, P, u, v)
        print(f"{name:<12} local cost after {conv_steps} steps {evaluate_cost(graph, P):.10g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
