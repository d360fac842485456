"""PNG plots of an evaluation (``dran-edge eval``): matplotlib, imported lazily, Agg backend.

- ``trajectories.png``: top view of every robot's estimate (initial, final) against mocap ground
  truth, with the objects: ground truth, each robot's copy, the robots' mean (the paper's
  Fig. 1b/c).
- ``rounds.png``: SR_cost, consensus error and bytes over the DRAN rounds (``rounds.csv``).
- ``errors.png``: ATE per robot (initial / final / centralized) and the translation error over
  time.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dran_edge import metrics
from dran_edge.errors import DependencyError


def _plt():
    try:
        import matplotlib
    except ImportError:
        raise DependencyError("plots need matplotlib: pip install 'dran-edge[eval]' (or pass "
                              "--no-plots)") from None
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def write_plots(report: dict[str, Any], eval_dir: Path) -> list[Path]:
    plt = _plt()
    data = report["_"]
    written = []
    for fn in (_trajectories, _rounds, _errors):
        p = fn(plt, report, data, eval_dir)
        if p is not None:
            written.append(p)
    return written


def _trajectories(plt, report, data, eval_dir):
    robots = data["robots"]
    aligned = data["aligned"]
    if not aligned and not data["objects"]:
        return None
    fig, ax = plt.subplots(figsize=(7.5, 7))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, (name, rb) in enumerate(robots.items()):
        c = colours[k % len(colours)]
        if name not in aligned:
            continue
        a = rb.assoc["final"]
        ax.plot(a.T_ref[:, 0, 3], a.T_ref[:, 1, 3], color="0.25", lw=1.0, ls="--",
                label="mocap" if k == 0 else None)
        if "init" in aligned[name]:
            Ti = aligned[name]["init"]
            ax.plot(Ti[:, 0, 3], Ti[:, 1, 3], color=c, lw=0.8, ls=":", alpha=0.7)
        Tf = aligned[name]["final"]
        ax.plot(Tf[:, 0, 3], Tf[:, 1, 3], color=c, lw=1.6, label=name)
    ob = data["objects"]
    if ob:
        Y, present, gt, y_avg = ob["Y"], ob["present"], ob["gt"], ob["y_avg"]
        for i, name in enumerate(ob["names"]):
            c = colours[list(robots).index(name) % len(colours)]
            P = Y[i][present[i]]
            ax.scatter(P[:, 0, 3], P[:, 1, 3], marker="x", s=25, color=c, lw=1)
        ok = np.all(np.isfinite(gt), axis=(-1, -2))
        if ok.any():
            ax.scatter(gt[ok, 0, 3], gt[ok, 1, 3], marker="s", s=70, facecolors="none",
                       edgecolors="k", label="objects (mocap)")
            for oid, g in zip(np.array(ob["ids"])[ok], gt[ok]):
                ax.annotate(str(oid), (g[0, 3], g[1, 3]), xytext=(4, 4),
                            textcoords="offset points", fontsize=7)
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


def _rounds(plt, report, data, eval_dir):
    rounds = data["rounds"]
    if rounds is None or len(rounds.get("round", [])) == 0:
        return None
    cost = data["cost"]
    r = rounds["round"]
    panels = []
    if "cost" in rounds and cost.get("F_init") is not None and cost.get("F_star") is not None:
        panels.append(("SR_cost (%)", metrics.sr_cost(cost["F_init"], rounds["cost"],
                                                       cost["F_star"])))
    elif "cost" in rounds:
        panels.append(("cost", rounds["cost"]))
    for col, label in (("consensus_error", "consensus error (CE)"), ("bias", "Bias"),
                       ("bytes_total", "bytes sent (total)")):
        if col in rounds:
            panels.append((label, rounds[col]))
    if not panels:
        return None
    fig, axes = plt.subplots(len(panels), 1, figsize=(7, 2.3 * len(panels)), sharex=True,
                             squeeze=False)
    for ax, (label, y) in zip(axes[:, 0], panels):
        ax.plot(r, y, lw=1.4)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
        if label.startswith("consensus") and np.nanmin(y) > 0:
            ax.set_yscale("log")
    axes[-1, 0].set_xlabel("round")
    p = eval_dir / "rounds.png"
    fig.tight_layout()
    fig.savefig(p, dpi=120)
    plt.close(fig)
    return p


def _errors(plt, report, data, eval_dir):
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
        rb = data["robots"][name]
        if name not in data["aligned"]:
            continue
        a = rb.assoc["final"]
        err = np.linalg.norm(data["aligned"][name]["final"][:, :3, 3] - a.T_ref[:, :3, 3], axis=1)
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
