"""``dran-edge bench suite --quick`` end to end (the numbers live in docs/benchmarks.md)."""

import json

import numpy as np

from dran_edge.cli.app import main
from dran_edge.experiments import suite


def test_suite_quick_writes_rows_table_and_plots(tmp_path, capsys):
    rc = main(["bench", "suite", "--quick", "--rounds", "30", "--no-dgs", "--out", str(tmp_path)])
    assert rc == 0, capsys.readouterr().err
    data = json.loads((tmp_path / "suite.json").read_text())
    rows = data["rows"]
    assert [r["case"] for r in rows] == [c.name for c in suite.default_cases(quick=True)]
    for r in rows:
        # the substructured init is the centralized chordal one (float32 on the wire)
        assert abs(r["F_init_over_F_chordal"] - 1) < 1e-3
        assert r["F_star"] <= r["F_chordal"] and r["dran_F_end_over_F_star"] >= 1 - 1e-9
        # one point per round: the refinement's (default --refine auto), then DRAN's to 30
        rounds = [p[0] for p in r["curve"]]
        assert rounds[0] == 0 and rounds[-1] == 30 and rounds == sorted(set(rounds))
        assert r["init_bytes"] > 0 and r["dran_bytes"] > r["init_bytes"]
        assert r["ATE_star_m"] > 0 and "F_over_F_star_at_50" not in r  # only rounds run
    assert set(data["worst"]) == {"car2d", "city3d"}
    table = (tmp_path / "suite.md").read_text().splitlines()
    assert len(table) == 2 + len(rows)
    assert (tmp_path / "suite_car2d.png").stat().st_size > 0


def test_suite_graphs_are_deterministic_per_seed():
    a, _ = suite.make_graph(suite.Case("car3d", 400, 7))
    b, _ = suite.make_graph(suite.Case("car3d", 400, 7))
    c, _ = suite.make_graph(suite.Case("car3d", 400, 8))
    assert np.array_equal(a.edges, b.edges) and np.array_equal(a.measurements, b.measurements)
    assert not (a.edges.shape == c.edges.shape and np.array_equal(a.measurements, c.measurements))
    # 1-3 % loop edges on the chains, interleaved splits give every robot several stretches
    assert 0.005 < (a.num_edges - a.num_vertices + 1) / a.num_vertices <= 0.031
    part = suite.make_partition(suite.Case("car3d", 400, 7, robots=5, split="interleaved"), a)
    assert all(np.count_nonzero(np.diff(p.vertices) > 1) >= 3 for p in part.parts)


def test_until_decided_ends_the_run_once_the_target_and_the_stop_are_known():
    from dran_edge.dran.exact_gn import RefineParams

    case = suite.Case("car2d", 240, 1, robots=3)
    full = suite.run_case(case, rounds=40, dgs=False, refine=RefineParams(mode="auto"))
    early = suite.run_case(
        case, rounds=40, dgs=False, refine=RefineParams(mode="auto"), until_decided=True
    )
    # the refinement converged (the run's stop) and F <= 1.001 F*: one DRAN round, then the end
    assert early["stopped_by"] == full["stopped_by"] == "refine"
    assert early["stop_round"] == full["stop_round"] == early["refine_rounds"]
    assert early["ended_early"] and not full["ended_early"]
    assert early["ended_round"] == early["refine_rounds"] + 1 < full["ended_round"] == 40
    assert early["curve"] == full["curve"][: len(early["curve"])]  # the same run, cut
    assert early["round_at_01pct"] == full["round_at_01pct"] is not None
    assert "F_over_F_star_at_50" not in early and early["rule_round"] is None
    assert early["central_status"] == "converged" and early["central_iterations"] > 0


def test_without_a_converged_refinement_the_rule_must_fire_before_the_run_ends():
    # no refinement: DRAN from the init reaches neither 1.001 F* nor its stop in 15 rounds,
    # so the undecided run goes on to the cap
    case = suite.Case("car2d", 240, 1, robots=3)
    r = suite.run_case(case, rounds=15, dgs=False, until_decided=True)
    assert not r["ended_early"] and r["ended_round"] == 15 and r["stop_round"] is None


def test_suite_filters_keep_the_suites_own_pose_counts():
    cases = suite.select_cases(families=["aniso2d"], robots=[5], splits=["contiguous"])
    assert [c.name for c in cases] == [
        c.name for c in suite.default_cases() if c.family == "aniso2d" and c.robots == 5
    ]
    assert [c.num_poses for c in cases] == [3000, 2000, 4000]  # seeds 1 2 3, as in the suite
    assert {c.robots for c in suite.select_cases(families=["car3d"])} == {3, 5, 10, 20}
    sized = suite.select_cases(seeds=[4], families=["city2d"], robots=[3, 10], poses=500)
    assert [c.name for c in sized] == ["city2d-n500-s4-r3-contig", "city2d-n500-s4-r10-contig"]


def test_a_callback_returning_true_ends_the_dran_run_there():
    from dran_edge.experiments.fleet import run_g2o_dran, table1_setup

    case = suite.Case("car2d", 240, 1, robots=3)
    g, _ = suite.make_graph(case)
    cfg, kw = table1_setup(g.dim)
    seen = []
    starts = []

    def stop_at_4(k, fleet):
        seen.append(k)
        return k >= 4

    res = run_g2o_dran(
        g, 3, cfg, max_rounds=50, stop=False, on_start=starts.append, callback=stop_at_4, **kw
    )
    assert res["rounds"] == 4 and seen == [1, 2, 3, 4] and starts == [{}]
