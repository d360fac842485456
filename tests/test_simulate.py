"""Simulated missions: determinism, the VIO drift and reset model, loops, visibility, comm graph,
and the run directory the simulator writes (read back with the project's own readers)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from dran_edge import geometry as geo
from dran_edge.formats import run_dir as rd
from dran_edge.sim import mission as sim
from dran_edge.errors import InputError

SMALL = sim.SimParams(robots=3, objects=4, duration_s=60.0, arena_m=6.0, seed=3)


@pytest.fixture(scope="module")
def mission() -> sim.Mission:
    return sim.generate_mission(SMALL)


def _segment_world_error(r: sim.RobotMission) -> np.ndarray:
    """Position error of the VIO output mapped into the world by each segment's true origin."""
    T_w = r.T_world_odom[r.segment] @ r.T_odom_body
    return np.linalg.norm(T_w[:, :3, 3] - r.T_world_body[:, :3, 3], axis=1)


def test_same_seed_same_mission_other_seed_other_mission(mission):
    again = sim.generate_mission(SMALL)
    for a, b in zip(mission.robots, again.robots):
        np.testing.assert_array_equal(a.odom_stamps_ns, b.odom_stamps_ns)
        np.testing.assert_array_equal(a.T_odom_body, b.T_odom_body)
        np.testing.assert_array_equal(a.loop_T_old_cur, b.loop_T_old_cur)
    assert again.comm_edges == mission.comm_edges
    other = sim.generate_mission(dataclasses.replace(SMALL, seed=4))
    assert not np.allclose(other.robots[0].T_odom_body[-1], mission.robots[0].T_odom_body[-1])


def test_paths_are_planar_circles_clear_of_the_boxes(mission):
    for r in mission.robots:
        xy = r.T_world_body[:, :2, 3]
        d_box = np.linalg.norm(xy[:, None] - mission.world.T_world_object[None, :, :2, 3], axis=-1)
        assert d_box.min() >= SMALL.clearance_m - 1e-9
        centre = np.asarray(r.path.centre_xy)
        radius = np.linalg.norm(xy - centre, axis=1)
        assert np.all(np.abs(radius / r.path.radius_m - 1) <= r.path.wobble + 1e-9)
        speed = np.linalg.norm(np.diff(xy, axis=0), axis=1) * SMALL.odom_rate_hz
        assert np.median(speed) == pytest.approx(r.path.speed_mps, rel=0.15)
        # heading follows the direction of travel
        step = np.diff(xy, axis=0)
        heading = r.T_world_body[:-1, :2, 0]
        cos = np.sum(step * heading, axis=1) / np.linalg.norm(step, axis=1)
        assert np.all(cos[np.linalg.norm(step, axis=1) > 1e-3] > 0.99)


def test_vio_drifts_realistically_and_starts_each_segment_at_identity():
    p = dataclasses.replace(SMALL, duration_s=180.0, resets_per_min=0.0)
    m = sim.generate_mission(p)
    for r in m.robots:
        err = _segment_world_error(r)
        assert err[0] == pytest.approx(0.0, abs=1e-12)
        travelled = np.sum(np.linalg.norm(np.diff(r.T_world_body[:, :3, 3], axis=0), axis=1))
        # VINS-Mono-like: drift is visible but stays within a few percent of the distance
        assert 1e-3 < err[-1] < 0.05 * travelled
        np.testing.assert_allclose(r.T_odom_body[0], np.eye(4), atol=0.02)


def test_resets_start_new_segments_after_a_gap():
    p = dataclasses.replace(SMALL, resets_per_min=1.5, duration_s=120.0)
    m = sim.generate_mission(p)
    total = 0
    for r in m.robots:
        n_seg = int(r.segment.max()) + 1
        assert len(r.reset_stamps_ns) == n_seg - 1 == len(r.T_world_odom) - 1
        total += n_seg - 1
        for s in r.reset_stamps_ns.tolist():
            i = int(np.searchsorted(r.odom_stamps_ns, s))
            gap_s = (r.odom_stamps_ns[i] - r.odom_stamps_ns[i - 1]) / 1e9
            assert gap_s >= p.reset_gap_s - 1e-6
            assert r.segment[i] == r.segment[i - 1] + 1
            # the new VIO world starts at the body pose: identity up to tilt noise
            np.testing.assert_allclose(r.T_odom_body[i][:3, 3], 0.0, atol=1e-9)
        assert np.all(_segment_world_error(r) < 2.0)
    assert total >= 2


def test_loops_measure_the_true_relative_pose_and_outliers_are_wrong():
    p = dataclasses.replace(SMALL, duration_s=180.0, loop_outlier_fraction=0.2)
    m = sim.generate_mission(p)
    n_in = n_out = 0
    for r in m.robots:
        kf_T = r.T_world_body[r.keyframes]
        kf_t = r.odom_stamps_ns[r.keyframes]
        for (o, c), T, bad in zip(r.loops, r.loop_T_old_cur, r.loop_outlier):
            assert kf_t[o] < kf_t[c] and c - o >= p.loop_min_age_kf
            err = geo.se3_log(geo.se3_between(geo.se3_between(kf_T[o], kf_T[c]), T))
            if bad:
                n_out += 1
            else:
                n_in += 1
                assert np.linalg.norm(err[:3]) < 6 * p.loop_noise_m * math.sqrt(3)
                assert np.linalg.norm(err[3:]) < 6 * p.loop_noise_rad * math.sqrt(3)
                assert (
                    np.linalg.norm(geo.se3_between(kf_T[o], kf_T[c])[:2, 3]) < p.loop_max_distance_m
                )
    assert n_in > 20
    assert 0 < n_out < n_in


def test_communication_graph_is_connected_and_sparse():
    for seed in range(20):
        rng = np.random.default_rng(seed)
        edges = sim.comm_graph(8, 0.1, rng)
        adj = {i: set() for i in range(8)}
        for a, b in edges:
            assert 0 <= a < b < 8
            adj[a].add(b)
            adj[b].add(a)
        seen, todo = {0}, [0]
        while todo:
            for j in adj[todo.pop()] - seen:
                seen.add(j)
                todo.append(j)
        assert seen == set(range(8))
        assert len(edges) < 28


def test_visibility_facing_range_and_occlusion():
    p = sim.SimParams(objects=2)
    world = sim.World(
        np.arange(2),
        np.stack([np.eye(4), geo.se3_from_rt(np.eye(3), np.r_[3.0, 0, 0])]),
        0.4,
        0.2,
        sim.face_tags(0.4),
    )
    body = geo.se3_from_rt(geo.so3_exp(np.r_[0, 0, math.pi]), np.r_[-2.0, 0.0, 0.0])
    # robot at (-2, 0) looks along -x: away from both boxes
    vis, _ = sim.visible_tags(world, (body @ sim.T_BODY_CAMERA)[None], p)
    assert not vis.any()
    # looking along +x: box 0's -x face (tag index 2) is seen; box 1 is hidden behind box 0
    body = geo.se3_from_rt(np.eye(3), np.r_[-2.0, 0.0, 0.0])
    cam = body @ sim.T_BODY_CAMERA
    cam[2, 3] = 0.2
    vis, T_ct = sim.visible_tags(world, cam[None], p)
    assert vis[0, 0].tolist() == [False, False, True, False]
    assert not vis[0, 1].any()
    # camera 0.15 m ahead of the body and 0.2 m above the tag centre (image y is down)
    np.testing.assert_allclose(T_ct[0, 0, 2][:3, 3], [0, 0.2, 2.0 - 0.15 - 0.201], atol=1e-9)
    # out of range
    far = geo.se3_from_rt(np.eye(3), np.r_[-6.0, 0.0, 0.0]) @ sim.T_BODY_CAMERA
    far[2, 3] = 0.2
    vis, _ = sim.visible_tags(world, far[None], p)
    assert not vis.any()


def test_every_robot_sees_boxes_and_boxes_are_shared(mission):
    seen = [set(sim._seen_objects(mission.world, r.path, SMALL).tolist()) for r in mission.robots]
    assert all(len(s) >= 2 for s in seen)
    assert any(seen[i] & seen[j] for i in range(len(seen)) for j in range(i + 1, len(seen)))


def test_direct_observations_match_the_geometry(mission):
    r = mission.robots[0]
    obs = sim.direct_observations(mission, r, np.random.default_rng(0))
    assert obs
    for stamp, items in obs[:20]:
        f = int(np.searchsorted(r.frame_stamps_ns, stamp))
        for oid, T, C in items:
            T_true = geo.se3_inverse(r.T_world_body_frames[f]) @ mission.world.T_world_object[oid]
            err = geo.se3_log(geo.se3_between(T_true, T))
            sig = np.sqrt(np.diag(C))
            assert np.all(np.abs(err) < 6 * sig)


def test_bad_parameters_are_rejected():
    with pytest.raises(InputError, match="robots"):
        sim.SimParams(robots=0)
    with pytest.raises(InputError, match="speed_mps"):
        sim.SimParams(speed_mps=5.0)


# ------------------------------------------------------------------------------ run directory
@pytest.fixture(scope="module")
def written_run(tmp_path_factory, mission):
    from dran_edge.sim.writer import write_run

    root = tmp_path_factory.mktemp("simrun") / "run"
    write_run(mission, root, frames="none")
    return root


def test_written_run_reads_back_with_the_projects_readers(written_run, mission):
    from dran_edge.comms.ingest import IngestDecodeError, iter_records
    from dran_edge.perception.calib import load_calibration

    from dran_edge.events import Keyframe, LoopClosure, ObservationBatch, OdometrySample, VioReset

    run = rd.open_run(written_run)
    m = run.mission
    assert [r.name for r in m.robots] == [r.name for r in mission.robots]
    assert m.comm_graph == mission.comm_edges
    assert m.start_ns == SMALL.start_ns and m.duration_s == SMALL.duration_s
    for r, truth in zip(m.robots, mission.robots):
        np.testing.assert_allclose(r.T_world_odom, truth.T_world_odom[0], atol=1e-8)
        cfg = run.load_config(r.name)
        assert cfg.robot.id == r.id
        assert sorted(n.id for n in cfg.neighbours) == list(m.neighbours(r.id))
        items = list(iter_records(run.read_ingest(r.name)))
        assert not [x for x in items if isinstance(x, IngestDecodeError)]
        events = [x.event for x in items]
        odo = [e for e in events if isinstance(e, OdometrySample)]
        assert len(odo) == len(truth.odom_stamps_ns)
        np.testing.assert_allclose(odo[-1].T_odom_body, truth.T_odom_body[-1], atol=1e-9)
        assert sum(isinstance(e, Keyframe) for e in events) == len(truth.keyframes)
        assert sum(isinstance(e, LoopClosure) for e in events) == len(truth.loops)
        assert sum(isinstance(e, VioReset) for e in events) == len(truth.reset_stamps_ns)
        assert sum(isinstance(e, ObservationBatch) for e in events) > 0
        calib = load_calibration(run.calib_dir, r.name)
        np.testing.assert_allclose(calib.camera.K, sim.CAMERA_K)
        np.testing.assert_allclose(calib.camera.T_body_camera, sim.T_BODY_CAMERA, atol=1e-9)
        assert calib.tags.tag_id.size == 4 * SMALL.objects


def test_written_mocap_is_motive_y_up_and_matches_the_truth(written_run, mission):
    from dran_edge.formats.motive import read_motive_csv

    text = (written_run / "mocap.csv").read_text()
    assert text.startswith("Format Version,1.23,")
    assert "Rotation Type,Quaternion" in text.splitlines()[0]
    take = read_motive_csv(written_run / "mocap.csv")
    r = mission.robots[1]
    body = take.body(r.name)
    k = np.flatnonzero(body.valid)[::50]
    T_true = r.path.poses(take.time_s[k]) @ sim.T_BODY_MARKER
    np.testing.assert_allclose(body.T_world_marker[k][:, :3, 3], T_true[:, :3, 3], atol=2e-6)
    assert not body.valid.all() or SMALL.mocap_dropout_per_min == 0
    box = take.body("box0")
    np.testing.assert_allclose(
        box.T_world_marker[0][:3, 3],
        (mission.world.T_world_object[0] @ sim._object_marker(0.4))[:3, 3],
        atol=2e-6,
    )


def test_run_dir_rejects_bad_missions_with_file_and_line(written_run, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(written_run, bad)
    path = bad / "mission.yaml"
    text = path.read_text()
    path.write_text(text.replace("comm_graph:", "comm_graph: [[1, 99]]\nold_graph:", 1))
    with pytest.raises(InputError) as exc:
        rd.open_run(bad)
    assert "mission.yaml" in str(exc.value) and "old_graph" in str(exc.value)
    import yaml

    data = yaml.safe_load(text)
    data["comm_graph"] = [[1, 2], [1, 99]]
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(InputError, match=r"mission.yaml:\d+: comm_graph\[1\]: .*99"):
        rd.open_run(bad)
    path.write_text(text.replace("name: dingo2", "name: dingo1", 1))
    with pytest.raises(InputError, match="appears more than once"):
        rd.open_run(bad)
    path.write_text(text)
    (bad / "robots" / "dingo3" / "ingest.bin").unlink()
    with pytest.raises(InputError, match="dingo3.*no ingest.bin"):
        rd.open_run(bad)
