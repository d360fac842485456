"""Small-angle-safe scalar coefficients shared by SO(3), SE(3) and SE(2).

Every function takes ``theta_sq`` = θ² (any shape) and evaluates the closed form where
θ² ≥ ``SMALL_SQ`` and a Taylor series in x = θ² below it, selected with ``np.where``.
The closed form is evaluated on a safe θ (1 where small) so no branch makes NaN or inf.
The series keep four terms: at θ² = 1e-2 the first omitted term is below 1e-13.
"""

from __future__ import annotations

import numpy as np

SMALL_SQ = 1e-2


def _split(theta_sq: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    theta_sq = np.asarray(theta_sq, dtype=np.float64)
    small = theta_sq < SMALL_SQ
    theta = np.sqrt(np.where(small, 1.0, theta_sq))
    return theta_sq, small, theta


def sinc(theta_sq):
    """sin θ / θ."""
    x, small, t = _split(theta_sq)
    return np.where(small, 1 - x / 6 + x**2 / 120 - x**3 / 5040, np.sin(t) / t)


def one_minus_cos_over_sq(theta_sq):
    """(1 − cos θ) / θ²."""
    x, small, t = _split(theta_sq)
    return np.where(small, 0.5 - x / 24 + x**2 / 720 - x**3 / 40320, (1 - np.cos(t)) / t**2)


def theta_minus_sin_over_cube(theta_sq):
    """(θ − sin θ) / θ³."""
    x, small, t = _split(theta_sq)
    return np.where(small, 1 / 6 - x / 120 + x**2 / 5040 - x**3 / 362880, (t - np.sin(t)) / t**3)


def se3_q_c2(theta_sq):
    """(θ² + 2 cos θ − 2) / (2 θ⁴), the second coefficient of Barfoot's Q(ρ, φ)."""
    x, small, t = _split(theta_sq)
    return np.where(
        small,
        1 / 24 - x / 720 + x**2 / 40320 - x**3 / 3628800,
        (t**2 + 2 * np.cos(t) - 2) / (2 * t**4),
    )


def se3_q_c3(theta_sq):
    """(2θ − 3 sin θ + θ cos θ) / (2 θ⁵), the third coefficient of Barfoot's Q(ρ, φ)."""
    x, small, t = _split(theta_sq)
    return np.where(
        small,
        1 / 120 - x / 2520 + x**2 / 120960 - x**3 / 9979200,
        (2 * t - 3 * np.sin(t) + t * np.cos(t)) / (2 * t**5),
    )


def so3_jinv_coeff(theta_sq):
    """1/θ² − cot(θ/2) / (2θ): the Φ² coefficient of J_r⁻¹(φ) and J_l⁻¹(φ), finite up to θ = π."""
    x, small, t = _split(theta_sq)
    half = 0.5 * t
    return np.where(
        small,
        1 / 12 + x / 720 + x**2 / 30240 + x**3 / 1209600,
        1 / t**2 - np.cos(half) / (2 * t * np.sin(half)),
    )
