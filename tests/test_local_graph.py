"""The bounded local graph: selection, segments, attachment, bounds, marginalisation, state."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dran_edge import geometry as geo
from dran_edge.daemon.checkpoint import dumps, loads
from dran_edge.config import AgentConfig, GraphBounds
from dran_edge.events import Keyframe, LoopClosure, ObservationBatch, OdometrySample, VioReset
from dran_edge.robot.keyframe_graph import (
    KIND_LOOP,
    KIND_OBSERVATION,
    KIND_ODOMETRY,
    OBJ,
    KeyframeGraph,
    compose_cov,
    fuse,
    gauge_anchor,
    invert_cov,
)
from dran_edge.robot.segments import Segmenter
from dran_edge.sim.vio import vio_mission


def cfg(max_nodes=100_000, max_edges=400_000, **kw) -> AgentConfig:
    return AgentConfig(graph=GraphBounds(max_nodes=max_nodes, max_edges=max_edges), **kw)


def feed(g: KeyframeGraph, events) -> None:
    for e in events:
        g.handle(e)


def pose(x=0.0, y=0.0, yaw=0.0) -> np.ndarray:
    return geo.se3_from_rt(geo.so3_exp(np.array([0, 0, yaw])), np.array([x, y, 0.0]))


# --------------------------------------------------------------------------- covariance algebra
def test_compose_covariance_matches_monte_carlo():
    rng = np.random.default_rng(0)
    Z1 = geo.se3_exp(np.array([1, 0.2, 0, 0.1, 0, 0.5]))
    Z2 = geo.se3_exp(np.array([0.5, 1, 0, 0, 0.2, 0.3]))
    S1, S2 = np.diag([1e-3] * 3 + [4e-4] * 3), np.diag([2e-3] * 3 + [1e-4] * 3)
    Z, S = compose_cov(Z1, S1, Z2, S2)
    n = 20000
    e1 = rng.multivariate_normal(np.zeros(6), S1, n)
    e2 = rng.multivariate_normal(np.zeros(6), S2, n)
    samples = (Z1 @ geo.se3_exp(e1)) @ (Z2 @ geo.se3_exp(e2))
    err = geo.se3_log(geo.se3_between(Z, samples))
    np.testing.assert_allclose(np.cov(err.T), S, atol=3e-4 * np.abs(S).max() + 5e-5)


def test_invert_and_fuse():
    Z = geo.se3_exp(np.array([1, 2, 3, 0.1, 0.2, 0.3]))
    S = np.diag([1.0, 2, 3, 0.1, 0.2, 0.3]) * 1e-3
    Zi, Si = invert_cov(*invert_cov(Z, S))
    np.testing.assert_allclose(Zi, Z, atol=1e-12)
    np.testing.assert_allclose(Si, S, atol=1e-12)
    Zf, Sf = fuse(Z, S, Z, S)
    np.testing.assert_allclose(Zf, Z, atol=1e-12)
    np.testing.assert_allclose(Sf, S / 2, atol=1e-12)


# --------------------------------------------------------------------------- selection, segments
def test_keyframe_selection_by_distance_angle_time():
    g = KeyframeGraph(cfg())
    b = g.bounds
    t = 1_000_000_000
    g.handle(Keyframe(t, pose()))
    g.handle(Keyframe(t + 10**8, pose(0.5 * b.keyframe_min_distance_m)))  # too close
    assert g.num_nodes == 1
    g.handle(Keyframe(t + 2 * 10**8, pose(1.1 * b.keyframe_min_distance_m)))  # far enough
    g.handle(
        Keyframe(
            t + 3 * 10**8, pose(1.1 * b.keyframe_min_distance_m, yaw=1.1 * b.keyframe_min_angle_rad)
        )
    )  # turned
    g.handle(
        Keyframe(
            t + 3 * 10**8 + int(1.1e9 * b.keyframe_max_interval_s),
            pose(1.1 * b.keyframe_min_distance_m, yaw=1.1 * b.keyframe_min_angle_rad),
        )
    )
    assert g.num_nodes == 4
    assert g.counters["keyframes_skipped"] == 1
    fa = g.factor_arrays()
    assert np.sum(fa["kind"] == KIND_ODOMETRY) == 3


def test_segments_from_reset_gap_and_jump():
    s = Segmenter(GraphBounds())
    t = 10**9
    assert s.odometry(t, pose())[1] == "first odometry"
    assert s.odometry(t + 10**8, pose(0.05))[1] is None
    assert "gap" in s.odometry(t + 3 * 10**9, pose(0.1))[1]
    assert "jump" in s.odometry(t + 3 * 10**9 + 10**8, pose(4.0))[1]
    sid = s.reset(t + 4 * 10**9, "feature_tracker_restart")
    assert s.current == sid == 3
    assert s.segment_at(t + 5 * 10**8) == 0 and s.segment_at(t + 10**10) == 3
    assert s.odometry(t, pose())[1] is None and s.stale_samples == 1


def test_no_odometry_edge_across_a_reset():
    m = vio_mission(120, seed=3, reset_at=(60,))
    g = KeyframeGraph(cfg())
    feed(g, m.events)
    fa = g.factor_arrays()
    odo = fa["kind"] == KIND_ODOMETRY
    seg = {k: g.node_segment[k] for k in g.node_keys().tolist()}
    assert all(seg[int(p)] == seg[int(q)] for p, q in zip(fa["p"][odo], fa["q"][odo]))
    assert len(set(seg.values())) == 2
    assert g.counters["resets"] == 1


def test_loop_and_observation_measurements_match_truth():
    m = vio_mission(
        200, seed=4, drift_t=1e-6, drift_r=1e-7, loop_sigma=(1e-6, 1e-7), obs_sigma=(1e-6, 1e-7)
    )
    g = KeyframeGraph(cfg())
    feed(g, m.events)
    fa = g.factor_arrays()
    stamps = dict(zip(g.node_keys().tolist(), g.node_stamps_ns().tolist()))
    true = dict(zip(m.keyframe_stamps_ns.tolist(), m.T_world_body_true))
    loops = np.flatnonzero(fa["kind"] == KIND_LOOP)
    obs = np.flatnonzero(fa["kind"] == KIND_OBSERVATION)
    assert len(loops) > 5 and len(obs) > 20
    for i in loops:
        T = geo.se3_between(true[stamps[int(fa["p"][i])]], true[stamps[int(fa["q"][i])]])
        assert geo.se3_geodesic_distance(T, fa["Z"][i]) < 1e-3
    for i in obs:  # observation frames lie between keyframes: attached by interpolation
        T = geo.se3_between(true[stamps[int(fa["p"][i])]], m.T_world_object_true[fa["q"][i] - OBJ])
        assert geo.se3_geodesic_distance(T, fa["Z"][i]) < 1e-3


def test_observation_before_its_odometry_waits_for_it():
    g = KeyframeGraph(cfg())
    t = 10**9
    g.handle(OdometrySample(t, pose()))
    g.handle(Keyframe(t, pose()))
    obs = ObservationBatch(
        t + 5 * 10**7,
        (
            __import__("dran_edge.events", fromlist=["ObjectObservation"]).ObjectObservation(
                t + 5 * 10**7, 4, pose(2.0), np.eye(6) * 1e-3
            ),
        ),
    )
    assert not g.handle(obs)  # odometry has not reached the frame yet
    assert g.handle(OdometrySample(t + 10**8, pose(0.1)))
    assert g.object_ids().tolist() == [4]


# --------------------------------------------------------------------------- bounds
def test_hard_caps_hold_over_a_long_mission():
    m = vio_mission(500, seed=6, reset_at=(250,))
    g = KeyframeGraph(cfg(max_nodes=80, max_edges=320))
    peak_nodes = peak_edges = 0
    for e in m.events:
        g.handle(e)
        peak_nodes = max(peak_nodes, g.num_nodes)
        peak_edges = max(peak_edges, g.num_factors)
    assert peak_nodes <= 80 and peak_edges <= 320
    assert g.counters["nodes_removed"] > 300
    assert g.prior is not None and len(g.prior["keys"]) <= 9 + 4  # objects + a few nodes


def test_marginalisation_is_exact_for_a_linearised_graph():
    """Removing nodes after the optimum leaves the optimum of the kept nodes unchanged."""
    m = vio_mission(250, seed=7)
    evs = [e for e in m.events if not isinstance(e, LoopClosure)]
    g = KeyframeGraph(cfg(robust_kernel="none"))
    feed(g, evs)
    for _ in range(3):
        g.solve()
    full = dict(zip(g.node_keys().tolist(), g.T_world_body()))
    objects = g.T_world_object().copy()
    # without the skeleton (its release from the prior is approximate: its own tests below)
    g.bounds = dataclasses.replace(g.bounds, max_nodes=60, max_edges=240, skeleton_fraction=0.0)
    g._enforce_bounds()
    assert g.num_nodes == 60
    for _ in range(3):
        g.solve()
    for k, T in zip(g.node_keys().tolist(), g.T_world_body()):
        assert geo.se3_geodesic_distance(full[k], T) < 1e-4
    np.testing.assert_allclose(g.T_world_object(), objects, atol=1e-4)


def test_protected_nodes_leave_last():
    m = vio_mission(100, seed=8)
    g = KeyframeGraph(cfg(max_nodes=40, max_edges=400))
    feed(g, m.events[: len(m.events) // 3])
    keep = g.node_keys()[:3]
    g.protect(keep)
    feed(g, m.events[len(m.events) // 3 :])
    assert set(keep.tolist()) <= set(g.node_keys().tolist())


# --------------------------------------------------------------------------- state, solver view
def test_state_round_trip_through_a_checkpoint():
    m = vio_mission(300, seed=9, reset_at=(150,))
    c = cfg(max_nodes=60, max_edges=240)
    a = KeyframeGraph(c)
    half = len(m.events) // 2
    feed(a, m.events[:half])
    b = KeyframeGraph.from_state(c, loads(dumps(a.to_state())))
    feed(a, m.events[half:])
    feed(b, m.events[half:])
    assert a.counters == b.counters
    np.testing.assert_allclose(a.T_world_body(), b.T_world_body())
    fa, fb = a.factor_arrays(), b.factor_arrays()
    for k in fa:
        np.testing.assert_allclose(fa[k], fb[k])


def test_problem_and_sparsified_prior():
    m = vio_mission(300, seed=10)
    g = KeyframeGraph(cfg(max_nodes=60, max_edges=240))
    feed(g, m.events)
    graph, poses, keys = g.problem()
    assert poses.shape == (len(keys), 4, 4)
    labels = [b.label for b in graph.factors]
    assert "marginal" in labels and "odometry" in labels
    dense = g.factor_arrays(include_prior=False)
    sparse = g.factor_arrays()
    # root edges, and a unary factor when the prior holds the gauge (node 0 marginalised; with
    # the skeleton node 0 stays and keeps its own gauge factor)
    gauge_in_prior = int(0 not in g.node_keys().tolist())
    assert len(sparse["p"]) == len(dense["p"]) + len(g.prior["keys"]) - 1 + gauge_in_prior
    res = g.solve()
    assert res is not None and np.isfinite(res.cost)


def test_gauge_anchor_rule():
    assert gauge_anchor(AgentConfig(robot_id=1, neighbours=(2, 6)))
    assert not gauge_anchor(AgentConfig(robot_id=3, neighbours=(2, 4)))
    assert gauge_anchor(AgentConfig(robot_id=7))


def test_reset_event_alone_changes_nothing_structural():
    g = KeyframeGraph(cfg())
    assert not g.handle(VioReset(5, "x"))
    with pytest.raises(ValueError):
        KeyframeGraph(AgentConfig(dim=2))


# --------------------------------------------------------------------------- consistency
def _star_graph(loops: int, seed: int) -> tuple[KeyframeGraph, dict, np.ndarray]:
    """Node n = 1 with odometry to p = 0 and to m = 2 (the bridge) and ``loops`` loop factors
    to nodes 3, 4, ...; zero residuals (measurements from the true poses), so the problem is
    linear-Gaussian in the tangent at the truth."""
    rng = np.random.default_rng(seed)
    g = KeyframeGraph(cfg(residual="geodesic", robust_kernel="none"), anchor_first=False)
    k = 3 + loops
    T = geo.se3_exp(rng.normal(scale=[0.5] * 3 + [0.3] * 3, size=(k, 6)))
    for key in range(k):
        g.node_stamp[key] = key
        g.node_segment[key] = 0
        g.node_est[key] = T[key]
        g.adj[key] = set()

    def cov(scale):
        A = rng.normal(size=(6, 6)) * 0.3 + np.eye(6)
        return scale**2 * (A @ A.T)

    pairs = [(0, 1, 0.01, KIND_ODOMETRY), (1, 2, 0.01, KIND_ODOMETRY)]
    pairs += [(1, 3 + i, 0.03 * (1 + i), KIND_LOOP) for i in range(loops)]
    for p, q, sig, kind in pairs:
        g._add_factor(p, q, geo.se3_between(T[p], T[q]), cov(sig), kind)
    return g, dict(zip(range(k), T)), T


def _information(g: KeyframeGraph, keys: list[int], T: np.ndarray) -> np.ndarray:
    from dran_edge.robot.keyframe_graph import _dense_normal_equations

    keys_arr = np.array(keys, dtype=np.int64)
    fa = g.factor_arrays(include_prior=False)
    blocks = g._blocks(fa, keys_arr, "geodesic")
    if g.prior is not None:
        blocks.append(g._prior_block(keys_arr))
    H, _ = _dense_normal_equations(blocks, len(keys), T[keys_arr])
    return H


@pytest.mark.parametrize("loops", [1, 3])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_node_removal_counts_no_information_twice(loops, seed):
    """Removing a node with loops: the kept graph's information on the other nodes is at most
    the exact marginal's (Schur complement) — conservative, no factor used twice."""
    g, _, T = _star_graph(loops, seed)
    every = list(range(3 + loops))
    H = _information(g, every, T)
    kept = [k for k in every if k != 1]
    sn, sk = np.arange(6, 12), np.array([6 * k + i for k in kept for i in range(6)])
    exact = H[np.ix_(sk, sk)] - H[np.ix_(sk, sn)] @ np.linalg.solve(
        H[np.ix_(sn, sn)], H[np.ix_(sn, sk)]
    )
    g.remove_node(1)
    approx = _information(g, kept, T)
    scale = float(np.max(np.abs(exact)))
    gap = np.linalg.eigvalsh(0.5 * ((exact - approx) + (exact - approx).T))
    assert gap.min() >= -1e-9 * scale, gap.min() / scale

    # and it keeps most of it: the p–m chain through the removed node survives
    def rel(Hm):  # information on m relative to p (p fixed)
        return Hm[6:12, 6:12]

    assert np.trace(rel(approx)) > 0.3 * np.trace(rel(exact))


def test_chain_node_removal_is_exact():
    g, _, T = _star_graph(0, seed=4)
    H = _information(g, [0, 1, 2], T)
    exact = H[np.ix_([*range(6), *range(12, 18)], [*range(6), *range(12, 18)])]
    Hnk = H[6:12][:, [*range(6), *range(12, 18)]]
    exact = exact - Hnk.T @ np.linalg.solve(H[6:12, 6:12], Hnk)
    g.remove_node(1)
    approx = _information(g, [0, 2], T)
    np.testing.assert_allclose(approx, exact, rtol=1e-6, atol=1e-6 * float(np.abs(exact).max()))


def test_blockdiag_bound_makes_dropped_correlations_conservative():
    from dran_edge.robot.keyframe_graph import _blockdiag_bound

    rng = np.random.default_rng(5)
    for k in (2, 3, 5):
        A = rng.normal(size=(6 * k, 6 * k))
        S = A @ A.T + 0.1 * np.eye(6 * k)
        D = np.zeros_like(S)
        for i in range(k):
            D[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] = S[6 * i : 6 * i + 6, 6 * i : 6 * i + 6]
        c = _blockdiag_bound(S)
        assert 1.0 <= c <= k
        assert np.linalg.eigvalsh(c * D - S).min() >= -1e-9 * np.abs(S).max()
        assert np.linalg.eigvalsh(0.95 * c * D - S).min() < 0  # the smallest such c


# --------------------------------------------------------------------------- skeleton
def _schur(H: np.ndarray, keep: list[int], n_vars: int) -> np.ndarray:
    """Marginal information on variables ``keep`` (indices) of an information matrix."""
    k = np.array([6 * v + i for v in keep for i in range(6)])
    o = np.setdiff1d(np.arange(6 * n_vars), k)
    return H[np.ix_(k, k)] - H[np.ix_(k, o)] @ np.linalg.solve(H[np.ix_(o, o)], H[np.ix_(o, k)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_skeleton_node_leaves_the_prior_with_its_exact_pair_marginal(seed):
    """Chain 0 – 1 – 2 – 3 with node 1 seeing an object; 0 and 2 are skeleton nodes. Removing 1
    puts 0, 2 and the object into the dense prior; 0 is then taken out of it as one relative
    factor (0, 2) (the prior's conditional of 0 given 2), the prior keeping its exact marginal
    on the rest. So the marginals on (0, 2) and on (2, 3, object) stay exact — nothing counted
    twice there — and the prior holds one skeleton node. (Only the prior is sparsified: with
    another path from the object to 2, the pair (0, 2) would lose that path's share.)"""
    rng = np.random.default_rng(seed)
    c = AgentConfig(
        graph=GraphBounds(skeleton_fraction=0.4), residual="geodesic", robust_kernel="none"
    )
    g = KeyframeGraph(c, anchor_first=False)
    T = geo.se3_exp(rng.normal(scale=[0.5] * 3 + [0.3] * 3, size=(5, 6)))
    for key in range(4):
        g.node_stamp[key], g.node_segment[key], g.node_est[key] = key, 0, T[key]
        g.adj[key] = set()
    g.obj_est[0] = T[4]
    g.adj[OBJ] = set()

    def cov(scale):
        A = rng.normal(size=(6, 6)) * 0.3 + np.eye(6)
        return scale**2 * (A @ A.T)

    for p, q, sig, kind in [
        (0, 1, 0.01, KIND_ODOMETRY),
        (1, 2, 0.02, KIND_ODOMETRY),
        (2, 3, 0.01, KIND_ODOMETRY),
        (1, OBJ, 0.03, KIND_OBSERVATION),
    ]:
        Tq = T[4] if q == OBJ else T[q]
        g._add_factor(p, q, geo.se3_between(T[p], Tq), cov(sig), kind)
    g.skeleton.add(0)
    g.skeleton.add(2)

    class ByKey(dict):  # poses indexed by an array of keys, as _information indexes them
        def __getitem__(self, keys):
            return np.stack([dict.__getitem__(self, int(k)) for k in keys])

    poses = ByKey({0: T[0], 1: T[1], 2: T[2], 3: T[3], OBJ: T[4]})
    H = _information(g, [0, 1, 2, 3, OBJ], poses)
    exact = _schur(H, [0, 2, 3, 4], 5)  # node 1 marginalised: variables 0, 2, 3, object
    g.remove_node(1)
    assert g.counters["skeleton_released_from_prior"] == 1
    assert [k for k in g.prior["keys"].tolist() if k in g.skeleton] == [2]
    kept = [0, 2, 3, OBJ]
    after = _information(g, kept, poses)
    for pair in ([0, 1], [1, 2, 3]):  # (0, 2) and (2, 3, object) in the kept order
        a, b = _schur(exact, pair, 4), _schur(after, pair, 4)
        np.testing.assert_allclose(b, a, atol=1e-6 * float(np.abs(a).max()))


def test_skeleton_stays_bounded_and_spans_the_mission():
    m = vio_mission(900, seed=11, reset_at=(450,))
    c = AgentConfig(graph=GraphBounds(max_nodes=60, max_edges=240, skeleton_fraction=0.4))
    g = KeyframeGraph(c)
    cap = int(c.graph.skeleton_fraction * 60)
    peak_skeleton = peak_prior = 0
    for e in m.events:
        g.handle(e)
        peak_skeleton = max(peak_skeleton, len(g.skeleton))
        peak_prior = max(peak_prior, 0 if g.prior is None else len(g.prior["keys"]))
        if g.prior is not None:  # the dense prior holds one skeleton node at most
            assert sum(k in g.skeleton for k in g.prior["keys"].tolist()) <= 1
        assert g.num_nodes <= 60 and g.num_factors <= 240
    assert peak_skeleton <= cap
    assert g.counters["skeleton_evicted"] > 0 and g.skeleton.stride >= 16
    keys = sorted(g.skeleton.nodes)
    assert len(keys) >= cap // 2 - 1  # thinned by halves, never emptied
    # evenly spread over the whole mission: from its start to the recent window
    assert keys[0] < 2 * g.skeleton.stride and keys[-1] > g.next_node - 60 - 2 * g.skeleton.stride
    assert max(np.diff(keys)) <= 2 * g.skeleton.stride
    assert peak_prior <= 9 + 9  # objects and a few nodes: it does not grow with the skeleton
    assert g.counters.get("skeleton_released_from_prior", 0) > 0


def _loop_attachment(m, skeleton_fraction: float):
    """Run mission ``m`` with small caps, then a loop from the newest keyframe to a long removed
    one: (the old end's node, whether it is a skeleton node, the loop's translation σ); without
    the archive, whose attachments are the subject of their own tests."""
    g = KeyframeGraph(
        AgentConfig(
            graph=GraphBounds(
                max_nodes=60, max_edges=240, skeleton_fraction=skeleton_fraction, archive_size=0
            )
        )
    )
    feed(g, m.events)
    kept = set(g.node_stamps_ns().tolist())
    # a keyframe that left the window long ago and is not kept
    old = next(i for i in range(150, 300) if int(m.keyframe_stamps_ns[i]) not in kept)
    cur = len(m.keyframe_stamps_ns) - 1
    rel = geo.se3_between(m.T_world_body_true[old], m.T_world_body_true[cur])
    before = g.factor_arrays(include_prior=False)
    stamp_old, stamp_cur = int(m.keyframe_stamps_ns[old]), int(m.keyframe_stamps_ns[cur])
    assert g.handle(LoopClosure(stamp_old, stamp_cur, rel, 60))
    after = g.factor_arrays(include_prior=False)
    new = [
        i
        for i in range(len(after["p"]))
        if after["kind"][i] == KIND_LOOP
        and not any(
            before["p"][j] == after["p"][i]
            and before["q"][j] == after["q"][i]
            and before["kind"][j] == KIND_LOOP
            for j in range(len(before["p"]))
        )
    ]
    assert len(new) == 1
    node = int(after["p"][new[0]])
    sigma_m = float(np.sqrt(np.trace(after["S"][new[0]][:3, :3]) / 3))
    return node, node in g.skeleton, sigma_m


def test_loop_into_an_old_place_attaches_to_a_skeleton_node():
    m = vio_mission(700, seed=12)  # one mission, fed to a fresh graph with and without skeleton
    node, on_skeleton, sigma_m = _loop_attachment(m, 0.4)
    node0, on_skeleton0, sigma0_m = _loop_attachment(m, 0.0)
    assert on_skeleton and not on_skeleton0
    assert sigma_m < 0.5 and sigma_m < 0.2 * sigma0_m  # short range instead of the window's edge


def test_sparsified_prior_of_a_gauge_free_prior_pins_nothing():
    """A prior of relative information only (no gauge in it) is singular: its sparsified form
    is relative factors only — no unary factor pinning the root at the linearisation point."""
    m = vio_mission(300, seed=10)
    g = KeyframeGraph(cfg(max_nodes=60, max_edges=240), anchor_first=False)
    feed(g, m.events)
    assert g.prior is not None and np.any(g.prior["keys"] < OBJ)
    dense = g.factor_arrays(include_prior=False)
    sparse = g.factor_arrays()
    assert not np.any(dense["p"] < 0) and not np.any(sparse["p"] < 0)
    assert len(sparse["p"]) == len(dense["p"]) + len(g.prior["keys"]) - 1  # root edges only
    assert np.all(np.isfinite(sparse["S"]))
