"""RobotCore.to_state / from_state (the daemon's checkpoint of its core) and the write-back."""

from __future__ import annotations

import numpy as np
import pytest

from dran_edge import geometry as geo
from dran_edge.daemon.checkpoint import dumps, loads
from dran_edge.config import AgentConfig, GraphBounds
from dran_edge.events import (
    EstimateUpdate,
    Tick,
)
from dran_edge.robot.core import RobotCore
from sim_events import single_robot_events


@pytest.fixture(scope="module")
def mission():
    _, r, events = single_robot_events(3)
    return r, events


def _ticks(events, period_ns=500_000_000):
    """[(events up to the tick, Tick)] on a fixed period."""
    out, i, t = [], 0, events[0][0] + period_ns
    while i < len(events):
        chunk = []
        while i < len(events) and events[i][0] <= t:
            chunk.append(events[i][2])
            i += 1
        out.append((chunk, Tick(t)))
        t += period_ns
    return out


def _feed(core, steps):
    last = None
    for chunk, tick in steps:
        for ev in chunk:
            core.handle(ev)
        for out in core.handle(tick):
            if isinstance(out, EstimateUpdate):
                last = out
    return last


def test_state_round_trips_through_a_checkpoint_and_continues_alike(mission):
    r, events = mission
    steps = _ticks(events)
    half = len(steps) // 2
    cfg = AgentConfig(robot_id=1)
    core = RobotCore(cfg, T_world_odom=r.T_world_odom[0])
    _feed(core, steps[:half])
    state = loads(dumps(core.to_state()))  # through the daemon's checkpoint format
    again = RobotCore.from_state(cfg, state)
    assert again.local_graph.num_nodes == core.local_graph.num_nodes > 10
    np.testing.assert_array_equal(again.T_world_odom, core.T_world_odom)
    assert again.local_graph.anchor_first == core.local_graph.anchor_first
    s0, T0 = core.initial_estimate()
    s1, T1 = again.initial_estimate()
    np.testing.assert_array_equal(s0, s1)
    np.testing.assert_allclose(T0, T1, atol=1e-12)
    a = _feed(core, steps[half:])
    b = _feed(again, steps[half:])
    assert a is not None and b is not None
    np.testing.assert_array_equal(a.keyframe_stamps_ns, b.keyframe_stamps_ns)
    np.testing.assert_allclose(a.T_world_body, b.T_world_body, atol=1e-6)
    assert a.object_ids == b.object_ids
    np.testing.assert_array_equal(core.initial_estimate()[0], again.initial_estimate()[0])


def test_to_state_holds_the_optimised_estimates(mission):
    r, events = mission
    steps = _ticks(events)
    core = RobotCore(AgentConfig(robot_id=1), T_world_odom=r.T_world_odom[0])
    _feed(core, steps[: len(steps) // 2])
    for k in range(5):  # rounds after the last rebuild move the estimates on
        core.handle(Tick(steps[-1][1].stamp_ns + k))
    a = core.agent
    G_inv = geo.se3_inverse(core.T_world_odom)
    g = core.local_graph
    stale = np.stack([g.node_est[int(k)] for k in a.problem.pose_ids.tolist()])
    assert np.abs(stale - G_inv @ a.x).max() > 1e-9, "the rounds should have moved the poses"
    state = core.to_state()
    nodes = np.asarray(state["graph"]["nodes"]).tolist()
    idx = [nodes.index(int(k)) for k in a.problem.pose_ids.tolist()]
    np.testing.assert_allclose(state["graph"]["node_est"][idx], G_inv @ a.x, atol=1e-12)
    objs = np.asarray(state["graph"]["objects"]).tolist()
    assert objs and set(objs) == set(a.y)
    for i, o in enumerate(objs):
        np.testing.assert_allclose(state["graph"]["obj_est"][i], G_inv @ a.y[o], atol=1e-12)


def test_dead_reckoning_stays_bounded_by_the_graph(mission):
    r, events = mission
    cfg = AgentConfig(robot_id=1, graph=GraphBounds(max_nodes=12, max_edges=48))
    core = RobotCore(cfg, T_world_odom=r.T_world_odom[0])
    _feed(core, _ticks(events))
    g = core.local_graph
    assert g.counters.get("nodes_added", 0) > g.num_nodes, "the graph should have dropped nodes"
    assert set(core.dead_reckoning) <= set(g.node_keys().tolist()) | set(
        core._dr_last_of_segment.values()
    )


def test_from_state_refuses_another_format(mission):
    state = RobotCore(AgentConfig(robot_id=1)).to_state()
    state["online"]["format"] = 99
    with pytest.raises(ValueError, match="state format"):
        RobotCore.from_state(AgentConfig(robot_id=1), state)
