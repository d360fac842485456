"""Relative-pose factors of the bounded local graph: variable keys, factor kinds, and the algebra
of measurements with covariance — compose, invert, fuse, split (docs/notes/solve-and-bounded-graph.md).

A factor is ``(p, q, Z, Σ, kind)``: ``Z ≈ T_p⁻¹ T_q`` with right noise, ``T_p⁻¹ T_q = Z Exp(ε)``,
``ε ~ N(0, Σ)`` in the tangent order [ρ, φ]; ``p = NONE`` for a unary prior. Pure numpy.
"""

from __future__ import annotations

import numpy as np

from dran_edge import geometry as geo
from dran_edge.config import NoiseModel, Residual
from dran_edge.solver.factors import whitening_from_information

OBJ = 1 << 40  # variable key of object k is OBJ + k; node keys are < OBJ
NONE = -1  # p of a unary prior

KIND_ODOMETRY, KIND_LOOP, KIND_OBSERVATION, KIND_PRIOR = 0, 1, 2, 3
KIND_NAMES = ("odometry", "loop", "observation", "prior")


def diag_covariance(noise: NoiseModel) -> np.ndarray:
    """Σ of an isotropic noise model, [ρ, φ] order."""
    return np.diag([noise.sigma_translation_m**2] * 3 + [noise.sigma_rotation_rad**2] * 3)


def compose_cov(
    Z_ab: np.ndarray, S_ab: np.ndarray, Z_bc: np.ndarray, S_bc: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(Z_ac, Σ_ac) of two chained measurements (right noise; independent)."""
    Ad = geo.se3_adjoint(geo.se3_inverse(Z_bc))
    return Z_ab @ Z_bc, Ad @ S_ab @ Ad.T + S_bc


def invert_cov(Z_ab: np.ndarray, S_ab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Z_ba, Σ_ba): the same measurement seen from the other end."""
    Ad = geo.se3_adjoint(Z_ab)
    return geo.se3_inverse(Z_ab), Ad @ S_ab @ Ad.T


def fuse(
    Z1: np.ndarray, S1: np.ndarray, Z2: np.ndarray, S2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Information-weighted fusion of two measurements of the same relative pose."""
    O1, O2 = np.linalg.inv(S1), np.linalg.inv(S2)
    S = np.linalg.inv(O1 + O2)
    delta = S @ O2 @ geo.se3_log(geo.se3_between(Z1, Z2))
    return Z1 @ geo.se3_exp(delta), 0.5 * (S + S.T)


def split_weights(a0: float, covariances: list[np.ndarray]) -> tuple[float, list[float]]:
    """Shares (w₀, [w_i]) of one factor's information Ω among its uses, w₀ + Σ w_i = 1.

    Use i composes the shared factor with a factor of covariance ``covariances[i]``; use 0 (the
    marginalisation) has scalar information ``a0`` (0: no such use). Giving use i the copy
    ``w_i Ω`` counts Ω exactly once: the copies sum to the original factor, and eliminating the
    removed node separately in each use is the original elimination with the constraint "all
    copies of the node are equal" dropped — which can only lose information, so the result is
    conservative (the kept graph's information ⪯ the exact marginal's). The shares maximise the
    scalar information Σ 1/(s_i + b/w_i) of the uses (s_i = tr Σ_i, a0 = 1/s_0, b the shared
    factor's): w_i ∝ 1/s_i — a precise partner gets most of the shared factor.
    """
    a = [a0] + [1.0 / max(float(np.trace(S)), 1e-300) for S in covariances]
    total = sum(a)
    if total <= 0.0:
        k = len(covariances)
        return 0.0, [1.0 / k] * k
    return a[0] / total, [x / total for x in a[1:]]


def _arrays(items: list) -> dict:
    """Factor tuples (p, q, Z, Σ, kind) as arrays."""
    if not items:
        return {
            "p": np.zeros(0, np.int64),
            "q": np.zeros(0, np.int64),
            "Z": np.zeros((0, 4, 4)),
            "S": np.zeros((0, 6, 6)),
            "kind": np.zeros(0, np.int8),
        }
    return {
        "p": np.array([f[0] for f in items], np.int64),
        "q": np.array([f[1] for f in items], np.int64),
        "Z": np.stack([f[2] for f in items]),
        "S": np.stack([f[3] for f in items]),
        "kind": np.array([f[4] for f in items], np.int8),
    }


def _whitening(S: np.ndarray, residual: str) -> np.ndarray:
    """Whitening of covariances Σ (m, 6, 6) for the given residual."""
    if len(S) == 0:
        return np.zeros((0, 6, 6)) if residual == Residual.GEODESIC else np.zeros((0, 12))
    if residual == Residual.GEODESIC:
        return whitening_from_information(np.linalg.inv(S))
    # chordal: isotropic precisions from the mean variances (eq. 2 chordal form)
    tau = 3.0 / np.trace(S[:, :3, :3], axis1=1, axis2=2)
    kappa = 0.5 * 3.0 / np.trace(S[:, 3:, 3:], axis1=1, axis2=2)
    from dran_edge.solver.factors import isotropic_whitening

    return isotropic_whitening(kappa, tau, Residual.CHORDAL, 3)
