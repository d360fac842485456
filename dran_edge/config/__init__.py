"""One robot's configuration: frozen dataclasses and a strict YAML loader (docs/config.md).

A robot reads one YAML file (schema and examples: ``docs/config.md``, ``calib/fleet/``)::

    robot:      {id: 1, name: dingo1, fleet: dingo6}
    neighbours: [{id: 2, name: dingo2, address: "10.42.0.12:5600"}]
    comms:      {port: 5600, key_file: /etc/dran-edge/fleet.key}
    ingest:     {socket_path: ""}          # "" -> $RUNTIME_DIRECTORY/ingest.sock
    camera:     {source: realsense, calib_dir: calib/cameras}
    daemon:     {state_dir: ""}            # "" -> $STATE_DIRECTORY
    agent:      {beta: 1.0, graph: {max_nodes: 400}}

Loading is strict: an unknown key, a wrong type or an out-of-range value raises
:class:`~dran_edge.errors.ConfigError` naming the file, the line, the key path (``agent.beta``)
and the reason. Every field has a default except ``robot.id``/``robot.name``/``robot.fleet``.

The dataclasses are pure (stdlib only) so the core (``AgentConfig``, ``GraphBounds``) can use
them; each field carries its unit in its name or docstring and its valid range in
``metadata`` (checked by the loader and again on direct construction).

The package is split by section: ``fields`` (range/choice metadata and checks), ``agent`` (the
pure core's sections), ``robot`` (the shell's sections and ``RobotConfig``), ``loader`` (strict
YAML). Every name is re-exported here: ``from dran_edge.config import X`` is the public path.
"""

from __future__ import annotations

from dran_edge.config.agent import AgentConfig, GraphBounds, NoiseModel, OdometryNoise
from dran_edge.config.fields import Residual, RobustKernel, StrChoice
from dran_edge.config.loader import (
    config_from_dict,
    config_to_dict,
    load_config,
    load_config_report,
)
from dran_edge.config.robot import (
    CameraSection,
    CommsSection,
    DaemonSection,
    IngestSection,
    Neighbour,
    RobotConfig,
    RobotSection,
    parse_address,
)

__all__ = [
    "AgentConfig",
    "CameraSection",
    "CommsSection",
    "DaemonSection",
    "GraphBounds",
    "IngestSection",
    "Neighbour",
    "NoiseModel",
    "OdometryNoise",
    "RobotConfig",
    "RobotSection",
    "Residual",
    "RobustKernel",
    "StrChoice",
    "config_from_dict",
    "config_to_dict",
    "load_config",
    "load_config_report",
    "parse_address",
]
