"""``dran-edge rehearse``: a fleet of real ``dran-edge run`` processes through a recorded run.

:func:`rehearse` (docs/rehearsal.md):

1. **Network and configs.** One network namespace per robot (:mod:`.netns`; loopback
   addresses where namespaces are not permitted). Each robot gets a config written from the
   run's ``robot.yaml``: its address and port, its neighbours' addresses (the run's
   communication graph), a fresh fleet key, the ingest socket, its own state directory,
   ``robot.T_world_odom`` from mission.yaml (as replay hands it to the core) and
   ``comms.period_s`` divided by ``speed`` (a round per half second of *mission* time, as
   in replay).
2. **Daemons.** ``dran-edge run --config ... --record ...`` per robot, started inside its
   namespace; the rehearsal waits until every status socket answers.
3. **Feeding.** Each robot's ``ingest.bin`` records go through its real ingest socket when
   the mission clock (``speed`` x wall time since the start) passes their stamp, as the VINS
   bridge would send them: while the daemon is down they wait in a queue and go out on
   reconnection. Runs with recorded frames get perception's observation records (the replay's
   pipeline, run here before the start) merged by stamp.
4. **Faults** (:mod:`.faults`) act when the mission clock reaches them.
5. **End.** After the data, ``settle_rounds`` more rounds of mission time, then until every
   daemon has journalled and applied what it was sent; SIGTERM (each checkpoints and stops).
6. **Outputs.** Each robot's final checkpoint is loaded into its core and written in replay's
   output format (``OUT/out``), scored by :func:`dran_edge.evaluation.score.evaluate_run` like
   ``dran-edge eval``; ``OUT/rehearsal.json`` has the metrics, per-robot daemon counters, the
   status timeline and the fault checks (nothing accepted lost; rejoin).

One robot's daemon (its state, records and robot.yaml) is in :mod:`.robot_daemon`; the report
in :mod:`.report`.

Size: over ~500 lines because the fleet's lifecycle (namespaces, start, faults, collection) as
one class; over 500 only by ruff format's layout.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dran_edge.formats import run_dir as rd
from dran_edge.errors import DranError, InputError
from dran_edge.rehearsal import faults as fl
from dran_edge.comms.drop_hook import write_rules
from dran_edge.daemon.notify import environ_without_systemd
from dran_edge.rehearsal.clock import clock_env, clock_step, find_faketime, write_faketime
from dran_edge.rehearsal.netns import make_net
from dran_edge.rehearsal.report import RehearsalResult, finish, round_row, sample
from dran_edge.rehearsal.robot_daemon import (
    RobotDaemon,
    daemon_config,
    ingest_records,
    perceived_records,
)

log = logging.getLogger(__name__)

#: Files and folders of the run the rehearsal's directory links to (it writes out/ and eval/).
_RUN_PARTS = ("mission.yaml", "calib", "robots")


@dataclass(frozen=True)
class RehearsalOptions:
    """How to rehearse a run."""

    speed: float = 1.0
    """Mission seconds per wall second (1: mission pace)."""
    net: str = "auto"
    """``auto`` (namespaces if permitted, else loopback), ``netns`` or ``loopback``."""
    settle_rounds: int = 20
    """Rounds of mission time after the data ends (as replay's settle rounds)."""
    faults: tuple[fl.Fault, ...] = ()
    out_dir: str | None = None
    """Where to write (default RUN/rehearsal); replaced if it holds a previous rehearsal."""
    evaluate: bool = True
    start_timeout_s: float = 120.0
    """How long the daemons may take to come up."""
    drain_timeout_s: float = 60.0
    """How long the end waits for the daemons to apply what they were sent."""
    poll_s: float = 0.5
    """Wall seconds between status polls of every daemon."""

    def __post_init__(self) -> None:
        if not self.speed > 0 or not math.isfinite(self.speed):
            raise InputError(f"--speed: expected a number > 0, got {self.speed}")
        if self.settle_rounds < 0:
            raise InputError(f"--settle-rounds: expected >= 0, got {self.settle_rounds}")


# ------------------------------------------------------------------------------ the fleet
class Fleet:
    """The daemons of one rehearsal, their network, feeding and faults (module docstring)."""

    def __init__(self, run_dir: str | Path, opt: RehearsalOptions):
        # Long: the rehearsal's set-up in order (namespaces, configs, keys, daemons), each step a
        # few lines; splitting it would only pass the same dozen fields around.
        import yaml

        from dran_edge.comms.auth import write_fleet_key
        from dran_edge.config import load_config

        self.opt = opt
        self.src = rd.open_run(run_dir)
        self.mission = self.src.mission
        self.out = (Path(opt.out_dir) if opt.out_dir else self.src.root / "rehearsal").resolve()
        _prepare_out(self.out, self.src)
        self.run = rd.open_run(self.out)
        infos = sorted(self.mission.robots, key=lambda r: r.id)
        self.names = {r.id: r.name for r in infos}
        configs = {r.id: self.src.load_config(r.name) for r in infos}
        periods = {c.comms.period_s for c in configs.values()}
        if len(periods) != 1:
            raise InputError(
                f"robots of one run must share comms.period_s, got {sorted(periods)}",
                path=str(self.src.root),
            )
        self.period_s = periods.pop()
        self.net, self.net_note = make_net(len(infos), opt.net)
        self._tmp = Path(tempfile.mkdtemp(prefix="dre-"))  # short paths for the sockets
        try:
            key_file = self.out / "fleet.key"
            write_fleet_key(key_file)
            self.daemons: dict[int, RobotDaemon] = {}
            for k, info in enumerate(infos):
                base = self.out / "daemons" / info.name
                base.mkdir(parents=True, exist_ok=True)
                raws, release, rejected = ingest_records(self.src, info.name)
                perceived = perceived_records(self.src, info.name)
                if perceived:
                    merged = sorted(
                        [(int(s), i, r) for i, (s, r) in enumerate(zip(release, raws))]
                        + [(s, len(raws) + i, r) for i, (s, r) in enumerate(perceived)]
                    )
                    release = np.array([m[0] for m in merged], np.int64)
                    raws = [m[2] for m in merged]
                d = RobotDaemon(
                    info.id,
                    info.name,
                    k,
                    base / "robot.yaml",
                    base / "state",
                    self._tmp / str(k),
                    base / "record",
                    base / "daemon.log",
                    base / "drop.json",
                    raws,
                    release,
                    rejected_in_file=rejected,
                )
                self.daemons[info.id] = d
            for k, info in enumerate(infos):
                d = self.daemons[info.id]
                nbrs = [
                    (j, self.names[j], self.net.endpoints[self.daemons[j].k])
                    for j in self.mission.neighbours(info.id)
                ]
                cfg = daemon_config(
                    self.src,
                    info,
                    self.net.endpoints[k],
                    nbrs,
                    key_file,
                    d,
                    self.period_s / opt.speed,
                )
                d.config.write_text(yaml.safe_dump(cfg, sort_keys=False), encoding="utf-8")
                load_config(d.config)  # what the daemon will load: fail here, not in it
                write_rules(d.drop_file, {})
            # A daemon whose rehearsal died stops by itself: SIGTERM when the rehearsal's
            # process ends (_stop_with_parent), and at the latest after the rounds the whole
            # rehearsal could last.
            wall_s = (
                opt.start_timeout_s
                + opt.drain_timeout_s
                + 120.0
                + (self.mission.duration_s + opt.settle_rounds * self.period_s) / opt.speed
            )
            self.max_rounds = int(math.ceil(wall_s / (self.period_s / opt.speed)))
            self.loss: dict[tuple[int, int], float] = {}
            self.silenced: set[int] = set()
            self.fault_log: list[dict] = []
            self.t0_wall: float | None = None
        except BaseException:
            self.close()
            raise

    # -------------------------------------------------------------------- clocks
    def mission_ns(self) -> int:
        assert self.t0_wall is not None
        return self.mission.start_ns + int((time.monotonic() - self.t0_wall) * self.opt.speed * 1e9)

    def mission_s(self) -> float:
        return (self.mission_ns() - self.mission.start_ns) * 1e-9

    # -------------------------------------------------------------------- processes
    def start(self, d: RobotDaemon) -> None:
        env = environ_without_systemd()
        env["DRAN_EDGE_DROP_FILE"] = str(d.drop_file)
        env["OPENBLAS_NUM_THREADS"] = "1"
        env.update(clock_env(d))
        argv = [
            sys.executable,
            "-m",
            "dran_edge.cli.app",
            "run",
            "--config",
            str(d.config),
            "--record",
            str(d.record_dir),
            "--max-rounds",
            str(self.max_rounds),
        ]
        with open(d.log_path, "ab") as logf:
            logf.write(f"--- start {d.starts + 1} ---\n".encode())
            logf.flush()
            d.proc = subprocess.Popen(
                self.net.wrap(d.k, argv),
                env=env,
                stdout=logf,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                preexec_fn=_stop_with_parent,
            )
        d.starts += 1
        d.last_status = None

    def wait_up(self, ds: list[RobotDaemon], timeout_s: float) -> None:
        from dran_edge.daemon.status import query_status

        end = time.monotonic() + timeout_s
        waiting = list(ds)
        while waiting:
            for d in list(waiting):
                if d.proc is not None and d.proc.poll() is not None:
                    raise DranError(
                        f"the daemon of {d.name} exited ({d.proc.returncode}) while "
                        f"starting; see {d.log_path}:\n{_tail(d.log_path)}"
                    )
                try:
                    st = query_status(d.status_path, timeout_s=1.0)
                except DranError:
                    continue
                pid = d.proc.pid if d.proc is not None else None
                if st.get("state") == "running" and st.get("pid") == pid:
                    waiting.remove(d)
            if waiting and time.monotonic() > end:
                raise DranError(
                    f"daemons not up after {timeout_s:g} s: "
                    f"{', '.join(d.name for d in waiting)} (logs in {self.out}/daemons)"
                )
            time.sleep(0.1)

    def kill(self, d: RobotDaemon) -> None:
        if d.proc is not None and d.proc.poll() is None:
            os.kill(d.proc.pid, signal.SIGKILL)
            d.proc.wait(timeout=30)
        self._disconnect(d)

    def stop_all(self, timeout_s: float = 60.0) -> dict[str, int | None]:
        for d in self.daemons.values():
            if d.proc is not None and d.proc.poll() is None:
                d.proc.send_signal(signal.SIGTERM)
        codes: dict[str, int | None] = {}
        end = time.monotonic() + timeout_s
        for d in self.daemons.values():
            if d.proc is None:
                continue
            try:
                codes[d.name] = d.proc.wait(timeout=max(0.1, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.kill(d.proc.pid, signal.SIGKILL)
                codes[d.name] = d.proc.wait(timeout=10)
                log.error("%s did not stop on SIGTERM within %g s: killed", d.name, timeout_s)
            self._disconnect(d)
        return codes

    # -------------------------------------------------------------------- feeding
    def feed(self, d: RobotDaemon, now_ns: int) -> None:
        end = int(np.searchsorted(d.release_ns, now_ns, side="right"))
        if end > d.next_record:
            d.queue.extend(range(d.next_record, end))
            d.next_record = end
        if not d.queue or d.proc is None or d.proc.poll() is not None:
            return
        if d.sock is None:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.settimeout(5.0)
            try:
                s.connect(str(d.ingest_path))
            except OSError:
                s.close()
                return  # not up yet: the records wait, as the bridge's queue does
            d.sock = s
            d.connections.append({"pid": d.proc.pid, "sent": [], "accepted": 0})
        batch = d.queue
        try:
            d.sock.sendall(b"".join(d.records[i] for i in batch))
        except OSError:
            self._disconnect(d)
            return
        d.connections[-1]["sent"].extend(batch)
        d.queue = []

    def _disconnect(self, d: RobotDaemon) -> None:
        if d.sock is not None:
            d.sock.close()
            d.sock = None

    # -------------------------------------------------------------------- status
    def poll(self) -> dict[int, dict]:
        from dran_edge.daemon.status import query_status

        t = self.mission_s()
        out = {}
        for d in self.daemons.values():
            if d.proc is None or d.proc.poll() is not None:
                continue
            try:
                st = query_status(d.status_path, timeout_s=1.0)
            except DranError:
                continue
            if st.get("pid") != d.proc.pid:
                continue
            d.last_status = st
            if d.connections and d.connections[-1]["pid"] == d.proc.pid:
                d.connections[-1]["accepted"] = int((st.get("ingest") or {}).get("records", 0))
            d.samples.append(sample(t, st))
            out[d.id] = st
        return out

    # -------------------------------------------------------------------- faults
    def apply(self, a: fl.Action) -> None:
        f = a.fault
        d = {r: self.daemons[r] for r in f.robots}
        entry = {
            "t_s": round(self.mission_s(), 3),
            "at_s": a.t_s,
            "action": a.what,
            "fault": f.describe(self.names),
            "index": a.index,
        }
        if f.kind == "kill":
            (dm,) = d.values()
            if a.what == "start":
                self.kill(dm)
            else:
                self.start(dm)
        elif f.kind == "partition":
            start = a.what == "start"
            if self.net.kind == "netns":
                if start:
                    self.net.partition([x.k for x in d.values()])
                else:
                    self.net.heal()
                entry["by"] = "network"
            else:
                entry["by"] = "drop hook"
                for i in self.daemons:
                    for j in self.daemons:
                        if (i in f.robots) != (j in f.robots):
                            self.loss[(i, j)] = 1.0 if start else 0.0
                self._write_drops()
        elif f.kind == "silent":
            (dm,) = d.values()
            on = a.what == "start"
            if self.net.silence(dm.k, on):
                entry["by"] = "network"
            else:
                entry["by"] = "drop hook"
                for j in self.daemons:
                    if j != dm.id:
                        self.loss[(dm.id, j)] = 1.0 if on else 0.0
                        self.loss[(j, dm.id)] = 1.0 if on else 0.0
                self._write_drops()
        elif f.kind == "loss":
            i, j = f.robots
            p = f.probability if a.what == "start" else 0.0
            self.loss[(i, j)] = self.loss[(j, i)] = p
            entry["by"] = "drop hook"
            self._write_drops()
        elif f.kind == "clock_step":
            (dm,) = d.values()
            entry.update(clock_step(dm, f.step_s))
        self.fault_log.append(entry)
        log.info("fault: %s %s at %.1f s", a.what, entry["fault"], entry["t_s"])

    def _write_drops(self) -> None:
        for i, d in self.daemons.items():
            write_rules(d.drop_file, {j: p for (a, j), p in self.loss.items() if a == i})

    # -------------------------------------------------------------------- cleanup
    def close(self) -> None:
        for d in getattr(self, "daemons", {}).values():
            if d.proc is not None and d.proc.poll() is None:
                os.kill(d.proc.pid, signal.SIGKILL)
                d.proc.wait(timeout=10)
            self._disconnect(d)
        net = getattr(self, "net", None)
        if net is not None:
            net.close()
        tmp = getattr(self, "_tmp", None)
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)


# ------------------------------------------------------------------------------ helpers
def _stop_with_parent() -> None:
    """In the child before exec: SIGTERM when the rehearsal's process dies (Linux prctl
    PR_SET_PDEATHSIG; kept across ``ip netns exec``'s exec). Elsewhere a no-op."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def _prepare_out(out: Path, src: rd.Run) -> None:
    """``out`` as a run directory: links to the run's inputs, room for out/ and eval/."""
    if out.exists() and any(out.iterdir()):
        if not (out / "rehearsal.json").exists() and not (out / "daemons").exists():
            raise InputError(
                "exists and is not a previous rehearsal; choose another --out", path=str(out)
            )
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    parts = list(_RUN_PARTS)
    if src.mission.mocap_file:
        parts.append(src.mission.mocap_file)
    for part in parts:
        target = (src.root / part).resolve()
        if target.exists():
            link = out / part
            link.parent.mkdir(parents=True, exist_ok=True)
            link.symlink_to(target)


def _tail(path: Path, n: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


# ------------------------------------------------------------------------------ the run
def rehearse(
    run_dir: str | Path, opt: RehearsalOptions = RehearsalOptions(), progress=None
) -> RehearsalResult:
    """Rehearse the run at ``run_dir`` (module docstring); writes ``OUT/rehearsal.json``."""
    wall0 = time.perf_counter()
    fleet = Fleet(run_dir, opt)
    try:
        if any(f.kind == "clock_step" for f in opt.faults):
            lib = find_faketime()
            for f in opt.faults:
                if f.kind == "clock_step" and lib:
                    d = fleet.daemons[f.robots[0]]
                    d.faketime_lib = lib
                    write_faketime(d)
        return _run(fleet, opt, wall0, progress)
    finally:
        fleet.close()


def _run(fleet: Fleet, opt: RehearsalOptions, wall0: float, progress) -> RehearsalResult:
    ds = list(fleet.daemons.values())
    phases = {"prepare": time.perf_counter() - wall0}
    t = time.perf_counter()
    for d in ds:
        fleet.start(d)
    fleet.wait_up(ds, opt.start_timeout_s)
    phases["start"] = time.perf_counter() - t
    t = time.perf_counter()
    last_release = max((int(d.release_ns[-1]) for d in ds if len(d.release_ns)), default=0)
    data_end_ns = max(last_release, fleet.mission.start_ns + int(fleet.mission.duration_s * 1e9))
    end_ns = data_end_ns + int(opt.settle_rounds * fleet.period_s * 1e9)
    todo = fl.actions(list(opt.faults))
    fleet.t0_wall = time.monotonic()
    step_s = min(0.05, 0.25 * fleet.period_s / opt.speed)
    next_poll = 0.0
    rows: list[dict] = []
    while True:
        now = fleet.mission_ns()
        while todo and fleet.mission.start_ns + int(todo[0].t_s * 1e9) <= now:
            fleet.apply(todo.pop(0))
        for d in ds:
            fleet.feed(d, now)
        if time.monotonic() >= next_poll:
            next_poll = time.monotonic() + opt.poll_s
            rows.append(round_row(len(rows), now, fleet.poll()))
            if progress:
                progress(
                    "mission s",
                    int((min(now, end_ns) - fleet.mission.start_ns) // 10**9),
                    int(math.ceil((end_ns - fleet.mission.start_ns) / 1e9)),
                )
        if now >= end_ns:
            break
        time.sleep(step_s)
    for a in todo:  # what is still pending at the end ends now (a late restart happens)
        if a.what == "end":
            fleet.apply(a)
    phases["mission"] = time.perf_counter() - t
    t = time.perf_counter()
    drained = _drain(fleet, opt.drain_timeout_s)
    rows.append(round_row(len(rows), fleet.mission_ns(), fleet.poll()))
    phases["drain"] = time.perf_counter() - t
    t = time.perf_counter()
    exit_codes = fleet.stop_all()
    phases["stop"] = time.perf_counter() - t
    return finish(fleet, opt, rows, drained, exit_codes, wall0, phases)


def _drain(fleet: Fleet, timeout_s: float) -> bool:
    """Wait until each live daemon accepted and applied every record sent on its connection."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        for d in fleet.daemons.values():
            fleet.feed(d, 2**63 - 1)
        fleet.poll()
        done = True
        for d in fleet.daemons.values():
            if d.proc is None or d.proc.poll() is not None:
                continue
            st = d.last_status or {}
            sent = len(d.connections[-1]["sent"]) if d.connections else 0
            if (
                d.queue
                or d.connections[-1]["accepted"] < sent
                or (st.get("journal") or {}).get("pending", 1) != 0
            ):
                done = False
        if done:
            return True
        time.sleep(0.2)
    log.warning("daemons did not apply everything they were sent within %g s", timeout_s)
    return False
