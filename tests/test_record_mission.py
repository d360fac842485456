"""Recording produces a complete run: run --record writes mission.yaml; merge-records combines
robots' recordings; replay and eval read the result without hand edits."""

from __future__ import annotations

import shutil

import numpy as np
from daemon_helpers import feed_and_drain, write_config
from test_daemon import RecordingNotifier

from dran_edge.cli.app import main
from dran_edge.config import load_config
from dran_edge.daemon.service import Daemon
from dran_edge.formats.recorded import ingest_span
from dran_edge.formats.run_dir import open_run
from dran_edge.sim.vio import vio_mission


def test_a_daemon_recording_replays_as_it_is(tmp_path):
    from dran_edge.replay.run import ReplayOptions, replay_run

    cfg = load_config(write_config(tmp_path, comms={"period_s": 0.05}))
    rec = tmp_path / "rec"
    d = Daemon(cfg, notifier=RecordingNotifier(), environ={}, record_dir=rec)
    d.start()
    m = vio_mission(20, seed=4)
    feed_and_drain(d, m.events)
    d.shutdown()
    run = open_run(rec)  # strict reader: mission.yaml complete and consistent
    stamps = [getattr(e, "stamp_ns", getattr(e, "stamp_cur_ns", None)) for e in m.events]
    assert run.mission.start_ns == min(stamps)
    assert run.mission.duration_s == (max(stamps) - min(stamps)) / 1e9
    assert [r.name for r in run.mission.robots] == ["testbot"]
    assert run.mission.fleet == cfg.robot.fleet and run.mission.mocap_file is None
    rep = replay_run(rec, ReplayOptions(workers=1, settle_rounds=2, evaluate=False)).report
    assert rep["robots"] == 1 and rep["ingest_rejected"] == {} and rep["keyframes"]["testbot"] > 3


def test_merge_records_builds_a_run_that_replays_and_evaluates(tmp_path, capsys):
    sim = tmp_path / "sim"
    assert (
        main(
            [
                "simulate",
                str(sim),
                "--robots",
                "3",
                "--objects",
                "3",
                "--duration-s",
                "12",
                "--frames",
                "none",
                "--seed",
                "8",
            ]
        )
        == 0
    )
    recs = []
    for name in ("dingo1", "dingo2", "dingo3"):  # what each robot's --record DIR holds
        r = tmp_path / f"rec_{name}" / "robots" / name
        shutil.copytree(sim / "robots" / name, r)
        recs.append(str(r.parent.parent))
    out = tmp_path / "run"
    orig = open_run(sim).mission
    assert (
        main(
            [
                "merge-records",
                str(out),
                *recs,
                "--mocap",
                str(sim / "mocap.csv"),
                "--mocap-start-ns",
                str(orig.mocap_start_ns),
            ]
        )
        == 0
    )
    assert "3 robots" in capsys.readouterr().out
    m = open_run(out).mission
    assert [(r.id, r.name, r.mocap_body) for r in m.robots] == [
        (r.id, r.name, r.name) for r in orig.robots
    ]
    assert m.comm_graph == orig.comm_graph and m.fleet == orig.fleet
    first, last = zip(
        *(ingest_span(sim / "robots" / n / "ingest.bin") for n in ("dingo1", "dingo2", "dingo3"))
    )
    assert m.start_ns == min(first) and np.isclose(m.duration_s, (max(last) - min(first)) / 1e9)
    assert main(["replay", str(out), "--workers", "1", "--settle-rounds", "2"]) == 0
    assert main(["eval", str(out), "--no-plots", "--json"]) == 0
    cap = capsys.readouterr().out
    assert '"ate_m"' in cap and '"mission.yaml mocap.start_ns"' in cap
    # a robot already in the run is refused (named); rewriting mission.yaml in place works
    assert (
        main(
            [
                "merge-records",
                str(out),
                str(tmp_path / "rec_dingo1"),
                "--mocap",
                str(tmp_path / "nope.csv"),
            ]
        )
        == 2
    )
    assert main(["merge-records", str(out)]) == 0
