"""The Ego-like object scenario (dran_edge.objects_sim): outliers leave the inlier data alone."""

import numpy as np

from dran_edge.objects_sim import SimParams, make_scenario


def test_outliers_change_only_the_outliers():
    """With outliers, a scenario has the trajectories, odometry and observation noise of the same
    seed without them, so the outlier-free run is the right comparison (20 % outlier target)."""
    small = dict(num_robots=4, num_objects=12, box_m=(15.0, 15.0, 3.0), goals_per_robot=2, seed=5)
    clean = make_scenario(SimParams(**small))
    dirty = make_scenario(SimParams(**small, outlier_ratio=0.2))
    wrong_ids = loops = 0
    for r, (c, d) in enumerate(zip(clean.problems, dirty.problems)):
        assert np.array_equal(clean.gt_robots[r], dirty.gt_robots[r])
        assert np.array_equal(c.x0, d.x0)
        n_odo = c.between.shape[0]
        assert np.array_equal(c.between_T, d.between_T[:n_odo])
        assert np.array_equal(c.obs_T, d.obs_T) and np.array_equal(c.obs_own, d.obs_own)
        wrong_ids += int((c.obs_object != d.obs_object).sum())
        loops += d.between.shape[0] - n_odo
        assert d.between_robust[n_odo:].all() and not d.between_robust[:n_odo].any()
    assert wrong_ids > 0 and loops > 0
