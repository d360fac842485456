"""How much does the distributed initialisation's precision decide a Table 1 run? (diagnostic)

Usage:
  .venv/bin/python tools/bench/init_precision.py DATASET.g2o F_STAR [--init KEY=VALUE ...]
      [--dran KEY=VALUE ...] [--centralized-init] [--no-dgs] [--max-rounds N] [--every N]

Runs DRAN with the Table 1 setup (``multiagent.table1_setup``) and the DGS baseline after the
same initialisation, and prints one line: the init's gap to F* and bytes, DRAN's final gap,
bytes and the bytes of its own phase (after the init), and the same for DGS.

- ``--init KEY=VALUE``: override a field of ``dist_init.InitParams`` (e.g. ``send_tol=1e-6
  max_iterations=100 sor=1.95``); both methods get the same init.
- ``--dran KEY=VALUE``: override a field of ``AgentConfig`` for DRAN (e.g. ``sor_omega=1.97
  send_threshold=1e-6 eps_u=0 eps_cost_rel=0``; the last two turn the stopping tests off).
- ``--centralized-init``: start both methods from the centralized chordal initialisation
  (``pgo.initial_poses(g, "chordal")``) instead of the distributed one: no init rounds or bytes.
  It shows what DRAN and DGS do from the exact solution of the relaxation the init distributes.
- ``--every N``: print F and bytes every N DRAN rounds.

F* is the centralized optimum (docs/benchmarks.md, centralised solver). Gaps are to F*, in percent;
MB = 10^6 bytes, every byte of every datagram (``Fleet`` accounting).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import dataclasses
import typing

import numpy as np

from dran_edge.config import AgentConfig
from dran_edge.experiments.dgs import run_g2o_dgs
from dran_edge.dran.dist_init import InitParams
from dran_edge.formats.g2o import read_g2o
from dran_edge.experiments.fleet import TABLE1_DELTA_EVERY, run_g2o_dran, table1_setup
from dran_edge.solver.objective import sesync_objective, sesync_weights
from dran_edge.dran.partition import partition_contiguous
from dran_edge.solver.centralized import initial_poses


def overrides(cls, pairs: list[str]) -> dict:
    """``KEY=VALUE`` strings to keyword arguments typed like the fields of dataclass ``cls``."""
    hints = typing.get_type_hints(cls)
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or key not in hints:
            raise SystemExit(f"{pair!r}: expected KEY=VALUE with KEY one of {sorted(hints)}")
        kind = hints[key]
        try:
            if kind is bool:
                out[key] = value.lower() in ("1", "true", "yes")
            elif kind is int:
                out[key] = int(value)
            else:
                out[key] = float(value)
        except ValueError:
            raise SystemExit(f"{pair!r}: {key} takes a number ({kind})") from None
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("f_star", type=float, help="the centralized optimum (docs/benchmarks.md)")
    ap.add_argument("--robots", type=int, default=5)
    ap.add_argument("--init", nargs="*", default=[], metavar="KEY=VALUE",
                    help="InitParams overrides (both methods)")
    ap.add_argument("--dran", nargs="*", default=[], metavar="KEY=VALUE",
                    help="AgentConfig overrides (DRAN)")
    ap.add_argument("--centralized-init", action="store_true",
                    help="start from the centralized chordal initialisation (no init bytes)")
    ap.add_argument("--no-dgs", action="store_true", help="run DRAN only")
    ap.add_argument("--max-rounds", type=int, default=None, help="cap on DRAN rounds")
    ap.add_argument("--every", type=int, default=0, help="print F and bytes every N DRAN rounds")
    args = ap.parse_args(argv)

    init_params = InitParams(gauss_seidel=True, **overrides(InitParams, args.init))
    dran_overrides = overrides(AgentConfig, args.dran)
    g = read_g2o(args.dataset)
    kappa, tau = sesync_weights(g.dim, g.information)
    part = partition_contiguous(g.edges, g.num_vertices, args.robots)
    cfg, kw = table1_setup(g.dim)
    cfg = dataclasses.replace(cfg, **dran_overrides)
    start = initial_poses(g, "chordal") if args.centralized_init else None

    def F(T):
        return sesync_objective(T, g.edges, g.measurements, kappa, tau)

    def gap(value):
        return f"{100 * (value / args.f_star - 1):.3f} %"

    def callback(k, fleet):
        if args.every and k % args.every == 0:
            poses = np.zeros((g.num_vertices, g.dim + 1, g.dim + 1))
            for r, p in enumerate(part.parts):
                poses[p.vertices] = fleet.agents[r].x
            print(f"  DRAN round {k}: {gap(F(poses))}, {fleet.traffic.bytes_total / 1e6:.3f} MB",
                  flush=True)

    r = run_g2o_dran(g, args.robots, cfg, init_params=init_params, max_rounds=args.max_rounds,
                     callback=callback, initial_poses=start, **kw)
    line = (f"{os.path.basename(args.dataset)}: init {gap(r['objective_init'])}, "
            f"{r['bytes_init'] / 1e6:.3f} MB, {r['init_rounds']} rounds | DRAN "
            f"{gap(r['objective_final'])}, {r['bytes_total'] / 1e6:.3f} MB (own phase "
            f"{(r['bytes_total'] - r['bytes_init']) / 1e6:.3f}), {r['rounds']} rounds")
    if not args.no_dgs:
        d = run_g2o_dgs(g, args.robots, init_params=init_params, delta_every=TABLE1_DELTA_EVERY,
                        initial_poses=start)
        line += (f" | DGS {gap(d['objective_final'])}, {d['bytes_total'] / 1e6:.3f} MB (own "
                 f"phase {(d['bytes_total'] - d['bytes_init']) / 1e6:.3f})")
    print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
