"""Paper metrics and the usual ones (dran_edge.evaluation.metrics), and our ATE against evo's."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dran_edge.evaluation import align, metrics
from dran_edge.formats import tum

DATA = Path(__file__).parent / "data" / "eval"


def _pose(R, p):
    T = np.tile(np.eye(4), np.shape(p)[:-1] + (1, 1))
    T[..., :3, :3] = R
    T[..., :3, 3] = p
    return T


def _random_poses(rng, shape, spread=2.0):
    n = int(np.prod(shape))
    R = Rotation.random(n, random_state=rng).as_matrix().reshape(shape + (3, 3))
    return _pose(R, rng.uniform(-spread, spread, shape + (3,)))


def _perturb(rng, T, sigma_p, sigma_r):
    shape = T.shape[:-2]
    n = int(np.prod(shape))
    dR = Rotation.from_rotvec(rng.normal(0, sigma_r, (n, 3))).as_matrix().reshape(shape + (3, 3))
    return _pose(T[..., :3, :3] @ dR, T[..., :3, 3] + rng.normal(0, sigma_p, shape + (3,)))


def test_ate_log_is_the_paper_formula_with_robot_weights():
    rng = np.random.default_rng(0)
    gt = _random_poses(rng, (30,))
    est = _perturb(rng, gt, 0.05, 0.02)
    robot = np.r_[np.zeros(10, int), np.ones(20, int)]
    # Written out by hand with scipy: sqrt(1/2 (mean_robot0 |e|^2 + mean_robot1 |e|^2)).
    sq = []
    for k in range(30):
        E = np.linalg.inv(gt[k]) @ est[k]
        phi = Rotation.from_matrix(E[:3, :3]).as_rotvec()
        th = np.linalg.norm(phi)
        W = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
        V = np.eye(3) + (1 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * W @ W
        rho = np.linalg.solve(V, E[:3, 3])
        sq.append(rho @ rho + phi @ phi)
    sq = np.array(sq)
    want = np.sqrt(0.5 * (sq[:10].mean() + sq[10:].mean()))
    assert metrics.ate_log_rmse(est, gt, robot) == pytest.approx(want, rel=1e-10)
    assert metrics.ate_log_rmse(est, gt) == pytest.approx(np.sqrt(sq.mean()), rel=1e-10)
    assert metrics.ate_log_rmse(gt, gt) == pytest.approx(0.0, abs=1e-12)


def test_success_ratios():
    assert metrics.sr_ate(1.0, 0.55, 0.5) == pytest.approx(90.0)
    np.testing.assert_allclose(
        metrics.sr_cost(10.0, np.array([10.0, 6.0, 2.0]), 2.0), [0.0, 50.0, 100.0]
    )
    assert np.isnan(metrics.sr_ate(1.0, 0.5, 1.0))


def test_frechet_mean_is_the_minimiser():
    rng = np.random.default_rng(3)
    center = _random_poses(rng, (4,))
    copies = _perturb(rng, np.broadcast_to(center, (5, 4, 4, 4)), 0.3, 0.4)  # (N=5, m=4)
    present = np.ones((5, 4), bool)
    present[1, 2] = present[4, 0] = False
    ce, y_avg = metrics.consistency_error(copies, present)

    def objective(y):  # 1/N sum_i 1/m_i sum_j |Log(y_ij^-1 y_j)|^2
        tot = 0.0
        for i in range(5):
            js = np.flatnonzero(present[i])
            e = metrics.pose_error_log(y[js], copies[i, js])
            tot += np.mean(np.sum(e * e, -1))
        return tot / 5

    assert ce == pytest.approx(objective(y_avg), rel=1e-10)
    # Any small move of the mean increases the objective (first-order optimality).
    for _ in range(20):
        xi = rng.normal(0, 1e-3, (4, 6))
        from dran_edge import geometry as geo

        assert objective(geo.se3_retract(y_avg, xi)) > ce
    # Identical copies: CE = 0 and the mean is the copy.
    same = np.broadcast_to(center, (3, 4, 4, 4))
    ce0, m0 = metrics.consistency_error(same, np.ones((3, 4), bool))
    assert ce0 == pytest.approx(0.0, abs=1e-20)
    np.testing.assert_allclose(m0, center, atol=1e-12)


def test_bias_formula_and_bias_of_mean():
    rng = np.random.default_rng(4)
    gt = _random_poses(rng, (3,))
    # Two robots with opposite translation offsets: each copy is 0.1 m off, the mean is exact.
    off = np.array([0.1, 0.0, 0.0])
    Y = np.stack(
        [_pose(gt[:, :3, :3], gt[:, :3, 3] + off), _pose(gt[:, :3, :3], gt[:, :3, 3] - off)]
    )
    present = np.ones((2, 3), bool)
    assert metrics.object_bias(Y, present, gt) == pytest.approx(0.1, rel=1e-9)
    _, y_avg = metrics.consistency_error(Y, present)
    assert metrics.object_bias_of_mean(y_avg, gt) == pytest.approx(0.0, abs=1e-9)
    tr, rot = metrics.object_errors(Y, present, gt)
    np.testing.assert_allclose(tr, 0.1, rtol=1e-9)
    np.testing.assert_allclose(rot, 0.0, atol=1e-6)


def test_relative_errors_ignore_a_common_transform_and_see_a_relative_one():
    rng = np.random.default_rng(5)
    A, B = _random_poses(rng, (50,)), _random_poses(rng, (50,))
    G = _random_poses(rng, ())
    r = metrics.inter_robot_error(G @ A, A, G @ B, B)
    assert r["trans_rmse_m"] < 1e-9 and r["rot_rmse_deg"] < 1e-6
    shift = _pose(np.eye(3), np.array([0.0, 0.2, 0.0]))
    r2 = metrics.inter_robot_error(A, A, B @ shift, B)
    assert r2["trans_rmse_m"] == pytest.approx(0.2, rel=1e-9)


def test_rpe_on_constant_velocity_drift():
    t = np.arange(0, 20, 0.1)
    ref = _pose(np.eye(3), np.outer(t, [1.0, 0, 0]))
    est = _pose(np.eye(3), np.outer(t, [1.02, 0, 0]))  # 2 % scale drift
    r = metrics.rpe(t, est, ref, delta_s=1.0)
    assert r["trans_rmse_m"] == pytest.approx(0.02, rel=1e-6)
    assert r["pairs"] == len(t) - 10


# -------------------------------------------------------------------------------------------
# evo as an oracle


def _evo_ape(ref_path, est_path, correct_scale):
    evo_file = pytest.importorskip("evo.tools.file_interface")
    from evo.core import metrics as evo_metrics
    from evo.core import sync

    ref = evo_file.read_tum_trajectory_file(str(ref_path))
    est = evo_file.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    est = copy.deepcopy(est)
    est.align(ref, correct_scale=correct_scale)
    out = {}
    for rel in (
        evo_metrics.PoseRelation.translation_part,
        evo_metrics.PoseRelation.rotation_angle_deg,
    ):
        ape = evo_metrics.APE(rel)
        ape.process_data((ref, est))
        out[rel.name] = ape.get_all_statistics()
    return out, ref.num_poses


@pytest.mark.parametrize("kind", ["se3", "sim3"])
def test_our_ate_equals_evo(kind):
    want, n = _evo_ape(DATA / "gt.tum", DATA / "est.tum", correct_scale=(kind == "sim3"))
    t_ref, T_ref = tum.read_tum(DATA / "gt.tum")
    t_est, T_est = tum.read_tum(DATA / "est.tum")
    a = align.associate(t_est, T_est, t_ref, T_ref)
    assert a.matched_poses == n == 196
    al = align.fit_alignment(kind, a.T_est, a.T_ref)
    T_al = al.apply(a.T_est)
    stats = metrics.ate_trans_stats_m(T_al, a.T_ref)
    tr = want["translation_part"]
    assert stats["rmse_m"] == pytest.approx(tr["rmse"], abs=1e-6)
    assert stats["max_m"] == pytest.approx(tr["max"], abs=1e-6)
    assert stats["mean_m"] == pytest.approx(tr["mean"], abs=1e-6)
    assert metrics.ate_trans_rmse_m(T_al, a.T_ref) == pytest.approx(tr["rmse"], abs=1e-6)
    rot = want["rotation_angle_deg"]
    assert metrics.ate_rot_rmse_deg(T_al, a.T_ref) == pytest.approx(rot["rmse"], abs=1e-6)
    assert stats["rmse_m"] > 0.01  # a fixture with real error, not a trivial zero


def test_our_tum_export_reads_back_in_evo(tmp_path):
    evo_file = pytest.importorskip("evo.tools.file_interface")
    t, T = tum.read_tum(DATA / "est.tum")
    p = tmp_path / "out.tum"
    tum.write_tum(p, t, T, header="exported by dran-edge")
    traj = evo_file.read_tum_trajectory_file(str(p))
    np.testing.assert_allclose(traj.timestamps, t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.array(traj.poses_se3), T, atol=1e-9)
