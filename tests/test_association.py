"""Object data association (dran_edge.dran.association) through its public API, on small
synthetic problems: one robot's views of a few objects from random poses, and neighbour copies
handed in as ``ObjectEntry`` values."""

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dran_edge.config import AgentConfig
from dran_edge.dran.association import ObjectAssociation, Provenance
from dran_edge.dran.counters import AgentCounters
from dran_edge.dran.problem import LocalProblem
from dran_edge.messages import ObjectEntry

SEEDS = range(4)
ME = 0  # the robot under test


def _T(t, R=None):
    T = np.eye(4)
    T[:3, :3] = np.eye(3) if R is None else R
    T[:3, 3] = t
    return T


def _problem(rng, positions, views, n_poses=10, noise_m=0.02):
    """Robot ME's problem: ``n_poses`` random poses within 6 m of the origin and one observation
    (T_body_object, ``noise_m`` of translation noise) per (pose, object id) in ``views``, of an
    object at ``positions[object id]``."""
    x = np.stack(
        [
            _T(rng.uniform(-6, 6, 3), Rotation.random(random_state=rng).as_matrix())
            for _ in range(n_poses)
        ]
    )
    own = np.array([p for p, _ in views], np.int64)
    obj = np.array([o for _, o in views], np.int64)
    T_wo = np.stack([_T(positions[o] + rng.normal(0, noise_m, 3)) for o in obj])
    obs_T = np.linalg.inv(x[own]) @ T_wo
    return dataclasses.replace(
        LocalProblem.empty(3, "geodesic"),
        pose_ids=np.arange(n_poses),
        x0=x,
        pose_stamps_ns=np.arange(n_poses),
        obs_own=own,
        obs_object=obj,
        obs_T=obs_T,
        obs_W=np.ones((len(views), 6)),
    )


def _association(problem, **config):
    cfg = AgentConfig(robot_id=ME, neighbours=(1, 2), object_min_views=2, **config)
    a = ObjectAssociation(ME, cfg, AgentCounters())
    a.reset(problem, problem.x0)
    return a


def _copy(oid, t, origin, hop=0, support=1):
    return ObjectEntry(oid, _T(t), origin, hop, support)


def _views(obj, poses):
    return [(p, obj) for p in poses]


@pytest.mark.parametrize("seed", SEEDS)
def test_a_lone_misread_is_held_back_and_no_copy_elsewhere_vouches_for_it(seed):
    """A phantom: one view labelled 7 where object 6 (seen from five poses) is. It waits
    (pending, no copy of 7), a neighbour's copy of the real object 7 far away does not
    corroborate it, and a copy of 7 where the view predicts it does."""
    rng = np.random.default_rng(seed)
    p6 = rng.uniform(-3, 3, 3)
    prob = _problem(rng, {6: p6, 7: p6}, _views(6, range(5)) + [(7, 7)])
    a = _association(prob)
    phantom = prob.obs_object == 7
    assert a.obs_pending[phantom].all() and not a.obs_ok[phantom].any()
    assert 7 not in a.y and a.obs_ok[~phantom].all() and 6 in a.y
    assert a.counters.obs_pending == 1
    a.absorb(1, _copy(7, p6 + (20.0, 0.0, 0.0), origin=1, support=3), round_=1)
    a.check(prob.x0)
    assert not a.obs_ok[phantom].any() and a.counters.obs_corroborated == 0
    a.absorb(1, _copy(7, p6, origin=1, support=3), round_=2)
    a.check(prob.x0)
    assert a.obs_ok[phantom].all() and a.counters.obs_corroborated == 1


@pytest.mark.parametrize("seed", SEEDS)
def test_two_objects_a_metre_apart_are_both_used(seed):
    """Two objects 1 m apart (more than object_exclusion_m), three views each: no view is held
    back, each copy starts at its own object, and the neighbours' copies at the true places
    reject nothing."""
    rng = np.random.default_rng(seed)
    p6 = rng.uniform(-3, 3, 3)
    pos = {6: p6, 8: p6 + Rotation.random(random_state=rng).apply([1.0, 0.0, 0.0])}
    prob = _problem(rng, pos, _views(6, [0, 1, 2]) + _views(8, [3, 4, 5]))
    a = _association(prob)
    assert a.obs_ok.all() and not a.obs_pending.any()
    assert a.counters.obs_shadowed == 0 and a.counters.obs_gated == 0
    for oid in (6, 8):
        assert np.linalg.norm(a.y[oid][:3, 3] - pos[oid]) < 0.1
        assert a.provenance[oid] == Provenance(hop=0, origin=ME, support=3)
    for j in (1, 2):
        for oid in (6, 8):
            a.absorb(j, _copy(oid, pos[oid], origin=j, support=3), round_=1)
    a.check(prob.x0)
    assert a.obs_ok.all() and a.counters.obs_rejected == 0
    assert not a.conflicts(((1, 6), (2, 8))).any()


@pytest.mark.parametrize("seed", SEEDS)
def test_an_unknown_object_is_adopted_from_the_nearest_copy_and_relayed(seed):
    """Alg. 1 lines 3–8 with hop counts: the copy with the fewest hops is adopted, one hop more,
    with its origin and support; a copy at the relay limit is not; an echo of this robot's own
    copy is no vote; a relay whose source loses its support becomes a bare estimate."""
    rng = np.random.default_rng(seed)
    prob = _problem(rng, {6: rng.uniform(-3, 3, 3)}, _views(6, [0, 1, 2]))
    a = _association(prob)
    t = rng.uniform(-3, 3, 3)
    limit = a.config.relay_max_hops
    a.absorb(1, _copy(9, t, origin=5, hop=1, support=4), round_=1)
    a.absorb(2, _copy(9, t + 0.1, origin=7, hop=0, support=2), round_=1)
    a.absorb(2, _copy(11, t, origin=7, hop=limit, support=2), round_=1)
    a.adopt_unknown()
    assert np.allclose(a.y[9][:3, 3], t + 0.1) and 11 not in a.y
    assert a.provenance[9] == Provenance(hop=1, origin=7, support=2)
    assert a.counters.objects_adopted == 1
    a.absorb(1, _copy(6, a.y[6][:3, 3], origin=ME, hop=1, support=3), round_=2)  # an echo
    assert sorted(a.votes()) == [9, 11]  # no vote on 6: its only copy is our own, echoed
    a.absorb(2, _copy(9, t + 0.1, origin=7, hop=0, support=0), round_=2)  # 7 dropped its views
    a.absorb(1, _copy(9, t, origin=5, hop=1, support=0), round_=2)
    a.update_provenance()
    assert a.provenance[9].support == 0 and 9 not in a.votes()
    assert a.provenance[6] == Provenance(hop=0, origin=ME, support=3)
    assert not a.absorb(2, _copy(9, t, origin=7), round_=1)  # older than the one held
    assert a.counters.stale_dropped == 1


@pytest.mark.parametrize("seed", SEEDS)
def test_a_wrong_association_is_dropped_and_comes_back_when_the_evidence_turns(seed):
    """Two views place object 6 20 m from where two other robots, with four views each, place
    it: the check rejects the two views, the copy restarts at the vote centre and becomes a
    relay of the first neighbour's copy. When the neighbours' copies move to where this robot's
    views put the object, the views are used again (the check runs every round)."""
    rng = np.random.default_rng(seed)
    p6 = rng.uniform(-3, 3, 3)
    wrong = p6 + Rotation.random(random_state=rng).apply([20.0, 0.0, 0.0])
    prob = _problem(rng, {6: wrong}, _views(6, [2, 7]))
    a = _association(prob)
    assert a.obs_ok.all() and np.linalg.norm(a.y[6][:3, 3] - wrong) < 0.1
    for j in (1, 2):
        a.absorb(j, _copy(6, p6, origin=j, support=4), round_=1)
    a.check(prob.x0)
    a.update_provenance()
    assert not a.obs_ok.any() and a.counters.obs_rejected == 2
    assert np.allclose(a.y[6][:3, 3], p6) and np.allclose(a.centres[6], p6)
    assert a.provenance[6] == Provenance(hop=1, origin=1, support=4)
    assert a.conflicts(((1, 6),)).tolist() == [False]
    for j in (1, 2):
        a.absorb(j, _copy(6, wrong, origin=j, support=4), round_=2)
    a.check(prob.x0)
    a.update_provenance()
    assert a.obs_ok.all() and a.counters.obs_rejected == 0
    assert a.provenance[6] == Provenance(hop=0, origin=ME, support=2)


def test_checkpoint_state_round_trips_and_reads_the_older_layout():
    rng = np.random.default_rng(0)
    prob = _problem(rng, {6: np.zeros(3)}, _views(6, [0, 1, 2]))
    a = _association(prob)
    a.absorb(1, _copy(9, np.ones(3), origin=5, hop=1, support=4), round_=3)
    a.adopt_unknown()
    state = a.to_state()
    b = _association(prob)
    b.load_state(state)
    assert b.to_state().keys() == state.keys()
    assert b.provenance == a.provenance and b.neighbour_copies.keys() == a.neighbour_copies.keys()
    old = {k: v for k, v in state.items() if k not in ("nbr_origin", "nbr_support", "support")}
    c = _association(prob)
    c.load_state(old)  # before provenance was sent: a copy came from its sender, support 1
    assert (c.neighbour_copies[(1, 9)].origin, c.neighbour_copies[(1, 9)].support) == (1, 1)
    assert c.provenance[9] == Provenance(hop=2, origin=5, support=1)
