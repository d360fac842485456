"""The daemon drives the RobotCore core: bad records are dropped, its checkpoint loads back."""

from __future__ import annotations

import socket

from daemon_helpers import write_config

from dran_edge.comms.ingest import encode_event
from dran_edge.config import load_config
from dran_edge.daemon.service import Daemon
from dran_edge.daemon.notify import Notifier
from dran_edge.robot.core import RobotCore
from dran_edge.sim.vio import vio_mission


def _daemon(tmp_path) -> Daemon:
    cfg = load_config(write_config(tmp_path, comms={"period_s": 0.05}))
    return Daemon(cfg, notifier=Notifier({}), environ={})


def _send_all(d: Daemon, events) -> None:
    with socket.socket(socket.AF_UNIX) as s:
        s.connect(str(d.ingest.path))
        s.sendall(b"".join(encode_event(e) for e in events))
    for _ in range(200):
        d.tick()
        if d.ingest.counters.records == len(events) and d.journal.pending_count == 0:
            break


def test_a_record_the_graph_raises_on_is_counted_and_dropped(tmp_path):
    d = _daemon(tmp_path)
    d.start()
    assert isinstance(d.agent, RobotCore) and d.graph is d.agent.local_graph
    m = vio_mission(60, seed=3)
    real = d.graph.handle
    raised = []

    def fails_on_every_tenth(event):
        if (len(raised) + fails_on_every_tenth.calls) % 10 == 9:
            raised.append(type(event).__name__)
            raise RuntimeError("graph bug")
        fails_on_every_tenth.calls += 1
        return real(event)

    fails_on_every_tenth.calls = 0
    d.graph.handle = fails_on_every_tenth
    try:
        _send_all(d, m.events)
        for _ in range(3):
            d.tick()
    finally:
        d.shutdown()
    assert len(raised) == len(m.events) // 10 > 0
    assert d.stats.agent_errors == len(raised)
    applied = sum(d.counters.applied.values())
    assert applied == len(m.events)  # every record consumed, the bad ones dropped
    assert d.last_estimate is not None and len(d.last_estimate.keyframe_stamps_ns) > 10


def test_the_checkpoint_loads_back_into_the_core(tmp_path):
    d = _daemon(tmp_path)
    d.start()
    _send_all(d, vio_mission(40, seed=4).events)
    for _ in range(5):
        d.tick()
    d.shutdown()
    nodes = d.graph.node_keys().tolist()
    x = d.agent.agent.x.copy()
    again = _daemon(tmp_path)
    again.start()
    try:
        assert again.counters.recovered_records == 0
        assert again.graph.node_keys().tolist() == nodes
        assert (again.agent.agent.x == x).all()
        # the graph was checkpointed with the optimised estimates written back
        ids = again.agent.agent.problem.pose_ids.tolist()
        est = again.graph.T_world_body()
        assert abs(est[[nodes.index(k) for k in ids]] - x).max() < 1e-12
    finally:
        again.shutdown()


def test_beta_is_checked_against_the_tag_observations(tmp_path, caplog):
    """At a status period the daemon compares agent.beta with the information of its tag
    observations (dran.beta_scale): the ratio goes into the status document, and a β far
    outside the measured window is logged once."""
    from dran_edge.daemon.status import status_document

    cfg = load_config(write_config(tmp_path, comms={"period_s": 0.05}, agent={"beta": 1e-3}))
    d = Daemon(cfg, notifier=Notifier({}), environ={})
    d.start()
    try:
        _send_all(d, vio_mission(60, seed=3).events)
        d._last_status = float("-inf")  # the next tick is a status period
        with caplog.at_level("WARNING", logger="dran_edge.daemon.service"):
            d.tick()
            d._last_status = float("-inf")
            d.tick()
        doc = status_document(d, "running")
    finally:
        d.shutdown()
    check = doc["beta_check"]
    assert check["beta"] == 1e-3 and check["observation_information"] > 0
    assert check["ratio"] == check["beta"] / check["observation_information"] < 0.003
    warned = [r for r in caplog.records if "agent.beta = 0.001" in r.getMessage()]
    assert len(warned) == 1 and "too weak" in warned[0].getMessage()
