"""The Foxglove view: the daemon's live WebSocket server and MCAP files of a run's outputs."""

from __future__ import annotations

import json
import socket
import struct
import time

import numpy as np
import pytest

pytest.importorskip("foxglove")
pytest.importorskip("mcap")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_daemon_live_view_reaches_a_websocket_client(tmp_path):
    websockets_sync = pytest.importorskip("websockets.sync.client")
    from daemon_helpers import write_config
    from test_daemon import RecordingNotifier

    from dran_edge.comms.ingest import encode_event
    from dran_edge.config import load_config
    from dran_edge.daemon.service import Daemon
    from dran_edge.sim.vio import vio_mission

    port = _free_port()
    cfg = load_config(
        write_config(tmp_path, comms={"period_s": 0.05}, daemon={"foxglove": f"127.0.0.1:{port}"})
    )
    d = Daemon(cfg, notifier=RecordingNotifier(), environ={})
    d.start()
    try:
        assert d.live.port == port
        with websockets_sync.connect(
            f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]
        ) as ws:
            channels = {}
            while len(channels) < 3:
                msg = json.loads(ws.recv(timeout=10))
                if msg["op"] == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
            assert set(channels) == {"/testbot/path", "/testbot/objects", "/testbot/stats"}
            subs = {1: "/testbot/stats", 2: "/testbot/path"}
            ws.send(
                json.dumps(
                    {
                        "op": "subscribe",
                        "subscriptions": [
                            {"id": k, "channelId": channels[t]["id"]} for k, t in subs.items()
                        ],
                    }
                )
            )
            m = vio_mission(40, seed=3)
            with socket.socket(socket.AF_UNIX) as s:
                s.connect(str(d.ingest.path))
                s.sendall(b"".join(encode_event(e) for e in m.events))
            got: dict[str, list[bytes]] = {t: [] for t in subs.values()}

            def with_poses() -> list[bytes]:  # a path published before ingest is only a frame
                return [p for p in got["/testbot/path"] if len(p) > 100]

            end = time.monotonic() + 30
            while time.monotonic() < end and not (with_poses() and len(got["/testbot/stats"]) >= 2):
                d.tick()
                try:
                    data = ws.recv(timeout=0.05)
                except TimeoutError:
                    continue
                if isinstance(data, bytes) and data[0] == 0x01:  # MessageData
                    sub = struct.unpack_from("<I", data, 1)[0]
                    got[subs[sub]].append(data[13:])
        stats = json.loads(got["/testbot/stats"][-1])
        assert stats["round"] is not None and stats["round"] > 0 and stats["keyframes"] > 0
        assert with_poses(), got["/testbot/path"]  # a protobuf PosesInFrame with poses
        assert d.counters.live_view_errors == 0 and d.live.published >= 2
    finally:
        d.shutdown()


def test_config_rejects_a_bad_live_view_address(tmp_path):
    from daemon_helpers import write_config

    from dran_edge.config import load_config
    from dran_edge.errors import ConfigError

    with pytest.raises(ConfigError, match="foxglove"):
        load_config(write_config(tmp_path, daemon={"foxglove": "localhost"}))


def test_mcap_of_a_replayed_run_reads_back(tmp_path):
    from mcap.reader import make_reader

    from dran_edge.replay.run import ReplayOptions, replay_run
    from dran_edge.sim.writer import write_run
    from dran_edge.sim.mission import SimParams, generate_mission
    from dran_edge.formats.tum import read_tum
    from dran_edge.viz.record import write_run_mcap

    run = tmp_path / "run"
    write_run(
        generate_mission(SimParams(robots=2, objects=4, duration_s=12, seed=2, arena_m=6.0)),
        run,
        frames="none",
    )
    replay_run(run, ReplayOptions(workers=1, evaluate=False, settle_rounds=4))
    path = tmp_path / "run.mcap"
    counts = write_run_mcap(run, path, step_s=1.0)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        read = {
            ch.topic: summary.statistics.channel_message_counts.get(cid, 0)
            for cid, ch in summary.channels.items()
        }
        rounds = [
            json.loads(m.data) for _s, ch, m in reader.iter_messages(topics=["/fleet/rounds"])
        ]
    assert read == counts
    steps = 12  # one message per mission second
    for name in ("dingo1", "dingo2"):
        t, _ = read_tum(run / "out" / name / f"{name}.tum")
        first = int(np.ceil(t[0] - 1767225600.0 - 1e-9))  # the first second with a keyframe
        assert read[f"/{name}/path"] == steps - max(first, 1) + 1
        assert read[f"/{name}/objects"] == 2 and read[f"/mocap/{name}"] == steps
    assert read["/links"] == steps and read["/mocap/objects"] == 2
    assert len(rounds) == read["/fleet/rounds"] == 24 + 4
    assert [r["round"] for r in rounds] == list(range(28))
