"""Trace one Table 1 run: objective and bytes every N rounds, and where it crosses 0.1 % of F*.

Usage: .venv/bin/python tools/bench/trace_g2o.py DATASET.g2o F_STAR [--every 10] [--max-rounds N]
           [--no-cost-stop] [--plain] [--sor 1.9] [--send-threshold 1e-4]
           [--resend-period 20]

Runs ``run_g2o_dran`` with ``multiagent.table1_setup`` (or ``--plain``) and a callback that
merges the robots' trajectories and evaluates the SE-Sync objective. ``--no-cost-stop`` turns
off both stopping tests (ε_u and the cost-decrease one) so the run goes to K_max: the curve
behind the stop-threshold trade-off in docs/benchmarks.md. Prints one line per sample:
round, F, bytes so far, the largest relative local-cost decrease of the robots' last steps.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import dataclasses
import json

import numpy as np

from dran_edge.g2o import read_g2o
from dran_edge.multiagent import run_g2o_dran, table1_setup
from dran_edge.objective import sesync_objective, sesync_weights
from dran_edge.partition import partition_contiguous


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("f_star", type=float, help="the centralized optimum (docs/benchmarks.md)")
    ap.add_argument("--robots", type=int, default=5)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--max-rounds", type=int, default=None)
    ap.add_argument("--no-cost-stop", action="store_true")
    ap.add_argument("--plain", action="store_true")
    ap.add_argument("--sor", type=float, default=None, help="override the SOR omega")
    ap.add_argument("--send-threshold", type=float, default=None,
                    help="override AgentConfig.send_threshold (re-send a pose once it moved more)")
    ap.add_argument("--resend-period", type=int, default=None,
                    help="override AgentConfig.resend_period_rounds (periodic re-send of unchanged poses)")
    args = ap.parse_args(argv)
    g = read_g2o(args.dataset)
    kappa, tau = sesync_weights(g.dim, g.information)
    part = partition_contiguous(g.edges, g.num_vertices, args.robots)
    cfg, kw = table1_setup(g.dim, plain=args.plain)
    if args.no_cost_stop:
        cfg = dataclasses.replace(cfg, eps_u=0.0, eps_cost_rel=0.0)
    if args.sor is not None:
        cfg = dataclasses.replace(cfg, sor_omega=args.sor)
    if args.send_threshold is not None:
        cfg = dataclasses.replace(cfg, send_threshold=args.send_threshold)
    if args.resend_period is not None:
        cfg = dataclasses.replace(cfg, resend_period_rounds=args.resend_period)
    crossed = []

    def callback(k, fleet):
        poses = np.zeros((g.num_vertices, g.dim + 1, g.dim + 1))
        for r, p in enumerate(part.parts):
            poses[p.vertices] = fleet.agents[r].x
        F = sesync_objective(poses, g.edges, g.measurements, kappa, tau)
        if not crossed and F <= 1.001 * args.f_star:
            crossed.append((k, fleet.traffic.bytes_total, F))
        if k % args.every == 0 or k <= 3:
            rel = max((a.last_decrease / a.last_cost if a.last_cost > 0 else float("nan"))
                      for a in fleet.agents)
            print(f"{k} {F:.6f} {fleet.traffic.bytes_total} {rel:.1e}", flush=True)

    res = run_g2o_dran(g, args.robots, cfg, max_rounds=args.max_rounds, callback=callback, **kw)
    summary = {k: v for k, v in res.items() if k not in ("poses", "poses_init")}
    summary["crossed_0.1pct"] = crossed[0] if crossed else None
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
