"""Table 1 of the paper: DRAN and our DGS baseline on the six g2o benchmarks, 5 robots.

Usage: .venv/bin/python tools/bench/bench_table1.py DATA_DIR [--robots 5] [--only NAME ...] [--json OUT]
       .venv/bin/python tools/bench/bench_table1.py --quick    # a small generated graph, seconds
       [--init auto|always|never]

Prints a Table-1-like table with the paper's columns next to ours: objective (SE-Sync convention)
at the distributed initialisation and at the end, rounds and total transmitted bytes (every byte
of every datagram, initialisation included) for DRAN and DGS. The gap is to our own centralized
optimum F* (the SE-Sync optimum to 3e-9, docs/benchmarks.md, centralised solver), not to the paper's
rounded column. DRAN runs with the Table 1 setup of ``experiments.fleet.table1_setup`` (colour schedule,
block SOR, delta entries; ``--plain`` for Alg. 1 as printed); DGS uses the same wire layout.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import _common  # one BLAS thread, before numpy (docs/benchmarks.md)

from dran_edge.dran.dist_init import InitParams
from dran_edge.experiments.dgs import run_g2o_dgs
from dran_edge.experiments.fleet import TABLE1_DELTA_EVERY, run_g2o_dran, table1_setup
from dran_edge.formats.g2o import read_g2o

# name: (paper DGS F, paper DRAN F, paper DGS MB, paper DRAN MB); files and F* in _common
PAPER = {
    "parking-garage": (1.33, 1.289, 5.41, 1.23),
    "sphere2500": (1689, 1687, 13.73, 1.34),
    "torus3D": (24246, 24227, 9.14, 3.23),
    "CSAIL": (31.49, 31.47, 11.857, 0.01),
    "intel": (428.89, 393.7, 0.06, 0.54),
    "manhattan": (242.05, 194.0, 152.31, 13.47),
}
NO_PAPER = (float("nan"),) * 4  # a generated graph (--quick) has no paper column


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("data_dir", nargs="?", default=_common.default_g2o_dir())
    ap.add_argument("--robots", type=int, default=5)
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--json", help="append one JSON line per run to this file")
    ap.add_argument(
        "--max-rounds",
        type=int,
        default=None,
        help="cap on DRAN rounds (default: K_max = 500 local steps per robot)",
    )
    ap.add_argument(
        "--plain", action="store_true", help="DRAN as Alg. 1 prints it (see module doc)"
    )
    ap.add_argument(
        "--quick",
        action="store_true",
        help="a small generated graph, 3 robots, 20 DRAN rounds: checks the script only",
    )
    ap.add_argument(
        "--init",
        choices=("auto", "always", "never"),
        default="auto",
        help="InitParams.direct of the distributed init (never: block iterations only)",
    )
    args = ap.parse_args(argv)
    if args.quick:  # the SE(2) graph only unless --only names the other: 1 s instead of 3
        args.robots, args.max_rounds = 3, args.max_rounds or 20
        with tempfile.TemporaryDirectory() as tmp:
            graphs = _common.quick_g2o_graphs(tmp)
            only = args.only or ["quick-se2"]
            return _run(args, tmp, {k: v for k, v in graphs.items() if k in only})
    if args.data_dir is None:
        ap.error("no DATA_DIR given and ../shared/data/g2o does not exist")
    graphs = {k: v for k, v in _common.G2O_GRAPHS.items() if not args.only or k in args.only}
    return _run(args, args.data_dir, graphs)


def _run(args, data_dir: str, graphs: dict[str, tuple[str, float]]) -> int:
    rows = []
    for name, (fname, F_star) in graphs.items():
        dgs_F, dran_F, dgs_MB, dran_MB = PAPER.get(name, NO_PAPER)
        g = read_g2o(Path(data_dir) / fname)
        cfg, run_kw = table1_setup(g.dim, "chordal", plain=args.plain)
        init = InitParams(gauss_seidel=True, direct=args.init)
        dran = run_g2o_dran(
            g, args.robots, cfg, max_rounds=args.max_rounds, init_params=init, **run_kw
        )
        dgs = run_g2o_dgs(
            g, args.robots, delta_every=0 if args.plain else TABLE1_DELTA_EVERY, init_params=init
        )
        row = {
            "dataset": name,
            "init": args.init,
            "F_star": F_star,
            "dran_F_init": dran["objective_init"],
            "dran_F": dran["objective_final"],
            "dran_gap_pct": 100 * (dran["objective_final"] / F_star - 1),
            "dran_rounds": dran["rounds_total"],
            "dran_MB": dran["bytes_total"] / 1e6,
            "dran_init_MB": dran["bytes_init"] / 1e6,
            "dran_step_ms": dran["local_step_ms_median"],
            "dran_wall_s": dran["wall_s"],
            "dgs_F": dgs["objective_final"],
            "dgs_gap_pct": 100 * (dgs["objective_final"] / F_star - 1),
            "dgs_rounds": dgs["rounds_total"],
            "dgs_MB": dgs["bytes_total"] / 1e6,
            "targets_met": {
                "F_within_0.1pct": dran["objective_final"] <= 1.001 * F_star,
                "MB_le_half_paper": dran["bytes_total"] / 1e6 <= 0.5 * dran_MB,
                "beats_dgs_F": dran["objective_final"] < dgs["objective_final"],
                "beats_dgs_MB": dran["bytes_total"] < dgs["bytes_total"],
            },
            "paper_dran_F": dran_F,
            "paper_dgs_F": dgs_F,
            "paper_dran_MB": dran_MB,
            "paper_dgs_MB": dgs_MB,
        }
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
        if args.json:
            with open(args.json, "a") as fh:
                fh.write(json.dumps(row) + "\n")
    hdr = (
        f"{'dataset':<15}{'F*':>11}{'DRAN F0':>11}{'DRAN F':>11}{'gap %':>7}{'DGS F':>11}"
        f"{'gap %':>7}{'DRAN MB':>8}{'≤50%':>6}{'DGS MB':>8}{'rounds':>7}  met"
    )
    print(hdr)
    for r in rows:
        met = " ".join(k for k, v in r["targets_met"].items() if v) or "-"
        print(
            f"{r['dataset']:<15}{r['F_star']:>11.6g}{r['dran_F_init']:>11.5g}{r['dran_F']:>11.6g}"
            f"{r['dran_gap_pct']:>7.3f}{r['dgs_F']:>11.6g}{r['dgs_gap_pct']:>7.3f}"
            f"{r['dran_MB']:>8.3f}{0.5 * r['paper_dran_MB']:>6.3g}{r['dgs_MB']:>8.3f}"
            f"{r['dran_rounds']:>7}  {met}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
