"""The archive of marginalised keyframes (dran_edge/robot/archive.py) and loops into it."""

from __future__ import annotations

import copy

import numpy as np

from dran_edge import geometry as geo
from dran_edge.config import AgentConfig, GraphBounds
from dran_edge.daemon.checkpoint import dumps, loads
from dran_edge.events import Keyframe, LoopClosure
from dran_edge.robot.archive import ArchivedPose, PoseArchive
from dran_edge.robot.keyframe_graph import (
    KIND_LOOP,
    KIND_OBSERVATION,
    NONE,
    OBJ,
    KeyframeGraph,
    invert_cov,
)
from dran_edge.sim.vio import vio_mission
from dran_edge.solver import lm


def cfg(archive_size: int = 4096, **kw) -> AgentConfig:
    return AgentConfig(
        graph=GraphBounds(max_nodes=60, max_edges=240, archive_size=archive_size), **kw
    )


def feed(g: KeyframeGraph, events) -> None:
    for e in events:
        g.handle(e)


def entry(stamp: int, segment: int = 0) -> ArchivedPose:
    T = geo.se3_exp(np.array([stamp * 0.1, 0, 0, 0, 0, 0.01 * stamp]))
    return ArchivedPose(stamp, segment, T, 1e-4 * np.eye(6), T, 0.1 * stamp, 0.01 * stamp)


def test_archive_stays_bounded_and_spans_the_mission():
    a = PoseArchive(16)
    for k in range(1000):
        a.add(entry(k, segment=k // 500))
        assert len(a) <= 16
    assert len(a) >= 8 and a.thinned > 0
    # still spans both segments from their start to their end
    for seg, lo, hi in ((0, 0, 499), (1, 500, 999)):
        assert a.nearest(seg, lo).stamp_ns - lo < 500 // 4
        assert hi - a.nearest(seg, hi).stamp_ns < 500 // 4
    assert a.nearest(2, 10) is None
    b = PoseArchive.from_state(16, loads(dumps(a.to_state())))
    assert len(b) == len(a) and b.thinned == a.thinned
    e, f = a.nearest(1, 777), b.nearest(1, 777)
    assert e.stamp_ns == f.stamp_ns
    np.testing.assert_array_equal(e.T_world_body, f.T_world_body)
    # a checkpoint written before entries had a reference: all in the world frame
    old = {k: v for k, v in a.to_state().items() if k not in ("ref_key", "T_ref_body")}
    f = PoseArchive.from_state(16, loads(dumps(old))).nearest(1, 777)
    assert f.ref_key == NONE
    np.testing.assert_array_equal(f.T_ref_body, e.T_world_body)


MISSION = vio_mission(300, seed=21)
_GRAPHS: dict = {}


def _mission_graph(archive_size: int, anchor_first: bool = True):
    """The mission streamed into a bounded graph, solved every 10 nodes as the daemon does
    (built once per setting; callers get a copy)."""
    key = (archive_size, anchor_first)
    if key not in _GRAPHS:
        g = KeyframeGraph(cfg(archive_size), anchor_first=anchor_first)
        for e in MISSION.events:
            g.handle(e)
            if isinstance(e, Keyframe) and g.counters.get("nodes_added", 0) % 10 == 0:
                g.solve(lm.LMParams(max_iterations=3))
        _GRAPHS[key] = g
    return MISSION, copy.deepcopy(_GRAPHS[key])


def test_archived_covariance_is_not_overconfident_on_a_mission():
    """Each archived keyframe's error against the truth (its pose relative to its reference
    object, or in the world), whitened by its covariance: on average no larger than a
    consistent Gaussian's (E[χ²₆] = 6). Over-confident covariances (information counted twice
    in the marginal) would push it above."""
    m, g = _mission_graph(4096)
    entries = [e for seg in sorted(g.archive._entries) for e in g.archive._entries[seg]]
    assert len(entries) > 30 and g.counters["nodes_archived"] == len(entries)
    i = np.searchsorted(m.keyframe_stamps_ns, [e.stamp_ns for e in entries])
    T_true = m.T_world_body_true[i]
    refs = np.array([e.ref_key for e in entries])
    assert np.mean(refs >= OBJ) > 0.9  # objects are seen from the start: nearly all relative
    T_ref_true = np.stack(
        [m.T_world_object_true[r - OBJ] if r >= OBJ else np.eye(4) for r in refs.tolist()]
    )
    T = np.stack([e.T_ref_body for e in entries])
    err = geo.se3_log(geo.se3_between(T, geo.se3_between(T_ref_true, T_true)))
    nees = [d @ np.linalg.solve(e.covariance, d) for d, e in zip(err, entries)]
    assert np.mean(nees) < 6.0, np.mean(nees)


def test_a_loop_into_a_removed_keyframe_becomes_a_factor_to_its_reference_object():
    """With the archive the old end is the removed keyframe's own estimate relative to an
    object, not a kept node hundreds of keyframes away through VIO odometry: a loop factor
    between the current node and that object, far more certain."""
    sigmas = {}
    for size in (4096, 0):
        m, g = _mission_graph(size)
        kept = set(g.node_stamps_ns().tolist())
        old = next(i for i in range(50, 150) if int(m.keyframe_stamps_ns[i]) not in kept)
        cur = len(m.keyframe_stamps_ns) - 1
        rel = geo.se3_between(m.T_world_body_true[old], m.T_world_body_true[cur])
        before = g.num_factors
        loops_before = dict(g.counters)
        assert g.handle(
            LoopClosure(int(m.keyframe_stamps_ns[old]), int(m.keyframe_stamps_ns[cur]), rel, 60)
        )
        fa = g.factor_arrays(include_prior=False)
        newest = int(g.node_keys()[-1])
        if size:
            assert g.counters["loops_to_archived_keyframes"] == 1 + loops_before.get(
                "loops_to_archived_keyframes", 0
            )
            sel = (fa["p"] == newest) & (fa["q"] >= OBJ) & (fa["kind"] == KIND_LOOP)
            assert sel.sum() == 1
            # its mean (T_x⁻¹ T_o): the archived pose relative to the object composed with the
            # loop, near the truth
            Z, S = invert_cov(fa["Z"][sel][0], fa["S"][sel][0])  # T_o⁻¹ T_x
            T_pred = g.obj_est[int(fa["q"][sel][0]) - OBJ] @ Z
            assert np.linalg.norm(T_pred[:3, 3] - m.T_world_body_true[cur][:3, 3]) < 0.5
        else:
            assert g.num_factors >= before  # a binary loop to a kept node
            sel = (fa["q"] == newest) & (fa["kind"] == KIND_LOOP) & (fa["p"] != NONE)
            S = fa["S"][sel][-1]
        sigmas[size] = float(np.sqrt(np.trace(S[:3, :3]) / 3))
    assert sigmas[4096] < 0.5 * sigmas[0], sigmas


def test_a_robot_without_absolute_information_archives_nothing():
    """A fleet robot that does not carry the gauge: its marginals hold no absolute information,
    so nothing is archived and loops of removed nodes are re-anchored as without the archive."""
    _, g = _mission_graph(4096, anchor_first=False)
    assert len(g.archive) == 0 and "nodes_archived" not in g.counters
    assert g.counters.get("loops_reanchored", 0) > 0
    fa = g.factor_arrays(include_prior=False)
    assert not np.any(fa["p"] == NONE)


def test_state_round_trip_keeps_the_archive():
    m = vio_mission(300, seed=9)
    a = KeyframeGraph(cfg())
    half = len(m.events) // 2
    feed(a, m.events[:half])
    assert len(a.archive) > 0
    b = KeyframeGraph.from_state(cfg(), loads(dumps(a.to_state())))
    feed(a, m.events[half:])
    feed(b, m.events[half:])
    assert a.counters == b.counters and len(a.archive) == len(b.archive)
    fa, fb = a.factor_arrays(), b.factor_arrays()
    for k in fa:
        np.testing.assert_allclose(fa[k], fb[k])


def test_the_agent_sees_loops_into_the_archive():
    """Loops into archived keyframes kept relative to an object reach the DRAN agent as views
    of that object (its observations); those in the world frame as robust priors."""
    from dran_edge.dran.problem import LocalProblem
    from dran_edge.robot.core import problem_from_graph

    _, g = _mission_graph(4096)
    fa = g.factor_arrays()
    loop = fa["kind"] == KIND_LOOP
    relative = int(np.sum(loop & (fa["q"] >= OBJ)))
    unary_loops = int(np.sum(loop & (fa["p"] == NONE)))
    assert relative > 0
    observations = int(np.sum((fa["kind"] == KIND_OBSERVATION) & (fa["q"] >= OBJ)))
    p = problem_from_graph(g, g.config.residual)
    assert p.obs_own.size == observations + relative
    assert p.prior_robust.shape == p.prior_own.shape and int(p.prior_robust.sum()) == unary_loops
    q = LocalProblem.from_dict(p.to_dict())
    assert q.obs_own.size == p.obs_own.size and q.prior_robust.sum() == unary_loops


def test_a_marginal_ignores_what_it_does_not_touch_and_refuses_a_free_direction():
    """``_archive_node``'s covariance is ``[H⁻¹]_nn`` for a regular system, is unchanged by a
    variable without information that ``n`` is not coupled to (a node of an earlier VIO segment
    left in the prior), and is refused when a direction without information touches ``n``."""
    m = vio_mission(30, seed=3)
    g = KeyframeGraph(cfg())
    feed(g, m.events)
    n = int(g.node_keys()[1])
    rng = np.random.default_rng(0)
    A = rng.normal(size=(18, 18))
    H = A @ A.T + 0.1 * np.eye(18)  # n is variable 1 of 3
    e = g._archive_node(n, H, 1)
    assert e is not None
    np.testing.assert_allclose(e.covariance, np.linalg.inv(H)[6:12, 6:12], rtol=1e-9)
    H4 = np.zeros((24, 24))
    H4[:18, :18] = H  # variable 3: no information at all, coupled to nothing
    np.testing.assert_allclose(g._archive_node(n, H4, 1).covariance, e.covariance, rtol=1e-9)
    # a free direction of variable 0 coupled to n: n's marginal is not finite
    v = np.zeros(18)
    v[0] = 1.0
    P = np.eye(18) - np.outer(v + np.eye(18)[6], v + np.eye(18)[6]) / 2.0  # null along v + e_6
    Hs = P @ H @ P
    singular = g.counters.get("archive_singular", 0)
    assert g._archive_node(n, Hs, 1) is None
    assert g.counters["archive_singular"] == singular + 1


def test_a_daemon_core_runs_its_rounds_on_loops_into_the_archive():
    """The daemon's RobotCore (a lone robot carries the gauge) on a mission that fills the
    archive: the DRAN agent's rounds run on the archive's robust priors and give finite
    estimates near the truth, and a checkpoint taken then continues alike."""
    from dran_edge.events import EstimateUpdate, Tick
    from dran_edge.robot.core import RobotCore

    m = vio_mission(240, seed=5)
    config = AgentConfig(graph=GraphBounds(max_nodes=50, max_edges=200))

    def run(core, events):
        last, kf = None, 0
        for e in events:
            core.handle(e)
            if isinstance(e, Keyframe):
                kf += 1
                if kf % 5 == 0:
                    for out in core.handle(Tick(int(e.stamp_ns) + 1)):
                        if isinstance(out, EstimateUpdate):
                            last = out
        return last

    half = len(m.events) // 2
    core = RobotCore(config)
    run(core, m.events[:half])
    again = RobotCore.from_state(config, loads(dumps(core.to_state())))
    a = run(core, m.events[half:])
    b = run(again, m.events[half:])
    g = core.local_graph
    assert (
        g.counters.get("loops_into_archive", 0) + g.counters.get("loops_to_archived_keyframes", 0)
        > 0
    )
    assert a is not None and b is not None
    assert np.all(np.isfinite(a.T_world_body))
    np.testing.assert_allclose(a.T_world_body, b.T_world_body, atol=1e-6)
    i = np.searchsorted(m.keyframe_stamps_ns, a.keyframe_stamps_ns)
    err = np.linalg.norm(a.T_world_body[:, :3, 3] - m.T_world_body_true[i, :3, 3], axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.2, np.sqrt(np.mean(err**2))  # 0.08 m here


def test_archive_covariances_come_from_the_prior_without_the_archive():
    """An archived keyframe's covariance is computed from a prior that never took in the
    archive's own factors (``prior_clean``), so archive information does not feed later archive
    entries: that prior holds no more information than the real one (Loewner order, on their
    common variables), and strictly less once archive factors were marginalised."""
    _, g = _mission_graph(4096)
    assert g.counters.get("loops_into_archive", 0) > 0
    full, clean = g.prior, g.prior_clean
    assert full is not None and clean is not None
    np.testing.assert_array_equal(full["keys"], clean["keys"])
    H_full, H_clean = full["W"].T @ full["W"], clean["W"].T @ clean["W"]
    # the linearisation points differ only where the two priors were built at other estimates
    gap = np.linalg.eigvalsh(H_full - H_clean)
    assert gap.min() > -1e-6 * np.abs(gap).max()
    assert gap.max() > 1e-3 * np.linalg.eigvalsh(H_full).max()


def test_an_archived_pose_is_kept_relative_to_what_it_is_known_best_against():
    """``_map_reference`` on a two-variable system (node n, object o, both at the identity, so
    ``T_o⁻¹ T_n``'s error is ``δn − δo``): when both share a large common error (the map's
    placement) and differ little, n is kept relative to o with the small covariance of the
    difference; when n's world pose is certain and o's is not (a keyframe near the gauge), in
    the world frame."""
    _, g = _mission_graph(4096)
    keys = np.array([5, OBJ + 3], dtype=np.int64)
    poses = np.stack([np.eye(4), np.eye(4)])
    I6 = np.eye(6)
    common, own = 1e-2, 1e-6
    C = np.block([[(common + own) * I6, common * I6], [common * I6, (common + own) * I6]])
    ref, T, S = g._map_reference(np.linalg.inv(C), 0, keys, poses, np.eye(4), C[:6, :6])
    assert ref == OBJ + 3
    np.testing.assert_allclose(S, 2 * own * I6, rtol=1e-6, atol=1e-12)
    C = np.block([[own * I6, 0 * I6], [0 * I6, common * I6]])
    ref, T, S = g._map_reference(np.linalg.inv(C), 0, keys, poses, np.eye(4), C[:6, :6])
    assert ref == NONE
    np.testing.assert_allclose(S, own * I6)
