"""The consensus penalty β against the information of the object observations.

β has the units of the factors' information: DRAN's iterates are unchanged when every factor's
information and β are multiplied by the same s (docs/dran.md, "β has the units of
information"). What matters is therefore β / s, with s the information of a typical tag
observation along its weakest axis: the median over the observation factors of the smallest
eigenvalue of Σ⁻¹ (= 1 / the largest eigenvalue of the covariance Σ).

Measured (docs/notes/object-simulation.md, "β has the units of information"): β / s in
0.01–0.2 converges fastest on the unit- and true-information simulations and on the demo
missions; β / s = 2·10⁻⁴ (the paper's β = 1 with the robot's ~5·10³ m⁻²) ended the `make demo`
replay at F/F* 1.43 instead of 1.09, and β / s ≈ 0.9–9 was 1.7–3× slower than 0.09 on the
true-information simulation. :func:`check` says when a configured β lies well outside that.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

#: β / s measured to converge fastest (see the module docstring).
GOOD_RATIO = (0.01, 0.2)
#: β / s outside this range gets a warning: ≥ 3× beyond the measured window on either side.
WARN_RATIO = (0.003, 1.0)


def observation_scale(covariances: Iterable[np.ndarray]) -> float | None:
    """Median over (k, 6, 6) observation covariances of the information along the weakest
    axis, 1 / λ_max(Σ); None without observations."""
    S = [np.asarray(c, float).reshape(-1, 6, 6) for c in covariances]
    S = [c for c in S if len(c)]
    if not S:
        return None
    lam_max = np.linalg.eigvalsh(np.concatenate(S))[:, -1]
    return float(np.median(1.0 / lam_max))


def check(beta: float, scale: float | None) -> tuple[float | None, str | None]:
    """(β / s, a warning or None) for a configured β and the observations' scale s."""
    if scale is None or scale <= 0.0:
        return None, None
    ratio = beta / scale
    if WARN_RATIO[0] <= ratio <= WARN_RATIO[1]:
        return ratio, None
    side = "weak" if ratio < WARN_RATIO[0] else "stiff"
    lo, hi = GOOD_RATIO
    return ratio, (
        f"agent.beta = {beta:g} is {ratio:.2g} x the information of a typical tag observation "
        f"along its weakest axis ({scale:.3g}): too {side} for the consensus to converge "
        f"quickly; {lo:g}-{hi:g} x ({lo * scale:.3g}-{hi * scale:.3g}) converged fastest "
        "where measured (docs/dran.md, 'beta has the units of information')"
    )
