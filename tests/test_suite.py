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
        assert len(r["curve"]) == 31 and r["curve"][0][0] == 0
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
