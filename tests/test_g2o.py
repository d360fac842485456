"""g2o read/write round trips, malformed input (file:line in every message) and the solve CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dran_edge.cli.app import main
from dran_edge.errors import InputError
from dran_edge.formats.g2o import read_g2o, write_g2o
from dran_edge.sim.graphgen import synthetic_graph

SE2_EDGE = "EDGE_SE2 0 1 1.0 0.0 0.1 10 0 0 10 0 20"
# upper triangle of diag(10, 10, 10, 20, 20, 20), row by row
SE3_EDGE = "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 20 0 0 20 0 20"


@pytest.mark.parametrize("dim", [2, 3])
def test_round_trip_is_exact(tmp_path, dim):
    g, _ = synthetic_graph(dim, side=4, seed=5)
    fixed = g.fixed.copy()
    fixed[3] = True
    g = type(g)(**{**g.__dict__, "fixed": fixed})
    path = tmp_path / "g.g2o"
    write_g2o(path, g)
    h = read_g2o(path)
    assert h.dim == dim
    np.testing.assert_array_equal(h.vertex_ids, g.vertex_ids)
    np.testing.assert_array_equal(h.edges, g.edges)
    np.testing.assert_array_equal(h.fixed, fixed)
    np.testing.assert_allclose(h.poses, g.poses, atol=1e-15)
    np.testing.assert_allclose(h.measurements, g.measurements, atol=1e-15)
    np.testing.assert_allclose(h.information, g.information, rtol=1e-15)


def test_file_without_vertices_and_sparse_ids(tmp_path):
    path = tmp_path / "novert.g2o"
    path.write_text(
        "# comment\n\nEDGE_SE2 10 20 1 0 0 1 0 0 1 0 1\nEDGE_SE2 20 30 1 0 0 1 0 0 1 0 1\n"
    )
    g = read_g2o(path)
    assert g.vertex_ids.tolist() == [10, 20, 30]
    assert not g.has_pose.any()
    assert g.edges.tolist() == [[0, 1], [1, 2]]
    assert g.edge_lines.tolist() == [3, 4]


def test_3d_quaternion_order_is_xyzw(tmp_path):
    path = tmp_path / "q.g2o"
    # 90° about z: qz = qw = √½
    path.write_text(
        "VERTEX_SE3:QUAT 0 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n" + SE3_EDGE + "\n"
    )
    g = read_g2o(path)
    np.testing.assert_allclose(g.poses[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(g.poses[0, :3, 3], [1, 2, 3])


@pytest.mark.parametrize(
    "text,line,fragment",
    [
        (SE2_EDGE + "\nEDGE_SE2 0 1 1.0 0.0 0.1 10 0 0 10 0\n", 2, "has 10 fields, expected 11"),
        ("VERTEX_SE2 0 0 0 x\n" + SE2_EDGE + "\n", 1, "'x', expected a number"),
        ("VERTEX_SE2 0 0 0 nan\n" + SE2_EDGE + "\n", 1, "expected a finite number"),
        ("VERTEX_XY 0 1 2\n", 1, "unsupported record 'VERTEX_XY'"),
        (SE2_EDGE + "\n" + SE3_EDGE + "\n", 2, "mixes 3D records into a 2D graph"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n" + SE2_EDGE + "\n", 2, "defined twice"),
        ("EDGE_SE2 1 1 1.0 0.0 0.1 10 0 0 10 0 20\n", 1, "to itself"),
        ("EDGE_SE2 0 1 1.0 0.0 0.1 10 0 0 -10 0 20\n", 1, "tau = 2/tr(Omega_tt^-1) is inf"),
        ("EDGE_SE2 0 1 1.0 0.0 0.1 10 0 0 10 0 -20\n", 1, "kappa = Omega_thth is -20"),
        (
            # 3D, translation block singular: tau = 0
            "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 10 0 0 0 0 0 0 0 0 0 0 10 0 0 0 20 0 0 20 0 20\n",
            1,
            "EDGE_SE3:QUAT 0 1: information matrix cannot be used: translation weight tau",
        ),
        ("EDGE_SE2 0 -1 1.0 0.0 0.1 10 0 0 10 0 20\n", 1, "negative"),
        (
            "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 2 " + SE3_EDGE.split(" ", 10)[10] + "\n",
            1,
            "quaternion norm",
        ),
        (SE2_EDGE + "\nFIX 7\n", 2, "FIX names vertex 7"),
        (SE2_EDGE + "\nFIX\n", 2, "FIX names no vertex"),
    ],
)
def test_malformed_lines_name_file_and_line(tmp_path, text, line, fragment):
    path = tmp_path / "bad.g2o"
    path.write_text(text)
    with pytest.raises(InputError) as info:
        read_g2o(path)
    message = str(info.value)
    assert message.startswith(f"{path}:{line}: "), message
    assert fragment in message
    assert info.value.line == line


def test_empty_and_missing_files(tmp_path):
    empty = tmp_path / "empty.g2o"
    empty.write_text("# nothing\n")
    with pytest.raises(InputError, match="no edges"):
        read_g2o(empty)
    with pytest.raises(InputError, match="cannot read"):
        read_g2o(tmp_path / "missing.g2o")


def test_solve_cli_json_and_output(tmp_path, capsys):
    g, _ = synthetic_graph(3, side=4, seed=2)
    src, out = tmp_path / "in.g2o", tmp_path / "out.g2o"
    write_g2o(src, g)
    code = main(["solve", str(src), "--out", str(out), "--json", "--quiet"])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    for key in (
        "vertices",
        "edges",
        "objective_input",
        "objective_init",
        "objective_final",
        "iterations",
        "status",
        "wall_s",
    ):
        assert key in report
    assert report["vertices"] == g.num_vertices and report["edges"] == g.num_edges
    assert report["status"] == "converged"
    assert report["objective_final"] <= report["objective_init"] + 1e-9
    assert report["objective_final"] <= report["objective_input"]
    h = read_g2o(out)
    np.testing.assert_array_equal(h.edges, g.edges)
    assert not np.allclose(h.poses, g.poses)  # optimised vertices were written


def test_solve_cli_reports_malformed_file_as_one_line(tmp_path, capsys):
    src = tmp_path / "bad.g2o"
    src.write_text(SE2_EDGE + "\nEDGE_SE2 0 2 1 0\n")
    code = main(["solve", str(src), "--out", str(tmp_path / "o.g2o")])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("dran-edge solve: error: ") and f"{src}:2:" in err[-1]
    assert "Traceback" not in "\n".join(err)


def test_solve_cli_file_init_needs_vertices(tmp_path, capsys):
    src = tmp_path / "novert.g2o"
    src.write_text(SE2_EDGE + "\n")
    assert main(["solve", str(src), "--out", str(tmp_path / "o.g2o"), "--init", "file"]) == 2
    assert "--init file needs a VERTEX line" in capsys.readouterr().err


def _indefinite_se3_line(i: int, j: int, coupling: float) -> str:
    """An EDGE_SE3:QUAT whose blocks are 10·I and 20·I (SE-Sync weights τ = 10,
    κ = 3/(2·tr(Ω_rr⁻¹)) = 10) but whose translation–rotation coupling ``coupling`` makes Ω
    indefinite when coupling² > 200."""
    info = np.diag([10.0, 10, 10, 20, 20, 20])
    info[0, 3] = info[3, 0] = coupling
    upper = " ".join(repr(float(x)) for x in info[np.triu_indices(6)])
    return f"EDGE_SE3:QUAT {i} {j} 1 0 0 0 0 0 1 {upper}"


def _chain_with_indefinite_edges(tmp_path, bad_edges: int):
    g, _ = synthetic_graph(3, side=3, layers=1, seed=4)
    path = tmp_path / "indef.g2o"
    write_g2o(path, g)
    lines = path.read_text().splitlines()
    # replace the first `bad_edges` EDGE lines' information by an indefinite one
    edge_rows = [k for k, line in enumerate(lines) if line.startswith("EDGE_SE3:QUAT")]
    for k in edge_rows[:bad_edges]:
        tok = lines[k].split()
        ok = _indefinite_se3_line(0, 1, 0.0).split()[10:]
        bad = _indefinite_se3_line(0, 1, 20.0).split()[10:]
        assert ok != bad
        lines[k] = " ".join(tok[:10] + bad)
    path.write_text("\n".join(lines) + "\n")
    return path, edge_rows


def test_indefinite_information_with_positive_sesync_weights_is_accepted(tmp_path, caplog):
    from dran_edge.solver.objective import not_positive_definite, sesync_weights
    from dran_edge.solver.centralized import pose_graph, solve_g2o

    path, edge_rows = _chain_with_indefinite_edges(tmp_path, bad_edges=2)
    with caplog.at_level("WARNING", logger="dran_edge.formats.g2o"):
        g = read_g2o(path)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1, warnings
    assert "2 of" in warnings[0] and f"line {edge_rows[0] + 1}" in warnings[0]
    bad, lam_min = not_positive_definite(g.information)
    assert bad.sum() == 2 and lam_min[0] < 0
    kappa, tau = sesync_weights(3, g.information)
    np.testing.assert_allclose([kappa[0], tau[0]], [10.0, 10.0])  # from the blocks only
    report = solve_g2o(g)
    assert report.result.status.value == "converged"
    assert report.objective_final <= report.objective_init
    # the full information cannot whiten these edges: rejected by edge and line
    with pytest.raises(InputError) as info:
        pose_graph(g, "geodesic", "information")
    i, j = (int(v) for v in g.vertex_ids[g.edges[0]])
    assert f"edge {i} {j} on line {edge_rows[0] + 1}" in str(info.value)
    assert "not positive definite" in str(info.value) and "1 more" in str(info.value)


def test_solve_cli_indefinite_information(tmp_path, capsys, caplog):
    path, edge_rows = _chain_with_indefinite_edges(tmp_path, bad_edges=1)
    out = tmp_path / "o.g2o"
    with caplog.at_level("WARNING"):
        assert main(["solve", str(path), "--out", str(out), "--quiet"]) == 0
    warned = [r.getMessage() for r in caplog.records if "not positive definite" in r.getMessage()]
    assert len(warned) == 1 and "1 of" in warned[0]
    code = main(
        ["solve", str(path), "--out", str(out)]
        + ["--weights", "information", "--residual", "geodesic"]
    )
    assert code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"{path}: edge" in last and f"on line {edge_rows[0] + 1}" in last
