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
    titles = [t for t, _, _ in panels]
    assert "not the summary's CE" in titles[1] and "grows as the graphs grow" in titles[0]
    per = dict((t.split(":")[0], y) for t, _, y in panels)
    assert np.array_equal(per["bytes sent per round"], [[200, 100, 100, 0], [300, 150, 150, 0]])
    ref = {"F_init": 20.0, "F_star": 4.0}
    sr = plots.round_panels(rounds, ref, 3, 2)[0]
    assert sr[1] == "SR_cost (%)" and np.allclose(sr[2], (20 - rounds["cost"]) / 16 * 100)


def test_eval_writes_the_labelled_rounds_plot(small_sim_run, tmp_path):
    run, _ = small_sim_run
    copy = tmp_path / "run"
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns("eval"))
    report = evaluate.evaluate_run(copy, evaluate.EvalOptions())
    written = evaluate.write_report(report, copy / "eval", plots=True)
    png = copy / "eval" / "rounds.png"
    assert png in written and png.stat().st_size > 10_000
