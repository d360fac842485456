"""Pose-graph factors, vectorised per factor type (paper eq. 2), with analytic Jacobians.

Every factor block holds ``m`` factors of one type as arrays and evaluates them in one numpy pass.
Tangents follow the geometry module: ``ξ = [ρ, φ]`` (SE(3)) or ``[x, y, θ]`` (SE(2)), right
perturbation ``T ⊕ ξ = T Exp(ξ)``.

Residuals of a relative measurement ``T̃`` between poses ``T_p`` and ``T_q`` (paper eq. 2):

- geodesic: ``r = Log(T̃⁻¹ T_p⁻¹ T_q)`` (dim 6 or 3);
- chordal:  ``r = T_p T̃ − T_q`` on the top d×(d+1) block, laid out as
  ``[vec_rowmajor(R_p R̃ − R_q), R_p t̃ + t_p − t_q]`` (dim 12 or 6).

A factor's cost is ``½ ρ(‖W r‖²)`` with ``W`` the whitening (``WᵀW = Ω``, the information) and
``ρ`` a robust kernel (identity without one). With ``W = diag(√κ·1_{d²}, √τ·1_d)`` the chordal
cost is exactly half of the SE-Sync term ``κ‖R_q − R_p R̃‖²_F + τ‖t_q − t_p − R_p t̃‖²``.

Robust kernels enter as iteratively reweighted least squares: at a linearisation point the factor's
whitened residual and Jacobian are scaled by ``√w`` with ``w = ρ'(s)``, ``s = ‖W r‖²``, so the
gradient ``Σ w Jᵀ W ᵀW r`` is exact and ``JᵀJ`` is the usual IRLS approximation.

A factor type is anything with the :class:`Factor` interface: ``variables`` (m, k) indices into the
graph's variables, ``kernel``, and ``linearize(poses) -> (r, J)`` returning whitened residuals
``(m, r)`` and Jacobians ``(m, k, r, dof)`` with respect to each endpoint's right perturbation
(a fixed endpoint's block is computed and ignored). New types (e.g. the DRAN consensus term of
paper eq. 6) are added from outside by implementing it.
"""

from __future__ import annotations

from dataclasses import dataclass
from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np

from dran_edge import geometry as geo
from dran_edge.config import Residual, RobustKernel

# ----------------------------------------------------------------------------- kernels


@dataclass(frozen=True)
class Huber:
    """Huber kernel on the whitened residual norm: ρ(s) = s for √s ≤ k, else 2k√s − k²."""

    threshold: float
    """k, in whitened units (standard deviations)."""

    def rho(self, s: np.ndarray) -> np.ndarray:
        r = np.sqrt(s)
        k = self.threshold
        return np.where(r <= k, s, 2.0 * k * r - k * k)

    def weight(self, s: np.ndarray) -> np.ndarray:
        """ρ'(s) = 1 for √s ≤ k, else k / √s."""
        r = np.sqrt(s)
        return np.where(r <= self.threshold, 1.0, self.threshold / np.maximum(r, 1e-300))


@dataclass(frozen=True)
class Cauchy:
    """Cauchy kernel: ρ(s) = c² log(1 + s / c²)."""

    scale: float | np.ndarray
    """c, in whitened units (standard deviations): one for the block, or one per factor (m,);
    an infinite c leaves that factor least squares (ρ(s) = s, its limit)."""

    def rho(self, s: np.ndarray) -> np.ndarray:
        c2 = np.square(self.scale)
        ls = np.isinf(c2)
        c2 = np.where(ls, 1.0, c2)
        return np.where(ls, s, c2 * np.log1p(s / c2))

    def weight(self, s: np.ndarray) -> np.ndarray:
        """ρ'(s) = 1 / (1 + s / c²)."""
        return 1.0 / (1.0 + s / np.square(self.scale))


Kernel = Huber | Cauchy


def make_kernel(name: str, width: float) -> Kernel | None:
    """The kernel a config names ('none', 'huber', 'cauchy'), of width ``width``."""
    if name == RobustKernel.NONE:
        return None
    if name == RobustKernel.HUBER:
        return Huber(width)
    if name == RobustKernel.CAUCHY:
        return Cauchy(width)
    raise ValueError(f"unknown robust kernel {name!r} (none, huber or cauchy)")


def kernel_cost(kernel: Kernel | None, s: np.ndarray) -> np.ndarray:
    """Per-factor cost ½ ρ(s) of squared whitened norms ``s``."""
    return 0.5 * (s if kernel is None else kernel.rho(s))


# ----------------------------------------------------------------------------- interface


@runtime_checkable
class Factor(Protocol):
    """A block of m factors of one type (see the module docstring)."""

    @property
    def variables(self) -> np.ndarray:
        """(m, k) int graph indices of each factor's variables."""
        ...

    @property
    def kernel(self) -> Kernel | None:
        """The robust kernel on the squared whitened norms, None for least squares."""
        ...

    def linearize(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals ``(m, r)`` and Jacobians ``(m, k, r, dof)`` at ``poses`` (n, D, D)."""
        ...

    def residuals(self, poses: np.ndarray) -> np.ndarray:
        """Whitened residuals ``(m, r)`` at ``poses``."""
        ...


# ----------------------------------------------------------------------------- residual maths


def _generators(d: int) -> np.ndarray:
    """Rotation generators G_k with [φ]^ = Σ φ_k G_k: (3, 3, 3) for SO(3), (1, 2, 2) for SO(2)."""
    if d == 3:
        return geo.hat3(np.eye(3))
    return np.array([[[0.0, -1.0], [1.0, 0.0]]])


def geodesic_residual(T_p: np.ndarray, T_q: np.ndarray, T_meas: np.ndarray) -> np.ndarray:
    """r = Log(T̃⁻¹ T_p⁻¹ T_q) (paper eq. 2, geodesic), batched."""
    return geo.log(geo.inverse(T_meas) @ geo.inverse(T_p) @ T_q)


def geodesic_jacobians(
    T_p: np.ndarray, T_q: np.ndarray, T_meas: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(r, J_p, J_q) of the geodesic residual.

    ``J_q = d/dδ r(T_p, T_q Exp δ) = J_r⁻¹(r)`` and
    ``J_p = d/dδ r(T_p Exp δ, T_q) = −J_r⁻¹(r) Adj(T_q⁻¹ T_p)`` at δ = 0, because
    ``T̃⁻¹ Exp(−δ) T_p⁻¹ T_q = E Exp(−Adj(T_q⁻¹ T_p) δ)`` with ``E = T̃⁻¹ T_p⁻¹ T_q``.
    """
    T_p_inv = geo.inverse(T_p)
    r = geo.log(geo.inverse(T_meas) @ T_p_inv @ T_q)
    Jr_inv = geo.right_jacobian_inv(r)
    J_q = Jr_inv
    J_p = -Jr_inv @ geo.adjoint(geo.inverse(T_q) @ T_p)
    return r, J_p, J_q


def chordal_residual(T_p: np.ndarray, T_q: np.ndarray, T_meas: np.ndarray) -> np.ndarray:
    """r = T_p T̃ − T_q (paper eq. 2, chordal) as ``[vec(R_p R̃ − R_q), R_p t̃ + t_p − t_q]``."""
    d = T_p.shape[-1] - 1
    E = (T_p @ T_meas - T_q)[..., :d, :]
    rot = E[..., :d].reshape(E.shape[:-2] + (d * d,))
    return np.concatenate([rot, E[..., d]], axis=-1)


def chordal_jacobians(
    T_p: np.ndarray, T_q: np.ndarray, T_meas: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(r, J_p, J_q) of the chordal residual.

    With ``T Exp(δ) ≈ T (I + δ^)`` and ``δ^ = [[Σ φ_k G_k, ρ], [0, 0]]``:
    ``d/dδ_p (T_p Exp δ_p T̃ − T_q)``: rotation block ``∂/∂φ_k = R_p G_k R̃``, translation block
    ``∂/∂ρ = R_p``, ``∂/∂φ_k = R_p G_k t̃``;
    ``d/dδ_q (T_p T̃ − T_q Exp δ_q)``: rotation ``∂/∂φ_k = −R_q G_k``, translation ``∂/∂ρ = −R_q``.
    """
    d = T_p.shape[-1] - 1
    G = _generators(d)
    nrot = G.shape[0]
    R_p, R_q, R_m = T_p[..., :d, :d], T_q[..., :d, :d], T_meas[..., :d, :d]
    t_m = T_meas[..., :d, d]
    batch = T_p.shape[:-2]
    r = chordal_residual(T_p, T_q, T_meas)
    rdim = d * d + d
    J_p = np.zeros(batch + (rdim, d + nrot))
    J_q = np.zeros(batch + (rdim, d + nrot))
    RpG = np.einsum("...ab,kbc->...kac", R_p, G)  # (..., k, d, d)
    J_p[..., : d * d, d:] = np.swapaxes(
        (RpG @ R_m[..., None, :, :]).reshape(batch + (nrot, d * d)), -1, -2
    )
    J_p[..., d * d :, :d] = R_p
    J_p[..., d * d :, d:] = np.swapaxes((RpG @ t_m[..., None, :, None])[..., 0], -1, -2)
    RqG = np.einsum("...ab,kbc->...kac", R_q, G)
    J_q[..., : d * d, d:] = -np.swapaxes(RqG.reshape(batch + (nrot, d * d)), -1, -2)
    J_q[..., d * d :, :d] = -R_q
    return r, J_p, J_q


def _tangent_generators(d: int) -> np.ndarray:
    """E_a with ξ^ = Σ ξ_a E_a for ξ = [ρ, φ]: (6, 4, 4) for SE(3), (3, 3, 3) for SE(2)."""
    G = _generators(d)
    E = np.zeros((d + G.shape[0], d + 1, d + 1))
    E[np.arange(d), np.arange(d), d] = 1.0
    E[d:, :d, :d] = G
    return E


def _sym_generator_products(d: int) -> np.ndarray:
    """½(E_a E_b + E_b E_a): the second derivative ∂²Exp(ξ)/∂ξ_a∂ξ_b at ξ = 0."""
    E = _tangent_generators(d)
    P: np.ndarray = np.einsum("aij,bjk->abik", E, E)
    sym: np.ndarray = 0.5 * (P + np.swapaxes(P, 0, 1))
    return sym


def chordal_second_order(
    T_p: np.ndarray, T_q: np.ndarray, T_meas: np.ndarray, S: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(H_pp, H_qq): ``Σ_i S_i ∂²r_i`` of the chordal residual for weights ``S`` (…, r).

    With ``S = WᵀW r`` this is the part of the Hessian of ``½‖W r(T_p Exp δ_p, T_q Exp δ_q)‖²``
    that Gauss–Newton drops; ``JᵀWᵀWJ + [[H_pp, 0], [0, H_qq]]`` is then the exact Hessian of
    the pullback at δ = 0 (r is separately linear in T_p Exp δ_p and T_q Exp δ_q, so there is no
    cross term). ``∂²(T_p Exp δ T̃)/∂δ_a∂δ_b = T_p ½(E_a E_b + E_b E_a) T̃``, hence
    ``H_pp[a, b] = ⟨T_pᵀ Ŝ T̃ᵀ, ½(E_aE_b + E_bE_a)⟩`` and ``H_qq[a, b] = −⟨T_qᵀ Ŝ, ·⟩`` with
    Ŝ the weights laid out as the top d×(d+1) block of a (d+1)×(d+1) matrix.
    """
    d = T_p.shape[-1] - 1
    D = d + 1
    Shat = np.zeros(S.shape[:-1] + (D, D))
    Shat[..., :d, :d] = S[..., : d * d].reshape(S.shape[:-1] + (d, d))
    Shat[..., :d, d] = S[..., d * d :]
    G2 = _sym_generator_products(d)
    Mp = np.swapaxes(T_p, -1, -2) @ Shat @ np.swapaxes(T_meas, -1, -2)
    Mq = -(np.swapaxes(T_q, -1, -2) @ Shat)
    return np.einsum("...ij,abij->...ab", Mp, G2), np.einsum("...ij,abij->...ab", Mq, G2)


_RESIDUALS: dict[
    str, tuple[Callable[..., np.ndarray], Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]]]
] = {
    Residual.GEODESIC: (geodesic_residual, geodesic_jacobians),
    Residual.CHORDAL: (chordal_residual, chordal_jacobians),
}


def residual_dim(residual: str, dim: int) -> int:
    """Length of one residual: geodesic 6/3, chordal 12/6 for SE(3)/SE(2)."""
    if residual == Residual.GEODESIC:
        return 6 if dim == 3 else 3
    if residual == Residual.CHORDAL:
        return dim * dim + dim
    raise ValueError(f"residual must be 'geodesic' or 'chordal', got {residual!r}")


# ----------------------------------------------------------------------------- weights


def whitening_from_information(information: np.ndarray) -> np.ndarray:
    """W with WᵀW = Ω for each ``(..., r, r)`` information (symmetric eigen-square-root, robust to
    near-singular Ω, where a Cholesky factor may fail)."""
    lam, V = np.linalg.eigh(np.asarray(information, dtype=np.float64))
    W: np.ndarray = np.sqrt(np.maximum(lam, 0.0))[..., :, None] * np.swapaxes(V, -1, -2)
    return W


def isotropic_whitening(kappa: np.ndarray, tau: np.ndarray, residual: str, dim: int) -> np.ndarray:
    """Diagonal whitening ``(m, r)`` giving cost ½·(SE-Sync term) to first order.

    chordal: ``[√κ]*d², [√τ]*d`` — exact. geodesic: ``[√τ]*d, [√(2κ)]*rot`` — since
    ``‖R − R Exp(φ)‖²_F ≈ 2‖φ‖²``, this matches the chordal cost near zero residual.
    """
    kappa = np.asarray(kappa, dtype=np.float64)
    tau = np.asarray(tau, dtype=np.float64)
    nrot = 3 if dim == 3 else 1
    if residual == Residual.CHORDAL:
        parts = [
            np.repeat(np.sqrt(kappa)[:, None], dim * dim, 1),
            np.repeat(np.sqrt(tau)[:, None], dim, 1),
        ]
    elif residual == Residual.GEODESIC:
        parts = [
            np.repeat(np.sqrt(tau)[:, None], dim, 1),
            np.repeat(np.sqrt(2 * kappa)[:, None], nrot, 1),
        ]
    else:
        raise ValueError(f"residual must be 'geodesic' or 'chordal', got {residual!r}")
    return np.concatenate(parts, axis=1)


def _whiten(W: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Apply a diagonal ``(m, r)`` or full ``(m, r, r)`` whitening to ``(m, r)`` or ``(m, r, c)``."""
    out: np.ndarray
    if W.ndim == 2:
        out = W * x if x.ndim == 2 else W[:, :, None] * x
    elif x.ndim == 2:
        out = np.einsum("mij,mj->mi", W, x)
    else:
        out = W @ x
    return out


# ----------------------------------------------------------------------------- factor blocks


@dataclass(frozen=True, eq=False)
class BetweenFactors:
    """m relative-pose factors ``T̃ = T_p⁻¹ T_q`` (odometry, loop, inter-robot, robot→object).

    The same maths serves every kind; which of p, q is private, public or fixed is the graph's
    business (an inter-robot factor to a neighbour's separator has a fixed q: an anchor).
    """

    variables: np.ndarray
    """(m, 2) int, graph indices of (p, q)."""
    measurements: np.ndarray
    """(m, D, D) ``T̃_p_q``."""
    whitening: np.ndarray
    """(m, r) diagonal or (m, r, r) full W with WᵀW = Ω in the residual's coordinates."""
    residual: str = Residual.GEODESIC
    """'geodesic' or 'chordal' (paper eq. 2)."""
    kernel: Kernel | None = None
    label: str = "between"
    """What the block models (odometry, loop, inter-robot, observation): for reports only."""

    def residuals(self, poses: np.ndarray) -> np.ndarray:
        fn = _RESIDUALS[self.residual][0]
        p, q = self.variables[:, 0], self.variables[:, 1]
        return _whiten(self.whitening, fn(poses[p], poses[q], self.measurements))

    def linearize(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        fn = _RESIDUALS[self.residual][1]
        p, q = self.variables[:, 0], self.variables[:, 1]
        r, J_p, J_q = fn(poses[p], poses[q], self.measurements)
        J = np.stack([_whiten(self.whitening, J_p), _whiten(self.whitening, J_q)], axis=1)
        return _whiten(self.whitening, r), J

    def second_order(self, poses: np.ndarray) -> np.ndarray | None:
        """(m, 2·dof, 2·dof) Hessian terms Gauss–Newton drops (chordal residual only, where
        they are cheap and matter: its residuals stay large at the optimum), else None."""
        if self.residual != Residual.CHORDAL:
            return None
        p, q = self.variables[:, 0], self.variables[:, 1]
        T_p, T_q = poses[p], poses[q]
        rw = _whiten(self.whitening, chordal_residual(T_p, T_q, self.measurements))
        S = (
            self.whitening * rw
            if self.whitening.ndim == 2
            else np.einsum("mji,mj->mi", self.whitening, rw)
        )
        H_pp, H_qq = chordal_second_order(T_p, T_q, self.measurements, S)
        dof = H_pp.shape[-1]
        out = np.zeros((p.shape[0], 2 * dof, 2 * dof))
        out[:, :dof, :dof] = H_pp
        out[:, dof:, dof:] = H_qq
        return out


@dataclass(frozen=True, eq=False)
class PriorFactors:
    """m unary factors pulling ``T_p`` to a given pose ``T̄``: residual φ(T̄, T_p) with identity
    measurement, i.e. geodesic ``Log(T̄⁻¹ T_p)`` or chordal ``T̄ − T_p``."""

    variables: np.ndarray
    """(m, 1) int, graph index of p."""
    measurements: np.ndarray
    """(m, D, D) the prior pose T̄."""
    whitening: np.ndarray
    residual: str = Residual.GEODESIC
    kernel: Kernel | None = None
    label: str = "prior"

    def _identity(self) -> np.ndarray:
        D = self.measurements.shape[-1]
        return np.broadcast_to(np.eye(D), self.measurements.shape)

    def residuals(self, poses: np.ndarray) -> np.ndarray:
        fn = _RESIDUALS[self.residual][0]
        r = fn(self.measurements, poses[self.variables[:, 0]], self._identity())
        return _whiten(self.whitening, r)

    def linearize(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        fn = _RESIDUALS[self.residual][1]
        r, _, J_q = fn(self.measurements, poses[self.variables[:, 0]], self._identity())
        return _whiten(self.whitening, r), _whiten(self.whitening, J_q)[:, None]

    def second_order(self, poses: np.ndarray) -> np.ndarray | None:
        """(m, dof, dof) Hessian terms Gauss–Newton drops (chordal residual only), else None."""
        if self.residual != Residual.CHORDAL:
            return None
        T_q = poses[self.variables[:, 0]]
        I = self._identity()
        rw = _whiten(self.whitening, chordal_residual(self.measurements, T_q, I))
        S = (
            self.whitening * rw
            if self.whitening.ndim == 2
            else np.einsum("mji,mj->mi", self.whitening, rw)
        )
        return chordal_second_order(self.measurements, T_q, I, S)[1]


def factor_cost(factor: Factor, poses: np.ndarray) -> float:
    """Σ ½ ρ(‖W r‖²) over one block."""
    r = factor.residuals(poses)
    return float(np.sum(kernel_cost(factor.kernel, np.sum(r * r, axis=1))))
