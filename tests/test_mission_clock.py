"""Replay checks mission.yaml's clock against the recorded stamps before it starts: a start_ns
that would make it tick through years of empty rounds is an error at once, one that is merely
off (100 s early, a wrong mocap.start_ns) is a warning."""

from __future__ import annotations

import pytest
import yaml

from dran_edge.formats import run_dir as rd
from dran_edge.errors import InputError

T0 = 1_767_225_600_000_000_000
S = 1_000_000_000


def _mission(start_ns, duration_s=20.0, mocap_start_ns=None):
    robot = rd.RunRobot(1, "r1", None, None, None)
    return rd.Mission("f", start_ns, duration_s, (robot,), (), (), "mocap.csv", mocap_start_ns)


@pytest.mark.parametrize("period_s", [0.5, 0.1])
def test_clock_cases(period_s):
    span = (T0, T0 + 20 * S)
    assert rd.check_mission_clock(_mission(T0), span, period_s) == []
    assert rd.check_mission_clock(_mission(T0 + S // 2), span, period_s) == []  # within 2 s
    with pytest.raises(InputError, match="start_ns 1 is 1.77e[+]09 s before the first"):
        rd.check_mission_clock(_mission(1), span, period_s)
    with pytest.raises(InputError, match="after every recorded stamp"):
        rd.check_mission_clock(_mission(T0 + 30 * S), span, period_s)
    (w, over) = rd.check_mission_clock(_mission(T0 - 100 * S), span, period_s)
    assert "100.0 s before the first recorded stamp" in w
    assert f"{int(100 / period_s)} rounds with no input" in w and str(T0) in w
    assert "records run 120.0 s from start_ns, but duration_s is 20" in over
    (w,) = rd.check_mission_clock(_mission(T0 + 5 * S, duration_s=15.0), span, period_s)
    assert "5.0 s after the first recorded stamp" in w
    (w,) = rd.check_mission_clock(_mission(T0, duration_s=100.0), span, period_s)
    assert "records end 20.0 s after start_ns" in w
    (w,) = rd.check_mission_clock(_mission(T0, mocap_start_ns=1), span, period_s)
    assert "mocap.start_ns is -1.77e+09 s from the first recorded stamp" in w
    assert rd.check_mission_clock(_mission(T0, mocap_start_ns=T0 + 30 * S), span, period_s) == []
    assert rd.check_mission_clock(_mission(1), None, period_s) == []  # nothing recorded


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    from dran_edge.sim.writer import write_run
    from dran_edge.sim.mission import SimParams, generate_mission

    d = tmp_path_factory.mktemp("clock") / "run"
    write_run(
        generate_mission(SimParams(robots=2, objects=2, duration_s=6.0, seed=3)),
        d,
        frames="none",
        workers=1,
    )
    return d


def _replay(run, tmp_path, edit):
    """``dran-edge replay`` (in process) on a copy of ``run`` whose mission.yaml ``edit`` changed."""
    import shutil

    from dran_edge.cli.app import main

    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    doc = yaml.safe_load((copy / "mission.yaml").read_text())
    edit(doc)
    (copy / "mission.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return main(["replay", str(copy), "--settle-rounds", "2", "--workers", "1"])


def test_replay_refuses_start_ns_1_at_once(small_run, tmp_path, capsys):
    rc = _replay(small_run, tmp_path, lambda d: d.update(start_ns=1))
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "mission.yaml" in err and "start_ns 1 is" in err and "empty rounds" in err


def test_replay_warns_early_start_and_wrong_mocap_start(small_run, tmp_path, caplog):
    def edit(d):
        d["start_ns"] -= 10 * S
        d["mocap"]["start_ns"] = 1

    with caplog.at_level("WARNING", logger="dran_edge.replay.run"):
        assert _replay(small_run, tmp_path, edit) == 0
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert "10.0 s before the first recorded stamp" in text
    assert "mocap.start_ns is" in text
    report = __import__("json").loads((tmp_path / "run" / "out" / "report.json").read_text())
    # start early, records outlasting duration_s from that start, mocap start
    assert len(report["warnings"]) == 3 and "duration_s is 6" in report["warnings"][1]
