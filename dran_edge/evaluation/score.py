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
otherwise ``merged.g2o`` (decentralized final estimate as vertices) is solved with our centralized
Schur-LM (dran_edge.solver.centralized) and mapped back to robots and stamps by ``merged_vertices.csv``.
SR_cost uses the SE-Sync objective of ``merged.g2o``: F_k at the file's vertices, F_init at the
robots' initial estimate (``<robot>_init.tum`` at the vertex stamps; each object placed by its
first observation from that trajectory — where the decentralized method starts, paper Sec. 6.2)
and F* at the centralized optimum (the chordal start's value is kept as ``F_chordal``);
without merged.g2o, ``cost_init / cost_final / cost_centralized`` of out/report.json. Per round,
SR_cost needs the latter (the convention of rounds.csv's cost column).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge.evaluation import align, metrics
from dran_edge.formats import motive, tum
from dran_edge import geometry as geo
from dran_edge.errors import DependencyError, InputError
from dran_edge.evaluation.report import json_safe, summary_markdown
from dran_edge.formats.run_outputs import (
    read_objects_csv,
    read_rounds_csv,
    read_vertex_map,
    trajectory_file,
)

log = logging.getLogger(__name__)

EVAL_FORMAT = "dran-edge-eval/1"


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


@dataclass
class _Robot:
    name: str
    T_body_marker: np.ndarray
    gt_time_s: np.ndarray | None = None
    gt_T: np.ndarray | None = None
    gt_valid: np.ndarray | None = None
    est: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    assoc: dict[str, align.Association] = field(default_factory=dict)
    objects: dict[int, np.ndarray] = field(default_factory=dict)


# ------------------------------------------------------------------------------- trajectory


def body_ground_truth(take: motive.MotiveTake, body: str, T_body_marker: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(time_s, T_world_body, valid) of a Motive body carrying a marker at ``T_body_marker``."""
    b = take.body(body)
    T = b.T_world_marker @ geo.se3_inverse(T_body_marker)
    return take.time_s, T, b.valid


def _overlap_fraction(stamps_s: np.ndarray, ref_s: np.ndarray) -> float:
    """Fraction of the estimate's time span inside the reference's, both in one clock."""
    lo, hi = max(stamps_s[0], ref_s[0]), min(stamps_s[-1], ref_s[-1])
    span = max(stamps_s[-1] - stamps_s[0], 1e-9)
    return float(max(hi - lo, 0.0) / span)


def resolve_time_offset(stamps_s, T_est, gt_time_s, gt_T, gt_valid, given: float | None, *,
                        positions_only: bool = False, same_clock_first: bool = False
                        ) -> tuple[float, str, dict]:
    """(offset ``t_ref = t_est + offset``, how it was found, details).

    In order: the ``given`` offset; with ``same_clock_first`` (a reference file with absolute
    stamps, as evo assumes) the **clock overlap** (offset 0 when at least half of the
    estimate's span lies inside the reference's); the **angular-speed correlation** (skipped
    for a positions-only estimate); the **position correlation** (linear speeds); the clock
    overlap. Raises InputError listing what was tried.
    """
    if given is not None:
        return float(given), "given", {}
    ref_s = np.asarray(gt_time_s)[np.asarray(gt_valid, bool)] if gt_valid is not None \
        else np.asarray(gt_time_s)
    overlap = _overlap_fraction(np.asarray(stamps_s), ref_s) if len(ref_s) else 0.0
    if same_clock_first and overlap >= 0.5:
        return 0.0, "clock overlap", {"overlap_fraction": overlap}
    tried = []
    for signal, name in (("angular", "angular-speed correlation"),
                         ("linear", "position correlation")):
        if signal == "angular" and positions_only:
            tried.append(f"{name}: skipped, the estimate has no orientations")
            continue
        try:
            res = align.estimate_time_offset(stamps_s, T_est, gt_time_s, gt_T,
                                             valid_ref=gt_valid, signal=signal)
        except InputError as exc:
            tried.append(f"{name}: {str(exc).replace('; give --time-offset S', '')}")
            continue
        return res.offset_s, f"estimated ({name})", {
            "correlation": res.correlation, "overlap_s": res.overlap_s, "tried": tried}
    if overlap >= 0.5:
        return 0.0, "clock overlap", {"overlap_fraction": overlap, "tried": tried}
    raise InputError("no clock offset found: " + "; ".join(tried) + "; and the clocks do not "
                     "overlap. Give --time-offset S (t_ref = t_est + S)")


def _positions_only(T: np.ndarray) -> bool:
    return bool(np.all(np.abs(np.asarray(T)[:, :3, :3] - np.eye(3)) < 1e-12))


def evaluate_trajectory(
    stamps_s: np.ndarray,
    T_est: np.ndarray,
    take: motive.MotiveTake | None,
    body: str | None,
    *,
    T_body_marker: np.ndarray | None = None,
    align_kind: str = "se3",
    time_offset_s: float | None = None,
    time_offset_source: str | None = None,
    max_gap_s: float = 0.1,
    rpe_delta_s: float = 1.0,
    reference: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Score one trajectory against one Motive body, or a ``reference`` (stamps_s, T) in the
    estimate's clock (``dran-edge eval traj``).

    A positions-only estimate (every rotation the identity: a file without orientations) is
    scored on positions: its rotation errors are reported as None. ``time_offset_source``
    names where a given offset came from (default "given").
    """
    if reference is not None:
        gt_t, gt_T = np.asarray(reference[0], np.float64), np.asarray(reference[1], np.float64)
        gt_v = np.ones(len(gt_t), bool)
        # a file has no occlusion flags: only a gap well above its own sample spacing is one
        if len(gt_t) > 1:
            max_gap_s = max(max_gap_s, 1.5 * float(np.median(np.diff(gt_t))))
        if T_body_marker is not None:
            gt_T = gt_T @ geo.se3_inverse(T_body_marker)
        what = "the reference"
    else:
        T_bm = np.eye(4) if T_body_marker is None else T_body_marker
        gt_t, gt_T, gt_v = body_ground_truth(take, body, T_bm)
        what = f"body {body!r}"
    pos_only = _positions_only(T_est)
    offset, source, details = resolve_time_offset(
        stamps_s, T_est, gt_t, gt_T, gt_v, time_offset_s, positions_only=pos_only,
        same_clock_first=reference is not None)
    if time_offset_s is not None and time_offset_source:
        source = time_offset_source
    a = align.associate(stamps_s, T_est, gt_t, gt_T, valid_ref=gt_v, time_offset_s=offset,
                        max_gap_s=max_gap_s, what=what)
    al = align.fit_alignment(align_kind, a.T_est, a.T_ref)
    T_al = al.apply(a.T_est)
    stats = metrics.ate_trans_stats_m(T_al, a.T_ref)
    rpe = metrics.rpe(a.stamps_s, T_al, a.T_ref, delta_s=rpe_delta_s)
    if pos_only:
        rpe = {k: (None if "rot" in k else v) for k, v in rpe.items()}
    return {
        "body": body,
        "matched_poses": a.matched_poses,
        "estimated_poses": int(len(stamps_s)),
        "positions_only": pos_only,
        "time_offset_s": offset,
        "time_offset_source": source,
        **{f"time_offset_{k}": v for k, v in details.items()},
        "align": al.to_json(),
        "ate_rmse_m": stats["rmse_m"],
        "ate_mean_m": stats["mean_m"],
        "ate_median_m": stats["median_m"],
        "ate_max_m": stats["max_m"],
        "ate_std_m": float(np.std(np.linalg.norm(T_al[:, :3, 3] - a.T_ref[:, :3, 3], axis=1))),
        "ate_min_m": float(np.min(np.linalg.norm(T_al[:, :3, 3] - a.T_ref[:, :3, 3], axis=1))),
        "ate_rot_rmse_deg": None if pos_only else metrics.ate_rot_rmse_deg(T_al, a.T_ref),
        "ate_log_rmse": None if pos_only else metrics.ate_log_rmse(T_al, a.T_ref),
        "rpe": rpe,
        "_": {"stamps_s": a.stamps_s, "T_est_aligned": T_al, "T_ref": a.T_ref},
    }


# ---------------------------------------------------------------------------------- run dir


def _find_mocap(run_dir: Path, mission, opt: EvalOptions) -> Path | None:
    if opt.mocap_path:
        p = Path(opt.mocap_path)
        if not p.exists():
            raise InputError("Motive CSV given with --mocap does not exist", path=str(p))
        return p
    if mission.mocap_file:
        p = run_dir / mission.mocap_file
        if not p.exists():
            raise InputError("mission.yaml names this mocap file but it does not exist",
                             path=str(p))
        return p
    p = run_dir / "mocap.csv"
    return p if p.exists() else None


def _initial_objective(g, vmap: dict, inits: dict[str, tuple[np.ndarray, np.ndarray]]
                       ) -> float | None:
    """F (SE-Sync) of merged.g2o at the robots' initial estimate, or None if one is missing.

    Pose vertices take ``trajectory_init.tum`` interpolated at their stamps; an object vertex
    is placed by its first observation edge (earliest stamp) from that initial trajectory,
    as a robot initialises an object it has not seen before.
    """
    from dran_edge.solver.objective import sesync_objective, sesync_weights

    P0 = g.poses.copy()
    ids = [int(v) for v in g.vertex_ids]
    kind = [vmap.get(v, ("", "", 0)) for v in ids]
    for name, (s_init, T_init) in inits.items():
        sel = np.array([k for k, kd in enumerate(kind) if kd[:2] == ("pose", name)], np.int64)
        if len(sel) == 0:
            continue
        stamps_ns = np.array([kind[k][2] for k in sel], np.int64)
        P0[sel], _ = geo.se3_interpolate(np.round(s_init * 1e9).astype(np.int64), T_init,
                                         stamps_ns)
    if any(kd[0] == "pose" and kd[1] not in inits for kd in kind):
        return None
    is_obj = np.array([kd[0] == "object" for kd in kind])
    stamp = np.array([kd[2] if kd[0] == "pose" else np.iinfo(np.int64).max for kd in kind],
                     np.int64)
    placed = np.zeros(len(ids), bool)
    obs = [k for k, (a, b) in enumerate(g.edges.tolist()) if is_obj[b] and not is_obj[a]]
    for k in sorted(obs, key=lambda k: stamp[g.edges[k, 0]]):
        a, b = g.edges[k]
        if not placed[b]:
            P0[b] = P0[a] @ g.measurements[k]
            placed[b] = True
    if (is_obj & ~placed).any():
        return None
    kappa, tau = sesync_weights(g.dim, g.information)
    return sesync_objective(P0, g.edges, g.measurements, kappa, tau)


def _centralized_from_g2o(run_dir: Path, finals: dict[str, tuple[np.ndarray, np.ndarray]],
                          notes: list[str],
                          inits: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
                          ) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict[str, Any]]:
    """Centralized trajectories {robot: (stamps_s, T)} and costs from merged.g2o.

    ``finals`` are the robots' exported final estimates: merged.g2o's vertex values must be
    the same poses (F_k is evaluated there); the largest difference is reported. ``inits``
    are the robots' initial estimates (F_init is evaluated there, see ``_initial_objective``).
    """
    names = list(finals)
    g2o_path = run_dir / "out" / "merged.g2o"
    if not g2o_path.exists():
        notes.append("SR_ATE / SR_cost: out/merged.g2o absent; no centralized solution")
        return {}, {}
    try:
        from dran_edge.formats.g2o import read_g2o
        from dran_edge.solver.centralized import solve_g2o
    except ImportError as exc:  # the solver is another module of this package
        notes.append(f"SR_ATE / SR_cost: centralized solver unavailable ({exc})")
        return {}, {}
    g = read_g2o(g2o_path)
    if g.dim != 3:
        raise InputError(f"expected SE(3) vertices in merged.g2o, got SE({g.dim})",
                         path=str(g2o_path))
    try:
        rep = solve_g2o(g, init="chordal")
        chordal = True
    except InputError as exc:
        # e.g. a disconnected merged graph (robots that never met, each fixed by its own
        # gauge): chordal initialisation needs one component; start from the file instead.
        notes.append(f"centralized: chordal initialisation failed ({exc}); solved from the "
                     "decentralized estimate, so F_init is not the chordal one")
        rep = solve_g2o(g, init="file")
        chordal = False
    cost = {
        "source": "merged.g2o (SE-Sync objective, objective.sesync_objective)",
        "F_k": rep.objective_input,
        "F_star": rep.objective_final,
        "centralized_status": str(getattr(rep.result.status, "value", rep.result.status)),
        "centralized_iterations": int(getattr(rep.result, "iterations", -1)),
    }
    if chordal:
        cost["F_chordal"] = rep.objective_init
    vmap_path = run_dir / "out" / "merged_vertices.csv"
    if not vmap_path.exists():
        notes.append("SR_ATE / SR_cost: out/merged_vertices.csv absent, cannot map merged.g2o "
                     "vertices to robots and stamps")
        return {}, cost
    vmap = read_vertex_map(vmap_path)
    F_init = _initial_objective(g, vmap, inits or {})
    if F_init is None:
        notes.append("SR_cost: some robot has no out/<robot>/<robot>_init.tum (or an object "
                     "no observation), so F_init at the initial estimate is unknown")
    else:
        cost["F_init"] = F_init
    out = {}
    ids = g.vertex_ids
    for name in names:
        sel = [k for k, vid in enumerate(ids) if vmap.get(int(vid), ("", "", 0))[:2] ==
               ("pose", name)]
        if not sel:
            continue
        sel = np.array(sel)
        stamps = np.array([vmap[int(ids[k])][2] for k in sel], dtype=np.int64)
        order = np.argsort(stamps, kind="stable")
        out[name] = (stamps[order] * 1e-9, rep.result.poses[sel[order]])
        # The file's vertex values against the exported trajectory at the same stamps.
        s_f, T_f = finals[name]
        s_ns = np.round(s_f * 1e9).astype(np.int64)
        pos = np.searchsorted(s_ns, stamps)
        hit = (pos < len(s_ns)) & (s_ns[np.minimum(pos, len(s_ns) - 1)] == stamps)
        if hit.any():
            d = np.linalg.norm(g.poses[sel[hit]][:, :3, 3] - T_f[pos[hit]][:, :3, 3], axis=1)
            worst = max(cost.get("merged_vs_trajectory_max_m", 0.0), float(d.max()))
            cost["merged_vs_trajectory_max_m"] = worst
    if cost.get("merged_vs_trajectory_max_m", 0.0) > 0.01:
        notes.append(
            f"merged.g2o: its vertex values differ from out/<robot>/<robot>.tum by up to "
            f"{cost['merged_vs_trajectory_max_m']:.3f} m at the same stamps (another frame?); "
            "F_k, SR_cost and the centralized solution (SR_ATE) are then not comparable")
    return out, cost


def evaluate_run(run_dir: str | Path, opt: EvalOptions = EvalOptions()) -> dict[str, Any]:
    """Score a run directory; returns the report (also the data the plots need, under ``_``)."""
    from dran_edge.formats.run_dir import read_mission

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError("expected a run directory (docs/run-format.md)", path=str(run_dir))
    if opt.align not in align.ALIGN_KINDS:
        raise InputError(f"alignment must be one of {', '.join(align.ALIGN_KINDS)}, "
                         f"got {opt.align!r}")
    mission = read_mission(run_dir / "mission.yaml")
    out_dir = run_dir / "out"
    notes: list[str] = []
    robots: dict[str, _Robot] = {}
    for r in mission.robots:
        rb = _Robot(r.name, r.T_body_marker)
        for kind in ("final", "init", "centralized"):
            p = trajectory_file(out_dir, r.name, kind)
            if p is not None:
                rb.est[kind] = tum.read_tum(p)
        p = out_dir / r.name / "objects.csv"
        if p.exists():
            rb.objects = read_objects_csv(p)
        if "final" not in rb.est:
            notes.append(f"robot {r.name}: out/{r.name}/{r.name}.tum absent; robot skipped")
            continue
        robots[r.name] = rb
    if not robots:
        raise InputError("no robot has out/<name>/<name>.tum (written by 'dran-edge "
                         "replay' for every robot that produced an estimate)", path=str(out_dir))

    # Centralized solution (SR_ATE, SR_cost).
    cost: dict[str, Any] = {}
    if any("centralized" in rb.est for rb in robots.values()):
        notes.append("centralized trajectories read from out/centralized/")
    elif opt.centralized:
        central, cost = _centralized_from_g2o(
            run_dir, {n: rb.est["final"] for n, rb in robots.items()}, notes,
            {n: rb.est["init"] for n, rb in robots.items() if "init" in rb.est})
        for name, est in central.items():
            robots[name].est["centralized"] = est
    report_json = out_dir / "report.json"
    replay_report: dict[str, Any] = {}
    if report_json.exists():
        try:
            replay_report = json.loads(report_json.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise InputError(f"not valid JSON: {exc.msg}", path=str(report_json),
                             line=exc.lineno) from None
    # Costs given by the replay (cost_init / cost_final / cost_centralized) are in the
    # convention of rounds.csv's cost column; merged.g2o's are SE-Sync objectives. Never mix.
    replay_cost = {k_cost: float(replay_report[k_rep]) for k_rep, k_cost in
                   (("cost_init", "F_init"), ("cost_final", "F_k"),
                    ("cost_centralized", "F_star"))
                   if isinstance(replay_report.get(k_rep), (int, float))
                   and not isinstance(replay_report.get(k_rep), bool)}
    if not cost and replay_cost:
        cost = {"source": "out/report.json (the convention of rounds.csv)", **replay_cost}
    if all(cost.get(k) is not None for k in ("F_init", "F_k", "F_star")):
        cost["sr_cost_pct"] = metrics.sr_cost(cost["F_init"], cost["F_k"], cost["F_star"])
    if cost.get("F_k") is not None and cost.get("F_star") is not None:
        cost["F_over_Fstar"] = metrics.cost_ratio(cost["F_k"], cost["F_star"])
    # Per-round SR_cost needs F_init and F* in the convention of rounds.csv's cost column.
    round_cost_ref = replay_cost if {"F_init", "F_star"} <= replay_cost.keys() else None

    rounds = None
    if (out_dir / "rounds.csv").exists():
        rounds = read_rounds_csv(out_dir / "rounds.csv")

    # Ground truth.
    mocap_path = _find_mocap(run_dir, mission, opt)
    take = None
    if mocap_path is None:
        notes.append("no Motive CSV: ATE, SR_ATE, Bias and per-object errors need ground truth")
    else:
        take = motive.read_motive_csv(mocap_path, up_axis=mission.mocap_up_axis)
    bodies_used = []
    if take is not None:
        by_name = {r.name: r for r in mission.robots}
        for name, rb in robots.items():
            body = by_name[name].mocap_body
            if body is None:
                if name in take.bodies:
                    body = name
                else:
                    notes.append(f"robot {name}: no mocap_body in mission.yaml and no rigid body "
                                 f"of that name; not scored against mocap")
                    continue
            elif body not in take.bodies:
                raise InputError(
                    f"robot {name}: mocap_body {body!r} is not a rigid body of the Motive "
                    f"take; it has: {', '.join(sorted(take.bodies)) or '(none)'}",
                    path=str(mocap_path))
            rb.gt_time_s, rb.gt_T, rb.gt_valid = body_ground_truth(take, body, rb.T_body_marker)
            bodies_used.append(body)
        if not bodies_used:
            raise InputError(
                "no robot of mission.yaml matches a rigid body of the Motive take (robots: "
                f"{', '.join(robots)}; bodies: {', '.join(sorted(take.bodies)) or '(none)'}); "
                "set mocap_body in mission.yaml", path=str(mocap_path))

    scored = [n for n, rb in robots.items() if rb.gt_T is not None]
    offset_info: dict[str, Any] = {}
    if scored:
        if opt.time_offset_s is not None:
            offset, source = opt.time_offset_s, "given"
        elif mission.mocap_start_ns is not None:
            offset, source = -mission.mocap_start_ns * 1e-9, "mission.yaml mocap.start_ns"
        else:
            per = {}
            for n in scored:
                rb = robots[n]
                # The initial estimate is the raw odometry: locally smoother than the
                # optimised one, so its angular speed correlates best.
                src = rb.est.get("init", rb.est["final"])
                for signal in ("angular", "linear"):
                    try:
                        per[n] = align.estimate_time_offset(*src, rb.gt_time_s, rb.gt_T,
                                                            valid_ref=rb.gt_valid,
                                                            signal=signal).offset_s
                        break
                    except InputError as exc:
                        notes.append(f"robot {n}: time offset not estimated from {signal} "
                                     f"speeds ({exc})")
            if not per:
                raise InputError("could not estimate the mocap clock offset from any robot; "
                                 "give --time-offset or mocap.start_ns in mission.yaml")
            offset, source = float(np.median(list(per.values()))), "estimated"
            offset_info["per_robot_s"] = per
        offset_info.update({"time_offset_s": offset, "source": source})
        for n in scored:
            rb = robots[n]
            for kind, (s, T) in rb.est.items():
                rb.assoc[kind] = align.associate(s, T, rb.gt_time_s, rb.gt_T,
                                                 valid_ref=rb.gt_valid, time_offset_s=offset,
                                                 max_gap_s=opt.max_gap_s,
                                                 what=f"robot {n} ({kind} estimate)")

    # Alignment per estimate kind.
    alignments: dict[str, dict[str, align.Alignment]] = {}
    kinds = ("init", "final", "centralized")
    for kind in kinds:
        have = [n for n in scored if kind in robots[n].assoc]
        if not have:
            continue
        if opt.align == "paper":
            alignments[kind] = {}
            for n in have:
                rb = robots[n]
                anchor = rb.assoc.get("init", rb.assoc["final"])
                alignments[kind][n] = align.fit_alignment("paper", anchor.T_est, anchor.T_ref)
        else:
            Te = np.concatenate([robots[n].assoc[kind].T_est for n in have])
            Tr = np.concatenate([robots[n].assoc[kind].T_ref for n in have])
            a = align.fit_alignment(opt.align, Te, Tr)
            alignments[kind] = {n: a for n in have}

    # Trajectory metrics.
    per_robot: dict[str, Any] = {}
    overall: dict[str, Any] = {}
    aligned: dict[str, dict[str, np.ndarray]] = {}
    for kind, al_by in alignments.items():
        Te_all, Tr_all, grp = [], [], []
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
    for n, e in per_robot.items():
        if {"init", "final", "centralized"} <= e.keys():
            e["sr_ate_pct"] = metrics.sr_ate(e["init"]["ate_log_rmse"], e["final"]["ate_log_rmse"],
                                             e["centralized"]["ate_log_rmse"])
        if {"final", "centralized"} <= e.keys():
            e["ate_over_atestar"] = metrics.ate_ratio(e["final"]["ate_log_rmse"],
                                                      e["centralized"]["ate_log_rmse"])
    if {"init", "final", "centralized"} <= overall.keys():
        overall["sr_ate_pct"] = metrics.sr_ate(overall["init"]["ate_log_rmse"],
                                               overall["final"]["ate_log_rmse"],
                                               overall["centralized"]["ate_log_rmse"])
        overall["sr_ate_trans_pct"] = metrics.sr_ate(overall["init"]["ate_trans_rmse_m"],
                                                     overall["final"]["ate_trans_rmse_m"],
                                                     overall["centralized"]["ate_trans_rmse_m"])
    if {"final", "centralized"} <= overall.keys():
        overall["ate_over_atestar"] = metrics.ate_ratio(overall["final"]["ate_log_rmse"],
                                                        overall["centralized"]["ate_log_rmse"])
    elif scored:
        missing = [k for k in kinds if k not in overall]
        notes.append(f"SR_ATE: no {' / '.join(missing)} estimate to compare")

    # Inter-robot relative poses at common instants (no alignment needed).
    inter = _inter_robot(robots, aligned, offset_info.get("time_offset_s", 0.0), opt)

    # Objects.
    objects_rep, obj_plot = _objects(mission, robots, take, alignments.get("final", {}), notes)

    rounds_rep: dict[str, Any] = {}
    if rounds is not None:
        rounds_rep["count"] = int(len(rounds["round"]))
        if "bytes_total" in rounds:
            rounds_rep["bytes_total"] = float(np.nanmax(rounds["bytes_total"]))
        if "cost" in rounds and round_cost_ref is not None:
            rounds_rep["sr_cost_pct_last"] = float(metrics.sr_cost(
                round_cost_ref["F_init"], rounds["cost"][-1], round_cost_ref["F_star"]))
        elif "cost" in rounds:
            notes.append("rounds: no cost_init / cost_centralized in out/report.json, so "
                         "rounds.csv's cost is plotted as is, not as SR_cost")
    for key in ("bytes_total", "rounds", "mission_s", "replay_wall_s"):
        if key in replay_report:
            rounds_rep.setdefault(key if key.startswith("replay") else f"replay_{key}",
                                  replay_report[key])

    final = overall.get("final", {})
    summary = {
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
    report = {
        "format": EVAL_FORMAT,
        "summary": summary,
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
    report = json_safe(report)
    report["_"] = {"robots": robots, "aligned": aligned, "rounds": rounds, "objects": obj_plot,
                   "round_cost_ref": round_cost_ref,
                   "comm_graph": list(mission.comm_graph)}
    return report


def _inter_robot(robots, aligned, offset, opt) -> dict[str, Any]:
    """Robot b seen from robot a, for every pair, at common instants: the aligned final
    estimates (with the paper's per-robot frames these differ from the files)."""
    out: dict[str, Any] = {"pairs": {}}
    tr_all, rot_all = [], []
    scored = [n for n in robots if "final" in aligned.get(n, {})]
    for i, a in enumerate(scored):
        for b in scored[i + 1:]:
            sa, Ta = robots[a].assoc["final"].stamps_s, aligned[a]["final"]
            sb, Tb = robots[b].assoc["final"].stamps_s, aligned[b]["final"]
            lo, hi = max(sa[0], sb[0]), min(sa[-1], sb[-1])
            if hi - lo < 1.0 / opt.inter_robot_rate_hz:
                continue
            grid = np.arange(lo, hi, 1.0 / opt.inter_robot_rate_hz)
            Ea, oka = align.interpolate_track(sa, Ta, grid, max_gap_s=5.0)
            Eb, okb = align.interpolate_track(sb, Tb, grid, max_gap_s=5.0)
            Ga, gka = align.interpolate_track(robots[a].gt_time_s, robots[a].gt_T, grid + offset,
                                              valid=robots[a].gt_valid, max_gap_s=opt.max_gap_s)
            Gb, gkb = align.interpolate_track(robots[b].gt_time_s, robots[b].gt_T, grid + offset,
                                              valid=robots[b].gt_valid, max_gap_s=opt.max_gap_s)
            ok = oka & okb & gka & gkb
            if not ok.any():
                continue
            r = metrics.inter_robot_error(Ea[ok], Ga[ok], Eb[ok], Gb[ok])
            out["pairs"][f"{a}-{b}"] = r
            t, ang = metrics.relative_errors(Ea[ok], Ga[ok], Eb[ok], Gb[ok])
            tr_all.append(t)
            rot_all.append(ang)
    if tr_all:
        t, ang = np.concatenate(tr_all), np.concatenate(rot_all)
        out["trans_rmse_m"] = float(np.sqrt(np.mean(t * t)))
        out["rot_rmse_deg"] = float(np.sqrt(np.mean(ang * ang)))
    return out


def _objects(mission, robots, take, final_align, notes) -> tuple[dict[str, Any], dict]:
    names = list(robots)
    ids = sorted({oid for rb in robots.values() for oid in rb.objects}
                 | {o.id for o in mission.objects})
    if not ids or not any(rb.objects for rb in robots.values()):
        notes.append("objects: no out/<robot>/objects.csv; CE and Bias not computed")
        return {}, {}
    col = {oid: k for k, oid in enumerate(ids)}
    N, m = len(names), len(ids)
    Y = np.tile(np.eye(4), (N, m, 1, 1))
    present = np.zeros((N, m), bool)
    for i, n in enumerate(names):
        for oid, T in robots[n].objects.items():
            Y[i, col[oid]] = T
            present[i, col[oid]] = True
    ce, y_avg = metrics.consistency_error(Y, present)
    rep: dict[str, Any] = {"count": m, "copies": int(present.sum()), "ce": ce}
    gt = np.full((m, 4, 4), np.nan)
    if take is not None:
        for o in mission.objects:
            body = o.mocap_body or (o.name if o.name in take.bodies else None)
            if body is None:
                continue
            if body not in take.bodies:
                raise InputError(f"object {o.name}: mocap_body {body!r} is not a rigid body of "
                                 f"the Motive take; it has: {', '.join(sorted(take.bodies))}",
                                 path=take.path)
            b = take.bodies[body]
            if not b.valid.any():
                notes.append(f"object {o.name}: never tracked by mocap")
                continue
            T = b.T_world_marker[b.valid] @ geo.se3_inverse(o.T_object_marker)
            if o.id in col:
                gt[col[o.id]] = metrics.frechet_mean_se3(T, np.ones(len(T)))
    has_gt = np.all(np.isfinite(gt), axis=(-1, -2))
    Y_al = Y.copy()
    if final_align:
        for i, n in enumerate(names):
            if n in final_align:
                Y_al[i] = final_align[n].apply(Y[i])
    if has_gt.any():
        rep["bias"] = metrics.object_bias(Y_al, present, gt)
        _, y_avg_al = metrics.consistency_error(Y_al, present)
        rep["bias_of_mean"] = metrics.object_bias_of_mean(y_avg_al, gt)
        tr, rot = metrics.object_errors(Y_al, present, gt)
        rep["per_object"] = {
            str(oid): {
                "copies": int(present[:, k].sum()),
                "trans_err_m": {names[i]: tr[i, k] for i in range(N) if present[i, k]},
                "rot_err_deg": {names[i]: rot[i, k] for i in range(N) if present[i, k]},
            }
            for oid, k in col.items() if has_gt[k]
        }
    else:
        notes.append("objects: no object has a mocap rigid body; Bias not computed")
    return rep, {"ids": ids, "names": names, "Y": Y_al, "present": present, "gt": gt,
                 "y_avg": y_avg}


# ----------------------------------------------------------------------------------- output


def write_report(report: dict[str, Any], eval_dir: str | Path, *, plots: bool = True
                 ) -> list[Path]:
    """Write ``report.json``, ``summary.md`` and (``plots``) PNGs into ``eval_dir``."""
    eval_dir = Path(eval_dir)
    eval_dir.mkdir(parents=True, exist_ok=True)
    data = {k: v for k, v in report.items() if k != "_"}
    written = []
    p = eval_dir / "report.json"
    p.write_text(json.dumps(data, indent=2, sort_keys=False) + "\n", encoding="utf-8")
    written.append(p)
    p = eval_dir / "summary.md"
    p.write_text(summary_markdown(data), encoding="utf-8")
    written.append(p)
    if plots and "_" in report:
        written += write_plots(report, eval_dir)
    return written



# ------------------------------------------------------------------------------------- plots
# matplotlib is imported lazily (the ``eval`` extra), with the Agg backend:
# - trajectories.png: top view of every robot's estimate (initial, final) against mocap ground
#   truth, with the objects: ground truth and each robot's copy (the paper's Fig. 1b/c);
# - rounds.png: SR_cost, consensus error and bytes over the DRAN rounds (rounds.csv);
# - errors.png: ATE per robot (initial / final / centralized), translation error over time.


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
    """The PNG plots of ``report`` (from :func:`evaluate_run`) into ``eval_dir``."""
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
        Y, present, gt = ob["Y"], ob["present"], ob["gt"]
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


def round_panels(rounds: dict, ref: dict | None, n_robots: int, n_links: int
                 ) -> list[tuple[str, str, np.ndarray]]:
    """(title, y label, values) of rounds.png's panels, each saying what it plots.

    The consensus panel is rounds.csv's ``consensus_error``: per round, the largest of the
    robots' own consensus residuals — not the paper's CE of the summary (docs/eval.md). The
    cost is SR_cost when report.json gives ``cost_init`` and ``cost_centralized``, else the
    raw sum of the robots' local costs (which grows with the graphs). Bytes per round are
    shown per robot and per communication link, besides the cumulative total.
    """
    panels = []
    if "cost" in rounds and ref is not None:
        panels.append(("SR_cost per round (paper Sec. 6.2)", "SR_cost (%)",
                       metrics.sr_cost(ref["F_init"], rounds["cost"], ref["F_star"])))
    elif "cost" in rounds:
        panels.append(("sum of the robots' local costs (grows as the graphs grow; "
                       "not F/F*)", "cost (SE-Sync objective units)", rounds["cost"]))
    if "consensus_error" in rounds:
        panels.append(("largest robot's own consensus residual per round (not the "
                       "summary's CE)", "max_i residual_i", rounds["consensus_error"]))
    if "bias" in rounds:
        panels.append(("Bias per round", "Bias", rounds["bias"]))
    if "bytes_round" in rounds:
        b = np.asarray(rounds["bytes_round"], dtype=np.float64)
        panels.append(("bytes sent per round: per robot (mean) and per link (mean)",
                       "bytes / round", np.stack([b / max(n_robots, 1), b / max(n_links, 1)])))
    if "bytes_total" in rounds:
        panels.append(("bytes sent by all robots, cumulative", "bytes (total)",
                       rounds["bytes_total"]))
    return panels


def _rounds(plt, report, data, eval_dir):
    rounds = data["rounds"]
    if rounds is None or len(rounds.get("round", [])) == 0:
        return None
    r = rounds["round"]
    n_links = len(data.get("comm_graph") or ()) or 1
    panels = round_panels(rounds, data["round_cost_ref"], len(report.get("robots") or {}) or 1,
                          n_links)
    if not panels:
        return None
    fig, axes = plt.subplots(len(panels), 1, figsize=(7.5, 2.5 * len(panels)), sharex=True,
                             squeeze=False)
    for ax, (title, label, y) in zip(axes[:, 0], panels):
        if np.ndim(y) == 2:
            ax.plot(r, y[0], lw=1.4, label="per robot")
            ax.plot(r, y[1], lw=1.0, ls="--", label="per link")
            ax.legend(fontsize=7, loc="best")
        else:
            ax.plot(r, y, lw=1.4)
        ax.set_title(title, fontsize=8)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
        if title.startswith("largest") and np.nanmin(y) > 0:
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
