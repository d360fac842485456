"""Strict robot config loading: every bad input names its key path, line and reason."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml

from dran_edge.config import (
    AgentConfig,
    GraphBounds,
    NoiseModel,
    RobotConfig,
    config_from_dict,
    config_to_dict,
    load_config,
)
from dran_edge.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]

MINIMAL = """\
robot: {id: 1, name: dingo1, fleet: dingo6}
neighbours:
  - {id: 2, name: dingo2, address: "10.0.0.2:5600"}
  - {id: 3, name: dingo3, address: "[fd00::3]:5601"}
agent:
  beta: 2
  graph:
    max_nodes: 100
"""


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "robot.yaml"
    p.write_text(text)
    return p


def test_minimal_file_loads_with_defaults_and_derived_agent_fields(tmp_path):
    cfg = load_config(write(tmp_path, MINIMAL))
    assert isinstance(cfg, RobotConfig)
    assert cfg.robot.id == 1 and cfg.robot.fleet == "dingo6"
    assert cfg.agent.robot_id == 1
    assert cfg.agent.neighbours == (2, 3)
    assert cfg.agent.beta == 2.0 and isinstance(cfg.agent.beta, float)
    assert cfg.agent.graph.max_nodes == 100
    assert cfg.agent.graph.max_edges == GraphBounds().max_edges
    assert cfg.agent.eta == 0.1 and cfg.agent.k_max == 500  # paper defaults
    assert cfg.comms.datagram_max_bytes == 1200 and cfg.comms.period_s == 0.5


def test_configs_are_frozen():
    cfg = AgentConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.beta = 3.0  # type: ignore[misc]


@pytest.mark.parametrize(
    "edit, key, line, reason",
    [
        ("  beta: -2\n", "agent.beta", 6, "expected a value > 0.0"),
        ("  betta: 2\n", "agent.betta", 6, "unknown key"),
        ("  beta: fast\n", "agent.beta", 6, "expected a number"),
        ("  beta: true\n", "agent.beta", 6, "expected a number"),
        ("  k_max: 2.5\n", "agent.k_max", 6, "expected an integer"),
        ("  residual: euclid\n", "agent.residual", 6, "expected one of"),
        ("  robot_id: 4\n", "agent.robot_id", 6, "set from robot/neighbours"),
        ("  beta: .nan\n", "agent.beta", 6, "finite"),
    ],
)
def test_bad_agent_values_name_key_line_and_reason(tmp_path, edit, key, line, reason):
    text = MINIMAL.replace("  beta: 2\n", edit)
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, text))
    msg = str(info.value)
    assert f"{key}:" in msg
    assert reason in msg
    assert f"robot.yaml:{line}:" in msg
    assert info.value.line == line


def test_cross_field_check_names_nested_key(tmp_path):
    text = MINIMAL.replace("max_nodes: 100", "max_nodes: 100\n    max_edges: 50")
    with pytest.raises(ConfigError, match=r"agent\.graph\.max_edges: expected >= max_nodes"):
        load_config(write(tmp_path, text))


@pytest.mark.parametrize(
    "bad, key",
    [
        ('"10.0.0.2"', "neighbours[0].address"),
        ('"10.0.0.2:99999"', "neighbours[0].address"),
        ('"dingo2.local:5600"', "neighbours[0].address"),
    ],
)
def test_bad_neighbour_address(tmp_path, bad, key):
    text = MINIMAL.replace('"10.0.0.2:5600"', bad)
    with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]")):
        load_config(write(tmp_path, text))


def test_self_neighbour_and_duplicates_rejected(tmp_path):
    with pytest.raises(ConfigError, match="lists itself"):
        load_config(write(tmp_path, MINIMAL.replace("id: 3,", "id: 1,")))
    with pytest.raises(ConfigError, match="distinct"):
        load_config(write(tmp_path, MINIMAL.replace("id: 3,", "id: 2,")))


def test_duplicate_yaml_key_rejected_with_line(tmp_path):
    text = MINIMAL + "agent:\n  eta: 0.2\n"
    with pytest.raises(ConfigError, match="agent: duplicate key") as info:
        load_config(write(tmp_path, text))
    assert info.value.line == 9


def test_missing_required_and_wrong_section_type(tmp_path):
    with pytest.raises(ConfigError, match="robot.fleet: required key is missing"):
        load_config(write(tmp_path, "robot: {id: 1, name: a}\n"))
    with pytest.raises(ConfigError, match="robot: required key is missing"):
        load_config(write(tmp_path, "agent: {}\n"))
    with pytest.raises(ConfigError, match="comms: expected a mapping"):
        load_config(write(tmp_path, MINIMAL + "comms: 5\n"))
    with pytest.raises(ConfigError, match="empty"):
        load_config(write(tmp_path, ""))
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(write(tmp_path, "robot: {id: 1\n"))
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "absent.yaml")


def test_world_writable_socket_mode_and_long_fleet_name_rejected(tmp_path):
    with pytest.raises(ConfigError, match="ingest.socket_mode"):
        load_config(write(tmp_path, MINIMAL + "ingest: {socket_mode: 0o666}\n"))
    with pytest.raises(ConfigError, match="robot.fleet"):
        load_config(write(tmp_path, MINIMAL.replace("dingo6", "a_very_long_fleet_name")))


def test_direct_construction_is_validated_too():
    with pytest.raises(ConfigError, match="eta"):
        AgentConfig(eta=0.0)
    with pytest.raises(ConfigError, match="sigma_translation_m"):
        NoiseModel(sigma_translation_m=-1.0)


def test_round_trip_through_dict(tmp_path):
    cfg = load_config(write(tmp_path, MINIMAL))
    again = config_from_dict(yaml.safe_load(yaml.safe_dump(config_to_dict(cfg))))
    assert config_to_dict(again) == config_to_dict(cfg)
    assert again.agent == cfg.agent


def test_relative_paths_resolve_against_the_file(tmp_path):
    cfg = load_config(write(tmp_path, MINIMAL + "camera: {calib_dir: cams}\n"))
    assert cfg.resolve(cfg.camera.calib_dir) == tmp_path.resolve() / "cams"
    assert cfg.resolve("") is None


@pytest.mark.parametrize(
    "path", sorted((REPO / "calib" / "fleet").glob("*.yaml")), ids=lambda p: p.name
)
def test_shipped_fleet_configs_load(path):
    cfg = load_config(path)
    assert cfg.agent.robot_id == cfg.robot.id


def test_shipped_fleet_is_six_robots_plus_laptop():
    names = sorted(p.stem for p in (REPO / "calib" / "fleet").glob("*.yaml"))
    assert names == [f"dingo{i}" for i in range(1, 7)] + ["laptop"]
    cfgs = [load_config(REPO / "calib" / "fleet" / f"{n}.yaml") for n in names]
    assert len({c.robot.id for c in cfgs}) == 7
    assert len({c.robot.fleet for c in cfgs}) == 1
    by_id = {c.robot.id: c for c in cfgs}
    for c in cfgs:  # neighbour relation is symmetric across the fleet files
        for n in c.neighbours:
            assert c.robot.id in by_id[n.id].agent.neighbours
    laptop = by_id[[c.robot.id for c in cfgs if c.robot.name == "laptop"][0]]
    assert laptop.camera.source == "none" and not laptop.ingest.enabled


def test_every_config_key_is_documented():
    import dataclasses as dc

    from dran_edge import config as C

    text = (REPO / "docs" / "config.md").read_text()
    for cls in (
        C.RobotSection,
        C.Neighbour,
        C.CommsSection,
        C.IngestSection,
        C.CameraSection,
        C.DaemonSection,
        C.AgentConfig,
        C.OdometryNoise,
        C.NoiseModel,
        C.GraphBounds,
    ):
        for f in dc.fields(cls):
            if f.name != "source_path":
                assert f"| `{f.name}` |" in text, f"{cls.__name__}.{f.name} not in docs/config.md"
