"""The simulate / replay commands through the CLI entry point (exit codes, messages, outputs)."""

from __future__ import annotations

import json

from dran_edge.cli.app import main


def test_simulate_then_replay_through_the_cli(tmp_path, capsys):
    run = tmp_path / "run"
    rc = main(
        [
            "simulate",
            str(run),
            "--robots",
            "2",
            "--objects",
            "4",
            "--duration-s",
            "12",
            "--frames",
            "none",
            "--seed",
            "4",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "simulated 2 robots, 4 boxes, 12 s (seed 4)" in out
    assert (run / "mission.yaml").exists() and (run / "robots" / "dingo2" / "ingest.bin").exists()
    rc = main(["replay", str(run), "--json", "--settle-rounds", "4", "--workers", "1"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    report = json.loads(captured.out)
    assert report["robots"] == 2 and report["rounds"] == 24 + 4
    assert report["frames_processed"] == 0 and report["observations"] > 0
    assert (run / "out" / "dingo1" / "dingo1.tum").exists()
    # a second simulate into the same directory is refused (exit 2, names the directory)
    rc = main(["simulate", str(run), "--robots", "2", "--duration-s", "5"])
    err = capsys.readouterr().err
    assert rc == 2 and str(run) in err and "empty" in err


def test_replay_of_a_broken_run_names_the_file(tmp_path, capsys):
    (tmp_path / "mission.yaml").write_text("format: dran-edge-run/2\n")
    rc = main(["replay", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2
    assert "mission.yaml" in err
    rc = main(["replay", str(tmp_path), "--partition", "nonsense"])
    assert rc == 2 and "--partition" in capsys.readouterr().err
