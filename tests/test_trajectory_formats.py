"""Trajectory files as evo users have them: TUM / EuRoC CSV / KITTI detection (never guessing the
quaternion order), export of a run's mocap, eval traj against files, runs, positions only."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dran_edge import geometry as geo
from dran_edge.cli.app import main
from dran_edge.errors import InputError
from dran_edge.formats import trajectory as tr


def _poses(seed: int, n: int = 50) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    stamps = 1767225600.0 + np.cumsum(rng.uniform(0.05, 0.15, n))
    xyz = np.cumsum(rng.normal(0, 0.1, (n, 3)), axis=0)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return stamps, geo.se3_from_xyz_quat_xyzw(np.c_[xyz, q])


def _same_poses(Ta, Tb, atol=1e-8):
    return np.allclose(Ta, Tb, atol=atol)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("fmt", tr.FORMATS)
def test_write_then_detect_and_read_gives_the_poses_back(tmp_path, fmt, seed):
    stamps, T = _poses(seed)
    p = tmp_path / f"t{tr.SUFFIX[fmt]}"
    tr.write_trajectory(p, stamps, T, fmt)
    kw = {"kitti_times": p.with_suffix(".times.txt")} if fmt == "kitti" else {}
    got = tr.read_trajectory(p, **kw)
    assert (
        got.format == fmt and got.quat_order == {"tum": "xyzw", "euroc": "wxyz", "kitti": None}[fmt]
    )
    assert _same_poses(got.T, T) and np.allclose(got.stamps_s, stamps, atol=1e-6)
    assert not got.positions_only


def test_vins_and_euroc_groundtruth_layouts_are_w_first(tmp_path):
    stamps, T = _poses(3, 5)
    v = geo.se3_to_xyz_quat_wxyz(T)
    ns = np.round(stamps * 1e9).astype(np.int64)
    vins = tmp_path / "vins_result_no_loop.csv"  # t_ns, p, q wxyz, v, trailing comma
    vins.write_text(
        "".join(f"{s}," + ",".join(f"{x:.12f}" for x in r) + ",0,0,0,\n" for s, r in zip(ns, v))
    )
    gt = tmp_path / "data.csv"  # EuRoC state_groundtruth_estimate0: 17 columns with a header
    gt.write_text(
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
        "q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1]"
        ", b_w_RS_S_x [rad s^-1], b_w_RS_S_y, b_w_RS_S_z, b_a_RS_S_x, b_a_RS_S_y, "
        "b_a_RS_S_z\n"
        + "".join(
            f"{s}," + ",".join(f"{x:.12f}" for x in r) + ",0,0,0,0,0,0,0,0,0\n"
            for s, r in zip(ns, v)
        )
    )
    for p in (vins, gt):
        got = tr.read_trajectory(p)
        assert (got.format, got.quat_order) == ("euroc", "wxyz"), got.how
        assert _same_poses(got.T, T)


def test_an_ambiguous_w_first_csv_is_refused_not_scored_as_tum(tmp_path, capsys):
    """8 comma-separated columns, stamps in seconds, w first (VINS/EuRoC order): the reader
    cannot know the order, so it asks; with --quat-order wxyz it scores it right."""
    stamps, T = _poses(4, 200)
    v = geo.se3_to_xyz_quat_wxyz(T)
    amb = tmp_path / "est.csv"
    amb.write_text(
        "".join(f"{s:.9f}," + ",".join(f"{x:.10f}" for x in r) + "\n" for s, r in zip(stamps, v))
    )
    ref = tmp_path / "ref.tum"
    tr.write_trajectory(ref, stamps, T, "tum")
    with pytest.raises(InputError, match="cannot tell the quaternion order.*--quat-order"):
        tr.read_trajectory(amb)
    rc = main(["eval", "traj", str(amb), "--ref", str(ref), "--json"])
    err = capsys.readouterr().err
    assert rc == 2 and "quat-order" in err
    rc = main(["eval", "traj", str(amb), "--ref", str(ref), "--quat-order", "wxyz", "--json"])
    res = json.loads(capsys.readouterr().out)
    assert rc == 0 and res["ate_rot_rmse_deg"] < 1e-4 and res["ate_rmse_m"] < 1e-6
    assert res["time_offset_source"] == "clock overlap"
    # a header naming the columns decides, and contradicting it is an error
    named = tmp_path / "named.csv"
    named.write_text("# t, x, y, z, qw, qx, qy, qz\n" + amb.read_text())
    assert tr.read_trajectory(named).quat_order == "wxyz"
    with pytest.raises(InputError, match="header names the quaternion columns in wxyz"):
        tr.read_trajectory(named, quat_order="xyzw")


def test_exported_mocap_as_reference_scores_like_the_motive_csv_and_evo(
    small_sim_run, tmp_path, capsys
):
    run, _ = small_sim_run
    out = tmp_path / "mocap"
    assert main(["export", "mocap", str(run), "--format", "tum", "--out", str(out)]) == 0
    assert capsys.readouterr().out.split() == [
        str(out / f"{b}.tum") for b in ("dingo1", "dingo2", "dingo3", "box0", "box1", "box2")
    ]
    files = sorted(p.name for p in out.iterdir())
    assert files == ["box0.tum", "box1.tum", "box2.tum", "dingo1.tum", "dingo2.tum", "dingo3.tum"]
    est = run / "out" / "dingo2" / "dingo2.tum"
    assert main(["eval", "traj", str(est), "--json"]) == 0  # mocap, body, clock: mission.yaml
    by_run = json.loads(capsys.readouterr().out)
    assert by_run["time_offset_source"] == "mission.yaml mocap.start_ns"
    assert (
        main(
            [
                "eval",
                "traj",
                str(est),
                "--ref",
                str(out / "dingo2.tum"),
                "--json",
                "--save-results",
                str(tmp_path / "res.zip"),
            ]
        )
        == 0
    )
    by_file = json.loads(capsys.readouterr().out)
    assert by_file["time_offset_source"] == "clock overlap"
    assert by_file["matched_poses"] == by_run["matched_poses"] > 5
    assert by_file["ate_rmse_m"] == pytest.approx(by_run["ate_rmse_m"], abs=1e-6)
    evo_file = pytest.importorskip("evo.tools.file_interface")
    from evo.core import metrics, sync

    ref = evo_file.read_tum_trajectory_file(str(out / "dingo2.tum"))
    e = evo_file.read_tum_trajectory_file(str(est))
    ref, e = sync.associate_trajectories(ref, e, max_diff=0.01)
    e.align(ref)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    assert by_file["ate_rmse_m"] == pytest.approx(
        ape.get_statistic(metrics.StatisticsType.rmse), abs=1e-6
    )
    res = evo_file.load_res_file(str(tmp_path / "res.zip"), load_trajectories=True)
    assert res.stats["rmse"] == pytest.approx(by_file["ate_rmse_m"], abs=1e-12)
    assert (
        res.info["est_name"] == "dingo2"
        and len(res.np_arrays["error_array"]) == by_file["matched_poses"]
    )
    # EuRoC and KITTI exports carry the same poses
    for fmt in ("euroc", "kitti"):
        assert (
            main(["export", "mocap", str(run), "--format", fmt, "--out", str(tmp_path / fmt)]) == 0
        )
    a = tr.read_trajectory(out / "dingo2.tum")
    b = tr.read_trajectory(tmp_path / "euroc" / "dingo2.csv")
    c = tr.read_trajectory(
        tmp_path / "kitti" / "dingo2.kitti", kitti_times=tmp_path / "kitti" / "dingo2.times.txt"
    )
    assert _same_poses(a.T, b.T) and _same_poses(a.T, c.T, atol=1e-9)
    assert np.allclose(a.stamps_s, b.stamps_s, atol=1e-6)


def test_positions_only_estimate_finds_its_clock_by_position_correlation(
    small_sim_run, tmp_path, capsys
):
    """A dense positions-only track (identity quaternions), no offset given, no mission: the
    angular-speed search is skipped, the position correlation finds the clock."""
    from dran_edge.formats.motive import read_motive_csv
    from dran_edge.formats.run_dir import read_mission

    run, _ = small_sim_run
    m = read_mission(run / "mission.yaml")
    take = read_motive_csv(run / "mocap.csv", up_axis=m.mocap_up_axis)
    b = take.bodies["dingo1"]
    shift_s = 1767225600.0 + 0.37
    T = b.T_world_marker[b.valid].copy()
    T[:, :3, :3] = np.eye(3)
    est = tmp_path / "positions.tum"
    tr.write_trajectory(est, take.time_s[b.valid] + shift_s, T, "tum")
    rc = main(
        [
            "eval",
            "traj",
            str(est),
            "--mocap",
            str(run / "mocap.csv"),
            "--body",
            "dingo1",
            "--json",
            "--plot",
            str(tmp_path / "p.png"),
        ]
    )
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    res = json.loads(cap.out)
    assert res["positions_only"] and res["ate_rot_rmse_deg"] is None
    assert res["time_offset_source"] == "estimated (position correlation)"
    assert res["time_offset_s"] == pytest.approx(-shift_s, abs=0.03)
    assert res["ate_rmse_m"] < 0.01
    assert (tmp_path / "p.png").stat().st_size > 1000


def test_replay_outputs_carry_the_robot_name(small_sim_run):
    run, _ = small_sim_run
    for name in ("dingo1", "dingo2", "dingo3"):
        d = run / "out" / name
        assert (d / f"{name}.tum").exists() and (d / f"{name}_init.tum").exists()
        assert not (d / "trajectory.tum").exists()


def test_kitti_without_stamps_needs_a_file_reference(tmp_path, capsys):
    stamps, T = _poses(5, 30)
    p = tmp_path / "k.txt"
    np.savetxt(p, T[:, :3, :].reshape(-1, 12))
    got = tr.read_trajectory(p)
    assert got.format == "kitti" and not got.has_stamps and np.allclose(got.stamps_s[1], 0.1)
    rc = main(["eval", "traj", str(p), "--mocap", str(tmp_path / "m.csv"), "--body", "x"])
    assert rc == 2 and "KITTI poses have no stamps" in capsys.readouterr().err
    rc = main(["eval", "traj", str(p), "--ref", str(p), "--json"])
    assert rc == 0 and json.loads(capsys.readouterr().out)["ate_rmse_m"] < 1e-9


def test_a_bag_topic_is_an_estimate_and_a_reference(small_sim_run, tmp_path, capsys):
    pytest.importorskip("rosbags", reason="bags are read with rosbags")
    from dran_edge.formats.run_bag import write_run_bags

    run, _ = small_sim_run
    (bag,), _ = write_run_bags(run, tmp_path / "bags", "mcap")
    est_t, ref_t = "/dingo1/vins_estimator/odometry", "/vrpn_client_node/dingo1/pose"
    rc = main(
        [
            "eval",
            "traj",
            str(bag),
            "--topic",
            est_t,
            "--ref",
            str(bag),
            "--ref-topic",
            ref_t,
            "--json",
        ]
    )
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    by_bag = json.loads(cap.out)
    assert by_bag["time_offset_source"] == "clock overlap" and by_bag["matched_poses"] > 100
    # the same poses as TUM files score the same
    for topic, name in ((est_t, "est.tum"), (ref_t, "ref.tum")):
        t = tr.read_bag_trajectory(bag, topic)
        tr.write_trajectory(tmp_path / name, t.stamps_s, t.T, "tum")
    assert (
        main(
            [
                "eval",
                "traj",
                str(tmp_path / "est.tum"),
                "--ref",
                str(tmp_path / "ref.tum"),
                "--json",
            ]
        )
        == 0
    )
    by_file = json.loads(capsys.readouterr().out)
    assert by_file["ate_rmse_m"] == pytest.approx(by_bag["ate_rmse_m"], abs=1e-7)
    rc = main(
        ["eval", "traj", str(bag), "--topic", "/nope", "--ref", str(bag), "--ref-topic", ref_t]
    )
    err = capsys.readouterr().err
    assert rc == 2 and "no topic /nope in the bag" in err and est_t in err
