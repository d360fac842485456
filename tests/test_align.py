"""Association, clock offset and alignment (dran_edge.evaluation.align), and TUM files (dran_edge.formats.tum)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dran_edge.evaluation import align
from dran_edge.formats import tum
from dran_edge.errors import InputError


def _pose(R, p):
    T = np.tile(np.eye(4), np.shape(p)[:-1] + (1, 1))
    T[..., :3, :3] = R
    T[..., :3, 3] = p
    return T


def _wiggly_track(t, seed=0):
    """A ground-robot-like track: yaw rate varies smoothly, small roll/pitch, z wobble."""
    rng = np.random.default_rng(seed)
    freqs = rng.uniform(0.05, 0.6, 6)
    phases = rng.uniform(0, 2 * np.pi, 6)
    yaw = sum(np.sin(2 * np.pi * f * t + ph) / (2 * np.pi * f) for f, ph in zip(freqs, phases))
    roll = 0.05 * np.sin(0.7 * t)
    pitch = 0.04 * np.cos(0.3 * t)
    R = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], 1)).as_matrix()
    p = np.stack([2 * np.cos(0.1 * t), 1.5 * np.sin(0.13 * t), 0.2 + 0.1 * np.sin(0.5 * t)], 1)
    return _pose(R, p)


def _random_transform(rng, scale=1.0):
    return Rotation.random(random_state=rng).as_matrix(), rng.uniform(-3, 3, 3), scale


@pytest.mark.parametrize("kind,scale", [("se3", 1.0), ("sim3", 0.73)])
def test_umeyama_recovers_a_known_transform(kind, scale):
    rng = np.random.default_rng(1)
    T_ref = _wiggly_track(np.linspace(0, 60, 300))
    R, t, _ = _random_transform(rng)
    # est = inverse similarity of ref, so the alignment est -> ref must be (R, t, scale).
    p_est = ((T_ref[:, :3, 3] - t) @ R) / scale
    T_est = _pose(R.T @ T_ref[:, :3, :3], p_est)
    a = align.fit_alignment(kind, T_est, T_ref)
    np.testing.assert_allclose(a.R, R, atol=1e-9)
    np.testing.assert_allclose(a.t, t, atol=1e-9)
    assert a.scale == pytest.approx(scale, abs=1e-9)
    np.testing.assert_allclose(a.apply(T_est), T_ref, atol=1e-9)


def test_se3_alignment_does_not_invent_scale():
    rng = np.random.default_rng(2)
    T_ref = _wiggly_track(np.linspace(0, 60, 300))
    T_est = T_ref.copy()
    T_est[:, :3, 3] *= 0.5
    assert align.fit_alignment("se3", T_est, T_ref).scale == 1.0
    assert align.fit_alignment("sim3", T_est, T_ref).scale == pytest.approx(2.0, rel=1e-9)
    del rng


def test_yaw_alignment_leaves_roll_and_pitch_errors_visible():
    T_ref = _wiggly_track(np.linspace(0, 60, 300))
    tilt = Rotation.from_euler("ZYX", [40, 0, 5], degrees=True).as_matrix()  # yaw 40, roll 5
    T_est = _pose(tilt.T @ T_ref[:, :3, :3], (T_ref[:, :3, 3] - [1, 2, 0.3]) @ tilt)
    for kind, expect_deg in (("se3", 0.0), ("yaw", 5.0)):
        a = align.fit_alignment(kind, T_est, T_ref)
        E = np.swapaxes(T_ref[:, :3, :3], 1, 2) @ a.apply(T_est)[:, :3, :3]
        ang = np.degrees(np.linalg.norm(Rotation.from_matrix(E).as_rotvec(), axis=1))
        assert np.allclose(ang, expect_deg, atol=0.05), (kind, ang[:3])
        if kind == "yaw":
            # A yaw alignment is a rotation about z only.
            np.testing.assert_allclose(a.R[2], [0, 0, 1], atol=1e-12)
            pos_err = np.linalg.norm(a.apply(T_est)[:, :3, 3] - T_ref[:, :3, 3], axis=1)
            assert pos_err.max() > 0.01


def test_yaw_alignment_exact_for_a_pure_yaw_offset():
    T_ref = _wiggly_track(np.linspace(0, 60, 300))
    Rz = Rotation.from_euler("z", 123, degrees=True).as_matrix()
    T_est = _pose(Rz.T @ T_ref[:, :3, :3], (T_ref[:, :3, 3] - [4, -1, 0.5]) @ Rz)
    a = align.fit_alignment("yaw", T_est, T_ref)
    np.testing.assert_allclose(a.apply(T_est), T_ref, atol=1e-9)


def test_paper_alignment_uses_only_the_initial_frame():
    T_ref = _wiggly_track(np.linspace(0, 60, 300))
    T_world_odom = _pose(Rotation.from_euler("z", 70, degrees=True).as_matrix(), [1.0, -2.0, 0])
    T_est = np.linalg.inv(T_world_odom) @ T_ref
    T_est[150:, :3, 3] += 0.3  # a later drift must not change the alignment
    a = align.fit_alignment("paper", T_est, T_ref)
    np.testing.assert_allclose(a.apply(T_est)[:150], T_ref[:150], atol=1e-9)
    np.testing.assert_allclose(
        a.apply(T_est)[150:, :3, 3] - T_ref[150:, :3, 3],
        np.broadcast_to(T_world_odom[:3, :3] @ np.full(3, 0.3), (150, 3)),
        atol=1e-9,
    )


def test_interpolation_is_exact_for_constant_velocity_and_skips_gaps():
    t = np.arange(0, 10, 1 / 120)
    w = np.array([0.1, -0.2, 0.5])  # constant body rate: R(t) = Exp(w t)
    R = Rotation.from_rotvec(np.outer(t, w)).as_matrix()
    T = _pose(R, np.outer(t, [0.3, -0.1, 0.05]) + [1, 2, 3])
    valid = np.ones(len(t), bool)
    valid[600:700] = False  # 0.83 s occlusion
    q = np.array([0.5 + 0.3 / 120, 2.0 + 0.5 / 120, 5.4, 9.0])
    Tq, ok = align.interpolate_track(t, T, q, valid=valid, max_gap_s=0.1)
    np.testing.assert_array_equal(ok, [True, True, False, True])
    Rq = Rotation.from_rotvec(np.outer(q, w)).as_matrix()
    np.testing.assert_allclose(Tq[ok][:, :3, :3], Rq[ok], atol=1e-12)
    np.testing.assert_allclose(
        Tq[ok][:, :3, 3], (np.outer(q, [0.3, -0.1, 0.05]) + [1, 2, 3])[ok], atol=1e-12
    )


def test_associate_errors_for_non_overlapping_times():
    t = np.arange(0, 10, 0.1)
    T = _wiggly_track(t)
    with pytest.raises(InputError, match="time ranges do not overlap"):
        align.associate(t + 1000.0, T, t, T)
    a = align.associate(t + 1000.0, T, t, T, time_offset_s=-1000.0)
    assert a.matched_poses == len(t)


def test_associate_error_when_body_never_tracked():
    t = np.arange(0, 10, 0.1)
    T = _wiggly_track(t)
    with pytest.raises(InputError, match="never tracked"):
        align.associate(t, T, t, T, valid_ref=np.zeros(len(t), bool))


def test_time_offset_recovered_on_a_shifted_fixture():
    # Mocap at 120 Hz in take time; the estimate at 15 Hz with epoch stamps, a different world
    # frame and a rotated body frame, started 3 s into the take, clocks 0.237 s apart.
    offset_true = 1.7e9 - 3.0 + 0.237  # t_est = t_mocap + this;  offset_s = -this
    t_mocap = np.arange(0, 90, 1 / 120)
    T_mocap = _wiggly_track(t_mocap, seed=3)
    t_est_m = np.arange(3.0, 80.0, 1 / 15)  # mocap-clock instants of the estimated poses
    T_true = align.interpolate_track(t_mocap, T_mocap, t_est_m)[0]
    rng = np.random.default_rng(5)
    R_w, p_w, _ = _random_transform(rng)
    R_b = Rotation.from_euler("xyz", [90, 0, 10], degrees=True).as_matrix()
    T_est = _pose(R_w @ T_true[:, :3, :3] @ R_b, T_true[:, :3, 3] @ R_w.T + p_w)
    stamps = t_est_m + offset_true
    valid = np.ones(len(t_mocap), bool)
    valid[2000:2100] = False
    res = align.estimate_time_offset(stamps, T_est, t_mocap, T_mocap, valid_ref=valid)
    assert res.offset_s == pytest.approx(-offset_true, abs=0.005)
    assert res.correlation > 0.95
    # Within a bound around a given guess it finds the same.
    res2 = align.estimate_time_offset(
        stamps,
        T_est,
        t_mocap,
        T_mocap,
        valid_ref=valid,
        initial_offset_s=-offset_true + 0.5,
        max_offset_s=1.0,
    )
    assert res2.offset_s == pytest.approx(-offset_true, abs=0.005)


def test_time_offset_error_when_robot_never_turns():
    t = np.arange(0, 30, 0.05)
    T = _pose(np.eye(3), np.outer(t, [0.1, 0, 0]))
    with pytest.raises(InputError, match="time offset"):
        align.estimate_time_offset(t, T, t, T)


def test_unknown_alignment_kind():
    with pytest.raises(InputError, match="alignment must be one of"):
        align.fit_alignment("affine", np.eye(4)[None], np.eye(4)[None])


def test_tum_round_trip(tmp_path):
    t = 1.7e9 + np.arange(0, 5, 0.1)
    T = _wiggly_track(t - t[0])
    p = tmp_path / "x.tum"
    tum.write_tum(p, t, T, header="robot dingo1")
    s, T2 = tum.read_tum(p)
    np.testing.assert_allclose(s, t, atol=1e-9, rtol=0)
    np.testing.assert_allclose(T2, T, atol=1e-9)


@pytest.mark.parametrize(
    "line,msg",
    [
        ("1.0 0 0 0 0 0 0", "expected 8 numbers"),
        ("1.0 0 0 zero 0 0 0 1", "expected 8 numbers"),
        ("1.0 0 0 0 0 0 0 2", "unit quaternion"),
        ("0.5 0 0 0 0 0 0 1", "increasing stamps"),
        ("1.5 0 0 nan 0 0 0 1", "finite"),
    ],
)
def test_tum_errors_name_the_line(tmp_path, line, msg):
    p = tmp_path / "bad.tum"
    p.write_text("# header\n0.9 0 0 0 0 0 0 1\n\n" + line + "\n")
    with pytest.raises(InputError, match=rf"bad.tum:4: .*{msg}"):
        tum.read_tum(p)


# -------------------------------------------------------------------------------------------
# property tests


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(4, 60),
    scale=st.floats(0.2, 5.0),
    kind=st.sampled_from(["se3", "sim3"]),
)
def test_umeyama_property(seed, n, scale, kind):
    rng = np.random.default_rng(seed)
    p_ref = rng.normal(0, 2, (n, 3))
    R, t, _ = _random_transform(rng)
    s = scale if kind == "sim3" else 1.0
    p_est = ((p_ref - t) @ R) / s
    T_ref = _pose(np.eye(3), p_ref)
    T_est = _pose(R.T, p_est)
    a = align.fit_alignment(kind, T_est, T_ref)
    np.testing.assert_allclose(a.apply(T_est), T_ref, atol=1e-8)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), yaw_deg=st.floats(-180, 180))
def test_yaw_alignment_property(seed, yaw_deg):
    rng = np.random.default_rng(seed)
    p_ref = rng.normal(0, 2, (20, 3))
    Rz = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    t = rng.normal(0, 3, 3)
    T_ref = _pose(Rotation.random(20, random_state=rng).as_matrix(), p_ref)
    T_est = _pose(Rz.T @ T_ref[:, :3, :3], (p_ref - t) @ Rz)
    a = align.fit_alignment("yaw", T_est, T_ref)
    np.testing.assert_allclose(a.apply(T_est), T_ref, atol=1e-8)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), offset=st.floats(-5.0, 5.0))
def test_association_matches_each_estimate_with_the_reference_at_its_instant(seed, offset):
    rng = np.random.default_rng(seed)
    t_ref = np.sort(rng.uniform(0, 20, 400))
    t_ref = t_ref[np.r_[True, np.diff(t_ref) > 1e-6]]
    w = rng.normal(0, 0.3, 3)
    v = rng.normal(0, 0.5, 3)

    def truth(tt):  # constant twist: slerp/lerp are exact on it
        return _pose(Rotation.from_rotvec(np.outer(tt, w)).as_matrix(), np.outer(tt, v))

    t_est = np.sort(rng.uniform(t_ref[0], t_ref[-1], 50)) - offset
    a = align.associate(
        t_est, truth(t_est + offset), t_ref, truth(t_ref), time_offset_s=offset, max_gap_s=10.0
    )
    assert a.matched_poses == 50
    np.testing.assert_allclose(a.T_ref, a.T_est, atol=1e-8)
