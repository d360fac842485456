"""The multi-robot metrics of a run: relative poses between robots, and the object maps.

Inter-robot: robot b seen from robot a at common instants, against mocap (no alignment
needed). Objects: the consistency error CE between the robots' copies and, with mocap rigid
bodies for the objects, the Bias of each copy and of their mean (paper Sec. 6.2, docs/eval.md).
Used by :func:`dran_edge.evaluation.score.evaluate_run`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import InputError
from dran_edge.evaluation import align, metrics
from dran_edge.evaluation.run_inputs import RobotTracks
from dran_edge.formats import motive

if TYPE_CHECKING:
    from dran_edge.formats.run_dir import Mission


@dataclass(frozen=True)
class ObjectPlotData:
    """The robots' aligned object copies and the objects' ground truth, for trajectories.png."""

    ids: list[int]
    names: list[str]
    Y: np.ndarray
    """(robots, objects, 4, 4) aligned copies (identity where absent)."""
    present: np.ndarray
    """(robots, objects) bool."""
    gt: np.ndarray
    """(objects, 4, 4) mocap ground truth (NaN where unknown)."""
    y_avg: np.ndarray


def inter_robot_errors(
    robots: dict[str, RobotTracks],
    aligned: dict[str, dict[str, np.ndarray]],
    offset: float,
    rate_hz: float,
    max_gap_s: float,
) -> dict[str, Any]:
    """Robot b seen from robot a, for every pair, at common instants: the aligned final
    estimates (with the paper's per-robot frames these differ from the files)."""
    out: dict[str, Any] = {"pairs": {}}
    tr_all, rot_all = [], []
    scored = [n for n in robots if "final" in aligned.get(n, {})]
    for i, a in enumerate(scored):
        for b in scored[i + 1 :]:
            sa, Ta = robots[a].assoc["final"].stamps_s, aligned[a]["final"]
            sb, Tb = robots[b].assoc["final"].stamps_s, aligned[b]["final"]
            lo, hi = max(sa[0], sb[0]), min(sa[-1], sb[-1])
            if hi - lo < 1.0 / rate_hz:
                continue
            grid = np.arange(lo, hi, 1.0 / rate_hz)
            Ea, oka = align.interpolate_track(sa, Ta, grid, max_gap_s=5.0)
            Eb, okb = align.interpolate_track(sb, Tb, grid, max_gap_s=5.0)
            Ga, gka = robots[a].ground_truth_at(grid + offset, max_gap_s)
            Gb, gkb = robots[b].ground_truth_at(grid + offset, max_gap_s)
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


def object_maps(
    mission: Mission,
    robots: dict[str, RobotTracks],
    take: motive.MotiveTake | None,
    final_align: dict[str, align.Alignment],
    notes: list[str],
) -> tuple[dict[str, Any], ObjectPlotData | None]:
    """The report's ``objects`` section (CE, Bias, per-object errors) and the plot's data."""
    names = list(robots)
    ids = sorted(
        {oid for rb in robots.values() for oid in rb.objects} | {o.id for o in mission.objects}
    )
    if not ids or not any(rb.objects for rb in robots.values()):
        notes.append("objects: no out/<robot>/objects.csv; CE and Bias not computed")
        return {}, None
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
                raise InputError(
                    f"object {o.name}: mocap_body {body!r} is not a rigid body of "
                    f"the Motive take; it has: {', '.join(sorted(take.bodies))}",
                    path=take.path,
                )
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
            for oid, k in col.items()
            if has_gt[k]
        }
    else:
        notes.append("objects: no object has a mocap rigid body; Bias not computed")
    return rep, ObjectPlotData(ids=ids, names=names, Y=Y_al, present=present, gt=gt, y_avg=y_avg)
