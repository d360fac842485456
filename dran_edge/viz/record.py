"""A run's outputs as an MCAP file for Foxglove: paths, object maps, links, mocap ground truth.

``write_run_mcap(RUN, PATH)`` reads what ``dran-edge replay`` or ``dran-edge rehearse`` wrote
(``out/<robot>/<robot>.tum``, ``<robot>_init.tum``, ``objects.csv``, ``rounds.csv``;
docs/run-format.md) and the run's mocap, and writes the topics of :mod:`.messages` with
log times in mission time (the robots' clock):

- ``/<robot>/path`` and ``/<robot>/path_init``: the final and the odometry-only estimate of
  the keyframes up to each second of the mission (the final estimate revealed over time, not
  what the robot believed then), one message per ``step_s``;
- ``/<robot>/objects``: the robot's final object map (at the start and the end);
- ``/links``: the communication graph between the robots' positions, per ``step_s``;
- ``/mocap/<robot>``, ``/mocap/objects``: ground truth in the mocap world, which is the
  estimates' world when the robots were anchored by mocap (the paper's protocol);
- ``/fleet/rounds``: rounds.csv's rows as JSON.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from dran_edge.formats import run_dir as rd
from dran_edge.errors import DependencyError
from dran_edge.viz import messages as vm


Track = tuple[np.ndarray, np.ndarray]
"""(stamps_ns, T_world_body (n, 4, 4))."""


def _foxglove() -> Any:
    try:
        import foxglove
    except ImportError:
        raise DependencyError(
            "writing MCAP files needs the foxglove-sdk package (pip install 'dran-edge[viz]')"
        ) from None
    return foxglove


def _channels(foxglove: Any, ctx: Any, names: list[str], with_mocap: bool) -> dict[str, Any]:
    from foxglove.channels import PosesInFrameChannel, SceneUpdateChannel

    ch: dict[str, Any] = {}
    for n in names:
        ch[f"/{n}/path"] = PosesInFrameChannel(f"/{n}/path", context=ctx)
        ch[f"/{n}/path_init"] = PosesInFrameChannel(f"/{n}/path_init", context=ctx)
        ch[f"/{n}/objects"] = SceneUpdateChannel(f"/{n}/objects", context=ctx)
        if with_mocap:
            ch[f"/mocap/{n}"] = PosesInFrameChannel(f"/mocap/{n}", context=ctx)
    ch["/links"] = SceneUpdateChannel("/links", context=ctx)
    if with_mocap:
        ch["/mocap/objects"] = SceneUpdateChannel("/mocap/objects", context=ctx)
    ch["/fleet/rounds"] = foxglove.Channel("/fleet/rounds", message_encoding="json", context=ctx)
    return ch


def _mocap(run: rd.Run) -> tuple[dict[str, Track], dict[int, np.ndarray]] | None:
    """(robot paths {name: (stamps_ns, T_world_body)} in the robots' clock, object poses
    {id: T_world_object}) of the run's mocap, or None without one."""
    from dran_edge import geometry as geo
    from dran_edge.formats import motive

    m = run.mission
    if not m.mocap_file or not (run.root / m.mocap_file).exists():
        return None
    take = motive.read_motive_csv(run.root / m.mocap_file, up_axis=m.mocap_up_axis)
    start = m.mocap_start_ns if m.mocap_start_ns is not None else m.start_ns
    paths = {}
    for r in m.robots:
        body = r.mocap_body or r.name
        b = take.bodies.get(body)
        if b is not None:  # as dran_edge.evaluation.score.body_ground_truth
            T = b.T_world_marker @ geo.se3_inverse(r.T_body_marker)
            paths[r.name] = (
                start + np.round(np.asarray(take.time_s)[b.valid] * 1e9).astype(np.int64),
                np.asarray(T)[b.valid],
            )
    objects = {}
    for o in m.objects:
        body = o.mocap_body or o.name
        b = take.bodies.get(body)
        if b is not None and b.valid.any():
            first = int(np.argmax(b.valid))
            objects[o.id] = b.T_world_marker[first] @ geo.se3_inverse(o.T_object_marker)
    return paths, objects


class _Log:
    """The MCAP's channels and a count of the messages logged on each."""

    def __init__(self, channels: dict[str, Any]):
        self.channels = channels
        self.counts: dict[str, int] = {}

    def __call__(self, topic: str, msg: Any, t_ns: int) -> None:
        self.channels[topic].log(msg, log_time=int(t_ns))
        self.counts[topic] = self.counts.get(topic, 0) + 1


def _read_outputs(
    run: rd.Run, robots: list[rd.RunRobot]
) -> tuple[dict[str, Track], dict[str, Track], dict[str, dict[int, np.ndarray]]]:
    """(final estimates, initial estimates, object maps) of the robots that have them."""
    from dran_edge.formats.run_outputs import read_objects_csv, trajectory_file
    from dran_edge.formats.tum import read_tum

    est: dict[str, Track] = {}
    init: dict[str, Track] = {}
    objs: dict[str, dict[int, np.ndarray]] = {}
    for r in robots:
        d = run.out_dir / r.name
        for kind, into in (("final", est), ("init", init)):
            tum_path = trajectory_file(run.out_dir, r.name, kind)
            if tum_path is not None:
                t, T = read_tum(tum_path)
                into[r.name] = (np.round(np.asarray(t) * 1e9).astype(np.int64), np.asarray(T))
        if (d / "objects.csv").exists():
            objs[r.name] = read_objects_csv(d / "objects.csv")
    return est, init, objs


def _log_paths(
    log: _Log,
    names: list[str],
    est: dict[str, Track],
    init: dict[str, Track],
    gt_paths: dict[str, Track] | None,
    edges: list[tuple[str, str]],
    start_ns: int,
    end_ns: int,
    step_s: float,
) -> None:
    """Every ``step_s``: each robot's paths up to then, its mocap path and the links."""
    step = int(step_s * 1e9)
    for t_ns in range(start_ns + step, end_ns + step, step):
        t_ns = min(t_ns, end_ns)
        last = {}
        for n in names:
            for topic, src in ((f"/{n}/path", est), (f"/{n}/path_init", init)):
                if n in src:
                    t, T = src[n]
                    upto = int(np.searchsorted(t, t_ns, side="right"))
                    if upto:
                        log(topic, vm.path_message(t_ns, T[:upto]), t_ns)
                        if topic.endswith("/path"):
                            last[n] = T[upto - 1][:3, 3]
            if gt_paths is not None and n in gt_paths:
                t, T = gt_paths[n]
                upto = int(np.searchsorted(t, t_ns, side="right"))
                if upto:  # ground truth at 10 Hz at most, for the file's size
                    stride = max(1, int(np.ceil(upto / max(1.0, (t_ns - t[0]) * 1e-8))))
                    log(f"/mocap/{n}", vm.path_message(t_ns, T[:upto:stride]), t_ns)
        log("/links", vm.links_message(t_ns, last, edges), t_ns)


def _log_objects(
    log: _Log,
    names: list[str],
    objs: dict[str, dict[int, np.ndarray]],
    gt_objects: dict[int, np.ndarray] | None,
    start_ns: int,
    end_ns: int,
) -> None:
    """Each robot's object map and the mocap's objects, at the start and the end."""
    for k, n in enumerate(names):
        if n in objs and objs[n]:
            ids = sorted(objs[n])
            Ts = np.stack([objs[n][i] for i in ids])
            for t_ns in (start_ns, end_ns):
                log(f"/{n}/objects", vm.objects_message(t_ns, n, k, ids, Ts), t_ns)
    if gt_objects:
        ids = sorted(gt_objects)
        Ts = np.stack([gt_objects[i] for i in ids])
        for t_ns in (start_ns, end_ns):
            log("/mocap/objects", vm.objects_message(t_ns, "mocap", 7, ids, Ts, alpha=0.3), t_ns)


def _log_rounds(log: _Log, run: rd.Run) -> None:
    """rounds.csv's rows as JSON at their stamps (NaN as null)."""
    from dran_edge.formats.run_outputs import read_rounds_csv

    if not (run.out_dir / "rounds.csv").exists():
        return
    rows = read_rounds_csv(run.out_dir / "rounds.csv")
    for i in range(len(rows["round"])):
        row = {
            k: (None if isinstance(v[i], float) and math.isnan(v[i]) else float(v[i]))
            for k, v in rows.items()
        }
        t_ns = int(row.get("stamp_ns") or run.mission.start_ns)
        log("/fleet/rounds", json.dumps(row).encode(), t_ns)


def write_run_mcap(run_dir: str | Path, path: str | Path, step_s: float = 1.0) -> dict[str, int]:
    """Write the MCAP file (module docstring); returns ``{topic: messages written}``."""
    foxglove = _foxglove()
    run = rd.open_run(run_dir)
    m = run.mission
    robots = sorted(m.robots, key=lambda r: r.id)
    names = [r.name for r in robots]
    est, init, objs = _read_outputs(run, robots)
    gt = _mocap(run)
    ctx = foxglove.Context()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    writer = foxglove.open_mcap(str(path), allow_overwrite=True, context=ctx)
    try:
        log = _Log(_channels(foxglove, ctx, names, gt is not None))
        end_ns = m.start_ns + int(m.duration_s * 1e9)
        for src in (est, init):
            for t, _T in src.values():
                end_ns = max(end_ns, int(t[-1]))
        name_of = {r.id: r.name for r in robots}
        edges = [(name_of[a], name_of[b]) for a, b in m.comm_graph]
        _log_paths(
            log,
            names,
            est,
            init,
            gt[0] if gt is not None else None,
            edges,
            m.start_ns,
            end_ns,
            step_s,
        )
        _log_objects(log, names, objs, gt[1] if gt is not None else None, m.start_ns, end_ns)
        _log_rounds(log, run)
    finally:
        writer.close()
    return log.counts
