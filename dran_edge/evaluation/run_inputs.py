"""Load a run directory for scoring: the robots' estimates, the replay's report, the mocap.

The input side of :mod:`dran_edge.evaluation.score` (docs/run-format.md): per robot the
exported trajectories (``final``, ``init``, ``centralized``) and object map, ``out/report.json``,
and the Motive take with each robot's ground-truth body track
(``T_world_body = T_world_marker · T_body_marker⁻¹``). Absent optional files add a note; a
present but malformed one is an InputError.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dran_edge.errors import InputError
from dran_edge.evaluation import align
from dran_edge.evaluation.centralized import Track
from dran_edge.evaluation.traj_score import body_ground_truth
from dran_edge.formats import motive, tum
from dran_edge.formats.run_outputs import read_objects_csv, trajectory_file

if TYPE_CHECKING:
    from dran_edge.formats.run_dir import Mission


@dataclass
class RobotTracks:
    """One robot's estimates, its ground truth and their association (filled step by step)."""

    name: str
    T_body_marker: np.ndarray
    gt_time_s: np.ndarray | None = None
    gt_T: np.ndarray | None = None
    gt_valid: np.ndarray | None = None
    est: dict[str, Track] = field(default_factory=dict)
    """Estimate kind (ESTIMATE_KINDS) -> (stamps_s, T_world_body)."""
    assoc: dict[str, align.Association] = field(default_factory=dict)
    objects: dict[int, np.ndarray] = field(default_factory=dict)
    """Object id -> the robot's T_world_object (objects.csv)."""

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(time_s, T_world_body, valid) of the robot's mocap track (set by
        :func:`read_ground_truth`; ValueError for a robot without one)."""
        if self.gt_time_s is None or self.gt_T is None:
            raise ValueError(f"robot {self.name}: no mocap ground truth")
        return self.gt_time_s, self.gt_T, self.gt_valid

    def ground_truth_at(
        self, time_s: np.ndarray, max_gap_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """(T_world_body, ok) of the mocap track interpolated at ``time_s`` (mocap clock)."""
        gt_time_s, gt_T, gt_valid = self.ground_truth()
        return align.interpolate_track(gt_time_s, gt_T, time_s, valid=gt_valid, max_gap_s=max_gap_s)


def find_mocap(run_dir: Path, mission: Mission, mocap_path: str | None) -> Path | None:
    if mocap_path:
        p = Path(mocap_path)
        if not p.exists():
            raise InputError("Motive CSV given with --mocap does not exist", path=str(p))
        return p
    if mission.mocap_file:
        p = run_dir / mission.mocap_file
        if not p.exists():
            raise InputError(
                "mission.yaml names this mocap file but it does not exist", path=str(p)
            )
        return p
    p = run_dir / "mocap.csv"
    return p if p.exists() else None


def read_estimates(mission: Mission, out_dir: Path, notes: list[str]) -> dict[str, RobotTracks]:
    """Every robot's exported estimates and object map; a robot without a final one is skipped."""
    robots: dict[str, RobotTracks] = {}
    for r in mission.robots:
        rb = RobotTracks(r.name, r.T_body_marker)
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
        raise InputError(
            "no robot has out/<name>/<name>.tum (written by 'dran-edge "
            "replay' for every robot that produced an estimate)",
            path=str(out_dir),
        )
    return robots


def read_replay_report(out_dir: Path) -> dict[str, Any]:
    """out/report.json of the replay ({} when absent)."""
    report_json = out_dir / "report.json"
    if not report_json.exists():
        return {}
    try:
        replay_report: dict[str, Any] = json.loads(report_json.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(
            f"not valid JSON: {exc.msg}", path=str(report_json), line=exc.lineno
        ) from None
    return replay_report


def _robot_body(
    name: str, mission: Mission, take: motive.MotiveTake, mocap_path: Path, notes: list[str]
) -> str | None:
    """The Motive rigid body of robot ``name`` (mocap_body, else its own name), or None."""
    body = {r.name: r for r in mission.robots}[name].mocap_body
    if body is None:
        if name in take.bodies:
            return name
        notes.append(
            f"robot {name}: no mocap_body in mission.yaml and no rigid body "
            f"of that name; not scored against mocap"
        )
        return None
    if body not in take.bodies:
        raise InputError(
            f"robot {name}: mocap_body {body!r} is not a rigid body of the Motive "
            f"take; it has: {', '.join(sorted(take.bodies)) or '(none)'}",
            path=str(mocap_path),
        )
    return body


def read_ground_truth(
    run_dir: Path,
    mission: Mission,
    robots: dict[str, RobotTracks],
    mocap_path_given: str | None,
    notes: list[str],
) -> tuple[Path | None, motive.MotiveTake | None]:
    """(Motive CSV, take) of the run; sets each matched robot's ground-truth track."""
    mocap_path = find_mocap(run_dir, mission, mocap_path_given)
    if mocap_path is None:
        notes.append("no Motive CSV: ATE, SR_ATE, Bias and per-object errors need ground truth")
        return None, None
    take = motive.read_motive_csv(mocap_path, up_axis=mission.mocap_up_axis)
    bodies_used = []
    for name, rb in robots.items():
        body = _robot_body(name, mission, take, mocap_path, notes)
        if body is None:
            continue
        rb.gt_time_s, rb.gt_T, rb.gt_valid = body_ground_truth(take, body, rb.T_body_marker)
        bodies_used.append(body)
    if not bodies_used:
        raise InputError(
            "no robot of mission.yaml matches a rigid body of the Motive take (robots: "
            f"{', '.join(robots)}; bodies: {', '.join(sorted(take.bodies)) or '(none)'}); "
            "set mocap_body in mission.yaml",
            path=str(mocap_path),
        )
    return mocap_path, take
