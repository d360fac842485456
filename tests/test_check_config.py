"""``check-config`` loads what ``run`` loads and reports every problem; ``check-fleet``."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml
from dran_edge.comms import keys

from dran_edge.cli.app import main

REPO = Path(__file__).resolve().parents[1]
try:
    import cryptography  # noqa: F401  (the ed25519 key policy)

    HAVE_ED25519 = True
except ImportError:
    HAVE_ED25519 = False
needs_ed25519 = pytest.mark.skipif(
    not HAVE_ED25519, reason="no 'cryptography' (pip install .[comms])"
)


def _config(tmp_path, name="robot.yaml", **sections):
    cfg = {
        "robot": {"id": 1, "name": "dingo1", "fleet": "dingo6"},
        "neighbours": [{"id": 2, "name": "dingo2", "address": "10.42.0.12:5600"}],
        "comms": {"transport": "udp", "key_file": "fleet.key"},
        "camera": {
            "source": "realsense",
            "calib_dir": str(REPO / "calib" / "cameras"),
            "tags_file": str(REPO / "calib" / "tags.yaml"),
        },
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
        "  graph: {max_nodes: 400, max_edges: 50}\n"
    )
    rc, _, errors = _check(path, capsys)
    assert rc == 2
    want = [
        ("bad.yaml:3:", "neighbours[0].address: required"),
        ("bad.yaml:4:", "comms.port"),
        ("bad.yaml:4:", "comms.periodx: unknown key"),
        ("bad.yaml:6:", "agent.beta"),
        ("bad.yaml:7:", "agent.graph.max_edges"),
    ]
    assert len(errors) == len(want), errors
    for line, (where, what) in zip(errors, want):
        assert where in line and what in line, (line, where, what)
    # the strict loader still stops at the first (what run does)
    from dran_edge.config import load_config
    from dran_edge.errors import ConfigError

    with pytest.raises(ConfigError, match="neighbours"):
        load_config(path)


@needs_ed25519
@pytest.mark.parametrize("auth", ["ed25519", "pairwise"])
def test_robot_keys_are_checked(tmp_path, capsys, auth):
    keys.write_robot_key(tmp_path / "dingo1.key", 1)
    keys.write_robot_key(tmp_path / "dingo2.key", 2)
    keys.write_robot_key(tmp_path / "other.key", 1)
    pub = {r: (keys.load_public_key_file(tmp_path / f"dingo{r}.key.pub")[1],) for r in (1, 2)}
    keys.write_fleet_public_keys(tmp_path / "fleet.pub", "dingo6", pub)
    ed = {"auth": auth, "key_file": "dingo1.key", "public_keys_file": "fleet.pub"}
    rc, out, errors = _check(_config(tmp_path, comms=ed, camera={"source": "none"}), capsys)
    assert rc == 0 and f"{auth} key" in out, errors
    # a fleet HMAC key where a robot key is expected, and robot 2 missing from the keys
    keys.write_fleet_key(tmp_path / "fleet.key")
    keys.write_fleet_public_keys(tmp_path / "partial.pub", "dingo6", {1: pub[1]})
    rc, _, errors = _check(
        _config(
            tmp_path,
            comms={**ed, "key_file": "fleet.key", "public_keys_file": "partial.pub"},
            camera={"source": "none"},
        ),
        capsys,
    )
    assert rc == 2 and len(errors) == 2, errors
    assert "comms.auth: hmac" in errors[0] and "robot(s) [2]" in errors[1]
    # another robot's secret: its public key is not this robot's
    rc, _, errors = _check(
        _config(tmp_path, comms={**ed, "key_file": "other.key"}, camera={"source": "none"}), capsys
    )
    assert rc == 2 and "not robot 1's" in errors[0]


def _fleet(tmp_path, n=4, auth="hmac", edit=None):
    """A ring fleet of ``n`` robots in ``tmp_path``; ``edit(i, cfg)`` changes robot i's dict."""
    from dran_edge.cli.commands.check_fleet import check_fleet

    d = tmp_path / f"fleet-{auth}"
    d.mkdir(exist_ok=True)
    if auth == "hmac" and not (d / "fleet.key").exists():
        keys.write_fleet_key(d / "fleet.key")
    for i in range(1, n + 1):
        if auth != "hmac" and not (d / f"r{i}.key").exists():
            keys.write_robot_key(d / f"r{i}.key", i)
    if auth != "hmac":
        table = {i: (keys.load_public_key_file(d / f"r{i}.key.pub")[1],) for i in range(1, n + 1)}
        keys.write_fleet_public_keys(d / "fleet.pub", "ring", table)
    for i in range(1, n + 1):
        nb = [(i % n) + 1, ((i - 2) % n) + 1]
        cfg = {
            "robot": {"id": i, "name": f"r{i}", "fleet": "ring"},
            "neighbours": [{"id": j, "name": f"r{j}", "address": f"10.0.0.{j}:5600"} for j in nb],
            "comms": {
                "transport": "udp",
                "auth": auth,
                "key_file": "fleet.key" if auth == "hmac" else f"r{i}.key",
                **({"public_keys_file": "fleet.pub"} if auth != "hmac" else {}),
            },
        }
        if edit is not None:
            edit(i, cfg)
        (d / f"r{i}.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    return check_fleet(d)


@pytest.mark.parametrize(
    "auth",
    [
        "hmac",
        pytest.param("ed25519", marks=needs_ed25519),
        pytest.param("pairwise", marks=needs_ed25519),
    ],
)
def test_check_fleet_consistent_ring_is_ok(tmp_path, auth):
    rep = _fleet(tmp_path, auth=auth)
    assert rep.errors == [] and len(rep.robots) == 4


def test_check_fleet_finds_every_inconsistency(tmp_path):
    def edit(i, cfg):
        if i == 1:
            cfg["robot"]["fleet"] = "other"  # fleet name
            cfg["neighbours"].append({"id": 3, "name": "r3", "address": "10.0.0.3:5600"})
        if i == 2:
            cfg["neighbours"][0]["address"] = "10.0.0.9:5600"  # r3 at another address
        if i == 4:
            cfg["robot"]["id"] = 2  # duplicate id (and r4 vanishes)
            cfg["agent"] = {"beta": 1.0}  # the paper's β beside the others' default
        if i == 3:
            cfg["agent"] = {"sor_omega": 1.9}  # Table 1's over-relaxation: not over WiFi

    rep = _fleet(tmp_path, edit=edit)
    text = "\n".join(map(str, rep.errors))
    assert "disagree on the fleet name" in text
    assert "robot id 2 is used by 2 configs" in text
    assert "does not list r1 (id 1) back" in text
    assert "listed at different addresses" in text
    assert "neighbour 4 (r4) is not a robot of this directory" in text
    assert "robots disagree on agent.beta: 1.0 (r4); 250.0 (r1, r2, r3)" in text
    assert "agent.sor_omega is 1.9: over-relaxation needs every neighbour's newest" in text


@needs_ed25519
def test_check_fleet_keys(tmp_path, capsys):
    def mixed(i, cfg):
        if i == 2:
            cfg["comms"]["auth"] = "ed25519"

    rep = _fleet(tmp_path, edit=mixed)
    assert any("different key policies" in str(e) for e in rep.errors)
    # ed25519: robot 3's key pair replaced but the fleet's public keys not exported again
    rep = _fleet(tmp_path, auth="ed25519")
    assert rep.errors == []
    d = tmp_path / "fleet-ed25519"
    for f in ("r3.key", "r3.key.pub"):
        (d / f).unlink()
    keys.write_robot_key(d / "r3.key", 3)
    from dran_edge.cli.commands.check_fleet import check_fleet

    rep = check_fleet(d)
    text = "\n".join(map(str, rep.errors))
    assert text.count("that is not r3's own") == 2, text  # both of r3's neighbours
    assert main(["check-fleet", str(d)]) == 2
    assert "2 problems" in capsys.readouterr().err


def test_no_keys_checks_everything_but_the_key_files(tmp_path, capsys):
    """install.sh's case: the fleet key is not there yet; the rest is still checked."""
    path = _config(tmp_path, camera={"source": "none"})
    rc, _, errors = _check(path, capsys)
    assert rc == 2 and any("fleet.key" in e for e in errors)
    rc = main(["check-config", "--no-keys", str(path)])
    out = capsys.readouterr()
    assert rc == 0 and "not opened: --no-keys" in out.out
    bad = _config(tmp_path, "bad.yaml", camera={"source": "none"}, daemon={"state_dir": 5})
    assert main(["check-config", "--no-keys", str(bad)]) == 2
