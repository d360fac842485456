"""The PNG plots of ``dran-edge eval RUN_DIR``: trajectories.png, rounds.png, errors.png.

matplotlib is imported lazily (the ``eval`` extra), with the Agg backend:

- trajectories.png: top view of every robot's estimate (initial, final) against mocap ground
  truth, with the objects: ground truth and each robot's copy (the paper's Fig. 1b/c);
- rounds.png: SR_cost and F/F* at the replay's sampled rounds (report.json's ``round_costs``),
  consensus residual and bytes over the DRAN rounds (rounds.csv);
- errors.png: ATE per robot (initial / final / centralized), translation error over time.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dran_edge.errors import DependencyError

if TYPE_CHECKING:
    from dran_edge.evaluation.score import RunEvaluation, RunPlotData


def _plt() -> Any:
    try:
        import matplotlib
    except ImportError:
        raise DependencyError(
            "plots need matplotlib: pip install 'dran-edge[eval]' (or pass --no-plots)"
        ) from None
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def write_plots(evaluation: RunEvaluation, eval_dir: Path) -> list[Path]:
    """The PNG plots of ``evaluation`` (from :func:`~dran_edge.evaluation.score.evaluate_run`)
    into ``eval_dir``."""
    plt = _plt()
    written = []
    for fn in (_trajectories, _rounds, _errors):
        p = fn(plt, evaluation.report, evaluation.plot_data, eval_dir)
        if p is not None:
            written.append(p)
    return written


def _trajectories(
    plt: Any, report: dict[str, Any], data: RunPlotData, eval_dir: Path
) -> Path | None:
    robots = data.robots
    aligned = data.aligned
    if not aligned and not data.objects:
        return None
    fig, ax = plt.subplots(figsize=(7.5, 7))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, (name, rb) in enumerate(robots.items()):
        c = colours[k % len(colours)]
        if name not in aligned:
            continue
        a = rb.assoc["final"]
        ax.plot(
            a.T_ref[:, 0, 3],
            a.T_ref[:, 1, 3],
            color="0.25",
            lw=1.0,
            ls="--",
            label="mocap" if k == 0 else None,
        )
        if "init" in aligned[name]:
            Ti = aligned[name]["init"]
            ax.plot(Ti[:, 0, 3], Ti[:, 1, 3], color=c, lw=0.8, ls=":", alpha=0.7)
        Tf = aligned[name]["final"]
        ax.plot(Tf[:, 0, 3], Tf[:, 1, 3], color=c, lw=1.6, label=name)
    ob = data.objects
    if ob:
        Y, present, gt = ob.Y, ob.present, ob.gt
        for i, name in enumerate(ob.names):
            c = colours[list(robots).index(name) % len(colours)]
            P = Y[i][present[i]]
            ax.scatter(P[:, 0, 3], P[:, 1, 3], marker="x", s=25, color=c, lw=1)
        ok = np.all(np.isfinite(gt), axis=(-1, -2))
        if ok.any():
            ax.scatter(
                gt[ok, 0, 3],
                gt[ok, 1, 3],
                marker="s",
                s=70,
                facecolors="none",
                edgecolors="k",
                label="objects (mocap)",
            )
            for oid, g in zip(np.array(ob.ids)[ok], gt[ok]):
                ax.annotate(
                    str(oid),
                    (g[0, 3], g[1, 3]),
                    xytext=(4, 4),
                    textcoords="offset points",
                    fontsize=7,
                )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    o = report.get("overall", {}).get("final", {})
    title = f"alignment {report['align']}"
    if o:
        title += f" — ATE {o.get('ate_trans_rmse_m', float('nan')):.3f} m"
    ax.set_title(title + "\n(dotted: initial estimate, x: robots' object copies)", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    p = eval_dir / "trajectories.png"
    fig.tight_layout()
    fig.savefig(p, dpi=120)
    plt.close(fig)
    return p


Panel = tuple[str, str, np.ndarray, np.ndarray]
"""(title, y label, rounds, values) of one rounds.png panel; values (n,) or (2, n) (per robot,
per link)."""


def round_panels(
    rounds: dict[str, np.ndarray],
    round_costs: dict[str, np.ndarray] | None,
    n_robots: int,
    n_links: int,
) -> list[Panel]:
    """The panels of rounds.png, each saying what it plots.

    With ``round_costs`` (report.json's, sampled by the replay on the merged graph as of each
    sampled round k): SR_cost_k = (F_init,k − F_k)/(F_init,k − F*_k) (paper Sec. 6.2) and
    F_k/F*_k, both against the centralized optimum of the graph as of round k. Without them, the
    raw sum of the robots' local costs of rounds.csv (which grows with the graphs). The
    consensus panel is rounds.csv's ``consensus_error``: per round, the largest of the robots'
    own consensus residuals — not the paper's CE of the summary (docs/eval.md). Bytes per round
    are shown per robot and per communication link, besides the cumulative total.
    """
    panels: list[Panel] = []
    r = np.asarray(rounds["round"], dtype=np.float64)
    if round_costs is not None:
        rk = round_costs["round"]
        panels.append(
            (
                "SR_cost_k = (F_init,k − F_k)/(F_init,k − F*_k), paper Sec. 6.2: SE-Sync costs "
                "of the merged graph as of round k",
                "SR_cost (%)",
                rk,
                round_costs["sr_cost_pct"],
            )
        )
        panels.append(
            (
                "F_k / F*_k: the robots' estimate's SE-Sync cost over the centralized optimum "
                "of the merged graph as of round k",
                "F / F* (1 = optimum)",
                rk,
                round_costs["f_over_fstar"],
            )
        )
    elif "cost" in rounds:
        panels.append(
            (
                "sum of the robots' local costs (grows as the graphs grow; not F/F*)",
                "cost (SE-Sync objective units)",
                r,
                rounds["cost"],
            )
        )
    if "consensus_error" in rounds:
        panels.append(
            (
                "largest robot's own consensus residual per round (not the summary's CE)",
                "max_i residual_i",
                r,
                rounds["consensus_error"],
            )
        )
    if "bias" in rounds:  # a rounds.csv from elsewhere may carry the paper's Bias per round
        panels.append(("Bias per round (paper Sec. 6.2)", "Bias", r, rounds["bias"]))
    if "bytes_round" in rounds:
        b = np.asarray(rounds["bytes_round"], dtype=np.float64)
        panels.append(
            (
                f"bytes sent per round: per robot (mean of {n_robots}) and per link "
                f"(mean of {n_links})",
                "bytes / round",
                r,
                np.stack([b / max(n_robots, 1), b / max(n_links, 1)]),
            )
        )
    if "bytes_total" in rounds:
        panels.append(
            ("bytes sent by all robots, cumulative", "bytes (total)", r, rounds["bytes_total"])
        )
    return panels


def _rounds(plt: Any, report: dict[str, Any], data: RunPlotData, eval_dir: Path) -> Path | None:
    rounds = data.rounds
    if rounds is None or len(rounds.get("round", [])) == 0:
        return None
    panels = round_panels(
        rounds, data.round_costs, data.robot_count, len(data.comm_graph or ()) or 1
    )
    if not panels:
        return None
    fig, axes = plt.subplots(
        len(panels), 1, figsize=(7.5, 2.5 * len(panels)), sharex=True, squeeze=False
    )
    for ax, (title, label, x, y) in zip(axes[:, 0], panels):
        if np.ndim(y) == 2:
            ax.plot(x, y[0], lw=1.4, label="per robot")
            ax.plot(x, y[1], lw=1.0, ls="--", label="per link")
            ax.legend(fontsize=7, loc="best")
        elif len(x) < len(rounds["round"]):  # sampled rounds: mark the samples
            ax.plot(x, y, lw=1.4, marker="o", ms=3)
        else:
            ax.plot(x, y, lw=1.4)
        ax.set_title(title, fontsize=8)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
        if (title.startswith("largest") or title.startswith("F_k")) and np.nanmin(y) > 0:
            ax.set_yscale("log")
    axes[-1, 0].set_xlabel("round")
    p = eval_dir / "rounds.png"
    fig.tight_layout()
    fig.savefig(p, dpi=120)
    plt.close(fig)
    return p


def _errors(plt: Any, report: dict[str, Any], data: RunPlotData, eval_dir: Path) -> Path | None:
    per = report.get("robots", {})
    if not per:
        return None
    names = list(per)
    kinds = [k for k in ("init", "final", "centralized") if any(k in per[n] for n in names)]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    w = 0.8 / max(len(kinds), 1)
    x = np.arange(len(names))
    for j, kind in enumerate(kinds):
        v = [per[n].get(kind, {}).get("ate_trans_rmse_m") or np.nan for n in names]
        a1.bar(x + (j - (len(kinds) - 1) / 2) * w, v, w, label=kind)
    a1.set_xticks(x, names, rotation=30, fontsize=8)
    a1.set_ylabel("ATE translation RMSE (m)")
    a1.legend(fontsize=8)
    a1.grid(axis="y", alpha=0.3)
    for name in names:
        rb = data.robots[name]
        if name not in data.aligned:
            continue
        a = rb.assoc["final"]
        err = np.linalg.norm(data.aligned[name]["final"][:, :3, 3] - a.T_ref[:, :3, 3], axis=1)
        a2.plot(a.stamps_s - a.stamps_s[0], err, lw=1, label=name)
    a2.set_xlabel("time since the robot's first pose (s)")
    a2.set_ylabel("translation error (m)")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=8)
    p = eval_dir / "errors.png"
    fig.tight_layout()
    fig.savefig(p, dpi=120)
    plt.close(fig)
    return p
