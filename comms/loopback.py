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
each with a DISH on ``127.0.0.1:base_port + index`` and one RADIO per neighbour. Processes keep
in step on absolute deadlines from a shared start time: poll at ``t0 + k·period``, send at
``t0 + (k + ½)·period``, so a loopback delivery (well under a millisecond) lands in the next
round as on the bus. Each runner returns, per robot: the node's result, the link counters, and
the SHA-256 of every accepted datagram (sorted), so the two runs can be compared byte for byte.

``GossipNode`` is a small reference node (object relay with hop counts plus one separator per
round) used by the tests and ``tools/bench/bench_comms.py``.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import os
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
    #: Loopback runner only: round period and first DISH port.
    period_s: float = 0.1
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


def run_loopback_fleet(
    spec: FleetSpec, *, start_delay_s: float = 3.0, timeout_s: float = 60.0
) -> dict[int, dict]:
    """One process per robot over RADIO/DISH on 127.0.0.1; raises ``DranError`` on failure."""
    t0 = time.time() + start_delay_s
    with tempfile.TemporaryDirectory(prefix="dran-loop-") as tmp:
        procs = {}
        for i in spec.robot_ids:
            out = os.path.join(tmp, f"robot{i}.json")
            cmd = [
                sys.executable,
                "-m",
                "dran_edge.comms.loopback",
                "--robot",
                str(i),
                "--t0",
                repr(t0),
                "--out",
                out,
            ]
            # stderr to a file, not a pipe: a chatty node must never block on a full pipe.
            err_path = os.path.join(tmp, f"robot{i}.err")
            with open(err_path, "w", encoding="utf-8") as err_file:
                p = subprocess.Popen(
                    cmd,
                    stdin=subprocess.PIPE,
                    stdout=subprocess.DEVNULL,
                    stderr=err_file,
                    text=True,
                )
            procs[i] = (p, out, err_path)
            p.stdin.write(spec.to_json())
            p.stdin.close()
        try:
            deadline = t0 + spec.rounds * spec.period_s + timeout_s
            failures = []
            reports = {}
            for i, (p, out, err_path) in procs.items():
                try:
                    p.wait(timeout=max(deadline - time.time(), 1.0))
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
                    failures.append(f"robot {i}: timed out")
                    continue
                with open(err_path, encoding="utf-8", errors="replace") as f:
                    err = f.read()
                if p.returncode != 0:
                    failures.append(f"robot {i}: exit {p.returncode}: {err.strip()[-2000:]}")
                    continue
                with open(out, encoding="utf-8") as f:
                    reports[i] = json.load(f)
        finally:
            for p, _, _ in procs.values():
                if p.poll() is None:
                    p.kill()
                    p.wait()
        if failures:
            raise DranError("loopback fleet failed: " + "; ".join(failures))
    return reports


def _node_main(robot: int, t0: float, out: str) -> int:
    from dran_edge.comms.radio import RadioParams, RadioTransport

    spec = FleetSpec.from_json(sys.stdin.read())
    params = RadioParams(
        group=spec.group,
        bind=f"udp://127.0.0.1:{spec.port(robot)}",
        neighbours={j: f"udp://127.0.0.1:{spec.port(j)}" for j in spec.neighbours(robot)},
        max_datagram_bytes=spec.max_datagram_bytes,
    )
    node = _make_node(spec, robot)
    late = []
    with RadioTransport(params) as radio:
        link = _make_link(spec, robot, radio)
        for k in range(spec.rounds):
            _sleep_until(t0 + k * spec.period_s)
            received = _sorted(link.poll(now_ns=k))
            sends = node.step(k, received)
            if time.time() > t0 + (k + 0.5) * spec.period_s:
                late.append(k)
            _sleep_until(t0 + (k + 0.5) * spec.period_s)
            for msg, to in sends:
                link.send_message(msg, to)
        report = _report(node, link)
    report["late_rounds"] = late
    with open(out, "w", encoding="utf-8") as f:
        json.dump(report, f)
    return 0


def _sleep_until(t: float) -> None:
    while True:
        dt = t - time.time()
        if dt <= 0:
            return
        time.sleep(min(dt, 0.05))


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
    ap.add_argument("--t0", type=float, help="shared start time (time.time())")
    ap.add_argument("--out", help="JSON report path")
    ap.add_argument("--dish-target", metavar="BIND", help="run a DISH target bound to BIND")
    ap.add_argument("--max-s", type=float, default=600.0, help="DISH target time limit")
    a = ap.parse_args(argv)
    if a.dish_target:
        return _dish_target_main(a.robot, a.dish_target, a.max_s)
    if a.t0 is None or a.out is None:
        ap.error("--t0 and --out are required for a fleet node")
    return _node_main(a.robot, a.t0, a.out)


if __name__ == "__main__":
    sys.exit(main())
