"""``dran-edge bench objects`` end to end on a tiny scenario (the numbers live in docs/benchmarks.md)."""

import json

import pytest

from dran_edge.cli.app import main

#: ``bench objects`` on a toy: 3 robots, 4 objects.
TOY = ["bench", "objects", "--rho", "1.0", "--robots", "3", "--objects", "4"]
#: the toy with DRAN's rounds alone; the round count follows.
SMALL = [*TOY, "--refine", "off", "--rounds"]


@pytest.mark.parametrize(
    "flags, robust, min_views, beta, eta",
    [
        ([], False, 1, 1.0, 0.1),
        (["--robust"], True, 2, 1.0, 0.1),
        (["--outliers", "0.2"], True, 2, 1.0, 0.1),
        (["--beta", "0.1", "--eta", "0.3"], False, 1, 0.1, 0.3),
    ],
)
def test_bench_objects_reports_the_settings_it_ran_with(
    capsys, flags, robust, min_views, beta, eta
):
    rc = main([*SMALL, "3", "--json", *flags])
    assert rc == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert len(rows) == 1
    assert rows[0]["robust"] is robust and rows[0]["min_views"] == min_views
    assert rows[0]["beta"] == beta and rows[0]["eta"] == eta  # the paper's β, η unless given
    assert rows[0]["rounds"] <= 3
    assert set(rows[0]) >= {"SR_cost", "SR_ATE", "CE", "Bias", "ATE", "bytes"}


def test_bench_objects_history_has_one_row_per_n_rounds(capsys):
    rc = main([*SMALL, "4", "--history-every", "2", "--json"])
    assert rc == 0
    row = json.loads(capsys.readouterr().out.splitlines()[0])
    assert row["rounds"] == 4  # this toy does not meet the stopping rule in 4 rounds
    assert [h["round"] for h in row["history"]] == [2, 4]
    assert row["history"][-1]["ATE"] == row["ATE"]  # the last snapshot is the final state


def test_bench_objects_rejects_a_bad_round_count(capsys):
    assert main(["bench", "objects", "--rounds", "0"]) == 2
    assert "--rounds" in capsys.readouterr().err


@pytest.mark.parametrize("flag", ["--beta", "--eta"])
def test_bench_objects_rejects_a_non_positive_penalty_or_dual_step(capsys, flag):
    assert main(["bench", "objects", flag, "0"]) == 2
    assert f"{flag}: {flag[2:]}: expected a value > 0" in capsys.readouterr().err


def test_bench_objects_dual_momentum_flag(capsys):
    """--dual-momentum sets AgentConfig.dual_momentum, shows in the row, and is range-checked."""
    assert main([*SMALL, "2", "--json", "--dual-momentum", "0.8"]) == 0
    row = json.loads(capsys.readouterr().out.splitlines()[0])
    assert row["dual_momentum"] == 0.8
    assert main([*SMALL, "2", "--json"]) == 0
    assert "dual_momentum" not in json.loads(capsys.readouterr().out.splitlines()[0])
    assert main(["bench", "objects", "--dual-momentum", "1.5"]) == 2
    assert "--dual-momentum: dual_momentum: expected a value <= 0.95" in capsys.readouterr().err


def test_bench_objects_reports_the_ratios_to_the_centralized_solution(capsys):
    rc = main([*SMALL, "3", "--history-every", "3", "--json"])
    assert rc == 0
    row = json.loads(capsys.readouterr().out.splitlines()[0])
    assert row["F_over_Fstar"] == pytest.approx(row["F"] / row["F_star"])
    assert row["ATE_over_ATEstar"] == pytest.approx(row["ATE"] / row["ATE_star"])
    assert row["history"][-1]["F_over_Fstar"] == row["F_over_Fstar"]
    assert row["stopped_by"] is None  # 3 rounds: the round cap, not the stopping rule


def test_bench_g2o_reports_f_over_fstar_or_says_na(capsys, tmp_path):
    from dran_edge.formats.g2o import write_g2o
    from dran_edge.sim.graphgen import synthetic_graph

    g, _ = synthetic_graph(dim=2, side=5, layers=1, seed=1)
    path = tmp_path / "grid.g2o"
    write_g2o(path, g, g.poses)
    g2o = ["bench", "g2o", str(path), "--robots", "2", "--max-rounds", "5", "--refine", "off"]
    assert main([*g2o, "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["F_over_Fstar"] == pytest.approx(rep["objective_final"] / rep["F_star"])
    assert rep["F_over_Fstar"] >= 1 - 1e-9 and rep["stopped_by"] is None
    assert main([*g2o, "--no-reference"]) == 0
    out = capsys.readouterr().out
    assert "F_over_Fstar: n/a" in out


def test_bench_g2o_curve_counts_init_refinement_and_rounds(capsys, tmp_path):
    from dran_edge.formats.g2o import write_g2o
    from dran_edge.sim.graphgen import synthetic_graph

    g, _ = synthetic_graph(dim=2, side=5, layers=1, seed=1)
    path = tmp_path / "grid.g2o"
    write_g2o(path, g, g.poses)
    base = ["bench", "g2o", str(path), "--robots", "2", "--max-rounds", "5", "--json", "--curve"]
    assert main([*base, "--refine", "off"]) == 0
    rep = json.loads(capsys.readouterr().out)
    curve = rep["curve"]
    assert curve[0] == [0, rep["bytes_init"], rep["objective_init"]]
    assert [k for k, _, _ in curve] == list(range(rep["rounds"] + 1))  # one point per round
    assert curve[-1][1:] == [rep["bytes_total"], pytest.approx(rep["objective_final"])]
    assert all(b1 <= b2 for (_, b1, _), (_, b2, _) in zip(curve, curve[1:]))
    assert (
        main([*base, "--refine", "always", "--refine-hessian", "exact", "--refine-steps", "3"]) == 0
    )
    rep = json.loads(capsys.readouterr().out)
    assert rep["refine_hessian"] == "exact" and rep["refine_used"]
    # the init's end, the refinement's accepted points and its end, then DRAN's rounds
    assert len(rep["curve"]) == 1 + len(rep["refine_curve"]) + rep["rounds"]
    assert rep["curve"][-1][1] == rep["bytes_total"]
    per_gather = rep["refine_bytes"] / (rep["refine_trials"] + 1)
    frozen = ["--refine", "always", "--refine-hessian", "exact", "--refine-frozen"]
    assert main([*base, *frozen, "--refine-steps", "3"]) == 0
    rep = json.loads(capsys.readouterr().out)  # frozen gathers send less
    assert rep["refine_frozen"] and rep["refine_frozen_steps"] >= 1
    assert rep["refine_bytes"] / (rep["refine_trials"] + 1) < per_gather
    pcg = ["--refine", "always", "--refine-interface", "pcg", "--refine-steps", "3"]
    assert main([*base, *pcg]) == 0
    rep = json.loads(capsys.readouterr().out)  # the iterative interface solve
    assert rep["refine_interface"] == "pcg" and len(rep["refine_pcg_iterations"]) >= 1
    assert main([*base, *pcg, "--refine-frozen"]) == 2  # frozen steps need the dense interface
    assert "--refine-frozen needs --refine-interface dense" in capsys.readouterr().err
    # --polish: Newton steps from DRAN's estimate, after its rounds, their points on the curve
    assert main([*base, "--refine", "off", "--polish"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["polish"] and rep["polish_used"] and rep["polish_converged"]
    assert rep["rounds"] >= 1 and rep["polish_pcg_iterations"]
    assert rep["curve"][-1] == [
        rep["rounds_total"] - rep["init_rounds"],
        rep["bytes_total"],
        pytest.approx(rep["objective_final"]),
    ]
    assert rep["objective_final"] <= rep["polish_F_history"][0]
    assert rep["F_over_Fstar"] < 1 + 1e-8


def test_bench_objects_refines_by_default(capsys):
    """Without --refine the run is --refine auto: on the toy the exact distributed refinement
    converges before any DRAN round, at the centralized optimum."""
    assert main([*TOY, "--rounds", "50", "--json"]) == 0
    row = json.loads(capsys.readouterr().out.splitlines()[0])
    assert row["refine"] == "auto" and row["refine_used"] and row["stopped_by"] == "refine"
    assert row["F_over_Fstar"] < 1 + 1e-6
