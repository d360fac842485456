"""The Ego-like object scenario (dran_edge.experiments.objects): outliers leave the inlier data alone."""

import numpy as np
import pytest

from dran_edge.errors import InputError
from dran_edge.experiments.objects import SimParams, make_scenario

SMALL = dict(num_robots=4, num_objects=12, box_m=(15.0, 15.0, 3.0), goals_per_robot=2, seed=5)


@pytest.mark.parametrize("mode", ["add", "relabel"])
def test_outliers_change_only_the_outliers(mode):
    """With outliers, a scenario has the trajectories, odometry and observation noise of the same
    seed without them, so the outlier-free run is the right comparison (20 % outlier target).
    'add' keeps every observation and appends wrong-id copies; 'relabel' swaps ids in place."""
    clean = make_scenario(SimParams(**SMALL))
    dirty = make_scenario(SimParams(**SMALL, outlier_ratio=0.2, outlier_ids=mode))
    wrong_ids = loops = 0
    for r, (c, d) in enumerate(zip(clean.problems, dirty.problems)):
        assert np.array_equal(clean.gt_robots[r], dirty.gt_robots[r])
        assert np.array_equal(c.x0, d.x0)
        n_odo = c.between.shape[0]
        assert np.array_equal(c.between_T, d.between_T[:n_odo])
        n = c.obs_object.size
        if mode == "relabel":
            assert d.obs_object.size == n
            wrong_ids += int((c.obs_object != d.obs_object).sum())
        else:
            assert np.array_equal(c.obs_object, d.obs_object[:n])  # every right one kept
            extra = slice(n, None)
            wrong_ids += d.obs_object.size - n
            # each extra is a copy of a real detection (same keyframe, same measurement) with
            # another object's id
            for k, o, T in zip(d.obs_own[extra], d.obs_object[extra], d.obs_T[extra]):
                same = np.flatnonzero(
                    (c.obs_own == k) & np.all(np.isclose(c.obs_T, T), axis=(1, 2))
                )
                assert same.size == 1 and c.obs_object[same[0]] != o
        assert np.array_equal(c.obs_T, d.obs_T[:n]) and np.array_equal(c.obs_own, d.obs_own[:n])
        loops += d.between.shape[0] - n_odo
        assert d.between_robust[n_odo:].all() and not d.between_robust[:n_odo].any()
    assert wrong_ids > 0 and loops > 0


def test_the_false_loop_count_does_not_depend_on_the_id_mode():
    a = make_scenario(SimParams(**SMALL, outlier_ratio=0.2, outlier_ids="add"))
    b = make_scenario(SimParams(**SMALL, outlier_ratio=0.2, outlier_ids="relabel"))
    for p, q in zip(a.problems, b.problems):
        assert np.array_equal(p.between, q.between) and np.array_equal(p.between_T, q.between_T)


def test_bad_parameters_are_named():
    with pytest.raises(InputError, match="outlier_ids"):
        SimParams(outlier_ids="swap")
    with pytest.raises(InputError, match="outlier_ratio"):
        SimParams(outlier_ratio=1.0)
