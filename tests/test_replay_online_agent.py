"""RobotCore / problem_from_graph: ingest events -> bounded local graph -> the agent's problem."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dran_edge import geometry as geo
from dran_edge.config import AgentConfig
from dran_edge.events import (
    EstimateUpdate,
    Tick,
)
from dran_edge.robot.keyframe_graph import OBJ
from dran_edge.robot.core import RobotCore, problem_from_graph
from sim_events import single_robot_events


@pytest.fixture(scope="module")
def robot_events():
    return single_robot_events(2)


def _run(core, events, period_ns=500_000_000):
    start = events[0][0]
    last = None
    i = 0
    t = start + period_ns
    while i < len(events):
        while i < len(events) and events[i][0] <= t:
            core.handle(events[i][2])
            i += 1
        for out in core.handle(Tick(t)):
            if isinstance(out, EstimateUpdate):
                last = out
        t += period_ns
    return last


def test_problem_from_graph_maps_every_factor(robot_events):
    m, r, events = robot_events
    core = RobotCore(AgentConfig(robot_id=1))
    for _, _, ev in events:
        core.local_graph.handle(ev)
    g = core.local_graph
    G = geo.se3_from_rt(geo.so3_exp(np.r_[0, 0, 0.7]), np.r_[1.0, -2.0, 0.1])
    prob = problem_from_graph(g, "geodesic", G)
    fa = g.factor_arrays()
    n_obs = int(np.sum(fa["q"] >= OBJ))
    assert prob.n == g.num_nodes
    assert prob.between.shape[0] + prob.obs_own.size + prob.prior_own.size == len(fa["p"])
    assert prob.obs_own.size == n_obs > 0
    assert set(prob.obs_object.tolist()) <= set(range(4))
    assert prob.between_robust.sum() > 0  # the loops
    np.testing.assert_allclose(prob.x0, G @ g.T_world_body(), atol=1e-12)
    # the gauge prior sits on the first node, in the world frame
    assert prob.prior_own.tolist() == [0]
    np.testing.assert_allclose(prob.prior_T[0], G @ g.T_world_body()[0], atol=1e-9)
    # whitening: W^T W = inverse covariance
    k = int(np.flatnonzero((fa["p"] >= 0) & (fa["q"] < OBJ))[0])
    W = prob.between_W[0]
    np.testing.assert_allclose(W.T @ W, np.linalg.inv(fa["S"][k]), rtol=1e-6)


def test_online_agent_estimates_in_the_world_frame(robot_events):
    m, r, events = robot_events
    core = RobotCore(AgentConfig(robot_id=1), T_world_odom=r.T_world_odom[0])
    last = _run(core, events)
    assert last is not None and len(last.keyframe_stamps_ns) > 20
    truth = r.path.poses((last.keyframe_stamps_ns - m.params.start_ns) / 1e9)
    err = np.linalg.norm(last.T_world_body[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert err[0] < 0.01  # anchored where the robot started
    assert np.sqrt(np.mean(err**2)) < 0.1
    s0, T0 = core.initial_estimate()
    assert len(s0) == len(last.keyframe_stamps_ns)
    err0 = np.linalg.norm(T0[:, :3, 3] - truth[:, :3, 3], axis=1)
    # the optimised estimate beats odometry alone (loops and boxes correct the drift)
    assert np.sqrt(np.mean(err**2)) < np.sqrt(np.mean(err0**2))
    assert last.object_ids and set(last.object_ids) <= set(range(4))


def test_world_frame_only_before_the_first_keyframe(robot_events):
    _, r, events = robot_events
    core = RobotCore(AgentConfig(robot_id=1))
    for _, _, ev in events[:200]:
        core.handle(ev)
    with pytest.raises(ValueError, match="already has nodes"):
        core.set_world_frame(np.eye(4))


def test_without_world_frame_only_the_lowest_id_anchors():
    lone = RobotCore(AgentConfig(robot_id=3, neighbours=(5, 7)))
    assert lone.local_graph.anchor_first
    other = RobotCore(AgentConfig(robot_id=3, neighbours=(1, 5)))
    assert not other.local_graph.anchor_first
    with_frame = RobotCore(
        dataclasses.replace(AgentConfig(robot_id=3, neighbours=(1,))), T_world_odom=np.eye(4)
    )
    assert with_frame.local_graph.anchor_first
