"""DRAN agents in one process over encoded datagrams on the bus (multiagent, objects_sim)."""

import itertools

import numpy as np
import pytest
from dran_edge.comms.bus import Bus, BusParams, Partition, random_connected_graph

from dran_edge.config import AgentConfig
from dran_edge.consensus import metropolis_hastings_matrix
from dran_edge.multiagent import Fleet, neighbour_weights
from dran_edge.objects_sim import SimParams, make_scenario, run_objects

CFG = AgentConfig(robust_kernel="none", eps_phi=1e-6)
SMALL = SimParams(num_robots=3, num_objects=6, box_m=(12.0, 12.0, 3.0), goals_per_robot=2,
                  step_m=1.5, seed=3)


@pytest.fixture(scope="module")
def toy():
    return make_scenario(SMALL)


def test_three_robot_toy_reaches_consensus_and_the_centralized_answer(toy):
    out = run_objects(toy, CFG, [(0, 1), (1, 2), (0, 2)], max_rounds=80, history_every=20)
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

    bus = Bus(range(3), graph=[(0, 1), (1, 2)])
    W = neighbour_weights(bus)
    agents = [Agent(dataclasses.replace(CFG, robot_id=r, neighbours=tuple(sorted(W[r]))),
                    sc.problems[r], W[r]) for r in range(3)]
    only0 = set(agents[0].y) - set(agents[1].y) - set(agents[2].y)
    assert only0, "scenario must have an object only robot 0 sees"
    fleet = Fleet(agents, bus)
    fleet.step()
    assert not only0 & set(agents[2].y)
    fleet.step()
    fleet.step()
    assert only0 <= set(agents[2].y)
    assert all(agents[2].hops[o] == 2 for o in only0)


def test_same_seed_same_result_and_loss_is_tolerated(toy):
    graph = random_connected_graph(range(3), 0.5, seed=0)
    links = BusParams(loss_probability=0.3, latency_rounds=2)
    a = run_objects(toy, CFG, graph, links, max_rounds=25, seed=7)
    b = run_objects(toy, CFG, graph, links, max_rounds=25, seed=7)
    assert a["F"] == b["F"] and a["bytes"] == b["bytes"]
    assert a["dropped"] > 0
    assert a["SR_cost"] > 90.0
    c = run_objects(toy, CFG, graph, links, max_rounds=25, seed=8)
    assert (c["bytes"], c["dropped"]) != (a["bytes"], a["dropped"])  # the seed is the bus's


def test_weights_are_the_consensus_mh_weights_of_the_bus_graph():
    bus = Bus(range(4), graph=[(0, 1), (1, 2), (1, 3), (2, 3)])
    W = neighbour_weights(bus)
    A = np.zeros((4, 4), bool)
    for a, b in [(0, 1), (1, 2), (1, 3), (2, 3)]:
        A[a, b] = A[b, a] = True
    M = metropolis_hastings_matrix(A)
    assert [sorted(w) for w in W] == [[1], [0, 2, 3], [1, 3], [1, 2]]
    assert all(w[j] == M[i, j] for i, w in enumerate(W) for j in w)
    assert W[0][1] == 1.0 / 4.0  # 1 / (1 + max(deg 1, deg 3))


def test_fleet_traffic_is_the_bus_count_of_every_datagram_byte(toy):
    """The fleet's totals are the bus's; a partition cuts robot 2 off (no bytes to or from it
    while cut, since only links that are up carry datagrams), and the agents still run."""
    import dataclasses

    from dran_edge.agent import Agent

    bus = Bus(range(3), graph=[(0, 1), (1, 2), (0, 2)],
              partitions=[Partition(frozenset({2}), start_round=1, end_round=4)])
    W = neighbour_weights(bus)
    agents = [Agent(dataclasses.replace(CFG, robot_id=r, neighbours=tuple(sorted(W[r]))),
                    toy.problems[r], W[r]) for r in range(3)]
    fleet = Fleet(agents, bus)
    for _ in range(3):
        fleet.step()
    st = bus.stats()
    assert st["bytes_by_sender"].get("2", 0) == 0 and st["bytes_by_receiver"].get("2", 0) == 0
    assert st["bytes_total"] > 0 and fleet.round == bus.round == 3
    for _ in range(3):
        fleet.step()
    st = bus.stats()
    assert st["bytes_by_sender"]["2"] > 0 and st["bytes_by_receiver"]["2"] > 0
    t = fleet.traffic
    assert (t.bytes_total, t.datagrams, t.dropped) == (st["bytes_total"], st["datagrams_sent"], 0)
    assert sum(t.bytes_by_kind.values()) == t.bytes_total
    sent = sum(c.totals()["bytes_sent"] for c in (bus.endpoint(i).counters for i in range(3)))
    assert sent == t.bytes_total
