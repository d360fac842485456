"""RADIO/DISH transport: dependency checks, size cap, multi-process loopback fleet vs the bus,
and two hosts in network namespaces (skipped where not permitted)."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
import uuid

import pytest

from dran_edge.comms import radio
from dran_edge.comms.loopback import FleetSpec, run_bus_fleet, run_loopback_fleet
from dran_edge.comms.radio import RadioParams, RadioTransport
from dran_edge.errors import ConfigError, DependencyError, DranError

zmq = pytest.importorskip("zmq")
needs_draft = pytest.mark.skipif(not zmq.has("draft"), reason="pyzmq without drafts")


def _free_udp_ports(n):
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def _consecutive_free_ports(n):
    for _ in range(50):
        base = _free_udp_ports(1)[0]
        if base + n >= 65535:
            continue
        try:
            socks = []
            for p in range(base, base + n):
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(s)
                s.bind(("127.0.0.1", p))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    pytest.skip("no block of free UDP ports")


def test_without_drafts_one_clear_dependency_error(monkeypatch):
    monkeypatch.setattr(zmq, "has", lambda feature: False)
    with pytest.raises(DependencyError) as exc:
        RadioTransport(RadioParams(group="dran", bind="udp://127.0.0.1:5999"))
    text = str(exc.value)
    assert "\n" not in text and "draft" in text and "build_zmq_draft.sh" in text


@needs_draft
def test_unhardened_libzmq_is_refused_unless_allowed(monkeypatch):
    monkeypatch.setattr(radio, "hardened_libzmq_stamp", lambda: None)
    with pytest.raises(DependencyError, match="hardened"):
        RadioTransport(RadioParams(group="dran", bind="udp://127.0.0.1:5999"))


@needs_draft
def test_our_build_is_the_hardened_one():
    stamp = radio.hardened_libzmq_stamp()
    assert stamp is not None and "patch=" in stamp


def test_params_are_validated():
    with pytest.raises(ConfigError, match="15"):
        RadioParams(group="a-fleet-name-too-long", bind="udp://*:5670")
    with pytest.raises(ConfigError, match="15"):
        RadioParams(group="", bind="udp://*:5670")
    with pytest.raises(ConfigError, match="udp://"):
        RadioParams(group="dran", bind="tcp://*:5670")
    with pytest.raises(ConfigError, match="neighbour 2"):
        RadioParams(group="dran", bind="udp://*:5670", neighbours={2: "udp://*:5671"})
    with pytest.raises(ConfigError, match="max_datagram_bytes"):
        RadioParams(group="dran", bind="udp://*:5670", max_datagram_bytes=9000)


@needs_draft
def test_pair_delivers_and_never_hands_libzmq_an_oversized_message():
    pa, pb = _free_udp_ports(2)
    with (
        RadioTransport(
            RadioParams(
                group="dran.t",
                bind=f"udp://127.0.0.1:{pa}",
                neighbours={2: f"udp://127.0.0.1:{pb}"},
                max_datagram_bytes=1200,
            )
        ) as a,
        RadioTransport(RadioParams(group="dran.t", bind=f"udp://127.0.0.1:{pb}")) as b,
    ):
        time.sleep(0.1)
        assert not a.send(2, bytes(1201))  # refused before libzmq sees it
        assert not a.send(2, bytes(60_000))  # would overflow libzmq <= 4.3.5's buffer
        assert not a.send(3, b"x")  # not a neighbour
        payloads = [bytes([i]) * (1 + i * 4) for i in range(200)]
        for i, p in enumerate(payloads):
            assert a.send(2, p)
            if i % 10 == 9:
                time.sleep(0.005)  # stay within the kernel's default socket buffers
        got = []
        end = time.time() + 5
        while len(got) < len(payloads) and time.time() < end:
            b.wait(0.1)
            got += [d for _, d in b.receive()]
        assert got == payloads  # loopback: order and bytes preserved
        drops = a.counters.peers[2].dropped_by_reason
        assert dict(drops) == {"over_cap": 2}
        assert a.counters.peers[2].bytes_sent == sum(map(len, payloads))
        assert b.counters.totals()["bytes_received"] == sum(map(len, payloads))


@needs_draft
def test_four_processes_over_radio_dish_match_the_in_process_bus():
    """4 robots on a line (relay over 3 hops), each a separate process with its own DISH."""
    base = _consecutive_free_ports(4)
    spec = FleetSpec(
        robot_ids=(0, 1, 2, 3),
        edges=((0, 1), (1, 2), (2, 3)),
        rounds=10,
        base_port=base,
        node_config={"seed": 5},
        fleet_id=3,
    )
    on_bus = run_bus_fleet(spec)
    on_udp = run_loopback_fleet(spec)
    for i in spec.robot_ids:
        assert on_udp[i]["stalled_rounds"] == []
        assert on_udp[i]["result"] == on_bus[i]["result"]
        assert on_udp[i]["accepted_sha256"] == on_bus[i]["accepted_sha256"]  # same bytes
        assert on_udp[i]["counters"]["totals"] == on_bus[i]["counters"]["totals"]
        # Maps propagated over the line: everyone knows all four objects, hop = distance.
        objects = on_udp[i]["result"]["objects"]
        assert sorted(objects) == ["0", "1", "2", "3"]
        assert all(objects[str(j)]["hop"] == abs(i - j) for j in range(4))


@needs_draft
def test_dran_agents_in_three_processes_over_radio_dish_match_the_in_process_run():
    """Three DRAN agents (objects toy), one process each with its own DISH on
    loopback, end bit-identical to the same three agents in one process on the bus."""
    edges = ((0, 1), (1, 2))
    spec = FleetSpec(
        robot_ids=(0, 1, 2),
        edges=edges,
        rounds=12,
        base_port=_consecutive_free_ports(3),
        node_factory="dran_edge.experiments.dran_node:DranNode",
        node_config={
            "sim": {
                "num_robots": 3,
                "num_objects": 6,
                "box_m": [12.0, 12.0, 3.0],
                "goals_per_robot": 2,
                "step_m": 1.5,
                "seed": 3,
            },
            "edges": [list(e) for e in edges],
            "agent": {"robust_kernel": "none"},
        },
        fleet_id=5,
    )
    on_bus = run_bus_fleet(spec)
    on_udp = run_loopback_fleet(spec, timeout_s=120.0)
    for i in spec.robot_ids:
        assert on_udp[i]["stalled_rounds"] == []
        assert on_udp[i]["result"] == on_bus[i]["result"]  # every bit of every estimate
        assert on_udp[i]["accepted_sha256"] == on_bus[i]["accepted_sha256"]
        assert on_udp[i]["result"]["rounds"] == spec.rounds
        assert on_udp[i]["counters"]["totals"] == on_bus[i]["counters"]["totals"]
        assert on_udp[i]["counters"]["totals"]["datagrams_received"] > 0
    # Object maps are shared (and relayed over robot 1): all end with the same objects.
    known = [set(on_udp[i]["result"]["objects"]) for i in spec.robot_ids]
    assert known[0] == known[1] == known[2] and len(known[0]) > 0


@needs_draft
def test_a_node_process_that_fails_is_named_with_its_error():
    spec = FleetSpec(
        robot_ids=(0, 1),
        edges=((0, 1),),
        rounds=3,
        node_factory="dran_edge.comms.loopback:NoSuchNode",
        base_port=_consecutive_free_ports(2),
    )
    with pytest.raises(DranError, match=r"(?s)robot 0: exited .*NoSuchNode"):
        run_loopback_fleet(spec, timeout_s=30.0)


def _can_netns() -> bool:
    if shutil.which("ip") is None or os.geteuid() != 0:
        return False
    name = f"dranprobe{os.getpid()}"
    ok = subprocess.run(["ip", "netns", "add", name], capture_output=True).returncode == 0
    if ok:
        subprocess.run(["ip", "netns", "del", name], capture_output=True)
    return ok


@pytest.mark.network
@needs_draft
@pytest.mark.skipif(not _can_netns(), reason="network namespaces not permitted here")
def test_two_hosts_in_network_namespaces():
    """Robot 1 in namespace A (10.77.x.1), robot 2 in namespace B (10.77.x.2) over a veth."""
    tag = uuid.uuid4().hex[:6]
    ns_a, ns_b, va, vb = f"dranA{tag}", f"dranB{tag}", f"dva{tag}", f"dvb{tag}"
    net = f"10.77.{int(tag[:2], 16)}"

    def ip(*args, ns=None):
        cmd = (["ip", "netns", "exec", ns] if ns else []) + ["ip", *args]
        subprocess.run(cmd, check=True, capture_output=True)

    try:
        ip("netns", "add", ns_a)
        ip("netns", "add", ns_b)
        ip("link", "add", va, "type", "veth", "peer", "name", vb)
        ip("link", "set", va, "netns", ns_a)
        ip("link", "set", vb, "netns", ns_b)
        ip("addr", "add", f"{net}.1/24", "dev", va, ns=ns_a)
        ip("addr", "add", f"{net}.2/24", "dev", vb, ns=ns_b)
        for ns, dev in ((ns_a, va), (ns_b, vb)):
            ip("link", "set", dev, "up", ns=ns)
            ip("link", "set", "lo", "up", ns=ns)
        code = (
            "import sys, time\n"
            "from dran_edge.comms.radio import RadioParams, RadioTransport\n"
            "me, peer = sys.argv[1], sys.argv[2]\n"
            "t = RadioTransport(RadioParams(group='dran.ns', bind=f'udp://{me}:5670',\n"
            "                               neighbours={9: f'udp://{peer}:5670'}))\n"
            "got = set(); end = time.time() + 15; linger = None\n"
            "while time.time() < end and (linger is None or time.time() < linger):\n"
            "    t.send(9, ('hello from ' + me).encode())\n"
            "    t.wait(0.1)\n"
            "    got |= {d for _, d in t.receive()}\n"
            "    if got and linger is None: linger = time.time() + 1.0  # let the peer hear us\n"
            "print(sorted(got)); t.close(); sys.exit(0 if got else 1)\n"
        )
        procs = [
            subprocess.Popen(
                ["ip", "netns", "exec", ns, sys.executable, "-c", code, me, peer],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            for ns, me, peer in ((ns_a, f"{net}.1", f"{net}.2"), (ns_b, f"{net}.2", f"{net}.1"))
        ]
        outs = [p.communicate(timeout=60) for p in procs]
        for p, (_out, err) in zip(procs, outs, strict=True):
            assert p.returncode == 0, err
        assert f"hello from {net}.2" in outs[0][0] and f"hello from {net}.1" in outs[1][0]
    finally:
        subprocess.run(["ip", "netns", "del", ns_a], capture_output=True)
        subprocess.run(["ip", "netns", "del", ns_b], capture_output=True)
