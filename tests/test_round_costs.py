"""SR_cost per round: the replay samples the merged graph's F_init, F_k and F* as it stands at
every ``cost_every``-th round and at the last, where they equal the final evaluation's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dran_edge.errors import InputError
from dran_edge.evaluation import plots
from dran_edge.evaluation.score import EvalOptions, evaluate_run
from dran_edge.formats.run_outputs import read_rounds_csv
from dran_edge.replay import run as rp
from dran_edge.replay.round_costs import COLUMNS, RoundCosts


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """(run dir, replay report, evaluation) of the stored tiny run, replayed with the golden
    options (default cost_every)."""
    import golden_helpers

    d = tmp_path_factory.mktemp("round_costs")
    report = golden_helpers.replay_stored(d)
    return d / "stored", report, evaluate_run(d / "stored", EvalOptions(plots=False))


def test_every_sampled_round_has_finite_costs_above_the_optimum(stored):
    _, report, _ = stored
    rc = report["round_costs"]
    every = rp.ReplayOptions().cost_every
    assert rc["every"] == every > 0
    total = report["rounds"]
    expected = [k for k in range(total) if (k + 1) % every == 0 or k == total - 1]
    assert rc["round"] == expected and len(expected) >= 3
    for c in COLUMNS:
        assert len(rc[c]) == len(expected), c
    for c in ("F_init", "F_k", "F_star", "sr_cost_pct", "f_over_fstar"):
        assert all(v is not None and math.isfinite(v) for v in rc[c]), (c, rc[c])
    F_k, F_star = np.array(rc["F_k"]), np.array(rc["F_star"])
    assert np.all(F_star > 0) and np.all(F_k >= F_star * (1 - 1e-9))
    assert np.all(np.array(rc["F_init"]) > F_star)
    # the merged graph grows over the mission
    assert rc["vertices"][-1] > rc["vertices"][0] and rc["edges"][-1] > rc["edges"][0]
    # the warm start makes later solves short
    assert max(rc["centralized_iterations"][1:]) <= 10


def test_last_sample_equals_the_final_summary(stored):
    """At the last round the graph is merged.g2o's: the same F_init, F_k, F* and SR_cost as
    the evaluation's cost section (up to the TUM files' and the solver's precision)."""
    _, report, evaluation = stored
    cost = evaluation.report["cost"]
    rc = report["round_costs"]
    assert report["cost_init"] == rc["F_init"][-1]
    assert report["cost_final"] == rc["F_k"][-1]
    assert report["cost_centralized"] == rc["F_star"][-1]
    assert report["cost_init"] == pytest.approx(cost["F_init"], rel=1e-8)
    assert report["cost_final"] == pytest.approx(cost["F_k"], rel=1e-9)
    assert report["cost_centralized"] == pytest.approx(cost["F_star"], rel=1e-8)
    assert rc["sr_cost_pct"][-1] == pytest.approx(report["sr_cost"], abs=1e-6)
    assert rc["f_over_fstar"][-1] == pytest.approx(report["f_over_fstar"], rel=1e-8)
    # the new keys stay out of the golden summary
    assert not {"round_costs", "cost_init", "cost_final"} & set(rp.golden_summary(report))


def test_eval_plots_sr_cost_per_sampled_round(stored):
    run, report, evaluation = stored
    rc = report["round_costs"]
    rounds_rep = evaluation.report["rounds"]
    assert rounds_rep["cost_samples"] == len(rc["round"])
    assert rounds_rep["sr_cost_pct_last"] == pytest.approx(report["sr_cost"], abs=1e-6)
    data = evaluation.plot_data
    assert data.robot_count == report["robots"]
    panels = plots.round_panels(read_rounds_csv(run / "out" / "rounds.csv"), data.round_costs, 3, 2)
    (t_sr, y_sr, x_sr, sr), (t_f, y_f, _, f) = panels[:2]
    assert "SR_cost_k" in t_sr and "as of round k" in t_sr and y_sr == "SR_cost (%)"
    assert "F*_k" in t_f and "centralized optimum" in t_f and "F / F*" in y_f
    assert np.array_equal(x_sr, rc["round"])
    assert np.allclose(sr, rc["sr_cost_pct"], rtol=1e-12)
    assert np.allclose(f, rc["f_over_fstar"], rtol=1e-12)


def test_sampling_rule_and_option():
    assert [k for k in range(45) if RoundCosts(20, 45).due(k)] == [19, 39, 44]
    assert [k for k in range(40) if RoundCosts(20, 40).due(k)] == [19, 39]
    assert not any(RoundCosts(0, 45).due(k) for k in range(45))
    assert RoundCosts(0, 45).report() == {}
    with pytest.raises(InputError, match="cost_every"):
        rp.ReplayOptions(cost_every=-1)
