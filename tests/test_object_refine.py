"""The exact distributed refinement in the object simulation (experiments/object_refine.py)."""

import numpy as np

from dran_edge.comms.bus import static_graph
from dran_edge.dran.exact_gn import RefineParams
from dran_edge.experiments.object_refine import object_graph
from dran_edge.experiments.objects import (
    SimParams,
    bench_config,
    centralized,
    make_scenario,
    run_objects,
)

PATH = [(0, 1), (1, 2), (2, 3)]  # robots 0 and 3 talk only through 1 and 2


def _scenario():
    return make_scenario(SimParams(num_robots=4, num_objects=8, box_m=(20.0, 20.0, 5.0), seed=3))


def test_objects_couple_robots_that_are_no_neighbours_on_the_path():
    graph, _, off = centralized(_scenario())
    coupled = object_graph(graph, off).partition.neighbour_pairs()
    assert set(coupled) - set(PATH)  # so the tree relays some of them


def test_refined_run_reaches_the_centralized_optimum_and_counts_its_traffic():
    sc = _scenario()
    out = run_objects(
        sc,
        bench_config(False),
        static_graph(PATH),
        max_rounds=20,
        refine=RefineParams(mode="always", rel_tol=1e-12, max_steps=50),
    )
    assert out["refine_used"] and out["refine_converged"]
    assert abs(out["F"] - out["F_star"]) <= 1e-6 * out["F_star"]
    assert out["F_init"] > 10 * out["F_star"]
    assert out["stopped_by"] == "refine" and out["rounds"] == 0
    assert out["round"] == out["refine_rounds"] > 0
    assert out["bytes"] == out["refine_bytes"] > 0
    F_curve = [F for _, _, F in out["refine_curve"]]
    assert F_curve == sorted(F_curve, reverse=True)
    assert np.isclose(F_curve[-1], out["F"], rtol=1e-6)


def test_over_30_percent_loss_the_arq_gives_the_lossless_refinement():
    from dran_edge.comms.bus import BusParams

    sc, params = _scenario(), RefineParams(mode="always", rel_tol=1e-9)
    runs = [
        run_objects(sc, bench_config(False), static_graph(PATH), links, max_rounds=5, refine=params)
        for links in (None, BusParams(loss_probability=0.3))
    ]
    clean, lossy = runs
    assert lossy["refine_used"] and lossy["stopped_by"] == "refine"
    assert lossy["refine_F_history"] == clean["refine_F_history"]
    assert lossy["F"] == clean["F"] and lossy["ATE"] == clean["ATE"]
    assert lossy["dropped"] > 0 and lossy["refine_arq"]["retransmissions"] > 0
    assert lossy["round"] > clean["round"] and lossy["bytes"] > clean["bytes"]
    assert "refine_arq" not in clean


def test_an_unfinished_refinement_hands_over_to_dran():
    sc = _scenario()
    out = run_objects(
        sc,
        bench_config(False),
        static_graph(PATH),
        max_rounds=3,
        refine=RefineParams(mode="always", max_steps=1),
    )
    assert out["refine_used"] and not out["refine_converged"]
    assert out["rounds"] == 3 and out["round"] == out["refine_rounds"] + 3
    assert out["bytes"] > out["refine_bytes"]
    assert out["F"] < out["F_init"]


def test_robust_runs_are_not_refined():
    out = run_objects(
        _scenario(),
        bench_config(True),
        static_graph(PATH),
        max_rounds=1,
        refine=RefineParams(mode="always"),
    )
    assert not out["refine_used"] and out["refine_bytes"] == 0
    assert "least squares" in out["refine_reason"]
