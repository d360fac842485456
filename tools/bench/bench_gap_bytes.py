"""Benchmark: DRAN's (gap, MB) curve on Table 1 graphs against reference points of another
solver (by default DPGO's end points, docs/notes/generalisation.md, "DRAN against DPGO").

    .venv/bin/python tools/bench/bench_gap_bytes.py RUN.json [RUN.json ...] [--plot DIR]
    .venv/bin/python tools/bench/bench_gap_bytes.py --quick   # a generated 240-pose chain

Each RUN.json is the output of ``dran-edge bench g2o FILE --json --curve [...]`` (F* and the
curve: rounds after the init, bytes sent so far with the init's, F). The gap is (F − F*)/F*.
For every reference point (gap_ref, MB_ref) of the run's graph it prints the first curve point
at or below gap_ref: DRAN's MB there and the ratio MB_DRAN / MB_ref (the target: ≤ 0.1), or
"never" with the smallest gap DRAN reached. Only the reference's *end points* are compared,
not its whole curve. ``--quick``: runs ``bench g2o --refine auto --curve`` on a generated
240-pose 2D chain (3 robots) against a made-up reference point (1e-3, 1 MB), to exercise the
script. ``--plot DIR``: one PNG per graph (every run of that graph on it), gap against MB, log-log.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

#: DPGO from the centralized chordal init, 5-robot contiguous splits, 1000 iterations (one robot
#: per iteration; sphere2500: 500), bytes at 8·r·(d+1) per public pose per iteration, r = 5:
#: (gap, MB) where it ended, as measured outside this repository (docs/notes/generalisation.md).
DPGO_END = {
    "parking-garage": (1.0e-2, 239.0),
    "input_M3500_g2o": (1.1e-3, 94.0),
    "CSAIL": (9.1e-6, 17.0),
    "sphere2500": (2.3e-7, 32.0),
}


def gap_curve(run: dict) -> list[tuple[float, float]]:
    """(MB sent so far, init included; gap) per curve point of a ``bench g2o --curve`` run."""
    F_star = run["F_star"]
    return [(b / 1e6, (F - F_star) / F_star) for _, b, F in run["curve"]]


def first_at(curve: list[tuple[float, float]], gap: float) -> float | None:
    """MB of the first point at or below ``gap``; None if the curve never gets there."""
    return next((mb for mb, g in curve if g <= gap), None)


def compare(run: dict, refs: dict = DPGO_END) -> dict | None:
    """The row of one run: the reference point, DRAN's MB at that gap and the ratio."""
    ref = refs.get(run["dataset"])
    if ref is None:
        return None
    curve = gap_curve(run)
    mb = first_at(curve, ref[0])
    return {
        "dataset": run["dataset"],
        "refine": run.get("refine", "off"),
        "ref_gap": ref[0],
        "ref_MB": ref[1],
        "dran_MB": mb,
        "ratio": None if mb is None else mb / ref[1],
        "dran_best_gap": min(g for _, g in curve),
        "dran_end_gap": curve[-1][1],
        "dran_end_MB": curve[-1][0],
        "init_MB": run["bytes_init"] / 1e6,
    }


def _label(run: dict) -> str:
    label = f"DRAN, refine {run.get('refine', 'off')}"
    if run.get("refine_hessian"):
        label += f", {run['refine_hessian']} Hessian"
    if run.get("refine_used") is False:
        label += " (declined)"
    if run.get("polish_used"):
        label += f" + polish ({len(run.get('polish_F_history', [])) - 1} steps)"
    return label


def plot(runs: list[dict], row: dict | None, out_dir: Path) -> Path:
    """One PNG for one graph: every run's (MB, gap) curve and the reference point."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for run in runs:
        curve = gap_curve(run)
        ax.plot(
            [mb for mb, _ in curve],
            [max(g, 1e-12) for _, g in curve],
            ".-",
            ms=3,
            label=_label(run),
        )
    ax.axvline(runs[0]["bytes_init"] / 1e6, color="0.6", lw=0.6, ls=":", label="init's end")
    if row is not None:
        ax.plot([row["ref_MB"]], [row["ref_gap"]], "r*", ms=10, label="DPGO end point")
        ax.axvline(row["ref_MB"] / 10, color="r", lw=0.6, ls="--", label="1/10 of DPGO's MB")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("MB sent (init included)")
    ax.set_ylabel("(F − F*) / F*")
    ax.set_title(runs[0]["dataset"])
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"gap_bytes_{runs[0]['dataset']}.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _fmt(v, spec: str) -> str:
    return "never" if v is None else format(v, spec)


def _quick_run(tmp: Path) -> Path:
    """``bench g2o --json --curve --refine auto`` on a generated chain; the JSON's path."""
    import contextlib
    import io

    from dran_edge.cli.app import main as cli
    from dran_edge.experiments import suite
    from dran_edge.formats.g2o import write_g2o

    g, _ = suite.make_graph(suite.Case("car2d", 240, 1, robots=3))
    path = tmp / "quick-chain.g2o"
    write_g2o(path, g, g.poses)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
        rc = cli(
            ["bench", "g2o", str(path), "--robots", "3", "--json", "--curve", "--refine", "auto"]
        )
    if rc != 0:
        raise SystemExit(rc)
    out = tmp / "quick-chain.json"
    out.write_text(buf.getvalue())
    return out


def main(argv=None) -> int:
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="*", help="bench g2o --json --curve outputs")
    ap.add_argument("--quick", action="store_true", help="a generated chain (see above)")
    ap.add_argument("--plot", metavar="DIR", help="write gap_bytes_GRAPH.png here")
    args = ap.parse_args(argv)
    if args.quick:
        DPGO_END.setdefault("quick-chain", (1e-3, 1.0))
        args.runs = [str(_quick_run(Path(tempfile.mkdtemp(prefix="gap_bytes_"))))]
    if not args.runs:
        ap.error("give bench g2o --json --curve outputs, or --quick")
    print(
        "| graph | run | DPGO gap / MB | DRAN MB at that gap (init MB) | ratio | DRAN end gap / MB |"
    )
    print("|---|---|---|---|---|---|")
    by_graph: dict[str, list[dict]] = {}
    for path in args.runs:
        run = json.loads(Path(path).read_text())
        by_graph.setdefault(run["dataset"], []).append(run)
        row = compare(run)
        if row is None:
            continue
        print(
            f"| {row['dataset']} | {_label(run)} | {row['ref_gap']:.1e} / {row['ref_MB']:g} | "
            f"{_fmt(row['dran_MB'], '.3f')} ({row['init_MB']:.3f}) | {_fmt(row['ratio'], '.4f')} | "
            f"{row['dran_end_gap']:.2e} / {row['dran_end_MB']:.3f} |"
        )
    for runs in by_graph.values() if args.plot else ():
        plot(runs, compare(runs[0]), Path(args.plot))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
