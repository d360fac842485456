"""Run-level evaluation (dran_edge.evaluation.score) and ``dran-edge eval`` on a tiny run written here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dran_edge.cli import app as cli
from dran_edge.evaluation import score as evaluate
from dran_edge.formats import motive_write, tum
from dran_edge.errors import InputError

START_NS = 1_700_000_000_000_000_000
MOCAP_START_NS = START_NS - 2_500_000_000  # Motive's time 0 is 2.5 s before the mission start
DURATION_S = 40.0
OBJ_OFFSET_M = 0.04


def _pose(R, p):
    T = np.tile(np.eye(4), np.shape(p)[:-1] + (1, 1))
    T[..., :3, :3] = R
    T[..., :3, 3] = p
    return T


def _track(t, k):
    """Robot k drives a wobbly circle (yaw rate varies, so clock offsets are observable)."""
    yaw = 0.3 * t + 0.6 * np.sin(0.7 * t + k) + 0.3 * np.sin(1.9 * t + 2 * k)
    p = np.stack([2.0 * np.cos(0.15 * t + k) + k, 1.5 * np.sin(0.15 * t + k), 0.1 + 0 * t], 1)
    return _pose(Rotation.from_euler("z", yaw[:, None]).as_matrix(), p)


def _noisy(rng, T, sigma_p, sigma_r):
    dR = Rotation.from_rotvec(rng.normal(0, sigma_r, (len(T), 3))).as_matrix()
    return _pose(T[:, :3, :3] @ dR, T[:, :3, 3] + rng.normal(0, sigma_p, (len(T), 3)))


T_BODY_MARKER = _pose(
    Rotation.from_euler("x", 90, degrees=True).as_matrix(), np.array([0.05, 0.0, 0.3])
)
OBJECTS = {
    0: _pose(np.eye(3), np.array([1.0, 0.5, 0.2])),
    3: _pose(Rotation.from_euler("z", 40, degrees=True).as_matrix(), np.array([-1.0, 1.0, 0.2])),
}


def make_run(root: Path, *, with_start_ns=True, rounds_text=None, robot2_body="dingo2") -> dict:
    """A 2-robot run with mocap, final/initial/centralized trajectories, objects and rounds."""
    rng = np.random.default_rng(11)
    root.mkdir(parents=True, exist_ok=True)
    mocap_line = "mocap: {file: mocap.csv" + (
        f", start_ns: {MOCAP_START_NS}}}" if with_start_ns else "}"
    )
    q = [float(v) for v in Rotation.from_matrix(T_BODY_MARKER[:3, :3]).as_quat()]
    xyz = [float(v) for v in T_BODY_MARKER[:3, 3]]
    tbm = f"{{xyz: {xyz}, quat_xyzw: {q}}}"
    (root / "mission.yaml").write_text(
        "format: dran-edge-run/1\nfleet: test\n"
        f"start_ns: {START_NS}\nduration_s: {DURATION_S}\n"
        "robots:\n"
        f"  - {{id: 1, name: dingo1, mocap_body: dingo1, T_body_marker: {tbm}}}\n"
        f"  - {{id: 2, name: dingo2, mocap_body: {robot2_body}, T_body_marker: {tbm}}}\n"
        "objects:\n  - {id: 0, name: box0, mocap_body: box0}\n"
        "  - {id: 3, name: box3, mocap_body: box3}\n"
        "comm_graph: [[1, 2]]\n" + mocap_line + "\n"
    )
    # Mocap: 120 Hz from Motive time 0, covering the mission.
    t_m = np.arange(0, DURATION_S + 4.0, 1 / 120)
    t_mission = t_m - 2.5
    bodies = {}
    for k, name in ((0, "dingo1"), (1, "dingo2")):
        bodies[name] = _track(t_mission, k) @ T_BODY_MARKER
    bodies["dingo1"][1200:1230] = np.nan  # a 0.25 s occlusion
    for oid, T in OBJECTS.items():
        bodies[f"box{oid}"] = np.broadcast_to(T, (len(t_m), 4, 4)).copy()
    motive_write.write_motive_csv(
        root / "mocap.csv", motive_write.make_take(t_m, bodies, take_name="t")
    )
    truth = {}
    out = root / "out"
    for k, name in ((0, "dingo1"), (1, "dingo2")):
        t = np.arange(0, DURATION_S, 0.1)
        stamps = START_NS * 1e-9 + t
        gt = _track(t, k)
        truth[name] = (stamps, gt)
        init = _noisy(rng, gt, 0.0, 0.0)
        init[:, :3, 3] += np.outer(t / DURATION_S, [0.4, -0.3, 0.0])  # drift, exact first pose
        final = _noisy(rng, gt, 0.03, 0.01)
        central = _noisy(rng, gt, 0.02, 0.005)
        (out / name).mkdir(parents=True, exist_ok=True)
        (out / "centralized" / name).mkdir(parents=True, exist_ok=True)
        tum.write_tum(out / name / "trajectory_init.tum", stamps, init)
        tum.write_tum(out / name / "trajectory.tum", stamps, final)
        tum.write_tum(out / "centralized" / name / "trajectory.tum", stamps, central)
        sign = 1.0 if k == 0 else -1.0
        lines = ["object_id,x,y,z,qx,qy,qz,qw"]
        for oid, T in OBJECTS.items():
            p = T[:3, 3] + sign * np.array([OBJ_OFFSET_M, 0, 0])
            qo = Rotation.from_matrix(T[:3, :3]).as_quat()
            lines.append(",".join([str(oid)] + [repr(float(v)) for v in (*p, *qo)]))
        (out / name / "objects.csv").write_text("\n".join(lines) + "\n")
    (out / "rounds.csv").write_text(
        rounds_text
        or (
            "round,stamp_ns,bytes_total,cost,consensus_error\n"
            + "\n".join(
                f"{r},{START_NS + r * 500_000_000},{1200 * (r + 1)},{10.0 / (r + 1)},{0.5**r}"
                for r in range(20)
            )
            + "\n"
        )
    )
    (out / "report.json").write_text(
        json.dumps(
            {
                "bytes_total": 24000,
                "rounds": 20,
                "cost_init": 10.0,
                "cost_final": 0.5,
                "cost_centralized": 0.4,
            }
        )
    )
    return truth


def _ate_by_hand(root: Path, name: str, kind_file: str, truth) -> float:
    stamps, gt = truth[name]
    _, T = tum.read_tum(root / "out" / kind_file.format(name=name))
    d = T[:, :3, 3] - gt[:, :3, 3]
    if name == "dingo1":  # mocap occluded 7.5 s .. 7.74 s into the mission
        t = stamps - START_NS * 1e-9
        d = d[(t < 7.45) | (t > 7.75)]
    return float(np.sqrt(np.mean(np.sum(d * d, 1))))


def test_eval_run_with_paper_alignment(tmp_path):
    truth = make_run(tmp_path / "run")
    report = evaluate.evaluate_run(tmp_path / "run", evaluate.EvalOptions(align="paper"))
    written = evaluate.write_report(report, tmp_path / "run" / "eval")
    names = sorted(p.name for p in written)
    assert names == ["errors.png", "report.json", "rounds.png", "summary.md", "trajectories.png"]
    for p in written:
        assert p.stat().st_size > 200
    r = json.loads((tmp_path / "run" / "eval" / "report.json").read_text())
    assert r["time"]["source"] == "mission.yaml mocap.start_ns"
    assert r["time"]["time_offset_s"] == pytest.approx(-MOCAP_START_NS * 1e-9)
    for name in ("dingo1", "dingo2"):
        e = r["robots"][name]
        # The initial estimate starts exactly at the truth, so the paper's anchor is the identity
        # and the ATE is the noise we put in, computed here by hand.
        assert e["final"]["ate_trans_rmse_m"] == pytest.approx(
            _ate_by_hand(tmp_path / "run", name, "{name}/trajectory.tum", truth), abs=2e-5
        )
        assert e["init"]["ate_trans_rmse_m"] == pytest.approx(
            _ate_by_hand(tmp_path / "run", name, "{name}/trajectory_init.tum", truth), abs=2e-5
        )
        want_sr = (
            100
            * (e["init"]["ate_log_rmse"] - e["final"]["ate_log_rmse"])
            / (e["init"]["ate_log_rmse"] - e["centralized"]["ate_log_rmse"])
        )
        assert e["sr_ate_pct"] == pytest.approx(want_sr)
        assert 0 < e["sr_ate_pct"] < 100
        assert e["final"]["matched_poses"] == 400 - (3 if name == "dingo1" else 0)
        assert e["final"]["rpe"]["pairs"] > 300
    ob = r["objects"]
    # Robot copies are +-4 cm from the truth along x: Bias (paper formula) = 4 cm, the mean map
    # is exact, and CE (squared) = (4 cm)^2.
    # (Tolerances: the Motive CSV holds 6 decimals.)
    assert ob["bias"] == pytest.approx(OBJ_OFFSET_M, abs=2e-6)
    assert ob["bias_of_mean"] == pytest.approx(0.0, abs=2e-6)
    assert ob["ce"] == pytest.approx(OBJ_OFFSET_M**2, rel=1e-9)
    assert set(ob["per_object"]) == {"0", "3"}
    assert r["cost"]["sr_cost_pct"] == pytest.approx(100 * 9.5 / 9.6)
    assert r["rounds"]["count"] == 20 and r["rounds"]["bytes_total"] == 24000
    assert r["inter_robot"]["pairs"]["dingo1-dingo2"]["samples"] > 50
    md = (tmp_path / "run" / "eval" / "summary.md").read_text()
    assert "| dingo1 |" in md and "SR_ATE" in md


def test_eval_reads_the_replays_round_costs(tmp_path):
    """report.json's round_costs (the merged graph as of sampled rounds) give SR_cost and F/F*
    per round; without them a note says rounds.csv's raw cost is plotted; malformed ones are
    an error naming the file."""
    make_run(tmp_path / "run")
    rep_path = tmp_path / "run" / "out" / "report.json"
    report = evaluate.evaluate_run(tmp_path / "run", evaluate.EvalOptions(plots=False))
    assert report.plot_data.round_costs is None
    assert any("no round_costs" in n for n in report.report["notes"])
    rep = json.loads(rep_path.read_text())
    rep["round_costs"] = {
        "round": [9, 19],
        "F_init": [10.0, 20.0],
        "F_k": [4.0, 2.0],
        "F_star": [2.0, None],
    }
    rep_path.write_text(json.dumps(rep))
    report = evaluate.evaluate_run(tmp_path / "run", evaluate.EvalOptions(plots=False))
    rc = report.plot_data.round_costs
    assert rc is not None and np.array_equal(rc["round"], [9, 19])
    assert rc["sr_cost_pct"][0] == pytest.approx(75.0) and np.isnan(rc["sr_cost_pct"][1])
    assert rc["f_over_fstar"][0] == pytest.approx(2.0)
    assert report.report["rounds"]["cost_samples"] == 2
    rep["round_costs"]["F_k"] = [4.0]
    rep_path.write_text(json.dumps(rep))
    with pytest.raises(InputError, match="round_costs") as exc:
        evaluate.evaluate_run(tmp_path / "run", evaluate.EvalOptions(plots=False))
    assert "report.json" in str(exc.value)


def test_eval_run_estimates_the_clock_offset(tmp_path):
    make_run(tmp_path / "run", with_start_ns=False)
    report = evaluate.evaluate_run(
        tmp_path / "run", evaluate.EvalOptions(align="se3", plots=False)
    ).report
    assert report["time"]["source"] == "estimated"
    assert report["time"]["time_offset_s"] == pytest.approx(-MOCAP_START_NS * 1e-9, abs=0.01)
    a = report["robots"]["dingo1"]["final"]["alignment"]
    assert a["kind"] == "se3"
    assert report["robots"]["dingo1"]["final"]["ate_trans_rmse_m"] < 0.07


def test_eval_run_tolerates_missing_optional_files(tmp_path):
    make_run(tmp_path / "run")
    out = tmp_path / "run" / "out"
    for p in [
        out / "rounds.csv",
        out / "report.json",
        out / "dingo1" / "objects.csv",
        out / "dingo2" / "objects.csv",
        out / "dingo1" / "trajectory_init.tum",
    ]:
        p.unlink()
    for p in (out / "centralized").rglob("*.tum"):
        p.unlink()
    report = evaluate.evaluate_run(tmp_path / "run", evaluate.EvalOptions(plots=False)).report
    assert "sr_ate_pct" not in report["overall"]
    assert report["objects"] == {} and report["rounds"] == {}
    assert any("merged.g2o absent" in n for n in report["notes"])
    assert any("objects.csv" in n for n in report["notes"])
    assert report["robots"]["dingo1"]["final"]["ate_trans_rmse_m"] > 0


def test_eval_run_errors(tmp_path):
    make_run(tmp_path / "a", robot2_body="dingo9")
    with pytest.raises(
        InputError,
        match=r"robot dingo2: mocap_body 'dingo9' is not a rigid body"
        r".*box0, box3, dingo1, dingo2",
    ):
        evaluate.evaluate_run(tmp_path / "a", evaluate.EvalOptions(plots=False))
    bad_rounds = "round,stamp_ns,cost\n0,1,2.0\n1,2,x\n"
    make_run(tmp_path / "b", rounds_text=bad_rounds)
    with pytest.raises(InputError, match=r"rounds.csv:3: column 'cost': expected a number"):
        evaluate.evaluate_run(tmp_path / "b", evaluate.EvalOptions(plots=False))
    make_run(tmp_path / "c")
    for p in (tmp_path / "c" / "out").rglob("trajectory.tum"):
        p.unlink()
    with pytest.raises(InputError, match=r"no robot has out/<name>/<name>.tum"):
        evaluate.evaluate_run(tmp_path / "c", evaluate.EvalOptions(plots=False))
    make_run(tmp_path / "d")
    with pytest.raises(InputError, match="time ranges do not overlap"):
        evaluate.evaluate_run(
            tmp_path / "d", evaluate.EvalOptions(plots=False, time_offset_s=1000.0)
        )


def test_cli_eval_run_and_traj(tmp_path, capsys):
    truth = make_run(tmp_path / "run")
    assert cli.main(["eval", str(tmp_path / "run"), "--no-plots", "--align", "yaw"]) == 0
    out = capsys.readouterr().out
    assert "alignment: **yaw**" in out
    assert (tmp_path / "run" / "eval" / "report.json").exists()
    est = tmp_path / "run" / "out" / "dingo1" / "trajectory.tum"
    mocap = tmp_path / "run" / "mocap.csv"
    rc = cli.main(
        [
            "eval",
            "traj",
            str(est),
            "--mocap",
            str(mocap),
            "--body",
            "dingo1",
            "--time-offset",
            str(-MOCAP_START_NS * 1e-9),
            "--json",
        ]
    )
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    for key in ("ate_rmse_m", "ate_max_m", "matched_poses", "time_offset_s"):
        assert key in res
    # The body pose is the marker pose (no T_body_marker given to 'eval traj'); se3 alignment
    # absorbs the lever arm only in part, so just check it is a sane, finite number.
    assert 0 < res["ate_rmse_m"] < 0.5 and res["matched_poses"] == 397
    # With the pivot offset and the known clock, no alignment is needed and the ATE is the
    # noise put into the estimate, computed by hand.
    q = Rotation.from_matrix(T_BODY_MARKER[:3, :3]).as_quat()
    rc = cli.main(
        [
            "eval",
            "traj",
            str(est),
            "--mocap",
            str(mocap),
            "--body",
            "dingo1",
            "--time-offset",
            str(-MOCAP_START_NS * 1e-9),
            "--align",
            "none",
            "--json",
            "--T-body-marker",
            *map(str, T_BODY_MARKER[:3, 3]),
            *map(str, q),
        ]
    )
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["ate_rmse_m"] == pytest.approx(
        _ate_by_hand(tmp_path / "run", "dingo1", "{name}/trajectory.tum", truth), abs=2e-5
    )
    rc = cli.main(["eval", "traj", str(est), "--mocap", str(mocap), "--body", "nobody"])
    assert rc == 2
    assert "no rigid body named 'nobody'" in capsys.readouterr().err


@pytest.mark.parametrize("connected", [True, False])
def test_eval_run_solves_merged_g2o_for_the_centralized_solution(tmp_path, connected):
    pytest.importorskip("dran_edge.solver.centralized")
    from dran_edge.formats.g2o import G2oGraph, write_g2o

    truth = make_run(tmp_path / "run")
    out = tmp_path / "run" / "out"
    for p in (out / "centralized").rglob("*.tum"):
        p.unlink()
    # merged.g2o: every 10th keyframe of each robot, final estimate as vertex values, odometry
    # edges from the truth, each robot's first vertex fixed (its gauge).
    vids, poses, edges, meas, rows, fixed = [], [], [], [], [], []
    for r, name in enumerate(("dingo1", "dingo2"), start=1):
        stamps, gt = truth[name]
        _, T = tum.read_tum(out / name / "trajectory.tum")
        sel = np.arange(0, len(stamps), 10)
        base = len(vids)
        for j, k in enumerate(sel):
            vids.append(r * 1_000_000 + j)
            poses.append(T[k] if j else gt[k])
            rows.append(f"{r * 1_000_000 + j},pose,{name},{int(round(stamps[k] * 1e9))}")
            fixed.append(j == 0)
            if j:
                edges.append((base + j - 1, base + j))
                meas.append(np.linalg.inv(gt[sel[j - 1]]) @ gt[k])
    if connected:  # one inter-robot loop between the robots' 6th vertices
        (_, g1), (_, g2) = truth["dingo1"], truth["dingo2"]
        edges.append((5, 45))
        meas.append(np.linalg.inv(g1[50]) @ g2[50])
    g = G2oGraph(
        dim=3,
        vertex_ids=np.array(vids),
        poses=np.stack(poses),
        has_pose=np.ones(len(vids), bool),
        edges=np.array(edges),
        measurements=np.stack(meas),
        information=np.tile(100 * np.eye(6), (len(edges), 1, 1)),
        fixed=np.array(fixed),
        edge_lines=np.zeros(len(edges), np.int64),
    )
    write_g2o(out / "merged.g2o", g)
    (out / "merged_vertices.csv").write_text(
        "vertex_id,kind,name,stamp_ns\n" + "\n".join(rows) + "\n"
    )
    (out / "report.json").unlink()
    r = evaluate.evaluate_run(tmp_path / "run", evaluate.EvalOptions(plots=False)).report
    for name in ("dingo1", "dingo2"):
        e = r["robots"][name]
        assert e["centralized"]["matched_poses"] == 40
        # The centralized solution is the truth (exact odometry from the true first pose).
        assert e["centralized"]["ate_trans_rmse_m"] < 1e-4
    c = r["cost"]
    assert c["F_star"] < c["F_k"] and c["F_star"] < 1e-6  # consistent odometry: F* = 0
    # The vertex values are the exported trajectory except each robot's first (the truth).
    first_diff = [
        np.linalg.norm(
            tum.read_tum(out / n / "trajectory.tum")[1][0, :3, 3] - truth[n][1][0, :3, 3]
        )
        for n in ("dingo1", "dingo2")
    ]
    assert c["merged_vs_trajectory_max_m"] == pytest.approx(max(first_diff), abs=1e-9)
    if not connected:
        assert "F_chordal" not in c
        assert any("chordal initialisation failed" in n for n in r["notes"])
    # F_init is F at the robots' initial estimates (trajectory_init.tum at the vertex stamps),
    # whether or not the graph is connected.
    from dran_edge.solver.objective import sesync_objective, sesync_weights

    P0 = []
    for name in ("dingo1", "dingo2"):
        stamps, _ = truth[name]
        _, T0 = tum.read_tum(out / name / "trajectory_init.tum")
        P0 += [T0[k] for k in np.arange(0, len(stamps), 10)]
    kappa, tau = sesync_weights(3, g.information)
    F_init = sesync_objective(np.stack(P0), g.edges, g.measurements, kappa, tau)
    assert c["F_init"] == pytest.approx(F_init, rel=1e-9)
    assert c["F_init"] > c["F_star"]
    assert c["sr_cost_pct"] == pytest.approx(
        100 * (c["F_init"] - c["F_k"]) / (c["F_init"] - c["F_star"])
    )
    assert r["summary"]["sr_ate_pct"] == pytest.approx(r["overall"]["sr_ate_pct"])


def test_eval_run_error_when_no_robot_matches_a_body(tmp_path):
    make_run(tmp_path / "run")
    m = tmp_path / "run" / "mission.yaml"
    m.write_text(
        m.read_text().replace("mocap_body: dingo1, ", "").replace("mocap_body: dingo2, ", "")
    )
    other = tmp_path / "other.csv"
    t = np.arange(0, 50, 1 / 30)
    motive_write.write_motive_csv(other, motive_write.make_take(t, {"robotA": _track(t, 0)}))
    with pytest.raises(
        InputError,
        match=r"no robot of mission.yaml matches a rigid body .*"
        r"robots: dingo1, dingo2; bodies: robotA",
    ):
        evaluate.evaluate_run(
            tmp_path / "run", evaluate.EvalOptions(plots=False, mocap_path=str(other))
        )
    # With the run's own mocap the robots match by name, without mocap_body.
    r = evaluate.evaluate_run(tmp_path / "run", evaluate.EvalOptions(plots=False)).report
    assert set(r["robots"]) == {"dingo1", "dingo2"}
