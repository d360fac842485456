"""The daemon's status socket: the document it publishes (``status_document``), the server that
answers ``dran-edge status`` with it, and the client that asks."""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from dran_edge.errors import DranError

if TYPE_CHECKING:
    from dran_edge.daemon.service import Daemon

#: At most this many (newest) keyframes in the status document's ``estimate`` section.
STATUS_MAX_KEYFRAMES = 5000


def _estimate_section(est) -> dict | None:
    """The latest estimate for the ROS 2 bridge (dran_edge/ros/bridge2.py): keyframes as rows
    ``[stamp_ns, x, y, z, qx, qy, qz, qw]`` (world frame, newest STATUS_MAX_KEYFRAMES) and
    objects as ``[object_id, x, y, z, qx, qy, qz, qw]``."""
    if est is None or len(est.keyframe_stamps_ns) == 0:
        return None
    from dran_edge import geometry as geo

    order = np.argsort(np.asarray(est.keyframe_stamps_ns))[-STATUS_MAX_KEYFRAMES:]
    v = geo.se3_to_xyz_quat_xyzw(np.asarray(est.T_world_body)[order])
    kf = [
        [int(s)] + [round(float(x), 9) for x in row]
        for s, row in zip(np.asarray(est.keyframe_stamps_ns)[order].tolist(), v)
    ]
    objs = []
    if len(est.object_ids):
        w = geo.se3_to_xyz_quat_xyzw(np.asarray(est.T_world_object))
        objs = [[int(i)] + [round(float(x), 9) for x in row] for i, row in zip(est.object_ids, w)]
    return {"round": int(est.round), "keyframes": kf, "objects": objs}


class StatusServer:
    """Unix stream socket: each connection gets the latest status as one JSON document."""

    def __init__(self, path: Path, snapshot: Callable[[], dict], mode: int = 0o660):
        self.path = Path(path)
        self.snapshot = snapshot
        if self.path.exists() or self.path.is_symlink():
            self.path.unlink()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        old = os.umask(0o777 & ~mode)
        try:
            self._sock.bind(str(self.path))
        finally:
            os.umask(old)
        self._sock.listen(4)
        self._sock.settimeout(0.2)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="status", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except (socket.timeout, BlockingIOError):
                continue
            except OSError:
                if self._stop.is_set():
                    return
                continue
            try:
                conn.settimeout(1.0)
                conn.sendall(json.dumps(self.snapshot(), default=_json_default).encode() + b"\n")
            except OSError:
                pass
            finally:
                conn.close()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._sock.close()
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


def status_document(d: Daemon, state: str) -> dict:
    """The status ``d`` publishes in ``state`` (``starting``, ``running``, ``stopping``)."""
    est = d.last_estimate
    ingest = d.ingest
    transport_stats: dict = {}
    if d.transport is not None:
        try:
            transport_stats = d.transport.stats()
        except Exception:
            transport_stats = {"error": "stats unavailable"}
    has_graph = hasattr(d, "graph")  # no core yet before start()
    return {
        "state": state,
        "robot": {"id": d.cfg.robot.id, "name": d.cfg.robot.name, "fleet": d.cfg.robot.fleet},
        "pid": os.getpid(),
        "boot_epoch": getattr(d, "boot_epoch", None),
        "uptime_s": time.monotonic() - d.started_mono,
        "rounds": d.stats.as_dict(),
        "graph": {
            "nodes": d.graph.num_nodes if has_graph else 0,
            "factors": d.graph.num_factors if has_graph else 0,
            **(
                {}
                if est is None
                else {
                    "round": est.round,
                    "keyframes": int(len(est.keyframe_stamps_ns)),
                    "objects": len(est.object_ids),
                    "cost": est.cost,
                    "consensus_error": est.consensus_error,
                    "converged": est.converged,
                }
            ),
        },
        "graph_counters": dict(d.graph.counters) if has_graph else {},
        "neighbours": transport_stats.get("neighbours", {}),
        "transport": transport_stats,
        "ingest": None
        if ingest is None
        else {
            "socket": str(ingest.path),
            **ingest.counters.as_dict(),
            "rejected_by_reason": dict(ingest.rejected),
        },
        "journal": {
            "pending": d.journal.pending_count if hasattr(d, "journal") else 0,
            "position": d.applied_position,
        },
        "queues": {
            "observations_dropped": d.observations.dropped if hasattr(d, "observations") else 0,
            "frames_dropped": d.frames.dropped if hasattr(d, "frames") else 0,
        },
        "perception": None
        if d.perception is None
        else {"batches": d.perception.batches, "errors": d.perception.errors},
        "counters": d.counters.as_dict(),
        "agent": d.agent_health,
        "beta_check": getattr(d, "beta_check", None),
        "estimate": _estimate_section(est),
        "systemd": d.notifier.backend,
    }


def status_line(d: Daemon) -> str:
    """One line for systemd's STATUS= and the log."""
    s = d.snapshot()
    graph = s.get("graph") or {}
    ingest = s.get("ingest") or {}
    return (
        f"rounds={d.stats.ticks} late={d.stats.late} "
        f"solve_ms={1e3 * d.stats.round_last_s:.1f} "
        f"keyframes={graph.get('keyframes', 0)} objects={graph.get('objects', 0)} "
        f"records={ingest.get('records', 0)} rejected={ingest.get('rejected', 0)} "
        f"obs_dropped={s.get('queues', {}).get('observations_dropped', 0)} "
        f"neighbours={_heard_line(s.get('neighbours') or {})}"
    )


def _heard_line(neighbours: dict) -> str:
    """``heard/configured``: neighbours heard within the last 10 s, of those listed."""
    heard = sum(
        1
        for n in neighbours.values()
        if n.get("last_heard_s_ago") is not None and n["last_heard_s_ago"] < 10.0
    )
    return f"{heard}/{len(neighbours)}"


def query_status(path: str | Path, timeout_s: float = 2.0) -> dict:
    """The daemon's status document; DranError when nothing answers at ``path``."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(str(path))
        chunks = []
        while True:
            data = s.recv(65536)
            if not data:
                break
            chunks.append(data)
    except OSError as exc:
        raise DranError(f"no daemon answers at {path}: {exc.strerror or exc}") from None
    finally:
        s.close()
    try:
        return json.loads(b"".join(chunks))
    except ValueError:
        raise DranError(f"the daemon at {path} sent an unreadable status") from None
