r"""Tier 3 of the Schur–LM (:mod:`dran_edge.solver.lm`): the damped solve, once per μ trial
(paper Sec. 4, eqs. 7–11).

The tangent of all non-fixed variables is split into private ``u`` (eliminated) and public ``v``.
At a linearisation point with whitened Jacobian ``J`` and residual ``r`` the gradient is
``g = Jᵀr = [g_x; g_y]`` and the LM approximation of the Hessian is (eq. 7)

    M = JᵀJ + μI = [[A, C], [Cᵀ, B]] + μI.

The quadratic model ``m(u, v) = cost + ⟨g, (u, v)⟩ + ½⟨(u, v), M (u, v)⟩`` is minimised by
eliminating ``u`` for fixed ``v``:

    u*(v) = −(A + μI)⁻¹ (C v + g_x)                                    (eq. 8)
    h(v) = m(u*(v), v) = const + ⟨ĝ, v⟩ + ½⟨v, Ĥ v⟩                      (eq. 9)
    ĝ = g_y − Cᵀ (A + μI)⁻¹ g_x                                         (eq. 10)
    Ĥ = (B + μI) − Cᵀ (A + μI)⁻¹ C                                      (eq. 11)
    v = −Ĥ⁻¹ ĝ,   then u = u*(v),   x ← x ⊕ u,  y ← y ⊕ v.

Signs: (u, v) returned by :func:`schur_step` are the model's minimiser ``−M⁻¹ g`` (a descent
step, applied with ``+``). ``A`` is large and sparse: it is factorised once per damping trial
(supernodal multifrontal Cholesky, :mod:`dran_edge.solver.sparse_cholesky`, analysed once per topology;
or SuperLU in symmetric mode) and the factor is reused for the right-hand sides ``[g_x, C]``;
``Ĥ`` is small and dense (Cholesky). With no public variables this is plain sparse LM; with no
private ones it is dense LM on ``v``. With the exact Hessian (``LMParams.hessian='exact'``) the
blocks add the second-order terms of the chordal residual, making the model the exact Hessian
(damped Newton).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from dran_edge.solver.plan import StructurePlan
from dran_edge.solver.sparse_cholesky import (
    NotPositiveDefinite,
    NumericCholesky,
    SymbolicCholesky,
)


@runtime_checkable
class DampedFactor(Protocol):
    """A factorisation of ``A + μI`` (SuperLU's, or the supernodal Cholesky)."""

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``(A + μI)⁻¹ rhs`` for (n,) or (n, r) right-hand sides."""
        ...


@runtime_checkable
class TriangularFactor(DampedFactor, Protocol):
    """``L Lᵀ = P (A + μI) Pᵀ`` with its two triangular solves (the supernodal Cholesky)."""

    def forward(self, rhs: np.ndarray) -> np.ndarray:
        """``L⁻¹ P rhs`` as (n, r)."""
        ...

    def backward(self, y: np.ndarray) -> np.ndarray:
        """``Pᵀ L⁻ᵀ y`` as (n, r)."""
        ...


Factorize = Callable[[sp.csc_matrix, float], DampedFactor]
"""``factorize(A, mu)``: a factor of ``A + μI`` (see :func:`schur_step`)."""


class LinearSolveError(ArithmeticError):
    """A damped system could not be factorised (singular or not positive definite)."""


def superlu_factorize(A_mu: sp.csc_matrix, require_positive_definite: bool = False) -> DampedFactor:
    """Sparse LU of a symmetric positive definite matrix, SuperLU in symmetric mode.

    SuperLU factorises an indefinite matrix without complaint; with ``require_positive_definite``
    the factor's inertia is checked: with diagonal pivots only (``perm_r == perm_c``) the LU is
    a symmetric LDLᵀ with ``D = diag(U)``, so A is positive definite iff every pivot is > 0
    (Sylvester's law of inertia). A failed check raises :class:`LinearSolveError`."""
    try:
        lu = spla.splu(
            A_mu,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
    except RuntimeError as exc:  # SuperLU reports singular factors this way
        raise LinearSolveError(str(exc)) from None
    if require_positive_definite:
        pivots = lu.U.diagonal()
        if not np.array_equal(lu.perm_r, lu.perm_c) or not np.all(pivots > 0.0):
            raise LinearSolveError(
                f"damped matrix is not positive definite ({int(np.sum(~(pivots > 0.0)))} "
                "non-positive pivots)"
            )
    factor: DampedFactor = lu  # scipy's SuperLU (no stubs)
    return factor


def cholesky_factorizer(plan: StructurePlan) -> Factorize | None:
    """A ``factorize(A, mu)`` for :func:`schur_step` using the supernodal Cholesky of
    :mod:`dran_edge.solver.sparse_cholesky`, analysed once for the plan's pattern of A (tier 1).
    ``A`` must be a :class:`Linearization`'s A for this plan. None when there is no private block."""
    if plan.n_u == 0:
        return None
    symbolic = SymbolicCholesky(plan.A_indptr, plan.A_indices, plan.n_u, plan.dof)

    def factorize(A: sp.csc_matrix, mu: float) -> NumericCholesky:
        try:
            return symbolic.factorize(A.data, mu)
        except NotPositiveDefinite as exc:
            raise LinearSolveError(str(exc)) from None

    return factorize


def schur_step(
    A: sp.spmatrix,
    B: np.ndarray,
    C: sp.spmatrix | np.ndarray,
    g_x: np.ndarray,
    g_y: np.ndarray,
    mu: float,
    factorize: Factorize | None = None,
    require_positive_definite: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Tier 3: the minimiser (u, v) = −M⁻¹ g of the damped model (eqs. 8, 10, 11).

    One sparse factorisation of ``A + μI`` serves both right-hand sides ``[g_x, C]``: by
    ``factorize(A, mu)`` when given (an object with ``solve(rhs)``, e.g. from
    :func:`cholesky_factorizer`, which always checks definiteness), else SuperLU. Raises
    :class:`LinearSolveError` when a factorisation fails, and with ``require_positive_definite``
    also when the SuperLU factor of ``A + μI`` shows it is not positive definite (``Ĥ`` is always
    checked by its Cholesky): a model that is not convex has no minimiser, and its "step" is a
    saddle point (the exact Hessian far from the optimum).
    """
    n_u, n_v = g_x.shape[0], g_y.shape[0]
    if n_u == 0:
        Ainv_g = np.zeros(0)
        Ainv_C = np.zeros((0, n_v))
    else:
        if factorize is not None:
            lu = factorize(A, mu)
        else:
            lu = superlu_factorize(
                sp.csc_matrix(A + mu * sp.identity(n_u, format="csc")), require_positive_definite
            )
        C_dense = _dense(C)
        if n_v and isinstance(lu, TriangularFactor):
            # Cholesky: with Y = L⁻¹P[g_x, C], CᵀA⁻¹C = Y_Cᵀ Y_C and CᵀA⁻¹g_x = Y_Cᵀ y_g, and
            # u needs one back substitution of y_g + Y_C v (half the solves of A⁻¹[g_x, C])
            Y = lu.forward(np.column_stack([g_x, C_dense]))
            y_g, Y_C = Y[:, 0], Y[:, 1:]
            H_hat = B + mu * np.eye(n_v) - Y_C.T @ Y_C  # eq. 11
            g_hat = g_y - Y_C.T @ y_g  # eq. 10
            v = _reduced_step(H_hat, g_hat)
            u = -lu.backward(y_g + Y_C @ v)[:, 0]  # eq. 8
            return u, v
        X = lu.solve(np.column_stack([g_x, C_dense]) if n_v else g_x[:, None])
        Ainv_g, Ainv_C = X[:, 0], X[:, 1:]
    if n_v == 0:
        return -Ainv_g, np.zeros(0)
    C_dense = _dense(C)
    H_hat = B + mu * np.eye(n_v) - C_dense.T @ Ainv_C  # eq. 11
    g_hat = g_y - C_dense.T @ Ainv_g  # eq. 10
    v = _reduced_step(H_hat, g_hat)
    u = -(Ainv_g + Ainv_C @ v)  # eq. 8
    return u, v


def _reduced_step(H_hat: np.ndarray, g_hat: np.ndarray) -> np.ndarray:
    """v = −Ĥ⁻¹ ĝ, the minimiser of the reduced model h (eq. 9), by a dense Cholesky of Ĥ."""
    try:
        v: np.ndarray = -scipy.linalg.cho_solve(scipy.linalg.cho_factor(H_hat), g_hat)
        return v
    except np.linalg.LinAlgError as exc:
        raise LinearSolveError(f"reduced Hessian is not positive definite: {exc}") from None


def _dense(C: Any) -> np.ndarray:
    """``C`` (scipy sparse, which has no type stubs, or an array) as a dense array."""
    dense: np.ndarray = C.toarray() if sp.issparse(C) else np.asarray(C)
    return dense
