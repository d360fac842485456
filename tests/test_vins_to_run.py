"""dran-edge import-vins (dran_edge/formats/vins_csv.py): VINS-Mono CSVs (+ pose_graph.txt, images) -> a run directory."""

from __future__ import annotations


import numpy as np
import pytest

from dran_edge import geometry as geo
from dran_edge.formats import run_dir as rd
from dran_edge.sim import mission as sim


@pytest.fixture(scope="module")
def tool():
    """``dran-edge import-vins`` as the tests call it: ``tool.main(argv) -> exit code``."""
    from types import SimpleNamespace

    from dran_edge.cli.app import main

    return SimpleNamespace(main=lambda argv: main(["import-vins", *argv]))


@pytest.fixture(scope="module")
def robot():
    p = sim.SimParams(robots=1, objects=4, duration_s=40.0, arena_m=6.0, seed=5, resets_per_min=0)
    return sim.generate_mission(p).robots[0]


def _vins_rows(stamps, T, velocity=True) -> str:
    """Lines as VINS-Mono writes them: ns stamp, p, q (w first)[, v], trailing comma."""
    a = geo.se3_to_xyz_quat_wxyz(T)
    out = []
    for s, row in zip(stamps.tolist(), a):
        cells = [str(s)] + [f"{v:.6f}" for v in row] + (["0.1", "0.0", "0.0"] if velocity else [])
        out.append(",".join(cells) + ",")
    return "\n".join(out) + "\n"


def test_odometry_keyframes_and_loops_round_trip(tmp_path, tool, robot):
    from dran_edge.comms.ingest import IngestDecodeError, iter_records

    from dran_edge.events import Keyframe, LoopClosure, OdometrySample, VioReset

    stamps, T = robot.odom_stamps_ns, robot.T_odom_body
    # a 3 s image gap: VINS restarts; the converter must mark a new segment
    cut = len(stamps) // 2
    stamps = np.r_[stamps[:cut], stamps[cut:] + 3_000_000_000]
    (tmp_path / "no_loop.csv").write_text(_vins_rows(stamps, T))
    kf = robot.keyframes
    (tmp_path / "loop.csv").write_text(_vins_rows(stamps[kf], T[kf], velocity=False))
    # pose_graph.txt: one loop between keyframe 3 and keyframe 40 (index = keyframe number)
    lines = []
    T_rel = geo.se3_from_rt(geo.so3_exp(np.r_[0, 0, 0.1]), np.r_[0.3, -0.1, 0.0])
    for i, k in enumerate(kf[:45].tolist()):
        loop_index, info = -1, ["0"] * 8
        if i == 40:
            loop_index = 3
            a = geo.se3_to_xyz_quat_wxyz(T_rel)
            info = [f"{v:.9f}" for v in a] + ["5.7"]
        vals = (
            [str(i), f"{stamps[k] / 1e9:.9f}"]
            + ["0"] * 6
            + ["1", "0", "0", "0"] * 2
            + [str(loop_index)]
            + info
            + ["100"]
        )
        lines.append(" ".join(vals))
    (tmp_path / "pose_graph.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / "run"
    rc = tool.main(
        [
            str(out),
            "--name",
            "dingo1",
            "--id",
            "1",
            "--no-loop-csv",
            str(tmp_path / "no_loop.csv"),
            "--loop-csv",
            str(tmp_path / "loop.csv"),
            "--pose-graph",
            str(tmp_path / "pose_graph.txt"),
        ]
    )
    assert rc == 0
    run = rd.open_run(out)
    assert run.load_config("dingo1").robot.id == 1
    items = list(iter_records(run.read_ingest("dingo1")))
    assert not [x for x in items if isinstance(x, IngestDecodeError)]
    ev = [x.event for x in items]
    odo = [e for e in ev if isinstance(e, OdometrySample)]
    assert len(odo) == len(stamps)
    np.testing.assert_allclose(
        np.stack([e.T_odom_body for e in odo])[:, :3, 3], T[:, :3, 3], atol=1e-6
    )
    resets = [e for e in ev if isinstance(e, VioReset)]
    assert [r.stamp_ns for r in resets] == [int(stamps[cut])]
    kfs = [e for e in ev if isinstance(e, Keyframe)]
    assert len(kfs) == len(kf)
    loops = [e for e in ev if isinstance(e, LoopClosure)]
    assert len(loops) == 1
    assert (loops[0].stamp_old_ns, loops[0].stamp_cur_ns) == (
        int(stamps[kf[3]]),
        int(stamps[kf[40]]),
    )
    np.testing.assert_allclose(loops[0].T_old_cur, T_rel, atol=1e-6)
    m = run.mission
    assert m.start_ns == int(stamps[0])
    assert m.duration_s == pytest.approx((stamps[-1] - stamps[0]) / 1e9)


def test_second_robot_extends_the_run_and_links_it(tmp_path, tool, robot):
    csv = tmp_path / "a.csv"
    csv.write_text(_vins_rows(robot.odom_stamps_ns, robot.T_odom_body))
    out = tmp_path / "run"
    assert tool.main([str(out), "--name", "a", "--id", "1", "--no-loop-csv", str(csv)]) == 0
    assert (
        tool.main(
            [str(out), "--name", "b", "--id", "2", "--no-loop-csv", str(csv), "--neighbours", "1"]
        )
        == 0
    )
    run = rd.open_run(out)
    assert [r.name for r in run.mission.robots] == ["a", "b"]
    assert run.mission.comm_graph == ((1, 2),)
    assert [n.id for n in run.load_config("b").neighbours] == [1]
    # the same id twice is refused
    assert tool.main([str(out), "--name", "c", "--id", "2", "--no-loop-csv", str(csv)]) == 2


def test_images_become_a_frames_folder(tmp_path, tool, robot):
    import cv2
    from dran_edge.perception.sources import RecordedFramesSource

    csv = tmp_path / "a.csv"
    csv.write_text(_vins_rows(robot.odom_stamps_ns, robot.T_odom_body))
    imgs = tmp_path / "cam0"
    imgs.mkdir()
    stamps = robot.odom_stamps_ns[::20][:4]
    for s in stamps.tolist():
        cv2.imwrite(str(imgs / f"{s}.png"), np.full((48, 64), 128, np.uint8))
    out = tmp_path / "run"
    assert (
        tool.main(
            [str(out), "--name", "a", "--id", "1", "--no-loop-csv", str(csv), "--images", str(imgs)]
        )
        == 0
    )
    frames = list(RecordedFramesSource(out / "robots" / "a" / "frames"))
    assert [f.stamp_ns for f in frames] == stamps.tolist()
    assert frames[0].colour.shape == (48, 64, 3)


def test_malformed_csv_names_file_and_line(tmp_path, tool, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("1000,0,0,0,1,0,0,0,0,0,0,\n2000,0,0,0,0.5,0,0,0,0,0,0,\n")
    assert (
        tool.main([str(tmp_path / "r"), "--name", "a", "--id", "1", "--no-loop-csv", str(bad)]) == 2
    )
    assert "bad.csv:2: expected a unit quaternion" in capsys.readouterr().err
    bad.write_text("1000,0,0,0,1,0,0,0,\n")
    assert (
        tool.main([str(tmp_path / "r"), "--name", "a", "--id", "1", "--no-loop-csv", str(bad)]) == 2
    )
    assert "bad.csv:1: expected at least 11" in capsys.readouterr().err
    bad.write_text("abc,0,0,0,1,0,0,0,0,0,0,\n")
    assert (
        tool.main([str(tmp_path / "r"), "--name", "a", "--id", "1", "--no-loop-csv", str(bad)]) == 2
    )
    assert "bad.csv:1: expected a timestamp" in capsys.readouterr().err
