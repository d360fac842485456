"""Calibration files, object fusion and the frame -> ObservationBatch pipeline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pupil_apriltags")
pytest.importorskip("cv2")

from dran_edge.perception.calib import (  # noqa: E402
    load_calibration,
    load_camera,
    load_tag_map,
)
from dran_edge.perception.frame import Frame  # noqa: E402
from dran_edge.perception.pipeline import ObservationPipeline, PipelineParams  # noqa: E402
from dran_edge.perception.render import TagRenderer  # noqa: E402

from dran_edge import geometry as geo  # noqa: E402
from dran_edge.errors import ConfigError, InputError  # noqa: E402
from dran_edge.events import ObservationBatch  # noqa: E402

CALIB = Path(__file__).resolve().parents[1] / "calib"


# --------------------------------------------------------------------------- calibration
def test_example_calibration_loads():
    tags = load_tag_map(CALIB / "tags.yaml")
    assert tags.family == "tag36h11"
    assert sorted(set(tags.object_id.tolist())) == list(range(9))
    assert tags.tag_id.size == 36 and np.all(tags.size_m == 0.16)
    R = tags.T_object_tag[:, :3, :3]
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-9)
    # every tag's z axis (into the tag) points into its box: towards the object origin
    assert np.all(np.einsum("ki,ki->k", R[:, :, 2], tags.T_object_tag[:, :3, 3]) < 0)
    for i in range(1, 7):
        cal = load_calibration(CALIB, f"dingo{i}")
        assert cal.camera.robot == f"dingo{i}"
        assert (cal.camera.width, cal.camera.height) == (640, 480)
    assert tags.lookup(np.array([5, 999, 0])).tolist() == [5, -1, 0]


def write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


CAMERA = """format: dran-edge-camera/1
robot: r1
width: 640
height: 480
intrinsics: {fx: 600, fy: 600, cx: 320, cy: 240}
T_body_camera: {xyz: [0, 0, 0], quat_xyzw: [0, 0, 0, 1]}
"""


def test_camera_strict_errors_name_file_line_and_key(tmp_path):
    assert load_camera(write(tmp_path, "ok.yaml", CAMERA)).K[0, 0] == 600
    with pytest.raises(
        ConfigError,
        match=r"bad\.yaml:6: .*intrinsics\.fx.*unknown key|"
        r"bad\.yaml:5: intrinsics\.fz: unknown key",
    ):
        load_camera(write(tmp_path, "bad.yaml", CAMERA.replace("fx:", "fz:")))
    with pytest.raises(ConfigError, match=r"T_body_camera.quat_xyzw: expected a unit quaternion"):
        load_camera(write(tmp_path, "q.yaml", CAMERA.replace("[0, 0, 0, 1]", "[0, 0, 0, 2]")))
    with pytest.raises(ConfigError, match=r"width: expected an integer"):
        load_camera(write(tmp_path, "w.yaml", CAMERA.replace("640", "'640'")))
    with pytest.raises(ConfigError, match=r"extra: unknown key"):
        load_camera(write(tmp_path, "x.yaml", CAMERA + "extra: 1\n"))


def test_tag_map_rejects_duplicates(tmp_path):
    text = """format: dran-edge-tags/1
family: tag36h11
objects:
  - id: 0
    tags:
      - {tag_id: 3, size_m: 0.16, T_object_tag: {xyz: [0, 0, 0], quat_xyzw: [0, 0, 0, 1]}}
  - id: 1
    tags:
      - {tag_id: 3, size_m: 0.16, T_object_tag: {xyz: [0, 0, 0], quat_xyzw: [0, 0, 0, 1]}}
"""
    with pytest.raises(
        ConfigError,
        match=r"t\.yaml:9: objects\[1\]\.tags\[0\]\.tag_id: tag 3 "
        r"already used",
    ):
        load_tag_map(write(tmp_path, "t.yaml", text))


# --------------------------------------------------------------------------- pipeline
@pytest.fixture(scope="module")
def calib():
    return load_calibration(CALIB, "dingo2")


def view_of_box(
    calib, box: int, yaw_deg: float, distance_m: float, only_tag: int | None = None, seed: int = 0
):
    """Render box ``box`` seen at ``yaw_deg`` about its vertical axis; returns frame and truth."""
    cam, tags = calib.camera, calib.tags
    R_level = np.array([[0.0, 1, 0], [0, 0, -1], [-1, 0, 0]]).T  # object z up = camera -y
    T_co = geo.se3_from_rt(
        R_level @ geo.so3_exp(np.array([0, 0, np.deg2rad(yaw_deg)])), [0.05, 0.1, distance_m]
    )
    poses, ids = [], []
    for k in np.flatnonzero(tags.object_id == box):
        T_ct = T_co @ tags.T_object_tag[k]
        facing = T_ct[:3, 2] @ T_ct[:3, 3] / np.linalg.norm(T_ct[:3, 3]) > 0.2
        if facing and (only_tag is None or tags.tag_id[k] == only_tag):
            poses.append(T_ct)
            ids.append(int(tags.tag_id[k]))
    colour, depth = TagRenderer().render(
        cam.K,
        cam.width,
        cam.height,
        poses,
        ids,
        0.16,
        rng=np.random.default_rng(seed),
        noise_sigma=2.0,
    )
    return Frame(123_456_789, colour, depth, "cam"), cam.T_body_camera @ T_co, ids


def test_two_tags_of_one_box_are_fused(calib):
    pipe = ObservationPipeline(calib)
    frame, T_body_object, ids = view_of_box(calib, 4, 45.0, 1.3)
    assert len(ids) == 2
    res = pipe.process_detailed(frame)
    batch = res.batch
    assert isinstance(batch, ObservationBatch) and batch.stamp_ns == frame.stamp_ns
    assert [o.object_id for o in batch.observations] == [4]
    obs = batch.observations[0]
    assert obs.stamp_ns == frame.stamp_ns and res.objects.n_tags.tolist() == [2]
    d = geo.se3_log(geo.se3_between(obs.T_body_object, T_body_object))
    assert np.linalg.norm(d[:3]) < 0.01 and np.rad2deg(np.linalg.norm(d[3:])) < 1.0
    cov = obs.covariance
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    # one tag alone gives a larger (less certain) object covariance than the fused pair
    frame1, T1, _ = view_of_box(calib, 4, 45.0, 1.3, only_tag=ids[0])
    cov1 = pipe.process(frame1).observations[0].covariance
    assert np.trace(cov1[3:, 3:]) > np.trace(cov[3:, 3:])
    assert np.linalg.det(cov1) > np.linalg.det(cov)


def test_object_pose_in_body_frame_matches_truth_over_views(calib):
    pipe = ObservationPipeline(calib)
    for i, (box, yaw, dist) in enumerate([(0, 0.0, 1.0), (3, 20.0, 2.0), (8, -60.0, 1.5)]):
        frame, T_true, _ = view_of_box(calib, box, yaw, dist, seed=i)
        obs = pipe.process(frame).observations
        assert [o.object_id for o in obs] == [box]
        d = geo.se3_log(geo.se3_between(obs[0].T_body_object, T_true))
        assert np.linalg.norm(d[:3]) < 0.02 and np.rad2deg(np.linalg.norm(d[3:])) < 2.0


def test_unknown_tags_and_wrong_size_frames(calib):
    cam = calib.camera
    T = geo.se3_from_rt(np.diag([-1.0, -1, 1]), [0, 0, 1.0])
    colour, depth = TagRenderer().render(cam.K, 640, 480, [T], [300], 0.16)
    res = ObservationPipeline(calib).process_detailed(Frame(1, colour, depth))
    assert res.detections.tag_id.tolist() == [300]
    assert res.tag_poses.reject.tolist() == ["unknown_tag"] and res.batch.observations == ()
    sized = ObservationPipeline(calib, PipelineParams(default_tag_size_m=0.16))
    res = sized.process_detailed(Frame(1, colour, depth))
    assert res.tag_poses.accepted.tolist() == [True] and res.batch.observations == ()
    with pytest.raises(InputError, match="expected 640x480"):
        sized.process(Frame(1, colour[:240], None))


# --------------------------------------------------------------------------- daemon adapter
def robot_config(tmp_path, source: str, recording: str = ""):
    from dran_edge.config import load_config

    text = f"""robot: {{id: 2, name: dingo2, fleet: dingo6}}
camera:
  source: {source}
  calib_dir: {CALIB}/cameras/dingo2
  tags_file: {CALIB}/tags.yaml
  recording: "{recording}"
"""
    path = tmp_path / "dingo2.yaml"
    path.write_text(text)
    return load_config(path)


def test_daemon_producer_forwarded_frames(tmp_path, calib):
    from types import SimpleNamespace

    from dran_edge.perception.frame import frame_to_bytes
    from dran_edge.perception.pipeline import make_observation_source

    frame, T_true, _ = view_of_box(calib, 2, 30.0, 1.2)
    empty = Frame(5, np.full_like(frame.colour, 128), None, "cam")

    class Queue:
        def __init__(self, items):
            self.items = list(items)

        def get(self, timeout_s):
            return self.items.pop(0) if self.items else None

    def record(f, stamp_ns):
        return SimpleNamespace(
            kind=5, event=SimpleNamespace(stamp_ns=stamp_ns, payload=frame_to_bytes(f))
        )

    produce = make_observation_source(
        robot_config(tmp_path, "forwarded"), Queue([record(empty, 5), record(frame, 777)])
    )
    assert produce() is None  # a frame without tags: nothing to hand over
    batch = produce()
    assert batch.stamp_ns == 777 and [o.object_id for o in batch.observations] == [2]
    d = geo.se3_log(geo.se3_between(batch.observations[0].T_body_object, T_true))
    assert np.linalg.norm(d[:3]) < 0.02
    assert produce() is None  # queue empty: returns after the timeout


def test_daemon_producer_recorded_frames_end(tmp_path, calib):
    from dran_edge.perception.pipeline import make_observation_source
    from dran_edge.perception.sources import write_recorded_frames

    frames = [view_of_box(calib, b, 10.0 * b, 1.5, seed=b)[0] for b in (1, 5)]
    frames = [Frame(1000 * (i + 1), f.colour, f.depth, "cam") for i, f in enumerate(frames)]
    write_recorded_frames(tmp_path / "frames", frames)
    produce = make_observation_source(robot_config(tmp_path, "recorded", str(tmp_path / "frames")))
    got = [produce(), produce()]
    assert [b.stamp_ns for b in got] == [1000, 2000]
    assert [b.observations[0].object_id for b in got] == [1, 5]
    with pytest.raises(StopIteration):
        produce()


def test_daemon_producer_rejects_size_mismatch(tmp_path):
    from dran_edge.perception.pipeline import calibration_from_config

    from dran_edge.config import load_config

    path = tmp_path / "r.yaml"
    path.write_text(f"""robot: {{id: 2, name: dingo2, fleet: dingo6}}
camera: {{source: forwarded, calib_dir: {CALIB}/cameras, width: 1280, height: 720}}
""")
    with pytest.raises(ConfigError, match="calibrated for 640x480"):
        calibration_from_config(load_config(path))
