"""The daemon's perception worker: forwarded frames -> tag observations -> journal -> graph."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pupil_apriltags")
pytest.importorskip("cv2")

from daemon_helpers import write_config  # noqa: E402

from dran_edge import geometry as geo  # noqa: E402
from dran_edge.comms import ingest as I  # noqa: E402
from dran_edge.config import load_config  # noqa: E402
from dran_edge.daemon.service import Daemon  # noqa: E402
from dran_edge.perception.calib import load_calibration  # noqa: E402
from dran_edge.perception.frame import Frame, frame_to_bytes  # noqa: E402
from dran_edge.perception.render import TagRenderer  # noqa: E402

CALIB = Path(__file__).resolve().parents[1] / "calib"


def frame_of_box(calib, box: int, stamp_ns: int) -> Frame:
    cam, tags = calib.camera, calib.tags
    R_level = np.array([[0.0, 1, 0], [0, 0, -1], [-1, 0, 0]]).T
    T_co = geo.se3_from_rt(
        R_level @ geo.so3_exp(np.array([0, 0, np.deg2rad(20.0)])), [0.05, 0.1, 1.2]
    )
    poses, ids = [], []
    for k in np.flatnonzero(tags.object_id == box):
        T_ct = T_co @ tags.T_object_tag[k]
        if T_ct[:3, 2] @ T_ct[:3, 3] / np.linalg.norm(T_ct[:3, 3]) > 0.2:
            poses.append(T_ct)
            ids.append(int(tags.tag_id[k]))
    colour, depth = TagRenderer().render(
        cam.K,
        cam.width,
        cam.height,
        poses,
        ids,
        0.16,
        rng=np.random.default_rng(0),
        noise_sigma=2.0,
    )
    return Frame(stamp_ns, colour, depth, "cam")


def test_forwarded_frames_become_graph_observations(tmp_path):
    calib = load_calibration(CALIB, "dingo2")
    cfg = load_config(
        write_config(
            tmp_path,
            comms={"period_s": 0.05},
            camera={
                "source": "forwarded",
                "calib_dir": str(CALIB / "cameras" / "dingo2"),
                "tags_file": str(CALIB / "tags.yaml"),
                "width": calib.camera.width,
                "height": calib.camera.height,
            },
        )
    )
    d = Daemon(cfg, environ={})
    d.start()
    try:
        t = 1_700_000_000_000_000_000

        records = [
            I.pack_odometry(t, [0, 0, 0], [0, 0, 0, 1]),
            I.pack_keyframe(t, [0, 0, 0], [0, 0, 0, 1]),
            I.pack_frame(t + 100_000_000, frame_to_bytes(frame_of_box(calib, 2, 0))),
            I.pack_odometry(t + 200_000_000, [0.5, 0, 0], [0, 0, 0, 1]),
            I.pack_keyframe(t + 200_000_000, [0.5, 0, 0], [0, 0, 0, 1]),
        ]
        with socket.socket(socket.AF_UNIX) as s:
            s.connect(str(d.ingest.path))
            s.sendall(b"".join(records))
        end = time.monotonic() + 60
        while time.monotonic() < end and not d.graph.counters.get("observations_added"):
            d.tick()
            time.sleep(0.05)
    finally:
        d.request_stop()
        d.shutdown()
    assert d.ingest.counters.frames == 1
    assert d.perception.batches == 1 and d.perception.errors == 0
    assert d.counters.applied["ObservationBatch"] == 1
    assert d.graph.object_ids().tolist() == [2]
