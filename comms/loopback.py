"""Run robot nodes as separate processes over real RADIO/DISH, or all in one process on the bus.

A harness for tests and benchmarks (and for running the DRAN agents over UDP): one *node* per
robot, built by a factory named ``"module:function"``::

    node = factory(robot_id: int, neighbours: list[int], config: dict)
    node.step(round: int, received: list[NeighbourMessage])
        -> list[tuple[NeighbourMessage, list[int]]]   # messages and their recipients
    node.result() -> JSON-serialisable value

Both runners drive each node through ``link.NeighbourLink`` (encode, sign, verify, decode) with
the same round semantics as ``bus.BusParams(latency_rounds=1)``: in round k a node gets every
message sent to it in rounds < k (sorted by sender and sequence, so arrival order on UDP does
not matter), then its sends go out. ``run_bus_fleet`` does that in-process;
``run_loopback_fleet`` starts one process per robot (``python -m dran_edge.comms.loopback``),
each with a DISH on ``127.0.0.1:base_port + index`` and one RADIO per neighbour. The parent
keeps the processes in step over their stdin/stdout pipes, two phases per round (the datagrams
themselves only ever cross the UDP sockets):

1. ``poll k N``: the node reads its DISH until it holds the ``N`` datagrams sent to it in
   rounds < k (the parent adds up what the neighbours reported), or ``FleetSpec.wait_s``
   passed (then round k is listed in ``stalled_rounds``), and answers ``polled k``;
2. ``step k`` (once every node has polled): the node steps, sends, and answers ``sent k`` with
   its cumulative datagram count per neighbour.

So a slow process (a first solve, a busy machine) only slows the run down; it cannot move a
datagram into another round, and the UDP run matches the bus bit for bit unless a datagram is
really lost. Each runner returns, per robot: the node's result, the link counters, and the
SHA-256 of every accepted datagram (sorted), so the two runs can be compared byte for byte.

``GossipNode`` is a small reference node (object relay with hop counts plus one separator per
round) used by the tests and ``tools/bench/bench_comms.py``.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import os
import select
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from dran_edge import geometry as geo
from dran_edge.comms.auth import AuthPolicy
from dran_edge.comms.bus import Bus, BusParams
from dran_edge.comms.link import NeighbourLink
from dran_edge.errors import DranError
from dran_edge.messages import NeighbourMessage, ObjectEntry, SeparatorEntry


@dataclass(frozen=True)
class FleetSpec:
    """Everything both runners need; JSON-serialisable (passed to node processes)."""

    robot_ids: tuple[int, ...]
    #: Undirected communication edges.
    edges: tuple[tuple[int, int], ...]
    rounds: int
    #: ``"module:function"`` building a node (see the module docstring).
    node_factory: str = "dran_edge.comms.loopback:GossipNode"
    node_config: dict = field(default_factory=dict)
    fleet_id: int = 1
    group: str = "dran.loop"
    #: Fleet key as hex (tests only; robots read a key file).
    key_hex: str = "00" * 32
    boot_epoch: int = 1
    max_datagram_bytes: int = 1200
    #: Loopback runner only: how long a node waits for the datagrams sent to it in the
    #: previous round, and the first DISH port.
    wait_s: float = 5.0
    base_port: int = 46000

    def neighbours(self, robot: int) -> list[int]:
        return sorted({b if a == robot else a for a, b in self.edges if robot in (a, b)})

    def policy(self, robot: int) -> AuthPolicy:
        return AuthPolicy(
            fleet_id=self.fleet_id,
            self_id=robot,
            fleet_robots=frozenset(self.robot_ids),
            neighbours=frozenset(self.neighbours(robot)),
        )

    def port(self, robot: int) -> int:
        return self.base_port + list(self.robot_ids).index(robot)

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @staticmethod
    def from_json(text: str) -> FleetSpec:
        d = json.loads(text)
        d["robot_ids"] = tuple(d["robot_ids"])
        d["edges"] = tuple(tuple(e) for e in d["edges"])
        return FleetSpec(**d)


def _make_node(spec: FleetSpec, robot: int):
    module, _, name = spec.node_factory.partition(":")
    factory = getattr(importlib.import_module(module), name)
    return factory(robot, spec.neighbours(robot), dict(spec.node_config))


def _make_link(spec: FleetSpec, robot: int, transport) -> NeighbourLink:
    link = NeighbourLink(
        transport,
        key=bytes.fromhex(spec.key_hex),
        policy=spec.policy(robot),
        boot_epoch=spec.boot_epoch,
        max_datagram_bytes=spec.max_datagram_bytes,
    )
    link.accepted_datagrams = []
    return link


def _sorted(msgs: list[NeighbourMessage]) -> list[NeighbourMessage]:
    return sorted(msgs, key=lambda m: (m.sender_id, m.boot_epoch, m.sequence))


def _report(node, link: NeighbourLink) -> dict:
    return {
        "result": node.result(),
        "counters": link.counters.snapshot(),
        "accepted_sha256": sorted(hashlib.sha256(d).hexdigest() for d in link.accepted_datagrams),
    }


def run_bus_fleet(spec: FleetSpec, params: BusParams | None = None) -> dict[int, dict]:
    """All nodes in this process over a ``Bus`` with the spec's edges (default: lossless)."""
    params = BusParams() if params is None else params
    bus = Bus(spec.robot_ids, graph=spec.edges, params=params)
    nodes = {i: _make_node(spec, i) for i in spec.robot_ids}
    links = {i: _make_link(spec, i, bus.endpoint(i)) for i in spec.robot_ids}
    for k in range(spec.rounds):
        for i in spec.robot_ids:
            for msg, to in nodes[i].step(k, _sorted(links[i].poll(now_ns=k))):
                links[i].send_message(msg, to)
        bus.advance()
    return {i: _report(nodes[i], links[i]) for i in spec.robot_ids}


def run_loopback_fleet(spec: FleetSpec, *, timeout_s: float = 60.0) -> dict[int, dict]:
    """One process per robot over RADIO/DISH on 127.0.0.1, kept in step by this process (see
    the module docstring); raises ``DranError`` when a node fails or does not answer within
    ``timeout_s``."""
    with tempfile.TemporaryDirectory(prefix="dran-loop-") as tmp:
        procs: dict[int, tuple[subprocess.Popen, str, str]] = {}
        try:
            for i in spec.robot_ids:
                out = os.path.join(tmp, f"robot{i}.json")
                cmd = [
                    sys.executable,
                    "-m",
                    "dran_edge.comms.loopback",
                    "--robot",
                    str(i),
                    "--out",
                    out,
                ]
                # stderr to a file, not a pipe: a chatty node must never block on a full pipe.
                err_path = os.path.join(tmp, f"robot{i}.err")
                with open(err_path, "w", encoding="utf-8") as err_file:
                    p = subprocess.Popen(
                        cmd,
                        stdin=subprocess.PIPE,
                        stdout=subprocess.PIPE,
                        stderr=err_file,
                        text=True,
                        bufsize=1,
                    )
                procs[i] = (p, out, err_path)
                p.stdin.write(spec.to_json() + "\n")
            ask = _Steward(procs, timeout_s)
            ask.all("", "ready")
            # sent[j][i]: datagrams robot j has sent to robot i so far
            sent = {j: {} for j in spec.robot_ids}
            for k in range(spec.rounds):
                ask.all(
                    lambda i: f"poll {k} {sum(sent[j].get(i, 0) for j in spec.robot_ids)}",
                    f"polled {k}",
                )
                for j, reply in ask.all(f"step {k}", f"sent {k}").items():
                    sent[j] = {int(q): n for q, n in json.loads(reply).items()}
            ask.all("end", "done")
            reports = {}
            for i, (p, out, _) in procs.items():
                p.wait(timeout=timeout_s)
                with open(out, encoding="utf-8") as f:
                    reports[i] = json.load(f)
        finally:
            for p, _, _ in procs.values():
                if p.poll() is None:
                    p.kill()
                    p.wait()
                for stream in (p.stdin, p.stdout):
                    try:
                        stream.close()
                    except OSError:  # a pipe to a process that died
                        pass
    return reports


class _Steward:
    """The parent's side of the round protocol: one command line out, one answer line back."""

    def __init__(self, procs: dict, timeout_s: float):
        self.procs, self.timeout_s = procs, timeout_s

    def all(self, command, answer: str) -> dict[int, str]:
        """Send ``command`` (a string, or a function of the robot id; "" sends nothing) to every
        node, then read each one's answer line, which must start with ``answer``; returns the
        rest of each line."""
        for i, (p, _, _) in self.procs.items():
            text = command(i) if callable(command) else command
            if text:
                try:
                    p.stdin.write(text + "\n")
                except (BrokenPipeError, OSError):
                    self._fail(i, f"exited before {text!r}")
        replies = {}
        for i, (p, _, _) in self.procs.items():
            ready, _, _ = select.select([p.stdout], [], [], self.timeout_s)
            line = p.stdout.readline() if ready else None
            if line is None:
                self._fail(i, f"no {answer!r} within {self.timeout_s:.0f} s")
            if not line:
                self._fail(i, f"exited before answering {answer!r}")
            if not line.startswith(answer):
                self._fail(i, f"expected {answer!r}, got {line.strip()[:200]!r}")
            replies[i] = line[len(answer) :].strip()
        return replies

    def _fail(self, robot: int, what: str):
        p, _, err_path = self.procs[robot]
        if p.poll() is None:
            p.kill()
        p.wait()
        with open(err_path, encoding="utf-8", errors="replace") as f:
            err = f.read().strip()[-2000:]
        raise DranError(
            f"loopback fleet failed: robot {robot}: {what} (exit {p.returncode})"
            + (f": {err}" if err else "")
        )


def _node_main(robot: int, out: str) -> int:
    from dran_edge.comms.radio import RadioParams, RadioTransport

    # The protocol owns the stdout pipe; whatever the node (or a native library) prints goes
    # to stderr, a file.
    proto = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    spec = FleetSpec.from_json(sys.stdin.readline())
    params = RadioParams(
        group=spec.group,
        bind=f"udp://127.0.0.1:{spec.port(robot)}",
        neighbours={j: f"udp://127.0.0.1:{spec.port(j)}" for j in spec.neighbours(robot)},
        max_datagram_bytes=spec.max_datagram_bytes,
    )
    node = _make_node(spec, robot)
    stalled = []
    with RadioTransport(params) as radio:
        link = _make_link(spec, robot, radio)
        time.sleep(0.2)  # let libzmq's I/O thread bind the DISH and connect the RADIOs
        print("ready", file=proto)
        received: list[NeighbourMessage] = []
        while line := sys.stdin.readline():
            cmd, *args = line.split()
            if cmd == "poll":
                k, expected = int(args[0]), int(args[1])
                deadline = time.monotonic() + spec.wait_s
                while True:
                    received += link.poll(now_ns=k)
                    if radio.counters.totals()["datagrams_received"] >= expected:
                        break
                    if time.monotonic() > deadline:
                        stalled.append(k)
                        break
                    radio.wait(0.01)
                print(f"polled {k}", file=proto)
            elif cmd == "step":
                k = int(args[0])
                for msg, to in node.step(k, _sorted(received)):
                    link.send_message(msg, to)
                received = []
                counts = {
                    str(q): radio.counters.peers[q].datagrams_sent for q in spec.neighbours(robot)
                }
                print(f"sent {k} {json.dumps(counts)}", file=proto)
            elif cmd == "end":
                break
        report = _report(node, link)
    report["stalled_rounds"] = stalled
    with open(out, "w", encoding="utf-8") as f:
        json.dump(report, f)
    print("done", file=proto)
    return 0


# --------------------------------------------------------------------------- reference node
class GossipNode:
    """Reference node: relays object estimates with hop counts (paper Sec. 4.2.2 style).

    Robot i owns object ``i`` (a seeded random SE(3) pose) and, each round, sends every
    object it knows (own at hop 0, learnt ones at hop + 1, keeping the lowest hop) plus one
    separator (keyframe ``k``) to all neighbours. ``result()`` lists the objects known.
    """

    def __init__(self, robot: int, neighbours: list[int], config: dict):
        self.robot = robot
        self.neighbours = list(neighbours)
        rng = np.random.default_rng([int(config.get("seed", 0)), robot])
        xi = rng.normal(size=6) * np.array([20, 20, 2, 1, 1, 1])
        self.known: dict[int, tuple[np.ndarray, int, int]] = {robot: (geo.se3_exp(xi), robot, 0)}
        self.separator_poses = geo.se3_exp(rng.normal(size=(4, 6)))
        self.received = 0

    def step(self, round_: int, received: list[NeighbourMessage]):
        for msg in received:
            self.received += 1
            for e in msg.objects:
                hop = e.hop_count + 1
                cur = self.known.get(e.object_id)
                if cur is None or hop < cur[2]:
                    self.known[e.object_id] = (e.T_world_object, e.origin_robot, hop)
        if not self.neighbours:
            return []
        objects = tuple(
            ObjectEntry(oid, T, origin, hop) for oid, (T, origin, hop) in sorted(self.known.items())
        )
        sep = SeparatorEntry(
            self.robot,
            round_,
            1_000_000 * round_,
            self.separator_poses[round_ % len(self.separator_poses)],
        )
        msg = NeighbourMessage(
            sender_id=self.robot,
            round=round_,
            stamp_ns=1_000_000 * round_,
            separators=(sep,),
            objects=objects,
        )
        return [(msg, self.neighbours)]

    def result(self):
        return {
            "messages_received": self.received,
            "objects": {
                str(oid): {
                    "origin": origin,
                    "hop": hop,
                    "xyz_quat_xyzw": [round(float(v), 9) for v in geo.se3_to_xyz_quat_xyzw(T)],
                }
                for oid, (T, origin, hop) in sorted(self.known.items())
            },
        }


#: A message with this round number makes a DISH target print its counters and exit.
STOP_ROUND = 2**40


def _dish_target_main(robot: int, bind: str, max_s: float) -> int:
    """A live DISH for robustness tests: prints ``ready``, then ``ok SENDER SEQ ROUND`` per
    accepted datagram, and ``counters JSON`` + exit 0 on a message with ``STOP_ROUND``."""
    from dran_edge.comms.radio import RadioParams, RadioTransport

    spec = FleetSpec.from_json(sys.stdin.read())
    end = time.time() + max_s
    with RadioTransport(
        RadioParams(group=spec.group, bind=bind, max_datagram_bytes=spec.max_datagram_bytes)
    ) as radio:
        link = NeighbourLink(
            radio,
            key=bytes.fromhex(spec.key_hex),
            policy=spec.policy(robot),
            boot_epoch=spec.boot_epoch,
        )
        print("ready", flush=True)
        while time.time() < end:
            radio.wait(0.05)
            for msg in link.poll(now_ns=time.time_ns()):
                if msg.round == STOP_ROUND:
                    report = {
                        "link": link.counters.snapshot(),
                        "transport": radio.counters.snapshot(),
                    }
                    print("counters " + json.dumps(report), flush=True)
                    return 0
                print(f"ok {msg.sender_id} {msg.sequence} {msg.round}", flush=True)
    print("timeout", flush=True)
    return 3


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description="a loopback fleet node, or (--dish-target) a live DISH that reports what it "
        "accepts; FleetSpec JSON on stdin"
    )
    ap.add_argument("--robot", type=int, required=True)
    ap.add_argument("--out", help="JSON report path (fleet node; the round protocol on stdin)")
    ap.add_argument("--dish-target", metavar="BIND", help="run a DISH target bound to BIND")
    ap.add_argument("--max-s", type=float, default=600.0, help="DISH target time limit")
    a = ap.parse_args(argv)
    if a.dish_target:
        return _dish_target_main(a.robot, a.dish_target, a.max_s)
    if a.out is None:
        ap.error("--out is required for a fleet node")
    return _node_main(a.robot, a.out)


if __name__ == "__main__":
    sys.exit(main())
