"""The daemon in process with the real agent: tick loop, watchdog only after a good tick, queues."""

from __future__ import annotations

import socket

import numpy as np
from daemon_helpers import feed_and_drain, write_config

from dran_edge.comms.ingest import encode_event
from dran_edge.config import load_config
from dran_edge.daemon.service import Daemon, DropOldestQueue
from dran_edge.daemon.notify import Notifier
from dran_edge.sim.vio import vio_mission


class RecordingNotifier(Notifier):
    def __init__(self, watchdog_usec: int = 400_000):
        super().__init__({})
        self.watchdog_usec = watchdog_usec
        self.socket_path = "test"
        self.backend = "test"
        self.log: list[str] = []

    def notify(self, message: str) -> bool:
        self.log.append(message)
        return True


def make(tmp_path, **kw):
    cfg = load_config(write_config(tmp_path, comms={"period_s": 0.05}, **kw))
    return Daemon(cfg, notifier=RecordingNotifier(), environ={})


def test_ticks_feed_the_real_agent_and_report(tmp_path):
    d = make(tmp_path)
    d.start()
    m = vio_mission(60, seed=1)
    feed_and_drain(d, m.events)
    for _ in range(5):
        d.tick()
    d.shutdown()
    assert d.ingest.counters.records == len(m.events)
    assert d.last_estimate is not None and len(d.last_estimate.keyframe_stamps_ns) > 20
    log = d.notifier.log
    assert log[0].startswith("READY=1") and log[-1] == "STOPPING=1"
    assert "WATCHDOG=1" in log
    assert d.graph.counters["nodes_added"] > 20


def test_no_watchdog_after_a_failed_tick(tmp_path):
    d = make(tmp_path)
    d.start()
    d.tick()
    n_ok = d.notifier.log.count("WATCHDOG=1")
    assert n_ok == 1

    def broken(event):
        raise RuntimeError("agent bug")

    d.agent.handle = broken
    d._last_watchdog = float("-inf")
    for _ in range(3):
        d.tick()
    assert d.notifier.log.count("WATCHDOG=1") == n_ok
    assert d.stats.agent_errors == 3
    d.shutdown()


def test_run_keeps_absolute_deadlines(tmp_path):
    """Ten rounds on deadlines t0 + k·period: every period between the first round and the last
    was either a round or counted as missed (a loaded machine may miss some; none is run late
    as a catch-up), so no timing is asserted."""
    import time

    from dran_edge.events import Tick

    d = make(tmp_path)  # period 0.05 s
    d.start()
    handle = d.agent.handle
    starts = []

    def timed(event):
        if isinstance(event, Tick):
            starts.append(time.monotonic())
        return handle(event)

    d.agent.handle = timed
    d.run(max_ticks=10)
    assert d.stats.ticks == 10 == len(starts)
    periods = (starts[-1] - starts[0]) / 0.05
    assert abs(d.stats.ticks - 1 + d.stats.missed - periods) <= 1.5


def test_overlong_rounds_are_skipped_and_counted_not_queued(tmp_path):
    """A round that takes longer than the period (a slow core, a big graph): the loop does not
    run the missed rounds back to back to catch up (no backlog of ticks), it skips the whole
    periods missed and counts them (status 'missed'), and keeps its absolute deadlines."""
    import time

    from dran_edge.events import Tick

    d = make(tmp_path)  # period 0.05 s
    d.start()
    handle = d.agent.handle
    ticks_handled = []

    def slow(event):
        if isinstance(event, Tick):
            ticks_handled.append(time.monotonic())
            time.sleep(0.12)  # 2.4 periods
        return handle(event)

    d.agent.handle = slow
    d.run(max_ticks=6)
    assert d.stats.ticks == 6 == len(ticks_handled)
    # every period between the first and the last round was either run or counted as missed
    periods = (ticks_handled[-1] - ticks_handled[0]) / 0.05
    assert d.stats.missed >= 5 and abs(d.stats.ticks - 1 + d.stats.missed - periods) <= 1.5
    # no catch-up burst: consecutive rounds start at least one slow round apart
    assert min(np.diff(ticks_handled)) >= 0.12


def test_drop_oldest_queue_counts():
    q = DropOldestQueue(3)
    for i in range(10):
        q.put(i)
    assert q.dropped == 7 and q.drain() == [7, 8, 9]
    assert q.get(0.01) is None


def test_perception_batches_are_journalled_and_applied(tmp_path):
    d = make(tmp_path)
    d.start()
    m = vio_mission(30, seed=2)
    from dran_edge.events import ObservationBatch

    batches = [e for e in m.events if isinstance(e, ObservationBatch)]
    rest = [e for e in m.events if not isinstance(e, ObservationBatch)]
    with socket.socket(socket.AF_UNIX) as s:
        s.connect(str(d.ingest.path))
        s.sendall(b"".join(encode_event(e) for e in rest))
    for _ in range(100):
        d.tick()
        if d.ingest.counters.records == len(rest):
            break
    for b in batches:  # as the perception worker would hand them over
        d.observations.put(b)
    d.tick()
    d.shutdown()
    qsize = d.cfg.camera.queue_size
    assert len(batches) > qsize  # more than the queue holds: the oldest are dropped, counted
    assert d.observations.dropped == len(batches) - qsize
    assert d.counters.applied["ObservationBatch"] == qsize
    assert d.graph.counters.get("observations_added", 0) > 0
    assert np.isfinite(d.last_estimate.cost)


def test_record_writes_the_consumed_bytes(tmp_path):
    import yaml

    from dran_edge.comms.ingest import iter_records
    from dran_edge.config import config_from_dict

    cfg = load_config(write_config(tmp_path, comms={"period_s": 0.05}))
    rec = tmp_path / "rec"
    d = Daemon(cfg, notifier=RecordingNotifier(), environ={}, record_dir=rec)
    d.start()
    m = vio_mission(20, seed=4)
    data = b"".join(encode_event(e) for e in m.events)
    with socket.socket(socket.AF_UNIX) as s:
        s.connect(str(d.ingest.path))
        s.sendall(b"garbage" + data)
    for _ in range(200):
        d.tick()
        if d.ingest.counters.records == len(m.events) and d.journal.pending_count == 0:
            break
    d.shutdown()
    robot = rec / "robots" / "testbot"
    assert (robot / "ingest.bin").read_bytes() == data  # exactly the accepted records
    assert all(not isinstance(r, Exception) for r in iter_records(data))
    again = config_from_dict(yaml.safe_load((robot / "robot.yaml").read_text()))
    assert again.agent == cfg.agent and again.robot == cfg.robot
