"""rounds.png says what it plots: titles and units per panel, bytes per robot and per link."""

from __future__ import annotations

import shutil

import numpy as np

from dran_edge.evaluation import plots
from dran_edge.evaluation import score as evaluate


def test_round_panels_name_their_quantities():
    rounds = {
        "round": np.arange(4),
        "cost": np.array([5.0, 7, 9, 10]),
        "consensus_error": np.array([0.1, 0.05, 0.02, 0.024]),
        "bytes_round": np.array([600.0, 300, 300, 0]),
        "bytes_total": np.array([600.0, 900, 1200, 1200]),
    }
    panels = plots.round_panels(rounds, None, n_robots=3, n_links=2)
    titles = [t for t, _, _, _ in panels]
    assert "not the summary's CE" in titles[1] and "grows as the graphs grow" in titles[0]
    per = dict((t.split(":")[0], y) for t, _, _, y in panels)
    assert np.array_equal(per["bytes sent per round"], [[200, 100, 100, 0], [300, 150, 150, 0]])
    # with the replay's sampled costs: SR_cost and F/F* per sampled round instead of the raw sum
    sampled = {
        "round": np.array([1.0, 3]),
        "sr_cost_pct": np.array([50.0, 90]),
        "f_over_fstar": np.array([3.0, 1.2]),
    }
    sr, ratio = plots.round_panels(rounds, sampled, 3, 2)[:2]
    assert sr[1] == "SR_cost (%)" and "paper Sec. 6.2" in sr[0] and "as of round k" in sr[0]
    assert np.array_equal(sr[2], [1, 3]) and np.array_equal(sr[3], [50, 90])
    assert ratio[1].startswith("F / F*") and np.array_equal(ratio[3], [3.0, 1.2])


def test_eval_writes_the_labelled_rounds_plot(small_sim_run, tmp_path):
    run, _ = small_sim_run
    copy = tmp_path / "run"
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("eval"))
    report = evaluate.evaluate_run(copy, evaluate.EvalOptions())
    written = evaluate.write_report(report, copy / "eval", plots=True)
    png = copy / "eval" / "rounds.png"
    assert png in written and png.stat().st_size > 10_000
