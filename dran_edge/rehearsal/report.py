"""What a rehearsal reports: outputs from the daemons' checkpoints, metrics, input accounting,
rejoin times (docs/rehearsal.md, "What is checked")."""

from __future__ import annotations

import json
import logging
import math
import time
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from dran_edge.rehearsal import faults as fl

if TYPE_CHECKING:
    from dran_edge.rehearsal.fleet import Fleet, RehearsalOptions
    from dran_edge.rehearsal.robot_daemon import RobotDaemon
    from dran_edge.robot.core import RobotCore

log = logging.getLogger(__name__)

REPORT_FORMAT = "dran-edge-rehearse/1"


@dataclass
class RehearsalResult:
    report: dict
    out_dir: Path


def sample(t_s: float, st: dict) -> dict:
    g = st.get("graph") or {}
    r = st.get("rounds") or {}
    tr = st.get("transport") or {}
    heard = {str(k): v.get("last_heard_s_ago") for k, v in (st.get("neighbours") or {}).items()}
    return {
        "t_s": round(t_s, 3),
        "pid": st.get("pid"),
        "boot_epoch": st.get("boot_epoch"),
        "records": (st.get("ingest") or {}).get("records", 0),
        "pending": (st.get("journal") or {}).get("pending", 0),
        "ticks": r.get("ticks", 0),
        "late": r.get("late", 0),
        "missed": r.get("missed", 0),
        "round": g.get("round"),
        "keyframes": g.get("keyframes"),
        "objects": g.get("objects"),
        "cost": g.get("cost"),
        "consensus_error": g.get("consensus_error"),
        "converged": g.get("converged"),
        "bytes_sent": tr.get("bytes_sent", 0),
        "heard_s_ago": heard,
    }


def round_row(k: int, stamp_ns: int, statuses: dict[int, dict]) -> dict:
    """One row of rounds.csv from a status poll of the fleet (a sample, not an aligned round)."""
    costs, cerr, conv, sent = [], [], 0, 0
    for st in statuses.values():
        g = st.get("graph") or {}
        if isinstance(g.get("cost"), (int, float)) and math.isfinite(g["cost"]):
            costs.append(g["cost"])
        if isinstance(g.get("consensus_error"), (int, float)):
            cerr.append(g["consensus_error"])
        conv += bool(g.get("converged"))
        sent += int((st.get("transport") or {}).get("bytes_sent", 0))
    return {
        "round": k,
        "stamp_ns": stamp_ns,
        "bytes_total": sent,
        "bytes_round": 0,
        "cost": float(np.sum(costs)) if costs else math.nan,
        "consensus_error": float(np.max(cerr)) if cerr else math.nan,
        "converged_robots": conv,
        "datagrams_lost": 0,
    }


def _record_counts(d: RobotDaemon) -> Counter:
    """Multiset of the raw records the daemon applied, from its ``--record`` stream (a record
    re-applied from the journal after a crash appears twice there)."""
    from dran_edge.comms.ingest import IngestDecodeError, iter_records

    path = d.record_dir / "robots" / d.name / "ingest.bin"
    if not path.exists():
        return Counter()
    return Counter(
        item.raw
        for item in iter_records(path.read_bytes())
        if not isinstance(item, IngestDecodeError)
    )


def _accounting(d: RobotDaemon) -> dict:
    """Nothing accepted is lost: every record a daemon reported as accepted (its status'
    ``ingest.records`` at the last poll on that connection) was applied, by that daemon or,
    after a crash, by its successor from the journal."""
    applied = _record_counts(d)
    applied_set = set(applied)
    sent_total = sum(len(c["sent"]) for c in d.connections)
    accepted_lost, unconfirmed = 0, 0
    for c in d.connections:
        acc = min(c["accepted"], len(c["sent"]))
        accepted_lost += sum(1 for i in c["sent"][:acc] if d.records[i] not in applied_set)
        unconfirmed += len(c["sent"]) - acc
    fed = set(d.records[: d.next_record])
    never_applied = sum(1 for r in fed if r not in applied_set)
    return {
        "records_in_run": len(d.records),
        "records_sent": sent_total,
        "connections": len(d.connections),
        "accepted_reported": sum(min(c["accepted"], len(c["sent"])) for c in d.connections),
        "accepted_lost": accepted_lost,
        "sent_unconfirmed_at_kill": unconfirmed,
        "applied_distinct": len(applied_set & fed),
        "applied_twice": sum(1 for n in applied.values() if n > 1),
        "never_applied": never_applied,
        "queued_unsent": len(d.queue),
    }


def _collect(fleet: Fleet) -> dict:
    """Each robot's final checkpoint -> its core -> replay's RobotResult."""
    from dran_edge.daemon.checkpoint import CheckpointStore
    from dran_edge.config import load_config
    from dran_edge.daemon.service import default_agent_factory
    from dran_edge.replay.robots import robot_result

    results = {}
    for rid, d in fleet.daemons.items():
        cfg = load_config(d.config)
        state = CheckpointStore(d.state_dir).load()
        if state is None:
            log.warning("%s left no checkpoint", d.name)
            continue
        core = cast("RobotCore", default_agent_factory(cfg, state))
        last = core.agent.current_estimate(fleet.mission.start_ns)
        results[rid] = robot_result(rid, d.name, core, last, health=dict(state.get("counters", {})))
    return results


def finish(
    fleet: Fleet,
    opt: RehearsalOptions,
    rows: list[dict],
    drained: bool,
    exit_codes: dict,
    wall0: float,
    phases: dict,
) -> RehearsalResult:
    from dran_edge.replay.outputs import evaluation_metrics, json_clean, write_outputs

    run = fleet.run
    run.out_dir.mkdir(exist_ok=True)
    t = time.perf_counter()
    results = _collect(fleet)
    write_outputs(run, results, rows)
    phases["collect"] = time.perf_counter() - t
    robots: dict[str, dict[str, Any]] = {}
    for rid, d in fleet.daemons.items():
        last = d.samples[-1] if d.samples else {}
        robots[d.name] = {
            "id": rid,
            "starts": d.starts,
            "exit_code": exit_codes.get(d.name),
            "address": fleet.net.endpoints[d.k].dish,
            "netns": fleet.net.endpoints[d.k].netns,
            "ticks": last.get("ticks"),
            "late": last.get("late"),
            "missed": last.get("missed"),
            "keyframes": len(results[rid].last.keyframe_stamps_ns) if rid in results else 0,
            "objects": len(results[rid].last.object_ids) if rid in results else 0,
            "ingest": _accounting(d),
            "rejected_in_file": dict(d.rejected_in_file),
        }
    report: dict[str, Any] = {
        "format": REPORT_FORMAT,
        "run": str(fleet.src.root),
        "robots": len(fleet.daemons),
        "mission_s": float(fleet.mission.duration_s),
        "speed": opt.speed,
        "period_s": fleet.period_s,
        "daemon_period_s": fleet.period_s / opt.speed,
        "net": fleet.net.kind,
        "net_note": fleet.net_note,
        "drained": drained,
        "options": {k: v for k, v in asdict(opt).items() if k != "faults"},
        "faults": [f.describe(fleet.names) for f in opt.faults],
        "fault_log": fleet.fault_log,
        "per_robot": robots,
        "accepted_lost": sum(r["ingest"]["accepted_lost"] for r in robots.values()),
        "rejoin": _rejoin(fleet),
    }
    t = time.perf_counter()
    if opt.evaluate and fleet.mission.mocap_file:
        report.update(evaluation_metrics(run))
    phases["evaluate"] = time.perf_counter() - t
    report["rehearsal_wall_s"] = round(time.perf_counter() - wall0, 3)
    report["phases_wall_s"] = {k: round(v, 3) for k, v in phases.items()}
    timeline = {d.name: d.samples for d in fleet.daemons.values()}
    (fleet.out / "timeline.json").write_text(json.dumps(json_clean(timeline)) + "\n")
    (fleet.out / "rehearsal.json").write_text(json.dumps(json_clean(report), indent=2) + "\n")
    return RehearsalResult(report, fleet.out)


def _rejoin(fleet: Fleet) -> list[dict]:
    """For each restart or healed partition/silence: when the robot's neighbours heard it
    again and it heard them (mission seconds after the fault ended), from the status polls."""
    out = []
    for entry in fleet.fault_log:
        if entry["action"] != "end":
            continue
        f = next(a.fault for a in fl.actions(list(fleet.opt.faults)) if a.index == entry["index"])
        if f.kind not in ("kill", "partition", "silent"):
            continue
        t_end = entry["t_s"]
        for rid in f.robots:
            nbrs = fleet.mission.neighbours(rid)
            if f.kind == "partition":
                nbrs = tuple(j for j in nbrs if j not in f.robots)
            heard_by = {}
            for j in nbrs:
                heard_by[fleet.names[j]] = _first_heard(
                    fleet.daemons[j].samples, rid, t_end, fleet.opt.speed
                )
            hears = {
                fleet.names[j]: _first_heard(fleet.daemons[rid].samples, j, t_end, fleet.opt.speed)
                for j in nbrs
            }
            out.append(
                {
                    "fault": entry["fault"],
                    "robot": fleet.names[rid],
                    "ended_s": t_end,
                    "heard_by_s": heard_by,
                    "hears_s": hears,
                }
            )
    return out


def _first_heard(samples: list[dict], peer: int, after_s: float, speed: float) -> float | None:
    """Mission seconds after ``after_s`` at which a status sample first shows ``peer`` heard
    since then (the daemons' ``last_heard_s_ago`` is wall time: times ``speed``)."""
    for s in samples:
        if s["t_s"] <= after_s:
            continue
        ago = (s.get("heard_s_ago") or {}).get(str(peer))
        if ago is not None and s["t_s"] - ago * speed > after_s - 1e-6:
            return round(s["t_s"] - after_s, 3)
    return None
