"""``check-config`` loads what ``run`` loads and reports every problem; ``check-fleet``."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

from dran_edge.cli import main
from dran_edge.comms import keys

REPO = Path(__file__).resolve().parents[1]


def _config(tmp_path, name="robot.yaml", **sections):
    cfg = {
        "robot": {"id": 1, "name": "dingo1", "fleet": "dingo6"},
        "neighbours": [{"id": 2, "name": "dingo2", "address": "10.42.0.12:5600"}],
        "comms": {"transport": "udp", "key_file": "fleet.key"},
        "camera": {"source": "realsense", "calib_dir": str(REPO / "calib" / "cameras"),
                   "tags_file": str(REPO / "calib" / "tags.yaml")},
        "daemon": {"state_dir": str(tmp_path / "state")},
    }
    for k, v in sections.items():
        cfg[k] = {**cfg.get(k, {}), **v} if isinstance(v, dict) else v
    path = tmp_path / name
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def _check(path, capsys):
    rc = main(["check-config", str(path)])
    out = capsys.readouterr()
    return rc, out.out, [ln for ln in out.err.splitlines() if ": error: " in ln]


def test_a_good_config_is_ok_and_what_it_names_is_loaded(tmp_path, capsys):
    keys.write_fleet_key(tmp_path / "fleet.key")
    rc, out, errors = _check(_config(tmp_path), capsys)
    assert rc == 0 and errors == [] and "ok: robot dingo1" in out and "hmac key" in out


def test_everything_run_would_trip_on_is_reported_at_once(tmp_path, capsys):
    """The issue's case: missing key, calibration and tags; each named, all three reported."""
    path = _config(tmp_path, camera={"calib_dir": "nocalib", "tags_file": "notags.yaml"})
    rc, _, errors = _check(path, capsys)
    assert rc == 2 and len(errors) == 3, errors
    assert "fleet.key" in errors[0] and "cannot read" in errors[0]
    assert "camera.calib_dir" in errors[1] and "notags.yaml" in errors[2]
    keys.write_fleet_key(tmp_path / "fleet.key")
    os.chmod(tmp_path / "fleet.key", 0o644)
    rc, _, errors = _check(path, capsys)
    assert rc == 2 and "0644" in errors[0] and "chmod 600" in errors[0]


def test_every_schema_error_is_reported_with_its_line(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(
        "robot: {id: 1, name: dingo1, fleet: dingo6}\n"
        "neighbours:\n"
        "  - {id: 2, name: dingo2}\n"
        "comms: {port: 99999, periodx: 3}\n"
        "agent:\n"
        "  beta: fast\n"
        "  graph: {max_nodes: 400, max_edges: 50}\n")
    rc, _, errors = _check(path, capsys)
    assert rc == 2
    want = [("bad.yaml:3:", "neighbours[0].address: required"),
            ("bad.yaml:4:", "comms.port"), ("bad.yaml:4:", "comms.periodx: unknown key"),
            ("bad.yaml:6:", "agent.beta"), ("bad.yaml:7:", "agent.graph.max_edges")]
    assert len(errors) == len(want), errors
    for line, (where, what) in zip(errors, want):
        assert where in line and what in line, (line, where, what)
    # the strict loader still stops at the first (what run does)
    from dran_edge.config import load_config
    from dran_edge.errors import ConfigError

    with pytest.raises(ConfigError, match="neighbours"):
        load_config(path)


def test_ed25519_keys_are_checked(tmp_path, capsys):
    keys.write_robot_key(tmp_path / "dingo1.key", 1)
    keys.write_robot_key(tmp_path / "dingo2.key", 2)
    keys.write_robot_key(tmp_path / "other.key", 1)
    pub = {r: (keys.load_public_key_file(tmp_path / f"dingo{r}.key.pub")[1],) for r in (1, 2)}
    keys.write_fleet_public_keys(tmp_path / "fleet.pub", "dingo6", pub)
    ed = {"auth": "ed25519", "key_file": "dingo1.key", "public_keys_file": "fleet.pub"}
    rc, out, errors = _check(_config(tmp_path, comms=ed, camera={"source": "none"}), capsys)
    assert rc == 0 and "ed25519 key" in out, errors
    # a fleet HMAC key where a robot key is expected, and robot 2 missing from the keys
    keys.write_fleet_key(tmp_path / "fleet.key")
    keys.write_fleet_public_keys(tmp_path / "partial.pub", "dingo6", {1: pub[1]})
    rc, _, errors = _check(_config(tmp_path, comms={**ed, "key_file": "fleet.key",
                                                    "public_keys_file": "partial.pub"},
                                   camera={"source": "none"}), capsys)
    assert rc == 2 and len(errors) == 2, errors
    assert "comms.auth: hmac" in errors[0] and "robot(s) [2]" in errors[1]
    # another robot's secret: its public key is not this robot's
    rc, _, errors = _check(_config(tmp_path, comms={**ed, "key_file": "other.key"},
                                   camera={"source": "none"}), capsys)
    assert rc == 2 and "not robot 1's" in errors[0]
