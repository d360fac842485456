"""dran-edge import-bag on real bag files written by the rosbags writers (ROS 1, ROS 2 sqlite3,
ROS 2 MCAP): a simulated run exported as bags, imported and replayed gives the original's
numbers; malformed bags are clear errors or counted skips, never tracebacks."""

from __future__ import annotations

import shutil

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags", reason="the bag tests need rosbags (pip install '.[test]')")

from conftest import SMALL_REPLAY  # noqa: E402

from dran_edge.cli.app import main  # noqa: E402
from dran_edge.errors import DranError, InputError  # noqa: E402
from dran_edge.formats import run_bag  # noqa: E402
from dran_edge.formats.bag_map import read_mapping  # noqa: E402
from dran_edge.formats.bags import import_bags  # noqa: E402


def _write_mapping(path: Path, mapping: dict) -> Path:
    path.write_text(yaml.safe_dump(mapping, sort_keys=False), encoding="utf-8")
    return path


# ------------------------------------------------------------------------------ round trip
_SLOW = pytest.mark.slow


@pytest.mark.parametrize(
    "fmt,per_robot,replay",
    [
        ("ros1", True, True),
        ("sqlite3", False, False),
        ("mcap", False, False),
        pytest.param("sqlite3", False, True, marks=_SLOW),
        pytest.param("mcap", False, True, marks=_SLOW),
    ],
    ids=[
        "ros1-bag-per-robot-replay",
        "ros2-db3-namespaced-files",
        "ros2-mcap-namespaced-files",
        "ros2-db3-namespaced-replay",
        "ros2-mcap-namespaced-replay",
    ],
)
def test_bags_of_a_simulated_run_import_and_replay_to_the_same_numbers(
    small_sim_run, tmp_path, fmt, per_robot, replay, capsys
):
    """Every format gives the original's replay inputs (ingest bytes, frames, calibration,
    mocap); the replay itself is deterministic on its inputs (tests/test_replay.py), and is run
    here for the ROS 1 bags (all formats with -m slow)."""
    from dran_edge.formats.motive import read_motive_csv
    from dran_edge.replay.run import ReplayOptions, compare_summary, golden_summary, replay_run
    from dran_edge.formats.run_dir import open_run

    src, report = small_sim_run
    paths, mapping = run_bag.write_run_bags(src, tmp_path / "bags", fmt, per_robot=per_robot)
    assert all(p.exists() for p in paths)
    mp = _write_mapping(tmp_path / "map.yaml", mapping)
    out = tmp_path / "imported"
    rc = main(["import-bag", *map(str, paths), "--map", str(mp), "--out", str(out)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "skipped: none" in cap.out and "import-bag:" in cap.err  # progress on stderr
    for name in ("dingo1", "dingo2", "dingo3"):
        # the records the daemon consumes are byte for byte the original's, frames too; the
        # original's recorded perception output is not a ROS topic: the bags carry its frames
        assert (out / "robots" / name / "ingest.bin").read_bytes() == _without_observations(
            (src / "robots" / name / "ingest.bin").read_bytes()
        )
        a, b = src / "robots" / name / "frames", out / "robots" / name / "frames"
        assert (a / "frames.csv").read_text() == (b / "frames.csv").read_text()
        for f in sorted((a / "colour").iterdir()) + sorted((a / "depth").iterdir()):
            assert f.read_bytes() == (b / f.parent.name / f.name).read_bytes()
        cam_a = yaml.safe_load((src / "calib" / "cameras" / f"{name}.yaml").read_text())
        cam_b = yaml.safe_load((out / "calib" / "cameras" / f"{name}.yaml").read_text())
        for key in ("width", "height", "intrinsics", "distortion", "T_body_camera"):
            assert cam_a[key] == cam_b[key], key
    ma, mb = open_run(src).mission, open_run(out).mission
    assert (ma.start_ns, ma.duration_s, ma.comm_graph, ma.mocap_start_ns) == (
        mb.start_ns,
        mb.duration_s,
        mb.comm_graph,
        mb.mocap_start_ns,
    )
    ta = read_motive_csv(src / "mocap.csv", up_axis=ma.mocap_up_axis)
    tb = read_motive_csv(out / "mocap.csv", up_axis=mb.mocap_up_axis)
    assert np.array_equal(ta.time_s, tb.time_s) and list(ta.bodies) == list(tb.bodies)
    for body in ta.bodies:
        va, vb = ta.bodies[body].valid, tb.bodies[body].valid
        assert np.array_equal(va, vb)
        assert np.allclose(
            ta.bodies[body].T_world_marker[va], tb.bodies[body].T_world_marker[vb], atol=2e-6
        )
    if not replay:
        return
    # both replays detect the tags in the same frames (the original's recorded ones left aside)
    original = tmp_path / "original"
    shutil.copytree(src, original, ignore=shutil.ignore_patterns("out", "eval"))
    report = replay_run(original, ReplayOptions(**SMALL_REPLAY, redetect=True)).report
    rep = replay_run(out, ReplayOptions(**SMALL_REPLAY)).report
    assert rep["observations"] == report["observations"] > 0
    assert rep["frames_processed"] == report["frames_processed"] > 0
    assert abs(rep["sr_ate"] - report["sr_ate"]) < 1e-6
    assert (
        compare_summary(
            golden_summary(rep), golden_summary(report), rtol=0, atol=1e-6, count_rtol=0
        )
        == []
    )


def _without_observations(data: bytes) -> bytes:
    from dran_edge.comms import ingest

    return b"".join(
        r.raw
        for r in ingest.iter_records(data)
        if not isinstance(r, Exception) and r.kind != ingest.KIND_OBSERVATIONS
    )


def test_raw_images_become_the_same_pngs(small_sim_run, tmp_path):
    """sensor_msgs/Image (mono8, 16UC1) is encoded losslessly: the pixels are the original's."""
    import cv2

    src, _ = small_sim_run
    paths, mapping = run_bag.write_run_bags(
        src, tmp_path / "bags", "ros1", per_robot=True, raw_images=True
    )
    mapping["robots"] = [r for r in mapping["robots"] if r["name"] == "dingo2"]
    mapping["comm_graph"] = []
    del mapping["mocap"]
    out = tmp_path / "imported"
    import_bags(
        [p for p in paths if p.stem == "dingo2"],
        read_mapping(_write_mapping(tmp_path / "map.yaml", mapping)),
        out,
    )
    a, b = src / "robots" / "dingo2" / "frames", out / "robots" / "dingo2" / "frames"
    assert (a / "frames.csv").read_text() == (b / "frames.csv").read_text()
    for sub in ("colour", "depth"):
        files = sorted((a / sub).iterdir())
        assert len(files) == len(list((b / sub).iterdir())) > 5
        for f in files[::7]:
            x = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            y = cv2.imread(str(b / sub / f.name), cv2.IMREAD_UNCHANGED)
            assert x.dtype == y.dtype and np.array_equal(x, y)
    cam = yaml.safe_load((out / "calib" / "cameras" / "dingo2.yaml").read_text())
    orig = yaml.safe_load((src / "calib" / "cameras" / "dingo2.yaml").read_text())
    assert cam["intrinsics"] == orig["intrinsics"] and cam["T_body_camera"] == orig["T_body_camera"]


# ------------------------------------------------------------------------------ small bags
def _bag(tmp_path: Path, fmt: str, rows: list[tuple[str, str, int, object]], msgs) -> Path:
    path = tmp_path / ("b.bag" if fmt == "ros1" else "b")
    out = run_bag._BagOut(path, fmt, msgs.ts)
    for topic, typ, t, m in sorted(rows, key=lambda r: r[2]):
        out.write(topic, typ, t, m)
    out.close()
    return path


T0 = 1_767_225_600_000_000_000
ODOM = "nav_msgs/msg/Odometry"


def _odometry_rows(msgs, n=20, stamps=None):
    stamps = stamps if stamps is not None else [T0 + k * 100_000_000 for k in range(n)]
    return [
        ("/odom", ODOM, s, msgs.odometry(s, (0.1 * k, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)))
        for k, s in enumerate(stamps)
    ]


def _mapping(tmp_path: Path, **robot) -> Path:
    r = {"id": 1, "name": "r1", "odometry": "/odom"} | robot
    return _write_mapping(tmp_path / "map.yaml", {"format": "dran-edge-bag-map/1", "robots": [r]})


@pytest.mark.parametrize("fmt", run_bag.FORMATS)
def test_a_mapped_topic_missing_from_the_bag_is_named(tmp_path, fmt, capsys):
    msgs = run_bag._Msgs(run_bag._typestore(fmt))
    bag = _bag(tmp_path, fmt, _odometry_rows(msgs), msgs)
    mp = _mapping(tmp_path, keyframes="/vins_estimator/keyframe_pose")
    rc = main(["import-bag", str(bag), "--map", str(mp), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert "/vins_estimator/keyframe_pose" in err and "r1 keyframes" in err


def test_a_topic_of_the_wrong_message_type_is_named(tmp_path, capsys):
    msgs = run_bag._Msgs(run_bag._typestore("ros1"))
    rows = [
        (
            "/odom",
            "geometry_msgs/msg/PoseStamped",
            T0 + k,
            msgs.pose_stamped(T0 + k, (0, 0, 0, 0, 0, 0, 1)),
        )
        for k in range(1, 4)
    ]
    bag = _bag(tmp_path, "ros1", rows, msgs)
    rc = main(
        ["import-bag", str(bag), "--map", str(_mapping(tmp_path)), "--out", str(tmp_path / "o")]
    )
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert (
        "/odom" in err and "geometry_msgs/msg/PoseStamped" in err and "nav_msgs/msg/Odometry" in err
    )


def test_images_in_an_unsupported_encoding_are_counted_and_skipped(tmp_path):
    msgs = run_bag._Msgs(run_bag._typestore("sqlite3"))
    rows = _odometry_rows(msgs)
    for k in range(6):
        s = T0 + k * 300_000_000
        img = np.zeros((8, 16, 2), np.uint8)  # yuv422: 2 bytes per pixel
        m = msgs.image(s, img.reshape(8, 32), "yuv422")
        rows.append(("/cam", "sensor_msgs/msg/Image", s, m))
    s = T0 + 2_000_000_000
    rows.append(
        ("/cam", "sensor_msgs/msg/Image", s, msgs.image(s, np.zeros((8, 16), np.uint8), "mono8"))
    )
    bag = _bag(tmp_path, "sqlite3", rows, msgs)
    tags = tmp_path / "calib"
    tags.mkdir()
    (tags / "tags.yaml").write_text("format: dran-edge-tags/1\nfamily: tag36h11\nobjects: []\n")
    mp = _mapping(
        tmp_path,
        image={"topic": "/cam", "T_body_camera": {"xyz": [0, 0, 0], "quat_xyzw": [0, 0, 0, 1]}},
    )
    with pytest.raises(InputError, match="no camera_info"):
        import_bags([bag], read_mapping(mp), tmp_path / "o1")
    # without camera_info or a camera file the frames cannot be used: give the camera file
    (tags / "cameras").mkdir()
    (tags / "cameras" / "r1.yaml").write_text(
        yaml.safe_dump(
            {
                "format": "dran-edge-camera/1",
                "robot": "r1",
                "width": 16,
                "height": 16,
                "intrinsics": {"fx": 10.0, "fy": 10.0, "cx": 8.0, "cy": 8.0},
                "T_body_camera": {"xyz": [0, 0, 0], "quat_xyzw": [0, 0, 0, 1]},
            }
        )
    )
    m = yaml.safe_load(mp.read_text())
    m["calib"] = str(tags)
    summary = import_bags([bag], read_mapping(_write_mapping(mp, m)), tmp_path / "o3")
    r = summary["robots"]["r1"]
    assert r["skipped"] == {"unsupported_encoding": 6}
    assert "yuv422" in r["first_skip"]["unsupported_encoding"]
    assert r["written"]["frames"] == 1 and r["written"]["odometry"] == 20
    assert json.loads((tmp_path / "o3" / "import.json").read_text())["robots"]["r1"] == r


def test_non_monotonic_stamps_are_counted_and_skipped(tmp_path):
    from dran_edge.comms import ingest

    msgs = run_bag._Msgs(run_bag._typestore("mcap"))
    stamps = [T0 + k * 100_000_000 for k in range(10)]
    stamps[5] = stamps[2]  # a stamp going backwards
    stamps[6] = stamps[6 - 1]  # and a repeated one
    rows = _odometry_rows(msgs, stamps=stamps)
    for i, (t, ty, s, m) in enumerate(rows):  # receive times increase: bag order = list order
        rows[i] = (t, ty, T0 + i * 100_000_000 + 1, m)
    bag = _bag(tmp_path, "mcap", rows, msgs)
    summary = import_bags([bag], read_mapping(_mapping(tmp_path)), tmp_path / "o")
    r = summary["robots"]["r1"]
    assert r["skipped"] == {"non_monotonic:odometry": 2}
    assert r["written"]["odometry"] == 8 and r["written"]["keyframes"] == 2  # every 5th
    recs = list(ingest.iter_records((tmp_path / "o" / "robots" / "r1" / "ingest.bin").read_bytes()))
    got = [x.event.stamp_ns for x in recs if x.kind == ingest.KIND_ODOMETRY]
    assert got == sorted(set(stamps))[: len(got)] and np.all(np.diff(got) > 0)


def test_loops_resets_and_clock_offsets(tmp_path):
    """VINS loop edges and the PoseWithCovarianceStamped pair form; a Bool reset 1 ns after the
    last odometry; a robot clock offset shifts every stamp; records come out in stamp order
    although loops arrive late."""
    from dran_edge.comms import ingest

    msgs = run_bag._Msgs(run_bag._typestore("ros1"))
    rows = _odometry_rows(msgs)
    ts = msgs.ts.types
    rows.append(
        (
            "/loop",
            ODOM,
            T0 + 1_900_000_000,
            msgs.odometry(
                T0 + 1_500_000_000,
                (0.5, 0, 0, 0, 0, 0, 1),
                twist=((T0 + 200_000_000) / 1e9, 0, 0, 42.0, 0, 0),
            ),
        )
    )
    rows.append(
        ("/restart", "std_msgs/msg/Bool", T0 + 1_000_000_001, ts["std_msgs/msg/Bool"](data=True))
    )

    def pwcs(s, v):
        return ts["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=msgs.header(s),
            pose=ts["geometry_msgs/msg/PoseWithCovariance"](
                pose=msgs.pose(v), covariance=np.zeros(36)
            ),
        )

    rows.append(
        (
            "/pair/old",
            "geometry_msgs/msg/PoseWithCovarianceStamped",
            T0 + 1_950_000_000,
            pwcs(T0 + 300_000_000, (0, 0, 0, 0, 0, 0, 1)),
        )
    )
    rows.append(
        (
            "/pair/cur",
            "geometry_msgs/msg/PoseWithCovarianceStamped",
            T0 + 1_950_000_001,
            pwcs(T0 + 1_600_000_000, (0.7, 0, 0, 0, 0, 0, 1)),
        )
    )
    bag = _bag(tmp_path, "ros1", rows, msgs)
    off = -1_000
    for form, loops in (
        ("vins", {"topic": "/loop"}),
        ("pose_pair", {"form": "pose_pair", "old": "/pair/old", "cur": "/pair/cur"}),
    ):
        mp = _mapping(tmp_path, loops=loops, reset="/restart", clock_offset_ns=off)
        summary = import_bags([bag], read_mapping(mp), tmp_path / form)
        assert summary["robots"]["r1"]["written"]["loops"] == 1
        data = (tmp_path / form / "robots" / "r1" / "ingest.bin").read_bytes()
        recs = [r.event for r in ingest.iter_records(data)]
        loop = next(e for e in recs if type(e).__name__ == "LoopClosure")
        if form == "vins":
            # the old stamp travels as float seconds (docs/vins-mono.md): ~0.2 us resolution
            assert abs(loop.stamp_old_ns - (T0 + 200_000_000 + off)) < 1000
            assert (loop.stamp_cur_ns, loop.inliers) == (T0 + 1_500_000_000 + off, 42)
        else:
            assert (loop.stamp_old_ns, loop.stamp_cur_ns) == (
                T0 + 300_000_000 + off,
                T0 + 1_600_000_000 + off,
            )
        reset = next(e for e in recs if type(e).__name__ == "VioReset")
        assert reset.stamp_ns == T0 + 1_000_000_000 + off + 1
        stamps = [getattr(e, "stamp_ns", getattr(e, "stamp_cur_ns", 0)) for e in recs]
        assert stamps == sorted(stamps)
        mission = yaml.safe_load((tmp_path / form / "mission.yaml").read_text())
        assert mission["start_ns"] == T0 + off


def test_not_a_bag_and_a_bad_mapping_are_clear_errors(tmp_path, capsys):
    junk = tmp_path / "junk.bag"
    junk.write_bytes(b"#ROSBAG V2.0\n" + b"\x00" * 50)
    mp = _mapping(tmp_path)
    rc = main(["import-bag", str(junk), "--map", str(mp), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "junk.bag" in err and "Traceback" not in err
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: dran-edge-bag-map/1\nrobots:\n  - {id: 1, name: r1, odom: /x}\n")
    with pytest.raises(InputError, match=r"bad.yaml:3: robots\[0\].odom: unknown key"):
        read_mapping(bad)
    rc = main(
        ["import-bag", str(tmp_path / "nope.bag"), "--map", str(mp), "--out", str(tmp_path / "o2")]
    )
    assert rc == 2 and "nope.bag" in capsys.readouterr().err
    assert issubclass(InputError, DranError)


def test_list_shows_topics(tmp_path, capsys):
    msgs = run_bag._Msgs(run_bag._typestore("mcap"))
    bag = _bag(tmp_path, "mcap", _odometry_rows(msgs, n=3), msgs)
    assert main(["import-bag", "--list", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "/odom" in out and "nav_msgs/msg/Odometry" in out and out.rstrip().endswith("3")


@pytest.mark.parametrize("fmt", run_bag.FORMATS)
def test_max_rate_keeps_colour_depth_pairs_and_peeks_stamps(tmp_path, fmt):
    """max_rate_hz drops frames before decoding them (the stamp is read from the serialised
    header) and keeps colour and depth of a stamp together, whichever arrives first."""
    from dran_edge.formats.bags import peek_header_stamp_ns

    msgs = run_bag._Msgs(run_bag._typestore(fmt))
    rows = _odometry_rows(msgs, n=25)
    for k in range(25):  # 10 Hz frames; depth arrives before colour for odd k
        s = T0 + k * 100_000_000 + 7
        c = msgs.image(s, np.full((16, 16), k, np.uint8), "mono8")
        d = msgs.image(s, np.full((16, 16), 1000 + k, np.uint16), "16UC1")
        rows.append(("/cam", "sensor_msgs/msg/Image", s + (2 if k % 2 else 1), c))
        rows.append(("/depth", "sensor_msgs/msg/Image", s + (1 if k % 2 else 2), d))
    ts = msgs.ts
    raw = (ts.serialize_ros1 if fmt == "ros1" else ts.serialize_cdr)(
        rows[-1][3], "sensor_msgs/msg/Image"
    )
    assert peek_header_stamp_ns(raw, fmt != "ros1") == T0 + 24 * 100_000_000 + 7
    bag = _bag(tmp_path, fmt, rows, msgs)
    calib = tmp_path / "calib"
    (calib / "cameras").mkdir(parents=True)
    (calib / "tags.yaml").write_text("format: dran-edge-tags/1\nfamily: tag36h11\nobjects: []\n")
    (calib / "cameras" / "r1.yaml").write_text(
        yaml.safe_dump(
            {
                "format": "dran-edge-camera/1",
                "robot": "r1",
                "width": 16,
                "height": 16,
                "intrinsics": {"fx": 10.0, "fy": 10.0, "cx": 8.0, "cy": 8.0},
                "T_body_camera": {"xyz": [0, 0, 0], "quat_xyzw": [0, 0, 0, 1]},
            }
        )
    )
    m = {
        "format": "dran-edge-bag-map/1",
        "calib": str(calib),
        "robots": [
            {
                "id": 1,
                "name": "r1",
                "odometry": "/odom",
                "image": {"topic": "/cam", "depth": "/depth", "max_rate_hz": 3.0},
            }
        ],
    }
    s = import_bags([bag], read_mapping(_write_mapping(tmp_path / "m.yaml", m)), tmp_path / "o")
    r = s["robots"]["r1"]
    # at most 3 per second: frames at least 1/3 s apart, i.e. every 4th of the 10 Hz stream
    assert r["written"]["frames"] == 7 and r["written"]["frames_dropped_by_rate"] == 18
    assert r["skipped"] == {}
    import cv2

    lines = (tmp_path / "o" / "robots" / "r1" / "frames" / "frames.csv").read_text().split()[1:]
    ks = []
    for line in lines:
        stamp, c, d, _ = line.split(",")
        k = (int(stamp) - T0 - 7) // 100_000_000
        ks.append(k)
        f = tmp_path / "o" / "robots" / "r1" / "frames"
        assert cv2.imread(str(f / c), cv2.IMREAD_UNCHANGED)[0, 0] == k
        assert cv2.imread(str(f / d), cv2.IMREAD_UNCHANGED)[0, 0] == 1000 + k
    assert ks == list(range(0, 25, 4))
