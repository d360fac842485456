"""Consensus on public variables: Metropolis–Hastings weights, the dual update (eq. 5b) and the
biased-prior consensus factor (eq. 6) with its gradient (eq. 12) and Jacobian.

Augmented Lagrangian (eq. 4) and its iterations (eqs. 5a, 5b)::

    L(x, y, λ) = f(x, y) + Σ_i Σ_{j∈N_i} ⟨λ_ij, w_ij φ(y_i, y_j)⟩ + (β/2) ‖w_ij φ(y_i, y_j)‖²
    λ_ij ← λ_ij + η β w_ij φ(y_i, y_j)                                            (eq. 5b)

Biased prior (eq. 6): with the neighbour's copy y_j held fixed for the round,

    L̂_i = f_i(x_i, y_i) + Σ_{j∈N_i} (β/2) ‖w_ij φ(y_i, y_j) + λ_ij / β‖²

i.e. one whitened residual ``√β (w_ij φ(y_i, y_j) + λ_ij/β)`` per (neighbour, object), Jacobian
``√β w_ij ∂φ/∂y_i``. Its gradient on y_i is the consensus part of eq. 12,
``β w_ij (∂φ/∂y_i)ᵀ (w_ij φ + λ_ij/β)``; for the geodesic φ near consensus ``∂φ/∂y_i ≈ −I`` so
the gradient is ``−β w_ij (w_ij Log(y_i⁻¹ y_j) + λ_ij/β)`` — eq. 12's ``grad φ² = 2 Log_{y_i}(y_j)``
up to sign and the factor ½ of the squared norm.

φ (eq. 2 with the identity as measurement):

- geodesic ``φ(y_i, y_j) = Log(y_i⁻¹ y_j)`` (6 or 3 entries; exactly antisymmetric,
  ``φ(y_j, y_i) = −φ(y_i, y_j)``, so Σ_ij λ_ij stays zero when both ends update);
- chordal ``φ(y_i, y_j) = y_i − y_j`` on the top d×(d+1) block (12 or 6 entries).

Metropolis–Hastings weights (Xiao, Boyd & Lall 2005): ``w_ij = 1 / (1 + max(deg_i, deg_j))``
for neighbours, ``w_ii = 1 − Σ_j w_ij``; symmetric and doubly stochastic on any graph.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dran_edge import geometry as geo
from dran_edge.config import Residual
from dran_edge.solver.factors import Kernel, chordal_jacobians, chordal_residual, geodesic_jacobians


def metropolis_hastings_weight(degree_i: int, degree_j: int) -> float:
    """w_ij = 1 / (1 + max(deg_i, deg_j)) for an edge of the communication graph."""
    return 1.0 / (1.0 + max(int(degree_i), int(degree_j)))


def metropolis_hastings_matrix(adjacency: np.ndarray) -> np.ndarray:
    """(N, N) MH weight matrix of a symmetric 0/1 adjacency (diagonal ignored)."""
    A = np.asarray(adjacency, dtype=bool)
    A = A & ~np.eye(A.shape[0], dtype=bool)
    deg = A.sum(axis=1)
    W = np.where(A, 1.0 / (1.0 + np.maximum(deg[:, None], deg[None, :])), 0.0)
    W[np.diag_indices_from(W)] = 1.0 - W.sum(axis=1)
    return W


def phi(y_i: np.ndarray, y_j: np.ndarray, kind: str = "geodesic") -> np.ndarray:
    """φ(y_i, y_j) batched: geodesic ``Log(y_i⁻¹ y_j)`` or chordal ``y_i − y_j`` (eq. 2)."""
    if kind == Residual.GEODESIC:
        return geo.log(geo.inverse(y_i) @ y_j)
    if kind == Residual.CHORDAL:
        return chordal_residual(y_i, y_j, np.broadcast_to(np.eye(y_i.shape[-1]), y_i.shape))
    raise ValueError(f"phi kind must be 'geodesic' or 'chordal', got {kind!r}")


def phi_dim(kind: str, dim: int) -> int:
    """Entries of φ: geodesic 6/3, chordal 12/6 for SE(3)/SE(2)."""
    return (6 if dim == 3 else 3) if kind == Residual.GEODESIC else dim * dim + dim


def dual_update(
    lam: np.ndarray, phi_ij: np.ndarray, w: np.ndarray, beta: float, eta: float
) -> np.ndarray:
    """Eq. 5b: ``λ_ij + η β w_ij φ(y_i, y_j)`` for (m, r) duals, (m, r) φ and (m,) weights."""
    lam_new: np.ndarray = lam + eta * beta * np.asarray(w)[:, None] * phi_ij
    return lam_new


def consensus_error(y_i: np.ndarray, y_j: np.ndarray) -> np.ndarray:
    """(m,) squared geodesic distances ``‖Log(y_i⁻¹ y_j)‖²`` (the ε_φ test, Sec. 4.2.3)."""
    r = geo.log(geo.inverse(y_i) @ y_j)
    phi2: np.ndarray = np.sum(r * r, axis=-1)
    return phi2


@dataclass(frozen=True, eq=False)
class ConsensusFactors:
    """m biased-prior terms of eq. 6, one per (neighbour j, object) pair of robot i.

    ``variables[:, 0]`` is the local copy y_i (public), ``variables[:, 1]`` the neighbour's copy
    y_j (a FIXED variable of the local graph). Implements :class:`dran_edge.solver.factors.Factor`:
    whitened residual ``√β (w φ(y_i, y_j) + λ/β)`` and its Jacobian ``√β w ∂φ/∂y_i``.
    """

    variables: np.ndarray
    """(m, 2) graph indices of (y_i, y_j)."""
    w: np.ndarray
    """(m,) MH weights w_ij."""
    lam: np.ndarray
    """(m, r) duals λ_ij."""
    beta: float
    kind: str = "geodesic"
    kernel: Kernel | None = None
    label: str = "consensus"

    def _phi_and_jac(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        y_i, y_j = poses[self.variables[:, 0]], poses[self.variables[:, 1]]
        eye = np.broadcast_to(np.eye(y_i.shape[-1]), y_i.shape)
        if self.kind == Residual.GEODESIC:
            r, J_i, _ = geodesic_jacobians(y_i, y_j, eye)
        elif self.kind == Residual.CHORDAL:
            r, J_i, _ = chordal_jacobians(y_i, y_j, eye)
        else:
            raise ValueError(f"phi kind must be 'geodesic' or 'chordal', got {self.kind!r}")
        return r, J_i

    def residuals(self, poses: np.ndarray) -> np.ndarray:
        y_i, y_j = poses[self.variables[:, 0]], poses[self.variables[:, 1]]
        s = np.sqrt(self.beta)
        res: np.ndarray = s * (self.w[:, None] * phi(y_i, y_j, self.kind) + self.lam / self.beta)
        return res

    def linearize(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, J_i = self._phi_and_jac(poses)
        s = np.sqrt(self.beta)
        res = s * (self.w[:, None] * r + self.lam / self.beta)
        J = s * self.w[:, None, None] * J_i
        return res, np.stack([J, np.zeros_like(J)], axis=1)

    def gradient(self, poses: np.ndarray) -> np.ndarray:
        """(m, dof) gradient of the term on y_i (the consensus part of eq. 12): ``Jᵀ r``."""
        r, J = self.linearize(poses)
        grad: np.ndarray = np.einsum("mrd,mr->md", J[:, 0], r)
        return grad
