"""The SE-Sync-convention objective F and the edge weights it uses.

SE-Sync (Rosen et al., IJRR 2019, Problem 1, eq. 12), with no ½ factor:

    F(X) = Σ_(i,j) κ_ij ‖R_j − R_i R̃_ij‖²_F + τ_ij ‖t_j − t_i − R_i t̃_ij‖²

with κ, τ derived from each edge's information matrix Ω (translation block Ω_tt, rotation block
Ω_rr) exactly as SE-Sync's g2o loader does:

    SE(3): τ = 3 / tr(Ω_tt⁻¹),  κ = 3 / (2 tr(Ω_rr⁻¹))
    SE(2): τ = 2 / tr(Ω_tt⁻¹),  κ = Ω_θθ

This is the number the paper's Table 1 reports. ``--weights sesync`` builds factors whose cost is
½F (chordal residual, exact) or ½F to first order (geodesic residual); ``--weights information``
uses each edge's full information with the geodesic residual.
"""

from __future__ import annotations

import numpy as np

from dran_edge.config import Residual
from dran_edge.solver.factors import BetweenFactors, isotropic_whitening, whitening_from_information

WEIGHTS = ("sesync", "information")
RESIDUALS = (Residual.CHORDAL, Residual.GEODESIC)


def _trace_inverse(blocks: np.ndarray) -> np.ndarray:
    """tr(Ω⁻¹) of each (m, k, k) block; +inf for a singular block (no finite inverse)."""
    try:
        trace: np.ndarray = np.trace(np.linalg.inv(blocks), axis1=1, axis2=2)
        return trace
    except np.linalg.LinAlgError:  # one singular block fails the batch: edge by edge
        out = np.empty(blocks.shape[0])
        for k, block in enumerate(blocks):
            try:
                out[k] = np.trace(np.linalg.inv(block))
            except np.linalg.LinAlgError:
                out[k] = np.inf
        return out


def sesync_weights(dim: int, information: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(κ, τ), each (m,), from (m, r, r) information matrices in [translation, rotation] order.

    Only the blocks' traces of inverses are used, so Ω itself need not be positive definite; a
    singular block gives weight 0 and an indefinite one may give a negative or infinite weight:
    :func:`weight_problems` tells which edges cannot be used."""
    information = np.asarray(information, dtype=np.float64)
    with np.errstate(divide="ignore"):
        tau = dim / _trace_inverse(information[:, :dim, :dim])
        if dim == 3:
            kappa = 3.0 / (2.0 * _trace_inverse(information[:, 3:, 3:]))
        else:
            kappa = information[:, 2, 2].copy()
    return kappa, tau


def not_positive_definite(information: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mask, smallest eigenvalue) over (m, r, r) information matrices: which are not positive
    definite (smallest eigenvalue ≤ 0, or not finite)."""
    lam_min = np.linalg.eigvalsh(np.asarray(information, dtype=np.float64))[:, 0]
    return ~(lam_min > 0.0), lam_min


def weight_problems(dim: int, information: np.ndarray, weights: str) -> list[tuple[int, str]]:
    """(edge index, why) for every edge whose weights under ``weights`` cannot be used, in edge
    order; empty when all can. 'sesync' needs finite κ > 0 and τ > 0 (SE-Sync's loader computes
    them from the blocks alone, so an indefinite Ω with positive weights is usable);
    'information' needs Ω positive definite (it is the whitening's square)."""
    if weights == "sesync":
        kappa, tau = sesync_weights(dim, information)
        rule = "3/(2 tr(Omega_rr^-1))" if dim == 3 else "Omega_thth"
        out = []
        for k in np.flatnonzero(~(np.isfinite(kappa) & np.isfinite(tau) & (kappa > 0) & (tau > 0))):
            why = []
            if not (np.isfinite(tau[k]) and tau[k] > 0):
                why.append(f"translation weight tau = {dim}/tr(Omega_tt^-1) is {tau[k]:.6g}")
            if not (np.isfinite(kappa[k]) and kappa[k] > 0):
                why.append(f"rotation weight kappa = {rule} is {kappa[k]:.6g}")
            out.append((int(k), "; ".join(why) + " (SE-Sync weights must be finite and > 0)"))
        return out
    if weights == "information":
        bad, lam_min = not_positive_definite(information)
        return [
            (
                int(k),
                f"information matrix is not positive definite (smallest eigenvalue "
                f"{lam_min[k]:.6g}), which --weights information needs (use --weights sesync)",
            )
            for k in np.flatnonzero(bad)
        ]
    raise ValueError(f"weights must be one of {WEIGHTS}, got {weights!r}")


def sesync_objective(
    poses: np.ndarray,
    edges: np.ndarray,
    measurements: np.ndarray,
    kappa: np.ndarray,
    tau: np.ndarray,
) -> float:
    """F at ``poses`` (n, D, D) for edges (m, 2) with measurements (m, D, D) and weights (m,)."""
    d = poses.shape[-1] - 1
    Pi, Pj = poses[edges[:, 0]], poses[edges[:, 1]]
    Ri, Rj, ti, tj = Pi[:, :d, :d], Pj[:, :d, :d], Pi[:, :d, d], Pj[:, :d, d]
    Rm, tm = measurements[:, :d, :d], measurements[:, :d, d]
    rot = Rj - Ri @ Rm
    trans = tj - ti - (Ri @ tm[:, :, None])[:, :, 0]
    return float(
        np.sum(kappa * np.sum(rot * rot, axis=(1, 2))) + np.sum(tau * np.sum(trans * trans, axis=1))
    )


def edge_factors(
    dim: int,
    edges: np.ndarray,
    measurements: np.ndarray,
    information: np.ndarray,
    residual: str = "chordal",
    weights: str = "sesync",
    label: str = "between",
) -> BetweenFactors:
    """One :class:`BetweenFactors` block for g2o-style edges under a residual/weights choice.

    ``weights='information'`` uses Ω in full and needs ``residual='geodesic'``: the chordal
    residual's 12 (or 6) entries have no natural image of a 6×6 (or 3×3) information matrix.
    """
    if residual not in RESIDUALS:
        raise ValueError(f"residual must be one of {', '.join(RESIDUALS)}, got {residual!r}")
    if weights == "sesync":
        kappa, tau = sesync_weights(dim, information)
        W = isotropic_whitening(kappa, tau, residual, dim)
    elif weights == "information":
        if residual != Residual.GEODESIC:
            raise ValueError(
                "weights 'information' needs the geodesic residual; the chordal residual is "
                "weighted isotropically (use weights 'sesync')"
            )
        W = whitening_from_information(information)
    else:
        raise ValueError(f"weights must be one of {WEIGHTS}, got {weights!r}")
    return BetweenFactors(
        variables=np.asarray(edges, dtype=np.int64),
        measurements=np.asarray(measurements, dtype=np.float64),
        whitening=W,
        residual=residual,
        label=label,
    )
