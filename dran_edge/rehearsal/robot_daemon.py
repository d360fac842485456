"""One robot of a rehearsal: its daemon process's state, its ingest records and its config.

:class:`RobotDaemon` is what :class:`dran_edge.rehearsal.fleet.Fleet` knows about one robot's
``dran-edge daemon`` process (paths, the records still to send, status samples, restarts);
:func:`ingest_records` and :func:`perceived_records` are what it sends, released on the
mission clock as replay does; :func:`daemon_config` its robot.yaml.
"""

from __future__ import annotations

import socket
import subprocess
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge.formats import run_dir as rd


@dataclass
class RobotDaemon:
    """One robot's daemon process and what the rehearsal knows about it."""

    id: int
    name: str
    k: int
    config: Path
    state_dir: Path
    runtime_dir: Path
    record_dir: Path
    log_path: Path
    drop_file: Path
    records: list[bytes]
    release_ns: np.ndarray
    proc: subprocess.Popen | None = None
    next_record: int = 0
    queue: list[int] = field(default_factory=list)
    sock: socket.socket | None = None
    connections: list[dict] = field(default_factory=list)
    """Per connection: pid of the daemon, indices sent on it, records it reported accepted."""
    samples: list[dict] = field(default_factory=list)
    last_status: dict | None = None
    starts: int = 0
    clock_offset_s: float = 0.0
    faketime_lib: str | None = None
    """libfaketime preloaded into this daemon (a robot with a clock step), else None."""
    rejected_in_file: Counter = field(default_factory=Counter)
    """Records of the run's ingest.bin that do not decode (never sent), by reason."""

    @property
    def ingest_path(self) -> Path:
        return self.runtime_dir / "ingest.sock"

    @property
    def status_path(self) -> Path:
        return self.runtime_dir / "status.sock"


def ingest_records(run: rd.Run, name: str) -> tuple[list[bytes], np.ndarray, Counter[str]]:
    """The robot's records (raw bytes) and release stamps: a record goes out once the mission
    clock passes its stamp and every earlier record's (file order is kept, as replay does)."""
    from dran_edge.comms.ingest import IngestDecodeError, iter_records
    from dran_edge.replay.robots import event_stamp

    raws: list[bytes] = []
    stamps: list[int] = []
    rejected: Counter[str] = Counter()
    release = 0
    for item in iter_records(run.read_ingest(name)):
        if isinstance(item, IngestDecodeError):
            rejected[item.reason] += 1
            continue
        release = max(release, event_stamp(item.event))
        raws.append(item.raw)
        stamps.append(release)
    return raws, np.asarray(stamps, np.int64), rejected


def perceived_records(run: rd.Run, name: str) -> list[tuple[int, bytes]]:
    """Observation records of the robot's recorded frames, by replay's perception pipeline."""
    from dran_edge.comms.ingest import iter_records
    from dran_edge.replay.perception import perceive_window

    cfg = run.load_config(name)
    if cfg.camera.source != "recorded" or run.frames_dir(name) is None:
        return []
    calib = cfg.resolve(cfg.camera.calib_dir) or run.calib_dir
    _, _, records, _ = perceive_window((str(run.config_path(name)), str(calib), name, 0, 2**63 - 1))
    out = []
    for raw in records:
        for item in iter_records(raw):
            out.append((int(item.event.stamp_ns), item.raw))
    return out


def daemon_config(
    run: rd.Run,
    info: rd.RunRobot,
    ep: Any,
    neighbours: list[tuple[int, str, Any]],
    key_file: Path,
    d: RobotDaemon,
    period_s: float,
) -> dict[str, Any]:
    """The robot's own config rewritten for its rehearsal daemon: UDP on its network
    endpoint, the fleet key, ingest on its socket, no camera, its state and runtime dirs."""
    from dran_edge.config import config_to_dict

    cfg = config_to_dict(run.load_config(info.name))
    cfg["neighbours"] = [{"id": j, "name": nm, "address": nep.dish} for j, nm, nep in neighbours]
    if info.T_world_odom is not None:
        from dran_edge import geometry as geo

        cfg["robot"]["T_world_odom"] = [
            round(float(v), 12) for v in geo.se3_to_xyz_quat_xyzw(info.T_world_odom)
        ]
    cfg["comms"].update(
        transport="udp",
        bind_address=ep.address,
        port=ep.port,
        key_file=str(key_file),
        period_s=period_s,
    )
    cfg["ingest"].update(enabled=True, socket_path=str(d.ingest_path))
    cfg["camera"].update(source="none", recording="", calib_dir="", tags_file="")
    cfg["daemon"].update(
        state_dir=str(d.state_dir),
        runtime_dir=str(d.runtime_dir),
        checkpoint_period_s=max(0.5, 4 * period_s),
        status_period_s=5.0,
    )
    return cfg
