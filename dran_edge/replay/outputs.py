"""What a replay writes in ``RUN/out/`` (docs/run-format.md), and the metrics it adds.

Per robot ``<robot>.tum`` (final estimate), ``<robot>_init.tum`` (initial) and ``objects.csv``;
``rounds.csv``; ``merged.g2o`` + ``merged_vertices.csv`` (:mod:`dran_edge.replay.merged_g2o`);
``report.json``, with the headline numbers of :mod:`dran_edge.evaluation.score` when the run has
mocap. Shared by ``dran-edge replay`` and the rehearsal (:mod:`dran_edge.rehearsal`).
"""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import InputError
from dran_edge.formats import run_dir as rd
from dran_edge.replay.merged_g2o import write_merged_g2o

if TYPE_CHECKING:
    from dran_edge.replay.robots import RobotResult

log = logging.getLogger(__name__)


def json_clean(x: Any) -> Any:
    """``x`` with numpy scalars as Python numbers, non-finite floats as None, keys as str."""
    if isinstance(x, dict):
        return {str(k): json_clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def write_report(out_dir: Path, report: dict[str, Any]) -> None:
    """``out_dir/report.json`` (docs/run-format.md)."""
    (out_dir / "report.json").write_text(
        json.dumps(json_clean(report), indent=2) + "\n", encoding="utf-8"
    )


def evaluation_metrics(run: rd.Run) -> dict[str, Any]:
    """sr_ate, sr_cost, ate_m, ce, bias from dran_edge.evaluation.score (the numbers `eval` reports)."""
    from dran_edge.evaluation.score import EvalOptions, evaluate_run

    try:
        ev = evaluate_run(run.root, EvalOptions(plots=False)).report
    except InputError as exc:
        log.warning("evaluation failed: %s", exc)
        return {"evaluation_error": str(exc)}
    return {"metrics": pick_metrics(ev), **pick_metrics(ev)}


def pick_metrics(ev: dict[str, Any]) -> dict[str, Any]:
    """The headline numbers of an evaluation report (names of docs/run-format.md)."""

    def find(d: Any, *keys: str) -> Any:
        for key in keys:
            cur = d
            for part in key.split("."):
                if not isinstance(cur, dict) or part not in cur:
                    cur = None
                    break
                cur = cur[part]
            if cur is not None:
                return cur
        return None

    return {
        "sr_ate": find(ev, "sr_ate_pct", "summary.sr_ate_pct", "sr_ate"),
        "sr_cost": find(ev, "sr_cost_pct", "summary.sr_cost_pct", "cost.sr_cost_pct", "sr_cost"),
        "f_over_fstar": find(ev, "f_over_fstar", "summary.f_over_fstar", "cost.F_over_Fstar"),
        "ate_over_atestar": find(
            ev, "ate_over_atestar", "summary.ate_over_atestar", "overall.ate_over_atestar"
        ),
        "ate_m": find(ev, "ate_m", "summary.ate_m", "ate.final.rmse_m", "ate_rmse_m"),
        "ce": find(ev, "ce", "summary.ce", "objects.ce"),
        "bias": find(ev, "bias", "summary.bias", "objects.bias"),
    }


def initial_track(r: RobotResult) -> tuple[np.ndarray, np.ndarray, str]:
    """(stamps_ns, T_world_body, what it is) of a robot's initial estimate — ``<robot>_init.tum``
    and the F_init of SR_cost: odometry alone when the core gives it, else each keyframe's
    first estimate. Needs ``r.last`` (the robot's estimate)."""
    u = r.last
    assert u is not None
    if r.initial is not None and len(r.initial[0]):
        return r.initial[0], r.initial[1], "odometry alone, before any optimisation"
    stamps = np.asarray(u.keyframe_stamps_ns, dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    T0 = np.stack(
        [
            r.first_seen.get(int(s), u.T_world_body[i])
            for s, i in zip(stamps[order].tolist(), order.tolist())
        ]
    )
    return stamps[order], T0, "each keyframe's first estimate"


def _write_robot_files(d: Path, r: RobotResult) -> None:
    """``<robot>.tum`` (final), ``<robot>_init.tum`` (initial) and ``objects.csv`` of a robot;
    a robot without an estimate has none of them."""
    from dran_edge.formats.tum import write_tum

    d.mkdir(parents=True, exist_ok=True)
    u = r.last
    if u is None or len(u.keyframe_stamps_ns) == 0:
        for name in (f"{r.name}.tum", f"{r.name}_init.tum", "objects.csv"):
            (d / name).unlink(missing_ok=True)
        log.warning("robot %s produced no estimate", r.name)
        return
    stamps = np.asarray(u.keyframe_stamps_ns, dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    for name in ("trajectory.tum", "trajectory_init.tum"):  # the names of older replays
        (d / name).unlink(missing_ok=True)
    write_tum(
        d / f"{r.name}.tum",
        stamps * 1e-9,
        np.asarray(u.T_world_body)[order],
        header=f"{r.name}: final estimate (dran-edge replay)",
    )
    s0, T0, what = initial_track(r)
    o0 = np.argsort(s0, kind="stable")
    write_tum(
        d / f"{r.name}_init.tum",
        s0[o0] * 1e-9,
        T0[o0],
        header=f"{r.name}: initial estimate, {what} (dran-edge replay)",
    )
    with open(d / "objects.csv", "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["object_id", "x", "y", "z", "qx", "qy", "qz", "qw"])
        for oid, T in sorted(zip(u.object_ids, u.T_world_object), key=lambda x: x[0]):
            w.writerow([int(oid)] + [f"{v:.9f}" for v in geo.se3_to_xyz_quat_xyzw(T)])


#: Columns of rounds.csv (docs/run-format.md).
ROUNDS_COLUMNS = (
    "round",
    "stamp_ns",
    "bytes_total",
    "bytes_round",
    "cost",
    "consensus_error",
    "converged_robots",
    "datagrams_lost",
)


def _write_rounds_csv(path: Path, rounds_rows: list[dict[str, Any]]) -> None:
    """rounds.csv: floats with 9 significant digits, non-finite ones empty."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(ROUNDS_COLUMNS)
        for row in rounds_rows:
            w.writerow(
                [
                    ""
                    if isinstance(row[c], float) and not math.isfinite(row[c])
                    else (f"{row[c]:.9g}" if isinstance(row[c], float) else row[c])
                    for c in ROUNDS_COLUMNS
                ]
            )


def write_outputs(
    run: rd.Run, results: dict[int, RobotResult], rounds_rows: list[dict[str, Any]]
) -> None:
    """Per-robot TUM files and object maps, rounds.csv, merged.g2o (docs/run-format.md)."""
    out = run.out_dir
    for r in results.values():
        _write_robot_files(out / r.name, r)
    _write_rounds_csv(out / "rounds.csv", rounds_rows)
    write_merged_g2o(run, results)
