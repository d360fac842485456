"""Score one trajectory against one Motive rigid body or a reference trajectory.

The core of ``dran-edge eval traj`` (docs/eval.md): resolve the clock offset between the two
(given, clock overlap, or correlated speeds), associate the poses, align (se3 / sim3 / yaw /
none / paper) and compute ATE and RPE. A positions-only estimate (every rotation the identity,
a file without orientations) is scored on positions only. The run-level scorer
(:mod:`dran_edge.evaluation.score`) shares :func:`body_ground_truth` with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import InputError
from dran_edge.evaluation import align, metrics
from dran_edge.formats import motive


@dataclass(frozen=True)
class TrajectoryEvaluation:
    """What :func:`evaluate_trajectory` found: the printed / JSON result and the matched poses."""

    result: dict[str, Any]
    """The scores as ``dran-edge eval traj --json`` prints them (before ``json_safe``)."""
    stamps_s: np.ndarray
    """Estimate stamps of the matched poses (s, the estimate's clock)."""
    T_est_aligned: np.ndarray
    """The matched estimate poses after alignment, (n, 4, 4)."""
    T_ref: np.ndarray
    """The reference poses at the same instants, (n, 4, 4)."""


def body_ground_truth(
    take: motive.MotiveTake, body: str, T_body_marker: np.ndarray
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


def resolve_time_offset(
    stamps_s: np.ndarray,
    T_est: np.ndarray,
    gt_time_s: np.ndarray,
    gt_T: np.ndarray,
    gt_valid: np.ndarray | None,
    given: float | None,
    *,
    positions_only: bool = False,
    same_clock_first: bool = False,
) -> tuple[float, str, dict[str, Any]]:
    """(offset ``t_ref = t_est + offset``, how it was found, details).

    In order: the ``given`` offset; with ``same_clock_first`` (a reference file with absolute
    stamps, as evo assumes) the **clock overlap** (offset 0 when at least half of the
    estimate's span lies inside the reference's); the **angular-speed correlation** (skipped
    for a positions-only estimate); the **position correlation** (linear speeds); the clock
    overlap. Raises InputError listing what was tried.
    """
    if given is not None:
        return float(given), "given", {}
    ref_s = (
        np.asarray(gt_time_s)[np.asarray(gt_valid, bool)]
        if gt_valid is not None
        else np.asarray(gt_time_s)
    )
    overlap = _overlap_fraction(np.asarray(stamps_s), ref_s) if len(ref_s) else 0.0
    if same_clock_first and overlap >= 0.5:
        return 0.0, "clock overlap", {"overlap_fraction": overlap}
    tried = []
    for signal, name in (
        ("angular", "angular-speed correlation"),
        ("linear", "position correlation"),
    ):
        if signal == "angular" and positions_only:
            tried.append(f"{name}: skipped, the estimate has no orientations")
            continue
        try:
            res = align.estimate_time_offset(
                stamps_s, T_est, gt_time_s, gt_T, valid_ref=gt_valid, signal=signal
            )
        except InputError as exc:
            tried.append(f"{name}: {str(exc).replace('; give --time-offset S', '')}")
            continue
        return (
            res.offset_s,
            f"estimated ({name})",
            {"correlation": res.correlation, "overlap_s": res.overlap_s, "tried": tried},
        )
    if overlap >= 0.5:
        return 0.0, "clock overlap", {"overlap_fraction": overlap, "tried": tried}
    raise InputError(
        "no clock offset found: " + "; ".join(tried) + "; and the clocks do not "
        "overlap. Give --time-offset S (t_ref = t_est + S)"
    )


def _positions_only(T: np.ndarray) -> bool:
    return bool(np.all(np.abs(np.asarray(T)[:, :3, :3] - np.eye(3)) < 1e-12))


def _reference_track(
    take: motive.MotiveTake | None,
    body: str | None,
    T_body_marker: np.ndarray | None,
    max_gap_s: float,
    reference: tuple[np.ndarray, np.ndarray] | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, str]:
    """(time_s, T, valid, max_gap_s, what) of the reference: the file or the Motive body."""
    if reference is not None:
        gt_t, gt_T = np.asarray(reference[0], np.float64), np.asarray(reference[1], np.float64)
        gt_v = np.ones(len(gt_t), bool)
        # a file has no occlusion flags: only a gap well above its own sample spacing is one
        if len(gt_t) > 1:
            max_gap_s = max(max_gap_s, 1.5 * float(np.median(np.diff(gt_t))))
        if T_body_marker is not None:
            gt_T = gt_T @ geo.se3_inverse(T_body_marker)
        return gt_t, gt_T, gt_v, max_gap_s, "the reference"
    if take is None or body is None:
        raise InputError("expected a Motive take and a body, or a reference trajectory")
    T_bm = np.eye(4) if T_body_marker is None else T_body_marker
    gt_t, gt_T, gt_v = body_ground_truth(take, body, T_bm)
    return gt_t, gt_T, gt_v, max_gap_s, f"body {body!r}"


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
) -> TrajectoryEvaluation:
    """Score one trajectory against one Motive body, or a ``reference`` (stamps_s, T) in the
    estimate's clock (``dran-edge eval traj``).

    A positions-only estimate (every rotation the identity: a file without orientations) is
    scored on positions: its rotation errors are reported as None. ``time_offset_source``
    names where a given offset came from (default "given").
    """
    gt_t, gt_T, gt_v, max_gap_s, what = _reference_track(
        take, body, T_body_marker, max_gap_s, reference
    )
    pos_only = _positions_only(T_est)
    offset, source, details = resolve_time_offset(
        stamps_s,
        T_est,
        gt_t,
        gt_T,
        gt_v,
        time_offset_s,
        positions_only=pos_only,
        same_clock_first=reference is not None,
    )
    if time_offset_s is not None and time_offset_source:
        source = time_offset_source
    a = align.associate(
        stamps_s,
        T_est,
        gt_t,
        gt_T,
        valid_ref=gt_v,
        time_offset_s=offset,
        max_gap_s=max_gap_s,
        what=what,
    )
    al = align.fit_alignment(align_kind, a.T_est, a.T_ref)
    T_al = al.apply(a.T_est)
    stats = metrics.ate_trans_stats_m(T_al, a.T_ref)
    rpe: dict[str, float | None] = dict(metrics.rpe(a.stamps_s, T_al, a.T_ref, delta_s=rpe_delta_s))
    if pos_only:
        rpe = {k: (None if "rot" in k else v) for k, v in rpe.items()}
    err_m = np.linalg.norm(T_al[:, :3, 3] - a.T_ref[:, :3, 3], axis=1)
    result = {
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
        "ate_std_m": float(np.std(err_m)),
        "ate_min_m": float(np.min(err_m)),
        "ate_rot_rmse_deg": None if pos_only else metrics.ate_rot_rmse_deg(T_al, a.T_ref),
        "ate_log_rmse": None if pos_only else metrics.ate_log_rmse(T_al, a.T_ref),
        "rpe": rpe,
    }
    return TrajectoryEvaluation(result, a.stamps_s, T_al, a.T_ref)
