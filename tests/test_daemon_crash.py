"""Crash safety: kill -9 mid-mission, restart, and nothing accepted is lost (docs/architecture.md)."""

from __future__ import annotations

import signal
import socket

import numpy as np
from daemon_helpers import start_daemon, stop, wait_status, write_config

from dran_edge.dran.agent import Agent
from dran_edge.daemon.checkpoint import CheckpointStore
from dran_edge.comms.ingest import encode_event
from dran_edge.config import load_config
from dran_edge.events import Tick
from dran_edge.robot.keyframe_graph import KeyframeGraph, gauge_anchor
from dran_edge.robot.core import problem_from_graph
from dran_edge.sim.vio import vio_mission

ROUNDS_AFTER_DATA = 30


def ate(stamps: np.ndarray, T: np.ndarray, mission) -> float:
    i = np.searchsorted(mission.keyframe_stamps_ns, stamps)
    return float(np.mean(np.linalg.norm(T[:, :3, 3] - mission.T_world_body_true[i, :3, 3], axis=1)))


def reference(cfg, events, mission) -> tuple[dict, float]:
    """The same inputs without interruption, in process: counts and accuracy to match."""
    g = KeyframeGraph(cfg.agent, anchor_first=gauge_anchor(cfg.agent))
    a = Agent(cfg.agent)
    half = len(events) // 2
    for chunk in (events[:half], events[half:]):
        for ev in chunk:
            g.handle(ev)
        a.set_problem(problem_from_graph(g, cfg.agent.residual))
        for k in range(ROUNDS_AFTER_DATA):
            a.handle(Tick(k))
    return g.counters, ate(a.problem.pose_stamps_ns, a.x, mission)


def send(path, records: list[bytes]) -> None:
    with socket.socket(socket.AF_UNIX) as s:
        s.connect(str(path))
        for r in records:
            s.sendall(r)


def test_kill_9_mid_mission_loses_nothing_accepted(tmp_path):
    mission = vio_mission(240, seed=5)
    events = mission.events
    records = [encode_event(e) for e in events]
    # a round every 0.1 s: the 30 rounds after the data take 3 s, not 6 (the reference counts
    # rounds, not seconds); checkpoints stay 1 s apart (the kill must land after the last one)
    cfg_path = write_config(tmp_path, comms={"period_s": 0.1}, daemon={"checkpoint_period_s": 1.0})
    cfg = load_config(cfg_path)
    run = tmp_path / "run"
    status = run / "status.sock"

    # first life: half the mission, with a checkpoint inside it, then SIGKILL
    half = len(records) // 2
    quarter = half // 2
    proc = start_daemon(cfg_path, {})
    first_epoch = wait_status(status, lambda s: s["state"] == "running", proc=proc)["boot_epoch"]
    send(run / "ingest.sock", records[:quarter])
    wait_status(
        status,
        lambda s: s["counters"].get("checkpoints", 0) >= 2 and s["journal"]["pending"] == 0,
        proc=proc,
    )
    send(run / "ingest.sock", records[quarter:half])
    st = wait_status(status, lambda s: s["ingest"]["records"] == half, proc=proc)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    mid = CheckpointStore(tmp_path / "state").load()
    applied_at_kill = sum(v for k, v in mid["counters"].items() if k.startswith("applied_"))
    assert applied_at_kill < half, "the kill should land after the last checkpoint"

    # second life: recover, take the rest, run rounds, stop cleanly
    proc = start_daemon(cfg_path, {})
    st = wait_status(status, lambda s: s["state"] == "running", proc=proc)
    assert st["boot_epoch"] > first_epoch
    assert st["counters"].get("recovered_records", 0) >= half - applied_at_kill
    send(run / "ingest.sock", records[half:])
    st = wait_status(
        status,
        lambda s: s["ingest"]["records"] == len(records) - half and s["journal"]["pending"] == 0,
        proc=proc,
    )
    ticks0 = st["rounds"]["ticks"]
    wait_status(
        status,
        lambda s: s["rounds"]["ticks"] >= ticks0 + ROUNDS_AFTER_DATA,
        timeout_s=120,
        proc=proc,
    )
    rc, out = stop(proc)
    assert rc == 0, out

    final = CheckpointStore(tmp_path / "state").load()
    applied = sum(v for k, v in final["counters"].items() if k.startswith("applied_"))
    assert applied == len(records), "every accepted record applied exactly once"
    ref_counts, ref_ate = reference(cfg, events, mission)
    got = final["graph"]["counters"]
    for key in ("nodes_added", "loops_added", "observations_added", "resets"):
        assert got.get(key, 0) == ref_counts.get(key, 0), key
    assert got["loops_added"] > 0 and got["observations_added"] > 0
    agent = Agent.from_state(cfg.agent, final["agent"])
    got_ate = ate(agent.problem.pose_stamps_ns, agent.x, mission)
    assert got_ate <= 1.25 * ref_ate + 0.02, (got_ate, ref_ate)


def test_restart_after_clean_stop_resumes_without_replaying(tmp_path):
    mission = vio_mission(40, seed=2)
    records = [encode_event(e) for e in mission.events]
    cfg_path = write_config(tmp_path)
    status = tmp_path / "run" / "status.sock"
    proc = start_daemon(cfg_path, {})
    wait_status(status, lambda s: s["state"] == "running", proc=proc)
    send(tmp_path / "run" / "ingest.sock", records)
    wait_status(
        status,
        lambda s: s["ingest"]["records"] == len(records) and s["journal"]["pending"] == 0,
        proc=proc,
    )
    rc, out = stop(proc)
    assert rc == 0, out
    before = CheckpointStore(tmp_path / "state").load()
    proc = start_daemon(cfg_path, {})
    try:
        st = wait_status(status, lambda s: s["rounds"]["ticks"] >= 2, proc=proc)
    finally:
        stop(proc)
    assert st["counters"].get("recovered_records", 0) == 0
    assert st["graph"]["nodes"] == before["graph"]["nodes"].shape[0]
