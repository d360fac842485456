"""Score a run against OptiTrack: load, associate, align, compute the paper's metrics, report.

The shell behind ``dran-edge eval`` (docs/eval.md). It reads the run directory
(docs/run-format.md): ``mission.yaml``, the Motive CSV, and what ``dran-edge replay`` wrote under
``out/`` (per robot ``<robot>.tum``, ``<robot>_init.tum``, ``objects.csv``; ``merged.g2o``,
``merged_vertices.csv``, ``rounds.csv``, ``report.json``). Optional files that are absent only
remove the metrics that need them (the report's ``notes`` say which and why); a file that is
present but malformed is an error naming its line.

Ground truth: ``T_world_body = T_world_marker · T_body_marker⁻¹`` (mission.yaml's pivot offset),
objects averaged over their tracked frames (Fréchet mean). Time: ``t_mocap = t_est + offset``;
the offset is given, or from ``mission.yaml`` (``mocap.start_ns``), or estimated from angular
speeds (align.estimate_time_offset). Alignment: one for all robots (se3 / sim3 / yaw), none, or
the paper's protocol (per robot, the initial world-to-robot frame from mocap at the first
matched pose of the initial estimate; the same frame is used for the initial, final and
centralized estimates and the robot's object copies).

SR_ATE needs the centralized solution: ``out/centralized/<robot>/<robot>.tum`` if present;
otherwise merged.g2o solved centrally (:mod:`dran_edge.evaluation.centralized`, which also gives
SR_cost's SE-Sync costs F_init, F_k and F*); without merged.g2o, ``cost_init / cost_final /
cost_centralized`` of out/report.json (the same objective on the same graph, computed by the
replay). Per round, SR_cost and F/F* come from report.json's ``round_costs`` (the merged graph
as of sampled rounds, :mod:`dran_edge.replay.round_costs`). One trajectory alone is scored by
:mod:`dran_edge.evaluation.traj_score`; the multi-robot metrics are in
:mod:`dran_edge.evaluation.fleet_metrics`, the plots in :mod:`dran_edge.evaluation.plots`.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dran_edge.errors import InputError
from dran_edge.evaluation import align, metrics
from dran_edge.evaluation.centralized import centralized_from_g2o
from dran_edge.evaluation.fleet_metrics import ObjectPlotData, inter_robot_errors, object_maps
from dran_edge.evaluation.report import json_safe, summary_markdown
from dran_edge.evaluation.run_inputs import (
    RobotTracks,
    read_estimates,
    read_ground_truth,
    read_replay_report,
)
from dran_edge.formats.run_outputs import read_rounds_csv

if TYPE_CHECKING:
    from dran_edge.formats.run_dir import Mission

log = logging.getLogger(__name__)

EVAL_FORMAT = "dran-edge-eval/1"

ESTIMATE_KINDS = ("init", "final", "centralized")
"""The estimates of a robot that are scored: initial, decentralized final, centralized."""


@dataclass(frozen=True)
class EvalOptions:
    """How to score a run."""

    align: str = "paper"
    """Alignment: none, se3, sim3, yaw or paper (see align.py)."""
    mocap_path: str | None = None
    """Motive CSV to use instead of the run's (``mission.yaml`` mocap.file or ``mocap.csv``)."""
    time_offset_s: float | None = None
    """``t_mocap = t_est + time_offset_s``; None: from mission.yaml, else estimated."""
    max_gap_s: float = 0.1
    """Longest mocap occlusion gap interpolated across (s)."""
    rpe_delta_s: float = 1.0
    """Pose-pair spacing of the relative pose error (s)."""
    inter_robot_rate_hz: float = 2.0
    """Rate of the common instants at which inter-robot relative poses are compared (Hz)."""
    centralized: bool = True
    """Solve merged.g2o centrally when no centralized trajectories are given."""
    plots: bool = True
    """Write PNG plots (needs matplotlib, the ``eval`` extra)."""


@dataclass(frozen=True)
class RunPlotData:
    """What the plots need beyond the JSON report: the aligned tracks and the raw rounds."""

    robots: dict[str, RobotTracks]
    aligned: dict[str, dict[str, np.ndarray]]
    """Robot -> estimate kind -> aligned matched poses."""
    rounds: dict[str, np.ndarray] | None
    objects: ObjectPlotData | None
    round_costs: dict[str, np.ndarray] | None
    """report.json's ``round_costs`` as arrays (``round``, ``F_init``, ``F_k``, ``F_star``,
    ``sr_cost_pct``, ``f_over_fstar``; None where missing), None without them."""
    comm_graph: list[tuple[int, int]]
    """Undirected communication links (robot id pairs): the per-link bytes of rounds.png."""
    robot_count: int
    """Robots of the mission (all of them send): the per-robot bytes of rounds.png."""


@dataclass(frozen=True)
class RunEvaluation:
    """The result of :func:`evaluate_run`."""

    report: dict[str, Any]
    """The JSON report (report.json, ``--json``; ``summary`` holds the headline numbers)."""
    plot_data: RunPlotData


# ----------------------------------------------------------------------------------- scoring


def _centralized(
    run_dir: Path, robots: dict[str, RobotTracks], opt: EvalOptions, notes: list[str]
) -> dict[str, Any]:
    """Adds the centralized estimate to ``robots`` (from merged.g2o where none was exported);
    returns merged.g2o's costs (empty without them)."""
    cost: dict[str, Any] = {}
    if any("centralized" in rb.est for rb in robots.values()):
        notes.append("centralized trajectories read from out/centralized/")
    elif opt.centralized:
        central, cost = centralized_from_g2o(
            run_dir,
            {n: rb.est["final"] for n, rb in robots.items()},
            notes,
            {n: rb.est["init"] for n, rb in robots.items() if "init" in rb.est},
        )
        for name, est in central.items():
            robots[name].est["centralized"] = est
    return cost


def _cost_report(cost: dict[str, Any], replay_report: dict[str, Any]) -> dict[str, Any]:
    """The report's cost section with SR_cost and F/F*.

    The replay's costs (cost_init / cost_final / cost_centralized: the merged graph's SE-Sync
    objectives at the last round) are used only without merged.g2o's own, never mixed.
    """
    replay_cost = {
        k_cost: float(replay_report[k_rep])
        for k_rep, k_cost in (
            ("cost_init", "F_init"),
            ("cost_final", "F_k"),
            ("cost_centralized", "F_star"),
        )
        if isinstance(replay_report.get(k_rep), (int, float))
        and not isinstance(replay_report.get(k_rep), bool)
    }
    if not cost and replay_cost:
        cost = {
            "source": "out/report.json (cost_init / cost_final / cost_centralized)",
            **replay_cost,
        }
    if all(cost.get(k) is not None for k in ("F_init", "F_k", "F_star")):
        cost["sr_cost_pct"] = metrics.sr_cost(cost["F_init"], cost["F_k"], cost["F_star"])
    if cost.get("F_k") is not None and cost.get("F_star") is not None:
        cost["F_over_Fstar"] = metrics.cost_ratio(cost["F_k"], cost["F_star"])
    return cost


def _round_costs(replay_report: dict[str, Any], path: Path) -> dict[str, np.ndarray] | None:
    """report.json's ``round_costs`` as float arrays (None -> NaN), SR_cost and F/F* computed
    from its F_init, F_k and F_star; None when the replay sampled none."""
    rc = replay_report.get("round_costs")
    if not isinstance(rc, dict) or not rc.get("round"):
        return None
    try:
        out = {
            c: np.array([np.nan if v is None else float(v) for v in rc[c]])
            for c in ("round", "F_init", "F_k", "F_star")
        }
    except (KeyError, TypeError, ValueError):
        raise InputError(
            "round_costs: expected lists round, F_init, F_k, F_star of numbers",
            path=str(path),
        ) from None
    if len({len(v) for v in out.values()}) != 1:
        raise InputError("round_costs: lists of different lengths", path=str(path))
    out["sr_cost_pct"] = np.asarray(metrics.sr_cost(out["F_init"], out["F_k"], out["F_star"]))
    out["f_over_fstar"] = np.asarray(metrics.cost_ratio(out["F_k"], out["F_star"]))
    return out


def _estimated_offset(
    robots: dict[str, RobotTracks], scored: list[str], notes: list[str]
) -> dict[str, float]:
    """{robot: mocap clock offset (s)} estimated from angular, else linear, speeds."""
    per = {}
    for n in scored:
        rb = robots[n]
        gt_time_s, gt_T, gt_valid = rb.ground_truth()
        # The initial estimate is the raw odometry: locally smoother than the
        # optimised one, so its angular speed correlates best.
        src = rb.est.get("init", rb.est["final"])
        for signal in ("angular", "linear"):
            try:
                per[n] = align.estimate_time_offset(
                    *src, gt_time_s, gt_T, valid_ref=gt_valid, signal=signal
                ).offset_s
                break
            except InputError as exc:
                notes.append(f"robot {n}: time offset not estimated from {signal} speeds ({exc})")
    if not per:
        raise InputError(
            "could not estimate the mocap clock offset from any robot; "
            "give --time-offset or mocap.start_ns in mission.yaml"
        )
    return per


def _time_offset(
    mission: Mission,
    robots: dict[str, RobotTracks],
    scored: list[str],
    opt: EvalOptions,
    notes: list[str],
) -> dict[str, Any]:
    """The report's ``time`` section: ``t_mocap = t_est + time_offset_s`` and its source."""
    offset_info: dict[str, Any] = {}
    if opt.time_offset_s is not None:
        offset, source = opt.time_offset_s, "given"
    elif mission.mocap_start_ns is not None:
        offset, source = -mission.mocap_start_ns * 1e-9, "mission.yaml mocap.start_ns"
    else:
        per = _estimated_offset(robots, scored, notes)
        offset, source = float(np.median(list(per.values()))), "estimated"
        offset_info["per_robot_s"] = per
    offset_info.update({"time_offset_s": offset, "source": source})
    return offset_info


def _associate(
    robots: dict[str, RobotTracks], scored: list[str], offset_s: float, opt: EvalOptions
) -> None:
    """Matches every estimate of the ``scored`` robots to their ground truth."""
    for n in scored:
        rb = robots[n]
        gt_time_s, gt_T, gt_valid = rb.ground_truth()
        for kind, (s, T) in rb.est.items():
            rb.assoc[kind] = align.associate(
                s,
                T,
                gt_time_s,
                gt_T,
                valid_ref=gt_valid,
                time_offset_s=offset_s,
                max_gap_s=opt.max_gap_s,
                what=f"robot {n} ({kind} estimate)",
            )


def _fit_alignments(
    robots: dict[str, RobotTracks], scored: list[str], align_kind: str
) -> dict[str, dict[str, align.Alignment]]:
    """Estimate kind -> robot -> alignment: per robot (paper: anchored on the initial
    estimate, else the final) or one for all robots (se3 / sim3 / yaw / none)."""
    alignments: dict[str, dict[str, align.Alignment]] = {}
    for kind in ESTIMATE_KINDS:
        have = [n for n in scored if kind in robots[n].assoc]
        if not have:
            continue
        if align_kind == "paper":
            alignments[kind] = {}
            for n in have:
                rb = robots[n]
                anchor = rb.assoc.get("init", rb.assoc["final"])
                alignments[kind][n] = align.fit_alignment("paper", anchor.T_est, anchor.T_ref)
        else:
            Te = np.concatenate([robots[n].assoc[kind].T_est for n in have])
            Tr = np.concatenate([robots[n].assoc[kind].T_ref for n in have])
            a = align.fit_alignment(align_kind, Te, Tr)
            alignments[kind] = {n: a for n in have}
    return alignments


def _trajectory_metrics(
    robots: dict[str, RobotTracks],
    alignments: dict[str, dict[str, align.Alignment]],
    opt: EvalOptions,
) -> tuple[dict[str, Any], dict[str, Any], dict[str, dict[str, np.ndarray]]]:
    """(per robot, overall, aligned poses): ATE per robot and estimate kind, and over all."""
    per_robot: dict[str, Any] = {}
    overall: dict[str, Any] = {}
    aligned: dict[str, dict[str, np.ndarray]] = {}
    for kind, al_by in alignments.items():
        Te_all: list[np.ndarray] = []
        Tr_all: list[np.ndarray] = []
        grp: list[np.ndarray] = []
        for n, al in al_by.items():
            a = robots[n].assoc[kind]
            T_al = al.apply(a.T_est)
            aligned.setdefault(n, {})[kind] = T_al
            st = metrics.ate_trans_stats_m(T_al, a.T_ref)
            entry = {
                "matched_poses": a.matched_poses,
                "ate_log_rmse": metrics.ate_log_rmse(T_al, a.T_ref),
                "ate_trans_rmse_m": st["rmse_m"],
                "ate_trans_max_m": st["max_m"],
                "ate_rot_rmse_deg": metrics.ate_rot_rmse_deg(T_al, a.T_ref),
                "alignment": al.to_json(),
            }
            if kind == "final":
                entry["rpe"] = metrics.rpe(a.stamps_s, T_al, a.T_ref, delta_s=opt.rpe_delta_s)
            per_robot.setdefault(n, {})[kind] = entry
            Te_all.append(T_al)
            Tr_all.append(a.T_ref)
            grp.append(np.full(len(T_al), len(grp)))
        Te_c, Tr_c, g_c = np.concatenate(Te_all), np.concatenate(Tr_all), np.concatenate(grp)
        overall[kind] = {
            "robots": len(al_by),
            "ate_log_rmse": metrics.ate_log_rmse(Te_c, Tr_c, g_c),
            "ate_trans_rmse_m": metrics.ate_trans_rmse_m(Te_c, Tr_c, g_c),
        }
    return per_robot, overall, aligned


def _success_rates(
    per_robot: dict[str, Any], overall: dict[str, Any], scored: list[str], notes: list[str]
) -> None:
    """Adds SR_ATE and ATE/ATE* (paper Sec. 6.2) per robot and overall where all estimates are."""
    for e in per_robot.values():
        if {"init", "final", "centralized"} <= e.keys():
            e["sr_ate_pct"] = metrics.sr_ate(
                e["init"]["ate_log_rmse"],
                e["final"]["ate_log_rmse"],
                e["centralized"]["ate_log_rmse"],
            )
        if {"final", "centralized"} <= e.keys():
            e["ate_over_atestar"] = metrics.ate_ratio(
                e["final"]["ate_log_rmse"], e["centralized"]["ate_log_rmse"]
            )
    if {"init", "final", "centralized"} <= overall.keys():
        overall["sr_ate_pct"] = metrics.sr_ate(
            overall["init"]["ate_log_rmse"],
            overall["final"]["ate_log_rmse"],
            overall["centralized"]["ate_log_rmse"],
        )
        overall["sr_ate_trans_pct"] = metrics.sr_ate(
            overall["init"]["ate_trans_rmse_m"],
            overall["final"]["ate_trans_rmse_m"],
            overall["centralized"]["ate_trans_rmse_m"],
        )
    if {"final", "centralized"} <= overall.keys():
        overall["ate_over_atestar"] = metrics.ate_ratio(
            overall["final"]["ate_log_rmse"], overall["centralized"]["ate_log_rmse"]
        )
    elif scored:
        missing = [k for k in ESTIMATE_KINDS if k not in overall]
        notes.append(f"SR_ATE: no {' / '.join(missing)} estimate to compare")


def _rounds_report(
    rounds: dict[str, np.ndarray] | None,
    round_costs: dict[str, np.ndarray] | None,
    replay_report: dict[str, Any],
    notes: list[str],
) -> dict[str, Any]:
    """The report's ``rounds`` section: rounds.csv's count and bytes, the sampled costs' count
    and last SR_cost and F/F*, and the replay's own totals."""
    rounds_rep: dict[str, Any] = {}
    if rounds is not None:
        rounds_rep["count"] = int(len(rounds["round"]))
        if "bytes_total" in rounds:
            rounds_rep["bytes_total"] = float(np.nanmax(rounds["bytes_total"]))
    if round_costs is not None:
        rounds_rep["cost_samples"] = int(len(round_costs["round"]))
        rounds_rep["sr_cost_pct_last"] = float(round_costs["sr_cost_pct"][-1])
        rounds_rep["f_over_fstar_last"] = float(round_costs["f_over_fstar"][-1])
    elif rounds is not None and "cost" in rounds:
        notes.append(
            "rounds: no round_costs in out/report.json (replay --cost-every 0, or an older "
            "replay), so rounds.png shows rounds.csv's sum of local costs, not SR_cost"
        )
    for key in ("bytes_total", "rounds", "mission_s", "replay_wall_s"):
        if key in replay_report:
            rounds_rep.setdefault(
                key if key.startswith("replay") else f"replay_{key}", replay_report[key]
            )
    return rounds_rep


def _summary(
    overall: dict[str, Any], cost: dict[str, Any], objects_rep: dict[str, Any]
) -> dict[str, Any]:
    """The headline numbers (report.json's ``summary``)."""
    final = overall.get("final", {})
    return {
        "ate_m": final.get("ate_trans_rmse_m"),
        "ate_log": final.get("ate_log_rmse"),
        "sr_ate_pct": overall.get("sr_ate_pct"),
        "sr_cost_pct": cost.get("sr_cost_pct"),
        # None where no centralized solution was computed (reported as n/a)
        "f_over_fstar": cost.get("F_over_Fstar"),
        "ate_over_atestar": overall.get("ate_over_atestar"),
        "ce": objects_rep.get("ce"),
        "bias": objects_rep.get("bias"),
    }


def evaluate_run(run_dir: str | Path, opt: EvalOptions = EvalOptions()) -> RunEvaluation:
    """Score a run directory: the JSON report and the data its plots need."""
    from dran_edge.formats.run_dir import read_mission

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError("expected a run directory (docs/run-format.md)", path=str(run_dir))
    if opt.align not in align.ALIGN_KINDS:
        raise InputError(
            f"alignment must be one of {', '.join(align.ALIGN_KINDS)}, got {opt.align!r}"
        )
    mission = read_mission(run_dir / "mission.yaml")
    out_dir = run_dir / "out"
    notes: list[str] = []
    robots = read_estimates(mission, out_dir, notes)
    cost = _centralized(run_dir, robots, opt, notes)
    replay_report = read_replay_report(out_dir)
    cost = _cost_report(cost, replay_report)
    round_costs = _round_costs(replay_report, out_dir / "report.json")
    rounds = read_rounds_csv(out_dir / "rounds.csv") if (out_dir / "rounds.csv").exists() else None
    mocap_path, take = read_ground_truth(run_dir, mission, robots, opt.mocap_path, notes)

    scored = [n for n, rb in robots.items() if rb.gt_T is not None]
    offset_info: dict[str, Any] = {}
    if scored:
        offset_info = _time_offset(mission, robots, scored, opt, notes)
        _associate(robots, scored, offset_info["time_offset_s"], opt)
    alignments = _fit_alignments(robots, scored, opt.align)
    per_robot, overall, aligned = _trajectory_metrics(robots, alignments, opt)
    _success_rates(per_robot, overall, scored, notes)
    # Inter-robot relative poses at common instants (no alignment needed).
    inter = inter_robot_errors(
        robots,
        aligned,
        offset_info.get("time_offset_s", 0.0),
        opt.inter_robot_rate_hz,
        opt.max_gap_s,
    )
    objects_rep, obj_plot = object_maps(mission, robots, take, alignments.get("final", {}), notes)
    rounds_rep = _rounds_report(rounds, round_costs, replay_report, notes)

    report = {
        "format": EVAL_FORMAT,
        "summary": _summary(overall, cost, objects_rep),
        "run": str(run_dir),
        "mocap": str(mocap_path) if mocap_path else None,
        "align": opt.align,
        "time": offset_info,
        "robots": per_robot,
        "overall": overall,
        "inter_robot": inter,
        "objects": objects_rep,
        "cost": cost,
        "rounds": rounds_rep,
        "notes": notes,
    }
    plot_data = RunPlotData(
        robots=robots,
        aligned=aligned,
        rounds=rounds,
        objects=obj_plot,
        round_costs=round_costs,
        comm_graph=list(mission.comm_graph),
        robot_count=len(mission.robots),
    )
    return RunEvaluation(json_safe(report), plot_data)


# ----------------------------------------------------------------------------------- output


def write_report(
    evaluation: RunEvaluation, eval_dir: str | Path, *, plots: bool = True
) -> list[Path]:
    """Write ``report.json``, ``summary.md`` and (``plots``) PNGs into ``eval_dir``."""
    eval_dir = Path(eval_dir)
    eval_dir.mkdir(parents=True, exist_ok=True)
    data = evaluation.report
    written = []
    p = eval_dir / "report.json"
    p.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n", encoding="utf-8")
    written.append(p)
    p = eval_dir / "summary.md"
    p.write_text(summary_markdown(data), encoding="utf-8")
    written.append(p)
    if plots:
        from dran_edge.evaluation.plots import write_plots

        written += write_plots(evaluation, eval_dir)
    return written
