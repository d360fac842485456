"""Replay end to end on a tiny simulated run: outputs, determinism, the golden summary, options,
recorded observations against re-detection."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from dran_edge.comms.ingest import encode_event
from dran_edge.perception.recorded import perceive_frames
from dran_edge.replay import run as rp
from dran_edge.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "data" / "golden" / "tiny_replay.json"


@pytest.fixture(scope="module")
def regen():
    import golden_helpers

    return golden_helpers


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, regen):
    """The tiny run, simulated and replayed once for the module."""
    d = tmp_path_factory.mktemp("tiny")
    report = regen.tiny_run(d)
    return d / "run", report


def test_outputs_exist_and_are_readable(tiny):
    from dran_edge.evaluation.score import read_rounds_csv
    from dran_edge.formats.tum import read_tum

    run, report = tiny
    for key in ("robots", "mission_s", "replay_wall_s", "rounds", "bytes_total"):
        assert key in report
    assert report["robots"] == 3 and report["mission_s"] == 30.0
    # the simulator recorded the robots' perception output: replay uses it, runs no perception
    assert report["frames_processed"] == 0
    assert report["observation_sources"] == {n: "recorded" for n in ("dingo1", "dingo2", "dingo3")}
    assert (run / "robots" / "dingo1" / "frames" / "frames.csv").exists()
    assert report["observations"] > 0
    assert report["ingest_rejected"] == {}
    rounds = read_rounds_csv(run / "out" / "rounds.csv")
    assert len(rounds["round"]) == report["rounds"]
    assert np.all(np.diff(rounds["bytes_total"]) >= 0)
    assert rounds["bytes_total"][-1] == report["bytes_total"]
    on_disk = json.loads((run / "out" / "report.json").read_text())
    assert on_disk["rounds"] == report["rounds"]
    for name in ("dingo1", "dingo2", "dingo3"):
        assert report["keyframes"][name] > 5
        stamps, T = read_tum(run / "out" / name / f"{name}.tum")
        assert len(stamps) == report["keyframes"][name]
        assert stamps[0] * 1e9 >= 1.7e18
        s0, _ = read_tum(run / "out" / name / f"{name}_init.tum")
        assert len(s0) == len(stamps)
        assert report["objects_known"][name] >= 1
    assert (run / "out" / "merged.g2o").exists()
    # with mocap, the replay report carries the evaluation's headline numbers
    for key in ("sr_ate", "sr_cost", "ate_m", "ce", "bias"):
        assert key in report
    assert 0 < report["ate_m"] < 0.2
    # β against the observations' information (dran.beta_scale): the default is in the window
    beta = report["beta_check"]
    assert beta["ratio"] == pytest.approx(beta["beta"] / beta["observation_information"])
    assert 0.01 <= beta["ratio"] <= 0.2 and "warning" not in beta and "warnings" not in report


def test_same_run_same_numbers(tiny, tmp_path):
    run, report = tiny
    again = tmp_path / "again"
    shutil.copytree(run, again, ignore=shutil.ignore_patterns("out", "eval"))
    report2 = rp.replay_run(again, rp.ReplayOptions(workers=2, settle_rounds=10)).report
    assert (
        rp.compare_summary(
            rp.golden_summary(report2), rp.golden_summary(report), rtol=0, atol=0, count_rtol=0
        )
        == []
    )
    # the sampled costs too (the pool's workers send their robots' state between rounds)
    assert report2["round_costs"] == report["round_costs"]
    a = (run / "out" / "rounds.csv").read_text()
    b = (again / "out" / "rounds.csv").read_text()
    assert a == b


def test_matches_the_golden_summary(regen, tmp_path):
    """The stored recorded run (robots' own observations, no frames) replays to the golden
    summary exactly, on any CPU architecture: every count and byte, and every float to the
    summary's rp.GOLDEN_SIGNIFICANT_DIGITS digits. The inputs are identical everywhere; the back
    end's floating point differs in the last bits between CPUs. Measured in the arm64 root
    (tools/arm64_check.sh, docs/notes/arm64-check.md): every count and byte equal, floats
    within 2.3e-14 relative."""
    if not GOLDEN.exists():
        pytest.fail(f"{GOLDEN} missing: run tools/regen_golden.py")
    report = regen.replay_stored(tmp_path)
    assert report["frames_processed"] == 0
    # recorded with the paper's β = 1, 3.5e-4 of its observations' information: said so
    assert report["beta_check"]["beta"] == 1.0 and "too weak" in report["beta_check"]["warning"]
    assert report["warnings"] == [report["beta_check"]["warning"]]
    golden = json.loads(GOLDEN.read_text())
    actual = rp.golden_summary(report)
    diffs = rp.compare_summary(actual, golden, rtol=0, atol=0, count_rtol=0)
    assert diffs == [], (
        "replay differs from the golden summary (tools/regen_golden.py "
        "regenerates it when the change is intended):\n" + "\n".join(diffs)
    )


def _observations(data: bytes) -> dict[tuple[int, int], np.ndarray]:
    """(stamp_ns, object_id) -> T_body_object of every observation record in ingest bytes."""
    from dran_edge.events import ObservationBatch
    from dran_edge.replay.robots import decode_ingest

    events, rejected = decode_ingest(data, "test")
    assert not rejected
    return {
        (o.stamp_ns, o.object_id): o.T_body_object
        for ev in events
        if isinstance(ev, ObservationBatch)
        for o in ev.observations
    }


@pytest.fixture(scope="module")
def redetected(tiny):
    """Robot name -> observations perception finds in the tiny run's frames on this machine."""
    run, _ = tiny
    out = {}
    for name in ("dingo1", "dingo2", "dingo3"):
        d = run / "robots" / name
        batches, frames = perceive_frames(d / "robot.yaml", run / "calib", name)
        records = [encode_event(b) for b in batches]
        assert frames == 60
        out[name] = _observations(b"".join(records))
    return out


def test_simulator_records_what_perception_detects(tiny, redetected):
    """The observations the simulator wrote into ingest.bin are, byte for byte, what the
    perception pipeline finds in the frames on this machine (as the daemon journals them)."""
    run, _ = tiny
    for name in ("dingo1", "dingo2", "dingo3"):
        obs = _observations((run / "robots" / name / "ingest.bin").read_bytes())
        again = redetected[name]
        assert sorted(obs) == sorted(again) and len(obs) > 0
        assert all(np.array_equal(obs[k], again[k]) for k in obs)


def test_redetect_runs_perception_again(tiny, tmp_path):
    """--redetect ignores the recorded observations and detects them from the frames: on the
    machine that recorded them, the replay is the same as the recorded one."""
    run, report = tiny
    again = tmp_path / "redetect"
    shutil.copytree(run, again, ignore=shutil.ignore_patterns("out", "eval"))
    rep = rp.replay_run(again, rp.ReplayOptions(workers=2, settle_rounds=10, redetect=True)).report
    assert rep["frames_processed"] == 3 * 60
    assert set(rep["observation_sources"].values()) == {"redetected"}
    a, b = rp.golden_summary(rep), rp.golden_summary(report)
    for key in ("frames_processed", "observation_sources"):
        a.pop(key), b.pop(key)
    assert rp.compare_summary(a, b, rtol=0, atol=0, count_rtol=0) == []


def test_redetect_without_frames_is_an_error(regen, tmp_path):
    run = tmp_path / "stored"
    shutil.copytree(regen.GOLDEN_RUN, run)
    with pytest.raises(InputError, match="--redetect: robot dingo1 has recorded observations"):
        rp.replay_run(run, rp.ReplayOptions(redetect=True, workers=1))


#: Re-detection on another machine against the stored (x86-64) recording. Measured in the arm64
#: root (tools/arm64_check.sh -> tools/redetect_diff.py, docs/benchmarks.md): 68 of the 70
#: observations found (2 marginal tags missed, 2.9 %), matched ones within 2.5 mm and 0.51 deg.
#: Limits: 5 % found on one side only; 1 cm (4x) and 1 deg (2x) for a tag seen on both sides.
REDETECT_MISSED_MAX = 0.05
REDETECT_T_MAX_M = 0.01
REDETECT_R_MAX_DEG = 1.0


def test_redetect_stays_within_tolerance_of_the_recording(regen, redetected):
    """Perception on this machine's frames against the observations the golden run recorded.

    The renderer (OpenCV warps, blur) and the detector (quad fit, sub-pixel refinement) use
    floating point whose last bits differ across CPUs and SIMD kernels, so a tag at the edge of
    detectability can appear on one machine and not on the other, and a detected tag's corners
    move by a fraction of a pixel. On aarch64 (arm64 root under qemu) 2 of the 70 observations
    were missed and the others moved by up to 2.5 mm and 0.51 degrees (the rendered frames
    themselves differ: OpenCV's warps and blur). Tolerances above, on this machine's frames and
    perception against the x86-64 recording."""
    one_side, total = 0, 0
    for name in ("dingo1", "dingo2", "dingo3"):
        stored = _observations((regen.GOLDEN_RUN / "robots" / name / "ingest.bin").read_bytes())
        st = regen.compare(stored, redetected[name])
        assert st["max_translation_m"] < REDETECT_T_MAX_M, (name, st)
        assert st["max_rotation_deg"] < REDETECT_R_MAX_DEG, (name, st)
        one_side += st["only_recorded"] + st["only_here"]
        total += st["recorded"]
    assert total > 0 and one_side <= REDETECT_MISSED_MAX * total, (one_side, total)


def test_compare_summary_tolerance_and_ignore_list():
    gold = {"a": 1.0, "b": {"c": 2}, "d": None}
    assert rp.compare_summary({"a": 1.0000001, "b": {"c": 2}, "d": None}, gold) == []
    assert rp.compare_summary({"a": 1.1, "b": {"c": 2}, "d": None}, gold) == [
        "a: 1.1 != golden 1.0 (rtol 0.001)"
    ]
    assert rp.compare_summary({"a": 1.0, "b": {"c": 3}}, gold) == [
        "b.c: 3 != golden 2 (count rtol 0.02)",
        "d: missing",
    ]
    assert rp.compare_summary({"bytes_total": 1010}, {"bytes_total": 1000}) == []
    assert rp.compare_summary({"rounds": 71}, {"rounds": 70}) == ["rounds: 71 != golden 70"]
    summary = rp.golden_summary({"rounds": 3, "replay_wall_s": 9.9, "realtime_factor": 2.0})
    assert not set(rp.WALL_CLOCK_FIELDS) & set(summary)


def test_loss_reduces_what_arrives(tiny, tmp_path):
    run, report = tiny
    lossy = tmp_path / "lossy"
    shutil.copytree(run, lossy, ignore=shutil.ignore_patterns("out", "eval"))
    rep = rp.replay_run(
        lossy, rp.ReplayOptions(loss=0.5, settle_rounds=2, evaluate=False, workers=1)
    ).report
    assert report["bytes_total"] > 0
    assert sum(rep["datagrams_lost"].values()) > 0


def test_options_are_validated():
    with pytest.raises(InputError, match="transport"):
        rp.ReplayOptions(transport="tcp")
    with pytest.raises(InputError, match="loss"):
        rp.ReplayOptions(loss=1.5)
    with pytest.raises(InputError, match="bus"):
        rp.ReplayOptions(transport="udp", loss=0.1)
    assert rp.PartitionSpec.parse("3,4:20:40") == rp.PartitionSpec((3, 4), 20.0, 40.0)
    for bad in ("3:40:20", "x:1:2", "3:1"):
        with pytest.raises(InputError, match="--partition"):
            rp.PartitionSpec.parse(bad)


def test_missing_run_parts_are_named(tmp_path):
    with pytest.raises(InputError, match="run directory"):
        rp.replay_run(tmp_path / "nope")
    (tmp_path / "mission.yaml").write_text("format: dran-edge-run/1\n")
    with pytest.raises(InputError, match=r"mission.yaml.*required key is missing"):
        rp.replay_run(tmp_path)


def test_udp_loopback_gives_the_bus_numbers(tiny, tmp_path):
    """--transport udp: real RADIO/DISH sockets on 127.0.0.1, same rounds.csv as the bus."""
    from dran_edge.errors import DependencyError

    run, report = tiny
    udp = tmp_path / "udp"
    shutil.copytree(run, udp, ignore=shutil.ignore_patterns("out", "eval"))
    try:
        rep = rp.replay_run(
            udp, rp.ReplayOptions(transport="udp", settle_rounds=10, evaluate=False, workers=1)
        ).report
    except DependencyError as exc:
        pytest.skip(f"no draft-enabled ZeroMQ here: {exc}")
    assert rep["transport"] == "udp"
    assert rep["bytes_total"] == report["bytes_total"]
    assert (udp / "out" / "rounds.csv").read_text() == (run / "out" / "rounds.csv").read_text()


def test_delta_layout_default_saves_bytes_at_the_same_accuracy(tiny, tmp_path):
    """comms.delta_every (default 20) against whole values (0) on the same run: fewer bytes,
    the same trajectories to the quantisation's order (the UDP test above runs the default)."""
    run, report = tiny
    plain = tmp_path / "plain"
    shutil.copytree(run, plain, ignore=shutil.ignore_patterns("eval"))
    shutil.rmtree(plain / "out")
    for cfg in (plain / "robots").glob("*/robot.yaml"):
        text = cfg.read_text()
        assert "  delta_every: 20\n" in text
        cfg.write_text(text.replace("  delta_every: 20\n", "  delta_every: 0\n"))
    rep = rp.replay_run(plain, rp.ReplayOptions(settle_rounds=10, evaluate=False, workers=1)).report
    assert 0 < report["bytes_total"] < 0.8 * rep["bytes_total"]
    assert rep["rounds"] == report["rounds"]
    for robot in (run / "out").iterdir():
        if (robot / f"{robot.name}.tum").exists():
            a = np.loadtxt(robot / f"{robot.name}.tum")
            b = np.loadtxt(plain / "out" / robot.name / f"{robot.name}.tum")
            assert a.shape == b.shape and np.abs(a[:, 1:4] - b[:, 1:4]).max() < 0.01  # metres
