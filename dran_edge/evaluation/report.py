"""The text forms of an evaluation report (``dran-edge eval``): JSON-safe values and the Markdown
summary. Pure core module (numpy, stdlib); the report itself is built by dran_edge.evaluation.score.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def json_safe(x: Any) -> Any:
    """JSON-safe: NaN/inf -> None, numpy scalars/arrays -> Python."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, np.ndarray):
        return json_safe(x.tolist())
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def _f(v: Any, fmt: str = ".4f") -> str:
    return "—" if v is None else format(v, fmt)


def _na(v: Any, fmt: str = ".4f") -> str:
    """A ratio to the centralized solution, or why it is missing."""
    return "n/a (no centralized solution)" if v is None else format(v, fmt)


def summary_markdown(r: dict[str, Any]) -> str:
    """A short human summary of an eval report."""
    lines = [f"# Evaluation of `{r['run']}`", ""]
    lines.append(f"- mocap: `{r['mocap']}`" if r["mocap"] else "- mocap: none")
    lines.append(f"- alignment: **{r['align']}**")
    t = r.get("time") or {}
    if t:
        lines.append(
            f"- clock offset t_mocap − t_est: {_f(t.get('time_offset_s'), '.4f')} s "
            f"({t.get('source')})"
        )
    lines.append("")
    if r["robots"]:
        lines += [
            "## Trajectories",
            "",
            "| robot | poses | ATE trans (m) | ATE max (m) | rot RMSE (deg) | ATE log "
            "(paper) | ATE⁰ log | ATE* log | SR_ATE (%) | ATE/ATE* |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for n, e in r["robots"].items():
            f = e.get("final", {})
            lines.append(
                f"| {n} | {f.get('matched_poses', '—')} | {_f(f.get('ate_trans_rmse_m'))} | "
                f"{_f(f.get('ate_trans_max_m'))} | {_f(f.get('ate_rot_rmse_deg'), '.3f')} | "
                f"{_f(f.get('ate_log_rmse'))} | {_f(e.get('init', {}).get('ate_log_rmse'))} | "
                f"{_f(e.get('centralized', {}).get('ate_log_rmse'))} | "
                f"{_f(e.get('sr_ate_pct'), '.1f')} | {_na(e.get('ate_over_atestar'))} |"
            )
        o = r["overall"]
        lines += [
            "",
            f"Overall (each robot weighs 1/N): ATE log "
            f"{_f(o.get('final', {}).get('ate_log_rmse'))}, ATE trans "
            f"{_f(o.get('final', {}).get('ate_trans_rmse_m'))} m, SR_ATE "
            f"{_f(o.get('sr_ate_pct'), '.1f')} %, ATE/ATE* {_na(o.get('ate_over_atestar'))}.",
            "",
        ]
    ob = r.get("objects") or {}
    if ob:
        lines += [
            "## Objects",
            "",
            f"- {ob.get('count')} objects, {ob.get('copies')} robot copies",
            f"- CE (paper): {_f(ob.get('ce'), '.6f')}",
            f"- Bias (paper formula): {_f(ob.get('bias'))}; error of the mean map: "
            f"{_f(ob.get('bias_of_mean'))}",
            "",
        ]
    c = r.get("cost") or {}
    if c:
        lines += [
            "## Cost",
            "",
            f"- F_init {_f(c.get('F_init'))}, F_k {_f(c.get('F_k'))}, "
            f"F* {_f(c.get('F_star'))}, SR_cost {_f(c.get('sr_cost_pct'), '.1f')} %, "
            f"F/F* {_na(c.get('F_over_Fstar'))}",
            "",
        ]
    ir = r.get("inter_robot") or {}
    if ir.get("pairs"):
        lines += [
            "## Inter-robot relative poses",
            "",
            f"- {len(ir['pairs'])} pairs: translation RMSE {_f(ir.get('trans_rmse_m'))} m, "
            f"rotation RMSE {_f(ir.get('rot_rmse_deg'), '.3f')} deg",
            "",
        ]
    rd = r.get("rounds") or {}
    if rd:
        lines += ["## Rounds and bytes", ""] + [f"- {k}: {v}" for k, v in rd.items()] + [""]
    if r.get("notes"):
        lines += ["## Not computed / notes", ""] + [f"- {n}" for n in r["notes"]] + [""]
    return "\n".join(lines)
