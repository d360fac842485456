"""mission.yaml for runs recorded on robots (``dran-edge run --record``, ``merge-records``).

A recording holds, per robot, ``robots/<name>/robot.yaml`` and ``ingest.bin``
(docs/run-format.md). :func:`write_recorded_mission` derives the rest of a complete run from
them: the fleet and robots from the configs, ``start_ns`` / ``duration_s`` from the first and
last recorded stamps, ``comm_graph`` from the configured neighbours that are in the run, and
what is known of the mocap (a ``mocap.csv`` in the run: the file, and each robot whose name is
a rigid body of the take as its ``mocap_body``; ``mocap.start_ns`` is left out, so eval
estimates the clock offset unless it is added). What an existing mission.yaml says about a
robot, the objects or the mocap is kept. Pure apart from reading the files it names.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from dran_edge.formats import run_dir as rd
from dran_edge.errors import InputError


def ingest_span(path: str | Path, chunk: int = 1 << 20) -> tuple[int, int] | None:
    """(first, last) stamp of the records of an ``ingest.bin``, streamed; None if none decode."""
    from dran_edge.comms.ingest import StreamDecoder

    dec = StreamDecoder()
    lo: int | None = None
    hi: int | None = None
    with open(path, "rb") as f:
        while data := f.read(chunk):
            for rec in dec.feed(data):
                if isinstance(rec, Exception):
                    continue
                ev = rec.event
                s = getattr(ev, "stamp_ns", None)
                s = getattr(ev, "stamp_cur_ns", None) if s is None else s
                if s is None:
                    continue
                lo = s if lo is None else min(lo, s)
                hi = s if hi is None else max(hi, s)
    return None if lo is None or hi is None else (int(lo), int(hi))


def _robot_yaml(path: Path) -> tuple[int, str, str, tuple[int, ...]]:
    import yaml

    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
        r = data["robot"]
        nb = tuple(int(n["id"]) for n in data.get("neighbours") or ())
        return int(r["id"]), str(r["name"]), str(r.get("fleet", "fleet")), nb
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError) as exc:
        raise InputError(
            f"expected a recorded robot config with robot.id, robot.name "
            f"({type(exc).__name__}: {exc})",
            path=str(path),
        ) from None


def recorded_mission(run_dir: str | Path) -> rd.Mission:
    """The mission.yaml of a recording (see the module docstring)."""
    root = Path(run_dir)
    old = None
    if (root / "mission.yaml").exists():
        try:
            old = rd.read_mission(root / "mission.yaml")
        except InputError:
            old = None  # rebuilt from the recordings below
    robots: list[rd.RunRobot] = []
    spans: list[tuple[int, int]] = []
    links: set[tuple[int, int]] = set()
    fleet: str | None = None
    for d in sorted(p for p in (root / "robots").glob("*") if p.is_dir()):
        if not (d / "robot.yaml").exists() or not (d / "ingest.bin").exists():
            continue
        rid, name, fl, nb = _robot_yaml(d / "robot.yaml")
        span = ingest_span(d / "ingest.bin")
        if span is None:
            continue
        spans.append(span)
        fleet = fleet or fl
        prev = {r.name: r for r in old.robots}.get(name) if old else None
        robots.append(prev if prev is not None and prev.id == rid else rd.RunRobot(rid, name))
        links |= {(min(rid, n), max(rid, n)) for n in nb}
    if not robots:
        raise InputError(
            "no robot with robot.yaml and a non-empty ingest.bin under robots/", path=str(root)
        )
    assert fleet is not None  # set by the first robot
    ids = {r.id for r in robots}
    mocap_file = old.mocap_file if old else None
    if mocap_file is None and (root / "mocap.csv").exists():
        mocap_file = "mocap.csv"
    up = old.mocap_up_axis if old else "y"
    if mocap_file and (root / mocap_file).exists():
        robots = _with_mocap_bodies(root / mocap_file, robots, up)
    start = min(s[0] for s in spans)
    end = max(s[1] for s in spans)
    return rd.Mission(
        fleet=old.fleet if old else fleet,
        start_ns=start,
        duration_s=max((end - start) / 1e9, 1e-3),
        robots=tuple(sorted(robots, key=lambda r: r.id)),
        objects=old.objects if old else (),
        comm_graph=tuple(sorted(e for e in links if set(e) <= ids)),
        mocap_file=mocap_file,
        mocap_start_ns=old.mocap_start_ns if old else None,
        mocap_up_axis=up,
        simulation=old.simulation if old else None,
    )


def _with_mocap_bodies(path: Path, robots: list, up: str) -> list:
    from dran_edge.formats.motive import read_motive_csv

    try:
        bodies = set(read_motive_csv(path, up_axis=up).bodies)
    except InputError:
        return robots
    return [
        rd.RunRobot(r.id, r.name, r.name, r.T_body_marker, r.T_world_odom)
        if r.mocap_body is None and r.name in bodies
        else r
        for r in robots
    ]


def write_recorded_mission(run_dir: str | Path, mocap_start_ns: int | None = None) -> Path:
    """Write (or update) ``run_dir/mission.yaml`` from its recordings; returns its path.
    ``mocap_start_ns``: the robot-clock stamp of the mocap's time 0, when known."""
    from dataclasses import replace

    m = recorded_mission(run_dir)
    if mocap_start_ns is not None:
        if m.mocap_file is None:
            raise InputError(
                "a mocap start was given but the run has no mocap CSV", path=str(run_dir)
            )
        m = replace(m, mocap_start_ns=int(mocap_start_ns))
    return rd.write_mission(run_dir, m)


def merge_recordings(
    out_dir: str | Path,
    recordings: list[str | Path],
    mocap: str | Path | None = None,
    mocap_start_ns: int | None = None,
) -> Path:
    """Copy each recording's ``robots/<name>/`` (and a mocap CSV) into ``out_dir``, then write
    its mission.yaml. A robot name present twice is an error."""
    out = Path(out_dir)
    (out / "robots").mkdir(parents=True, exist_ok=True)
    for rec in map(Path, recordings):
        src = rec / "robots"
        if not src.is_dir():
            raise InputError(
                "expected a recording with robots/<name>/ (dran-edge run --record)", path=str(rec)
            )
        for d in sorted(p for p in src.iterdir() if p.is_dir()):
            dst = out / "robots" / d.name
            if dst.exists() and dst.resolve() != d.resolve():
                raise InputError(f"robot {d.name} is in two recordings", path=str(d))
            if not dst.exists():
                shutil.copytree(d, dst)
    if mocap is not None:
        if not Path(mocap).is_file():
            raise InputError("Motive CSV not found", path=str(mocap))
        shutil.copyfile(mocap, out / "mocap.csv")
    return write_recorded_mission(out, mocap_start_ns)
