"""Where does DRAN's stopping rule fire, and how far from F* is it then?

Design and results: docs/notes/stopping-rule.md.

    .venv/bin/python tools/bench/bench_stopping.py [--quick] [--seeds 0 1 2] [--robots 5]
        [--families chain2d grid2d chain3d grid3d] [--rules tail steps] [--max-rounds 600] [--json]

For every generated graph (families below, several seeds) it computes F* with the centralized
solver (``pgo.solve_g2o``: chordal init, exact-Hessian LM), then runs ``multiagent.run_g2o_dran``
with the Table 1 setup (colour schedule, SOR, deltas; 5 robots, contiguous split) under each
stopping rule, and prints per graph and rule: the round the fleet stopped (or "-" when it hit
--max-rounds), what stopped it (the criterion or K_max), F/F* there, and F/F* at rounds
50/100/200/500. "tail" is the default rule (AgentConfig.stop_rule); "steps" is the paper's ε_u/ε_v
test with the Table 1 relative-decrease stop (eps_cost_rel 1e-4), the rule before it.

Families (``graphgen`` grids, and long odometry chains with sparse loops generated here):
- ``grid2d`` / ``grid3d``: ``graphgen.synthetic_graph`` lawn-mower grids (2D 24×24; 3D 8×8×3);
- ``chain2d`` / ``chain3d``: a car driving ``laps`` laps of a rectangular circuit, one pose per
  metre, odometry noise (σ_t 0.05 m, σ_r 0.01 rad), loop closures on ~2 % of the poses to the
  nearest pose of an earlier lap, 1500 poses (--quick: 600).

The verdict line says whether any rule stopped above 1.01 × F* (the requirement) and the worst
F/F* at a stop per rule.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from dran_edge import geometry as geo
from dran_edge.formats.g2o import G2oGraph
from dran_edge.sim.graphgen import synthetic_graph
from dran_edge.experiments.fleet import run_g2o_dran, table1_setup
from dran_edge.solver.objective import sesync_objective, sesync_weights
from dran_edge.solver.centralized import solve_g2o

CHECK_ROUNDS = (50, 100, 200, 500)


def _graph(dim, T, edges, sig, rng) -> G2oGraph:
    Z = geo.between(T[edges[:, 0]], T[edges[:, 1]])
    dof = geo.dof(dim)
    Z = geo.retract(Z, rng.normal(size=(edges.shape[0], dof)) * sig)
    info = np.diag(1.0 / sig**2)
    m, n = edges.shape[0], T.shape[0]
    return G2oGraph(
        dim=dim,
        vertex_ids=np.arange(n, dtype=np.int64),
        poses=T.copy(),
        has_pose=np.ones(n, bool),
        edges=edges.astype(np.int64),
        measurements=Z,
        information=np.broadcast_to(info, (m, dof, dof)).copy(),
        fixed=np.zeros(n, bool),
        edge_lines=np.arange(1, m + 1, dtype=np.int64),
    )


def chain_graph(dim: int, n: int, seed: int, laps: int = 4, loop_frac: float = 0.02) -> G2oGraph:
    """A car on ``laps`` laps of a rectangle (one pose per metre, lanes 0–2 m apart per lap),
    odometry between consecutive poses and loops on ``loop_frac`` of the poses of later laps."""
    rng = np.random.default_rng(seed)
    per_lap = n // laps
    a = per_lap * 0.3  # rectangle a × b with perimeter per_lap
    b = per_lap * 0.5 - a
    s = np.arange(n) % per_lap + 0.0
    lane = (np.arange(n) // per_lap) * rng.uniform(0.0, 2.0)
    edges_of = np.array([0.0, a, a + b, 2 * a + b, per_lap])
    side = np.searchsorted(edges_of, s, side="right") - 1
    u = s - edges_of[side]
    legs = [np.c_[u, -lane], np.c_[a + lane, u], np.c_[a - u, b + lane], np.c_[-lane, b - u]]
    xy = np.select([(side == k)[:, None] for k in range(4)], legs)
    yaw = side * (np.pi / 2)
    if dim == 2:
        T = geo.se2_from_xy_theta(np.c_[xy, yaw])
        sig = np.array([0.05, 0.05, 0.01])
    else:
        z = 2.0 * np.sin(2 * np.pi * s / per_lap)
        R = geo.so3_exp(np.c_[rng.normal(0, 0.02, (n, 2)), yaw])
        T = geo.se3_from_rt(R, np.c_[xy, z])
        sig = np.array([0.05, 0.05, 0.05, 0.01, 0.01, 0.01])
    odo = np.c_[np.arange(n - 1), np.arange(1, n)]
    later = np.arange(per_lap, n)
    pick = rng.choice(later, max(1, int(loop_frac * n)), replace=False)
    pos = T[:, :dim, dim]
    loops = []
    for i in pick.tolist():
        earlier = np.arange(0, (i // per_lap) * per_lap)
        j = int(earlier[np.argmin(np.linalg.norm(pos[earlier] - pos[i], axis=1))])
        loops.append((j, i))
    return _graph(dim, T, np.vstack([odo, np.asarray(loops)]), sig, rng)


def make_graph(family: str, seed: int, quick: bool) -> G2oGraph:
    if family == "grid2d":
        return synthetic_graph(
            dim=2,
            side=16 if quick else 24,
            layers=1,
            loop_radius_m=1.1,
            sigma_t_m=0.05,
            sigma_r_rad=0.02,
            seed=seed,
        )[0]
    if family == "grid3d":
        return synthetic_graph(
            dim=3,
            side=6 if quick else 8,
            layers=3,
            loop_radius_m=1.1,
            sigma_t_m=0.05,
            sigma_r_rad=0.02,
            seed=seed,
        )[0]
    if family in ("chain2d", "chain3d"):
        return chain_graph(2 if family == "chain2d" else 3, 600 if quick else 1500, seed)
    raise SystemExit(f"unknown family {family!r}")


def rule_config(rule: str, dim: int):
    return table1_setup(dim, stop=rule)


def run_case(g: G2oGraph, F_star: float, rule: str, robots: int, max_rounds: int) -> dict:
    kappa, tau = sesync_weights(g.dim, g.information)
    cfg, kw = rule_config(rule, g.dim)
    at: dict = {}
    state = {"agents": None}

    def cb(k, fleet):
        state["agents"] = fleet.agents
        if k in CHECK_ROUNDS:
            at[k] = _merged_F(g, fleet, kappa, tau) / F_star

    t0 = time.perf_counter()
    res = run_g2o_dran(g, robots, cfg, max_rounds=max_rounds, callback=cb, **kw)
    agents = state["agents"] or []
    stopped = res["rounds"] < max_rounds
    reasons = sorted({a.stop_reason for a in agents if a.stop_reason})
    return {
        "rule": rule,
        "rounds": res["rounds"],
        "stopped": stopped,
        "stopped_by": "+".join(reasons) if stopped else "-",
        "F_over_Fstar": res["objective_final"] / F_star,
        "F_init_over_Fstar": res["objective_init"] / F_star,
        "at": at,
        "bytes": res["bytes_total"],
        "wall_s": time.perf_counter() - t0,
    }


def _merged_F(g, fleet, kappa, tau) -> float:
    from dran_edge.dran.partition import partition_contiguous

    part = partition_contiguous(g.edges, g.num_vertices, len(fleet.agents))
    T = np.empty_like(g.poses)
    for r, p in enumerate(part.parts):
        T[p.vertices] = fleet.agents[r].x
    return sesync_objective(T, g.edges, g.measurements, kappa, tau)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller graphs, one seed, 300 rounds")
    ap.add_argument("--seeds", type=int, nargs="+", default=None)
    ap.add_argument("--robots", type=int, default=5)
    ap.add_argument("--families", nargs="+", default=["chain2d", "grid2d", "chain3d", "grid3d"])
    ap.add_argument("--rules", nargs="+", default=["tail", "steps"], choices=("tail", "steps"))
    ap.add_argument("--max-rounds", type=int, default=None)
    ap.add_argument("--json", action="store_true", help="one JSON object per run")
    args = ap.parse_args(argv)
    seeds = args.seeds if args.seeds is not None else ([0] if args.quick else [0, 1, 2])
    max_rounds = args.max_rounds or (300 if args.quick else 600)
    worst: dict = {}
    for fam in args.families:
        for seed in seeds:
            g = make_graph(fam, seed, args.quick)
            F_star = solve_g2o(g).objective_final
            for rule in args.rules:
                r = run_case(g, F_star, rule, args.robots, max_rounds)
                r.update(
                    {
                        "family": fam,
                        "seed": seed,
                        "poses": g.num_vertices,
                        "edges": g.num_edges,
                        "F_star": F_star,
                    }
                )
                if r["stopped"]:
                    worst[rule] = max(worst.get(rule, 0.0), r["F_over_Fstar"])
                if args.json:
                    print(json.dumps(r), flush=True)
                else:
                    at = " ".join(f"@{k}:{v:.5f}" for k, v in sorted(r["at"].items()))
                    stop = f"{r['rounds']:>4} ({r['stopped_by']})" if r["stopped"] else "   - (cap)"
                    print(
                        f"{fam:>8} s{seed} n={g.num_vertices:<5} {rule:>5}: stop {stop} "
                        f"F/F*={r['F_over_Fstar']:.5f} init {r['F_init_over_Fstar']:.3f} "
                        f"bytes={r['bytes']} {at} [{r['wall_s']:.0f} s]",
                        flush=True,
                    )
    bad = {k: v for k, v in worst.items() if v > 1.01}
    print(
        "worst F/F* at a stop: "
        + ", ".join(f"{k} {v:.5f}" for k, v in sorted(worst.items()))
        + ("; ABOVE 1.01: " + ", ".join(sorted(bad)) if bad else "; none above 1.01"),
        file=sys.stderr if args.json else sys.stdout,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
