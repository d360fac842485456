"""Benchmark: the generalisation suite (``dran_edge.experiments.suite``), the current init against
a baseline init, side by side, worst case per family.

    .venv/bin/python tools/bench/bench_generalisation.py [--quick] [--families F ...]
        [--seeds S ...] [--rounds N] [--baseline never|none] [--baseline-rounds N] [--out DIR]

For every case of the suite (or of ``--families`` × ``--seeds`` at the suite's sizes): the
centralized optimum F* and chordal F, then DRAN (Table 1 setup) from the distributed init with
``InitParams.direct="auto"`` (substructured exact stages where cheap) and, for the baseline,
``direct="never"`` (the block Gauss–Seidel iterations alone, as before). DGS runs on the current
init only. Prints one line per family with the worst case of each number, current | baseline,
and writes ``current/`` and ``baseline/`` (suite.json, suite.md, plots) under ``--out``.
``--baseline-rounds 0`` measures the baseline's initialisation only (no DRAN rounds): the cheap
way to compare F_init/F_chordal and init bytes on big suites.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from dran_edge.experiments import suite  # noqa: E402

KEYS = [
    ("F_init_over_F_chordal", ".4f"),
    ("init_bytes", ".0f"),
    ("F_over_F_star_at_300", ".4f"),
    ("F_over_F_star_at_1000", ".4f"),
    ("stop_F_over_F_star", ".4f"),
    ("dran_F_end_over_F_star", ".4f"),
    ("bytes_at_1pct", ".0f"),
    ("dgs_F_end_over_F_star", ".4f"),
]


def worst(rows: list, key: str):
    vals = [r.get(key) for r in rows]
    if any(v is None for v in vals) and key.startswith(("bytes_at", "round_at")):
        return None  # some case never got there
    vals = [v for v in vals if v is not None]
    return max(vals) if vals else None


def run(cases, rounds: int, init: str, dgs: bool, out: Path | None) -> list:
    rows = []
    for k, case in enumerate(cases):
        t0 = time.perf_counter()
        row = suite.run_case(case, rounds=rounds, init_direct=init, dgs=dgs)
        print(
            f"[{init} {k + 1}/{len(cases)}] {case.name}: F_init/F_chord "
            f"{row['F_init_over_F_chordal']:.4f}, end {row['dran_F_end_over_F_star']:.5f} F*, "
            f"stop at {row['stop_round']}, {time.perf_counter() - t0:.0f} s",
            file=sys.stderr,
            flush=True,
        )
        rows.append(row)
        if out is not None:  # after every case, so a long run leaves its partial results
            out.mkdir(parents=True, exist_ok=True)
            (out / "suite.json").write_text(
                json.dumps({"rounds": rounds, "init": init, "rows": rows}, indent=1)
            )
    if out is not None and rows:
        (out / "suite.md").write_text(suite.markdown_table(rows) + "\n")
        suite.plot(rows, out)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="the suite's two small graphs, 200 rounds")
    ap.add_argument("--families", nargs="+", choices=sorted(suite.FAMILIES))
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument(
        "--rounds", type=int, default=None, help="DRAN rounds (default 1000, quick 200)"
    )
    ap.add_argument(
        "--baseline",
        choices=("never", "none"),
        default="never",
        help="baseline init: the block iterations only (never), or no baseline",
    )
    ap.add_argument(
        "--baseline-rounds",
        type=int,
        default=None,
        help="DRAN rounds of the baseline (default: --rounds; 0: init only)",
    )
    ap.add_argument("--no-dgs", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    rounds = args.rounds or (200 if args.quick else 1000)
    cases = suite.default_cases(args.quick, tuple(args.seeds))
    if args.families:
        cases = [c for c in cases if c.family in args.families]
    cur = run(cases, rounds, "auto", not args.no_dgs, args.out and args.out / "current")
    base = []
    if args.baseline != "none":
        b_rounds = rounds if args.baseline_rounds is None else max(args.baseline_rounds, 1)
        base = run(cases, b_rounds, args.baseline, False, args.out and args.out / "baseline")
    fams = sorted({r["family"] for r in cur})
    print(
        "worst case per family: current (direct=auto)"
        + (" / baseline (direct=never)" if base else "")
    )
    print("| family | cases | " + " | ".join(k for k, _ in KEYS) + " |")
    print("|---|---|" + "---|" * len(KEYS))
    for fam in fams:
        rc = [r for r in cur if r["family"] == fam]
        rb = [r for r in base if r["family"] == fam]
        cells = []
        for key, spec in KEYS:
            a = worst(rc, key)
            s = "–" if a is None else format(a, spec)
            if rb and not (
                key.startswith("dgs")
                or (
                    args.baseline_rounds == 0 and key not in ("F_init_over_F_chordal", "init_bytes")
                )
            ):
                b = worst(rb, key)
                s += " / " + ("–" if b is None else format(b, spec))
            cells.append(s)
        print(f"| {fam} | {len(rc)} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
