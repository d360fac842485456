"""DRAN agents in one process over encoded datagrams (dran_edge.multiagent, objects_sim)."""

import itertools

import numpy as np
import pytest

from dran_edge.config import AgentConfig
from dran_edge.multiagent import LinkModel, adjacency_from_pairs, is_connected, random_connected
from dran_edge.objects_sim import SimParams, make_scenario, run_objects

CFG = AgentConfig(robust_kernel="none", eps_phi=1e-6)
SMALL = SimParams(num_robots=3, num_objects=6, box_m=(12.0, 12.0, 3.0), goals_per_robot=2,
                  step_m=1.5, seed=3)


@pytest.fixture(scope="module")
def toy():
    return make_scenario(SMALL)


def test_three_robot_toy_reaches_consensus_and_the_centralized_answer(toy):
    A = adjacency_from_pairs(3, [(0, 1), (1, 2), (0, 2)])
    out = run_objects(toy, CFG, A, max_rounds=80, history_every=20)
    ces = [h["CE"] for h in out["history"]]
    assert ces[-1] < 1e-4 and all(b < a for a, b in itertools.pairwise(ces))  # CE goes to zero
    assert out["SR_cost"] > 99.0  # percent
    # the trajectories match the centralized LM's up to a small fraction of the initial error
    assert abs(out["ATE"] - out["ATE_star"]) < 0.1 * out["ATE_init"]


def test_relay_reaches_a_robot_two_hops_away():
    sc = make_scenario(SimParams(num_robots=3, num_objects=8, box_m=(30.0, 30.0, 3.0),
                                 goals_per_robot=2, seed=3))
    import dataclasses

    from dran_edge.agent import Agent
    from dran_edge.multiagent import Fleet, metropolis_weights

    A = adjacency_from_pairs(3, [(0, 1), (1, 2)])
    W = metropolis_weights(A)
    agents = [Agent(dataclasses.replace(CFG, robot_id=r, neighbours=tuple(sorted(W[r]))),
                    sc.problems[r], W[r]) for r in range(3)]
    only0 = set(agents[0].y) - set(agents[1].y) - set(agents[2].y)
    assert only0, "scenario must have an object only robot 0 sees"
    fleet = Fleet(agents, A)
    fleet.step()
    assert not only0 & set(agents[2].y)
    fleet.step()
    fleet.step()
    assert only0 <= set(agents[2].y)
    assert all(agents[2].hops[o] == 2 for o in only0)


def test_same_seed_same_result_and_loss_is_tolerated(toy):
    A = random_connected(3, 0.5, np.random.default_rng(0))
    assert is_connected(A)
    links = LinkModel(loss=0.3, latency_rounds=1)
    a = run_objects(toy, CFG, A, links, max_rounds=25, seed=7)
    b = run_objects(toy, CFG, A, links, max_rounds=25, seed=7)
    assert a["F"] == b["F"] and a["bytes"] == b["bytes"]
    assert a["dropped"] > 0
    assert a["SR_cost"] > 90.0
