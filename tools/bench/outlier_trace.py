"""Trace the object simulation with outliers: which wrong observations get past the gates, and
what the trajectories' ATE does over the rounds (diagnostic behind docs/benchmarks.md).

Usage: .venv/bin/python tools/bench/outlier_trace.py [--rounds 300] [--every 50] [--rho 0.3]
           [--outliers 0.2] [--outlier-kinds both|ids|loops] [--outlier-ids add|relabel]
           [--drop-wrong] [--min-views K] [--seed 0]

Same scenario, communication graph and agent settings as ``dran-edge bench objects --rho 0.3
--outliers 0.2`` (``objects_sim.bench_config``). Whether an observation is wrong is read
from the ground truth (its prediction lies > 0.5 m from the labelled object). Every ``--every``
rounds: wrong and right observations the agents use (``Agent.obs_ok``), the right ones held
back as lone views (``Agent.obs_pending``, not yet corroborated), the object copies in the
fleet and how many lie more than ``association_gate_m`` from their object, the ATE, and the
median whitened residual of the right observations in use with its Cauchy weight. At the end:
each wrong observation in use, and each right one still held back (its keyframe, how far the
robot's estimate puts it from the object, the nearest neighbour copy). ``--drop-wrong`` removes
the wrong observations from the scenario first (an oracle: the same trajectories with perfect
id association; the false loops stay). ``--min-views`` overrides the robust settings' 2.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import dataclasses

import numpy as np

from dran_edge import geometry as geo
from dran_edge.evaluation import metrics
from dran_edge.dran.agent import Agent
from dran_edge.comms.bus import Bus, BusParams, random_connected_graph
from dran_edge.solver.factors import Cauchy
from dran_edge.experiments.fleet import Fleet, neighbour_weights
from dran_edge.experiments.objects import SimParams, bench_config, make_scenario


def wrong_mask(sc, r: int, p) -> np.ndarray:
    """Per observation of robot r: does its ground-truth prediction miss the labelled object?"""
    pred = sc.gt_robots[r][p.obs_own] @ p.obs_T
    return np.linalg.norm(pred[:, :3, 3] - sc.gt_objects[p.obs_object][:, :3, 3], axis=1) >= 0.5


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=300)
    ap.add_argument("--every", type=int, default=50)
    ap.add_argument("--rho", type=float, default=0.3)
    ap.add_argument("--outliers", type=float, default=0.2)
    ap.add_argument("--outlier-kinds", choices=("both", "ids", "loops"), default="both")
    ap.add_argument("--outlier-ids", choices=("add", "relabel"), default="add",
                    help="wrong ids added to the right observations, or replacing them")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--drop-wrong", action="store_true")
    ap.add_argument("--min-views", type=int, default=None,
                    help="AgentConfig.object_min_views (default: the robust settings' 2)")
    args = ap.parse_args(argv)
    sc = make_scenario(SimParams(seed=args.seed, outlier_ratio=args.outliers,
                                     outlier_kinds=args.outlier_kinds, outlier_ids=args.outlier_ids))
    if args.drop_wrong:
        problems = []
        for r, p in enumerate(sc.problems):
            keep = ~wrong_mask(sc, r, p)
            problems.append(dataclasses.replace(p, obs_own=p.obs_own[keep], obs_object=p.obs_object[keep],
                                                obs_T=p.obs_T[keep], obs_W=p.obs_W[keep]))
        sc = dataclasses.replace(sc, problems=problems)
    cfg = bench_config(robust=True, min_views=args.min_views)
    ids = range(len(sc.problems))
    bus = Bus(ids, graph=random_connected_graph(ids, args.rho, seed=args.seed + 1),
              params=BusParams(seed=args.seed))
    W = neighbour_weights(bus)
    agents = [Agent(dataclasses.replace(cfg, robot_id=r, neighbours=tuple(sorted(W[r])), dim=3), p,
                    weights=W[r]) for r, p in enumerate(sc.problems)]
    wrong = [wrong_mask(sc, r, p) for r, p in enumerate(sc.problems)]
    gt_x = np.concatenate(sc.gt_robots)

    def callback(k, _fleet):
        if k % args.every:
            return
        used_wrong = sum(int((a.obs_ok & w).sum()) for a, w in zip(agents, wrong))
        used_right = sum(int((a.obs_ok & ~w).sum()) for a, w in zip(agents, wrong))
        held = sum(int((a.obs_pending & ~a.obs_ok & ~w).sum()) for a, w in zip(agents, wrong))
        off = [np.linalg.norm(T[:3, 3] - sc.gt_objects[o][:3, 3]) for a in agents for o, T in a.y.items()]
        far = int((np.asarray(off) > cfg.association_gate_m).sum())
        ate = metrics.ate_log_rmse(np.concatenate([a.x for a in agents]), gt_x)
        # whitened residual norm of every right observation in use, and its Cauchy weight
        res = []
        for a, p, w in zip(agents, sc.problems, wrong):
            i = np.flatnonzero(a.obs_ok & ~w)
            Y = np.stack([a.y[int(o)] for o in p.obs_object[i]]) if i.size else np.zeros((0, 4, 4))
            xi = geo.log(geo.between(a.x[p.obs_own[i]] @ p.obs_T[i], Y))
            res.append(np.linalg.norm(xi * p.obs_W[i], axis=1))
        res = np.concatenate(res)
        weight = Cauchy(cfg.object_robust_threshold).weight(res ** 2)
        print(f"round {k}: wrong observations used {used_wrong}/{sum(int(w.sum()) for w in wrong)}, "
              f"right {used_right}/{sum(int((~w).sum()) for w in wrong)} ({held} held back), "
              f"copies {len(off)} ({far} > {cfg.association_gate_m:g} m off), ATE {ate:.3f}, "
              f"right residuals median {np.median(res):.4f} (Cauchy weight median "
              f"{np.median(weight):.2f})", flush=True)

    Fleet(agents, bus).run(args.rounds, callback=callback)
    for r, (a, p, w) in enumerate(zip(agents, sc.problems, wrong)):
        pred = sc.gt_robots[r][p.obs_own] @ p.obs_T
        for i in np.flatnonzero(a.obs_ok & w):
            label = int(p.obs_object[i])
            true = int(np.argmin(np.linalg.norm(sc.gt_objects[:, :3, 3] - pred[i, :3, 3], axis=1)))
            apart = np.linalg.norm(sc.gt_objects[label][:3, 3] - sc.gt_objects[true][:3, 3])
            same = p.obs_object == label
            print(f"  robot {r}, pose {p.obs_own[i]}: object {true} labelled {label} ({apart:.2f} m "
                  f"apart); the robot's observations labelled {label}: {same.sum()}, "
                  f"{int((same & ~w).sum())} of them right")
        votes = a._votes()
        est = (a.x[p.obs_own] @ p.obs_T)[:, :3, 3]
        for i in np.flatnonzero(a.obs_pending & ~a.obs_ok & ~w):
            label = int(p.obs_object[i])
            near = (f"{np.linalg.norm(votes[label][0] - est[i], axis=1).min():.2f} m away"
                    if label in votes else "none")
            print(f"  held back: robot {r}, pose {p.obs_own[i]}, object {label}: the estimate puts it "
                  f"{np.linalg.norm(est[i] - sc.gt_objects[label][:3, 3]):.2f} m from the object; "
                  f"nearest neighbour copy {near}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
