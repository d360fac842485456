"""``dran.beta_scale``: β against the information of the tag observations."""

import numpy as np

from dran_edge.dran import beta_scale


def _cov(sigma_t_m: float, sigma_r_rad: float, k: int) -> np.ndarray:
    return np.tile(np.diag([sigma_t_m**2] * 3 + [sigma_r_rad**2] * 3), (k, 1, 1))


def test_scale_is_the_median_information_along_the_weakest_axis():
    # 1.4 cm / 0.5°: translation is the weaker axis, 1/σ_t² = 5102 m⁻²
    a = _cov(0.014, np.radians(0.5), 5)
    assert beta_scale.observation_scale([a]) == np.float64(1 / 0.014**2).item()
    # a rotated covariance has the same weakest axis; the median ignores a few weak outliers
    R = np.linalg.qr(np.random.default_rng(0).normal(size=(6, 6)))[0]
    b = R @ a @ R.T
    weak = _cov(1.0, 1.0, 2)
    assert np.isclose(beta_scale.observation_scale([b, weak[:1], a[:2], weak[1:]]), 1 / 0.014**2)
    assert beta_scale.observation_scale([np.zeros((0, 6, 6))]) is None
    assert beta_scale.observation_scale([]) is None


def test_check_warns_only_far_outside_the_measured_window():
    s = 5000.0
    ratio, warning = beta_scale.check(250.0, s)
    assert ratio == 0.05 and warning is None
    for beta in (s * beta_scale.WARN_RATIO[0], s * beta_scale.WARN_RATIO[1]):
        assert beta_scale.check(beta, s)[1] is None  # the edges are still accepted
    ratio, warning = beta_scale.check(1.0, s)  # the paper's β on the robot's information
    assert ratio == 2e-4 and "too weak" in warning and "agent.beta = 1 " in warning
    assert "50-1e+03" in warning  # the window in the configuration's units
    assert "too stiff" in beta_scale.check(10 * s, s)[1]
    assert beta_scale.check(1.0, None) == (None, None)
