r"""Levenberg–Marquardt with the Schur complement of the paper (Sec. 4, eqs. 7–11).

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
private ones it is dense LM on ``v``. Optionally (``LMParams.hessian='exact'``) the blocks add the
second-order terms of the chordal residual, making the model the exact Hessian (damped Newton).

Three tiers, each a pure function: :func:`build_plan` (index maps and sparsity pattern, once per
topology), :func:`linearize` (residuals, Jacobians, ``A, B, C, g_x, g_y``, once per iteration) and
:func:`schur_step` (the damped solve, once per μ trial). :func:`solve` runs the LM loop with
Nielsen's damping update; a rejected trial never counts toward convergence.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from dran_edge import geometry as geo
from dran_edge.solver.factors import Factor, factor_cost
from dran_edge.solver.graph import PoseGraph, VariableKind
from dran_edge.solver.sparse_cholesky import NotPositiveDefinite, SymbolicCholesky

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- tier 1: structure


@dataclass(frozen=True, eq=False)
class StructurePlan:
    """Index maps and sparsity patterns of one graph topology (see :func:`build_plan`)."""

    dof: int
    private_vars: np.ndarray
    """(p,) graph indices of private variables, in the order of ``u`` (dof entries each)."""
    public_vars: np.ndarray
    """(q,) graph indices of public variables, in the order of ``v``."""
    A_indices: np.ndarray
    A_indptr: np.ndarray
    A_diag: np.ndarray
    """Positions of A's diagonal in its CSC data array."""
    A_src: np.ndarray
    A_tgt: np.ndarray
    C_indices: np.ndarray
    C_indptr: np.ndarray
    C_src: np.ndarray
    C_tgt: np.ndarray
    B_src: np.ndarray
    B_tgt: np.ndarray
    """Targets in the flattened dense (n_v, n_v) B."""
    gx_src: np.ndarray
    gx_tgt: np.ndarray
    gy_src: np.ndarray
    gy_tgt: np.ndarray
    H_offsets: tuple[int, ...]
    """Start of each factor block's (m, k·dof, k·dof) Hessian blocks in the concatenated array."""
    g_offsets: tuple[int, ...]

    @property
    def n_u(self) -> int:
        return int(self.private_vars.shape[0]) * self.dof

    @property
    def n_v(self) -> int:
        return int(self.public_vars.shape[0]) * self.dof


def _block_csc_plan(brow, bcol, base, stride, nbr: int, nbc: int, dof: int, with_diag: bool):
    """Scatter plan of dense dof×dof blocks into one CSC matrix (nbr·dof × nbc·dof).

    Block i sits at block (brow[i], bcol[i]) and its element (r, c) is read at
    ``base[i] + r·stride[i] + c`` of the concatenated Hessian blocks. The pattern is unique at
    block level (every stored block is dense); ``with_diag`` adds all diagonal blocks so that a
    damping μI has somewhere to go. Returns indices, indptr, src, tgt and the data positions of
    the diagonal (empty without ``with_diag``)."""
    keys = bcol.astype(np.int64) * nbr + brow
    if with_diag:
        keys = np.concatenate([keys, np.arange(nbr, dtype=np.int64) * (nbr + 1)])
    uniq, inv = np.unique(keys, return_inverse=True)
    ub_row, ub_col = uniq % max(nbr, 1), uniq // max(nbr, 1)
    col_start = np.searchsorted(ub_col, np.arange(nbc + 1))
    blocks_per_col = np.diff(col_start)
    rank = np.arange(uniq.size) - col_start[ub_col]
    # scalar column j = bc·dof + c holds dof entries per block of block column bc
    indptr = np.concatenate([[0], np.cumsum(np.repeat(blocks_per_col * dof, dof))]).astype(np.int32)
    ar = np.arange(dof)
    # the scalar rows of column (bc, c): all blocks of bc in order, dof rows each (same for all c)
    col_rows = (ub_row[:, None] * dof + ar).ravel()  # per block, its dof rows
    indices = (
        np.concatenate(
            [
                col_rows[col_start[bc] * dof : col_start[bc + 1] * dof]
                for bc in range(nbc)
                for _ in range(dof)
            ]
        )
        if uniq.size
        else np.zeros(0)
    )
    indices = indices.astype(np.int32)
    r, c = np.divmod(np.arange(dof * dof), dof)
    n_src = brow.shape[0]
    blk = inv[:n_src]
    src = (base[:, None] + r[None] * stride[:, None] + c[None]).ravel()
    tgt = (
        indptr[(ub_col[blk] * dof)[:, None] + c[None]] + (rank[blk] * dof)[:, None] + r[None]
    ).ravel()
    diag = np.zeros(0, dtype=np.int64)
    if with_diag:
        d = inv[n_src:]
        diag = (indptr[(ub_col[d] * dof)[:, None] + ar] + (rank[d] * dof)[:, None] + ar).ravel()
    return indices, indptr, src, tgt.astype(np.int64), diag


def build_plan(graph: PoseGraph) -> StructurePlan:
    """Tier 1: variable ordering (private first, then public) and the scatter plans that turn the
    per-factor blocks ``JᵀJ`` and ``Jᵀr`` into ``A`` (sparse), ``C`` (sparse), ``B`` (dense),
    ``g_x`` and ``g_y``. Depends only on the topology."""
    dof = graph.dof
    kinds = graph.kinds
    private_vars = np.flatnonzero(kinds == VariableKind.PRIVATE)
    public_vars = np.flatnonzero(kinds == VariableKind.PUBLIC)
    slot = np.full(graph.num_variables, -1, dtype=np.int64)
    slot[private_vars] = np.arange(private_vars.shape[0])
    slot[public_vars] = np.arange(public_vars.shape[0])

    rr, cc = np.divmod(np.arange(dof * dof), dof)
    ar = np.arange(dof)
    parts: dict[str, list[np.ndarray]] = {
        key: []
        for key in (
            "A_r",
            "A_c",
            "A_s",
            "A_k",
            "C_r",
            "C_c",
            "C_s",
            "C_k",
            "B_r",
            "B_c",
            "B_s",
            "gx_t",
            "gx_s",
            "gy_t",
            "gy_s",
        )
    }
    H_offsets, g_offsets = [], []
    H_off = g_off = 0
    for block in graph.factors:
        var = np.asarray(block.variables, dtype=np.int64)
        m, k = var.shape
        kd = k * dof
        H_offsets.append(H_off)
        g_offsets.append(g_off)
        kind = kinds[var]
        sl = slot[var]
        fi = np.arange(m, dtype=np.int64)
        for a in range(k):
            g_src = g_off + (fi * kd + a * dof)[:, None] + ar[None]
            g_tgt = sl[:, a, None] * dof + ar[None]
            for name, want in (("gx", VariableKind.PRIVATE), ("gy", VariableKind.PUBLIC)):
                sel = kind[:, a] == want
                parts[name + "_t"].append(g_tgt[sel].ravel())
                parts[name + "_s"].append(g_src[sel].ravel())
            for b in range(k):
                # element (f, a·dof+i, b·dof+j) of the (m, kd, kd) block array
                base = H_off + fi * kd * kd + a * dof * kd + b * dof
                for name, ka, kb in (
                    ("A", VariableKind.PRIVATE, VariableKind.PRIVATE),
                    ("C", VariableKind.PRIVATE, VariableKind.PUBLIC),
                ):
                    sel = (kind[:, a] == ka) & (kind[:, b] == kb)
                    parts[name + "_r"].append(sl[sel, a])
                    parts[name + "_c"].append(sl[sel, b])
                    parts[name + "_s"].append(base[sel])
                    parts[name + "_k"].append(np.full(int(sel.sum()), kd, dtype=np.int64))
                sel = (kind[:, a] == VariableKind.PUBLIC) & (kind[:, b] == VariableKind.PUBLIC)
                parts["B_r"].append((sl[sel, a, None] * dof + rr[None]).ravel())
                parts["B_c"].append((sl[sel, b, None] * dof + cc[None]).ravel())
                parts["B_s"].append((base[sel, None] + (rr * kd + cc)[None]).ravel())
        H_off += m * kd * kd
        g_off += m * kd

    cat = {
        key: (np.concatenate(val) if val else np.zeros(0, np.int64)) for key, val in parts.items()
    }
    n_pu, n_pv = private_vars.shape[0], public_vars.shape[0]
    A_indices, A_indptr, A_src, A_tgt, A_diag = _block_csc_plan(
        cat["A_r"], cat["A_c"], cat["A_s"], cat["A_k"], n_pu, n_pu, dof, True
    )
    C_indices, C_indptr, C_src, C_tgt, _ = _block_csc_plan(
        cat["C_r"], cat["C_c"], cat["C_s"], cat["C_k"], n_pu, n_pv, dof, False
    )
    return StructurePlan(
        dof=dof,
        private_vars=private_vars,
        public_vars=public_vars,
        A_indices=A_indices,
        A_indptr=A_indptr,
        A_diag=A_diag,
        A_src=A_src,
        A_tgt=A_tgt,
        C_indices=C_indices,
        C_indptr=C_indptr,
        C_src=C_src,
        C_tgt=C_tgt,
        B_src=cat["B_s"],
        B_tgt=cat["B_r"] * public_vars.shape[0] * dof + cat["B_c"],
        gx_src=cat["gx_s"],
        gx_tgt=cat["gx_t"],
        gy_src=cat["gy_s"],
        gy_tgt=cat["gy_t"],
        H_offsets=tuple(H_offsets),
        g_offsets=tuple(g_offsets),
    )


# ----------------------------------------------------------------------------- tier 2: linearisation


@dataclass(frozen=True, eq=False)
class Linearization:
    """The undamped normal equations at one point: JᵀJ = [[A, C], [Cᵀ, B]], Jᵀr = [g_x; g_y]."""

    A: sp.csc_matrix
    B: np.ndarray
    C: sp.csc_matrix
    g_x: np.ndarray
    g_y: np.ndarray
    cost: float
    """Σ ½ ρ(‖W r‖²) at the linearisation point."""


def block_normal_equations(
    block: Factor, poses: np.ndarray, exact_hessian: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """(JᵀJ blocks (m, kd, kd), Jᵀr (m, kd), cost) of one factor block, with IRLS weights; with
    ``exact_hessian`` plus the block's ``second_order`` terms where it has them."""
    r, J = block.linearize(poses)
    m, k, rdim, dof = J.shape
    s = np.sum(r * r, axis=1)
    Jt = np.ascontiguousarray(np.transpose(J, (0, 1, 3, 2))).reshape(m, k * dof, rdim)
    kernel = block.kernel
    if kernel is None:
        cost = 0.5 * float(np.sum(s))
        H = Jt @ np.swapaxes(Jt, 1, 2)
        g = (Jt @ r[:, :, None])[:, :, 0]
    else:
        cost = 0.5 * float(np.sum(kernel.rho(s)))
        w = kernel.weight(s)
        H = (Jt * w[:, None, None]) @ np.swapaxes(Jt, 1, 2)
        g = (Jt @ (w[:, None] * r)[:, :, None])[:, :, 0]
    if exact_hessian and hasattr(block, "second_order"):
        H2 = block.second_order(poses)
        if H2 is not None:
            H = H + (H2 if kernel is None else kernel.weight(s)[:, None, None] * H2)
    return H, g, cost


def linearize(
    graph: PoseGraph, plan: StructurePlan, poses: np.ndarray, exact_hessian: bool = False
) -> Linearization:
    """Tier 2: residuals and Jacobians of every block, scattered into A, B, C, g_x, g_y (eq. 7).

    ``exact_hessian`` adds the second-order residual terms of the blocks that provide them
    (chordal residual): [[A, C], [Cᵀ, B]] is then the Hessian of the pullback, not JᵀJ, and LM
    becomes a damped Newton method (quadratic instead of linear convergence for the chordal cost).
    """
    Hs, gs, cost = [], [], 0.0
    for block in graph.factors:
        H, g, c = block_normal_equations(block, poses, exact_hessian)
        Hs.append(H.ravel())
        gs.append(g.ravel())
        cost += c
    H_all = np.concatenate(Hs) if Hs else np.zeros(0)
    g_all = np.concatenate(gs) if gs else np.zeros(0)
    n_u, n_v = plan.n_u, plan.n_v
    A_data = np.bincount(plan.A_tgt, weights=H_all[plan.A_src], minlength=plan.A_indices.shape[0])
    C_data = np.bincount(plan.C_tgt, weights=H_all[plan.C_src], minlength=plan.C_indices.shape[0])
    B = np.bincount(plan.B_tgt, weights=H_all[plan.B_src], minlength=n_v * n_v).reshape(n_v, n_v)
    return Linearization(
        A=sp.csc_matrix((A_data, plan.A_indices, plan.A_indptr), shape=(n_u, n_u)),
        B=B,
        C=sp.csc_matrix((C_data, plan.C_indices, plan.C_indptr), shape=(n_u, n_v)),
        g_x=np.bincount(plan.gx_tgt, weights=g_all[plan.gx_src], minlength=n_u),
        g_y=np.bincount(plan.gy_tgt, weights=g_all[plan.gy_src], minlength=n_v),
        cost=cost,
    )


def evaluate_cost(graph: PoseGraph, poses: np.ndarray) -> float:
    """Σ over blocks of Σ ½ ρ(‖W r‖²) at ``poses``."""
    return float(sum(factor_cost(block, poses) for block in graph.factors))


def retract(plan: StructurePlan, poses: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """New poses: private ``x ⊕ u``, public ``y ⊕ v``, fixed unchanged (stacked tangents)."""
    out = poses.copy()
    dof = plan.dof
    if plan.private_vars.size:
        out[plan.private_vars] = geo.retract(poses[plan.private_vars], u.reshape(-1, dof))
    if plan.public_vars.size:
        out[plan.public_vars] = geo.retract(poses[plan.public_vars], v.reshape(-1, dof))
    return out


# ----------------------------------------------------------------------------- tier 3: damped solve


class LinearSolveError(ArithmeticError):
    """A damped system could not be factorised (singular or not positive definite)."""


def _factorize(A_mu: sp.csc_matrix, require_positive_definite: bool = False):
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
    return lu


def cholesky_factorizer(plan: StructurePlan) -> Callable[[sp.csc_matrix, float], object] | None:
    """A ``factorize(A, mu)`` for :func:`schur_step` using the supernodal Cholesky of
    :mod:`dran_edge.solver.sparse_cholesky`, analysed once for the plan's pattern of A (tier 1).
    ``A`` must be a :class:`Linearization`'s A for this plan. None when there is no private block."""
    if plan.n_u == 0:
        return None
    symbolic = SymbolicCholesky(plan.A_indptr, plan.A_indices, plan.n_u, plan.dof)

    def factorize(A: sp.csc_matrix, mu: float):
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
    factorize: Callable[[sp.csc_matrix, float], object] | None = None,
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
            lu = _factorize(
                sp.csc_matrix(A + mu * sp.identity(n_u, format="csc")), require_positive_definite
            )
        C_dense = C.toarray() if sp.issparse(C) else np.asarray(C)
        if n_v and hasattr(lu, "forward"):
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
    C_dense = C.toarray() if sp.issparse(C) else np.asarray(C)
    H_hat = B + mu * np.eye(n_v) - C_dense.T @ Ainv_C  # eq. 11
    g_hat = g_y - C_dense.T @ Ainv_g  # eq. 10
    v = _reduced_step(H_hat, g_hat)
    u = -(Ainv_g + Ainv_C @ v)  # eq. 8
    return u, v


def _reduced_step(H_hat: np.ndarray, g_hat: np.ndarray) -> np.ndarray:
    """v = −Ĥ⁻¹ ĝ, the minimiser of the reduced model h (eq. 9), by a dense Cholesky of Ĥ."""
    try:
        return -scipy.linalg.cho_solve(scipy.linalg.cho_factor(H_hat), g_hat)
    except np.linalg.LinAlgError as exc:
        raise LinearSolveError(f"reduced Hessian is not positive definite: {exc}") from None


# ----------------------------------------------------------------------------- the LM loop


AUTO_CHOLESKY_MIN_POSES = 1000
"""linear_solver='auto' uses the supernodal Cholesky from this many private SE(3) poses on."""


class LMStatus(str, Enum):
    CONVERGED = "converged"
    MAX_ITERATIONS = "max_iterations"
    LINEAR_SOLVE_FAILED = "linear_solve_failed"
    NON_FINITE = "non_finite"
    STALLED = "stalled"
    """No damping up to ``mu_max`` decreased the cost, yet the model predicted a decrease above
    ``cost_tol``: the Jacobian disagrees with the cost (a bug or an extreme kernel)."""


@dataclass(frozen=True)
class LMParams:
    """Levenberg–Marquardt parameters. Costs are Σ ½ρ(‖W r‖²)."""

    max_iterations: int = 100
    """Cap on accepted steps (linearisations)."""
    max_trials: int = 30
    """Cap on damped solves per iteration before giving up."""
    mu_init: float = 1e-12
    """Initial μ relative to the largest diagonal entry of JᵀJ: near-Gauss–Newton first steps
    (rejected steps raise μ). On the six benchmark graphs 1e-12 needs 3–6 iterations from the
    chordal initialisation where 1e-8 needed up to 13, and no more from odometry/file values."""
    mu_min: float = 1e-20
    """Absolute lower bound of μ."""
    cost_tol: float = 1e-10
    """Converged when an accepted step's (cost_old − cost_new) / cost_old < cost_tol, or when no
    step is accepted and the model predicted less than that."""
    step_tol: float = 1e-10
    """Converged when an accepted step's ‖(u, v)‖₂ < step_tol (metres/radians mixed)."""
    gradient_tol: float = 0.0
    """Converged when ‖g‖_∞ ≤ gradient_tol at a linearisation point (whitened units)."""
    hessian: str = "gauss_newton"
    """'gauss_newton' (M = JᵀJ + μI, the paper's LM) or 'exact' (adds the chordal residual's
    second-order terms — damped Newton). The exact model keeps its own damping μ_N, separate
    from the Gauss–Newton μ: in an iteration where ``A + μ_N I`` or ``Ĥ`` is not positive
    definite, or the Newton step does not lower the cost (then μ_N grows, Nielsen), the iteration
    continues with the Gauss–Newton model at its own μ. (With one shared μ, Gauss–Newton
    steps kept shrinking μ while the Newton model, indefinite or overshooting at that μ, failed
    every iteration: linear convergence at two solves per iteration. See
    docs/notes/solve-and-bounded-graph.md.)"""
    newton_damping: str = "separate"
    """'separate' (the μ_N above, with the definiteness check) or 'shared' (one μ for both models
    and no definiteness check on SuperLU factors: the policy before, kept for benchmarks)."""
    linear_solver: str = "superlu"
    """Factorisation of A + μI: 'superlu', 'cholesky' (supernodal, dran_edge.solver.sparse_cholesky) or
    'auto' (cholesky for SE(3) graphs with ≥ AUTO_CHOLESKY_MIN_POSES private poses, else superlu;
    from tools/bench/bench_cholesky.py: 2–7× faster factorisations on the 3D benchmark graphs,
    no gain on the small 2D ones once its analysis is paid). The Cholesky makes many small BLAS
    calls, which a multi-threaded OpenBLAS on an oversubscribed machine slows down badly: shells
    that use it set OPENBLAS_NUM_THREADS=1 before numpy loads."""


@dataclass(frozen=True, eq=False)
class LMResult:
    status: LMStatus
    poses: np.ndarray
    """Best iterate (lowest cost seen); (n, D, D)."""
    cost: float
    """Cost at ``poses``."""
    iterations: int
    """Accepted steps."""
    trials: int
    """Damped solves, accepted or not."""
    cost_history: tuple[float, ...]
    """Cost at the start and after every accepted step."""
    reason: str
    """One line on why the loop stopped."""


NEWTON_MU_DECREASE = 0.1
"""Smallest factor by which an accepted Newton step lowers μ_N (Nielsen's rule uses 1/3): the
Newton model converges quadratically once it is convex, so a μ_N raised while it was not (far
from the optimum) must fall back quickly; with 1/3 parking-garage needed one iteration more than
with the shared μ."""


class _Damping:
    """Nielsen's damping update, one μ (and ν) per model: Gauss–Newton and Newton (exact)."""

    def __init__(self, mu_min: float, shared: bool = False):
        self.mu_min = mu_min
        self.shared = shared
        """One μ for both models; a failed Newton trial leaves it to the Gauss–Newton one."""
        self.mu_gn: float | None = None
        self.mu_newton = 0.0
        self.nu = {False: 2.0, True: 2.0}

    def start(self, mu0: float) -> None:
        self.mu_gn = self.mu_newton = mu0

    def mu(self, exact: bool) -> float:
        return self.mu_newton if exact and not self.shared else self.mu_gn

    def _set(self, exact: bool, mu: float) -> None:
        if exact and not self.shared:
            self.mu_newton = mu
        else:
            self.mu_gn = mu

    def accept(self, exact: bool, rho: float) -> None:
        """A step lowered the cost; ρ = actual / predicted decrease."""
        floor = NEWTON_MU_DECREASE if exact and not self.shared else 1.0 / 3.0
        factor = max(floor, 1.0 - (2.0 * rho - 1.0) ** 3)
        self._set(exact, max(self.mu(exact) * factor, self.mu_min))
        self.nu[exact] = 2.0

    def reject(self, exact: bool) -> None:
        """A step failed (no decrease, or the damped model could not be factorised)."""
        if exact and self.shared:
            return  # the old policy: Gauss–Newton retries at the same μ
        self._set(exact, self.mu(exact) * self.nu[exact])
        self.nu[exact] *= 2.0


def solve(
    graph: PoseGraph,
    poses: np.ndarray,
    params: LMParams = LMParams(),
    plan: StructurePlan | None = None,
    callback: Callable[[int, float, float], None] | None = None,
) -> LMResult:
    """Minimise the graph's cost from ``poses`` by Schur–LM; never raises on numerical trouble.

    ``callback(iteration, cost, mu)`` is called after every accepted step (progress reports).
    """
    plan = build_plan(graph) if plan is None else plan
    if params.linear_solver not in ("cholesky", "superlu", "auto"):
        raise ValueError(
            f"linear_solver must be 'cholesky', 'superlu' or 'auto', got {params.linear_solver!r}"
        )
    use_cholesky = params.linear_solver == "cholesky" or (
        params.linear_solver == "auto"
        and plan.dof == 6
        and plan.private_vars.shape[0] >= AUTO_CHOLESKY_MIN_POSES
    )
    if params.hessian not in ("gauss_newton", "exact"):
        raise ValueError(f"hessian must be 'gauss_newton' or 'exact', got {params.hessian!r}")
    if params.newton_damping not in ("separate", "shared"):
        raise ValueError(
            f"newton_damping must be 'separate' or 'shared', got {params.newton_damping!r}"
        )
    shared = params.newton_damping == "shared"
    factorize = cholesky_factorizer(plan) if use_cholesky else None
    poses = np.asarray(poses, dtype=np.float64)
    cost = evaluate_cost(graph, poses)
    history = [cost]
    trials = 0

    def stop(status: LMStatus, iterations: int, reason: str) -> LMResult:
        """The result at the current (best) iterate."""
        return LMResult(status, poses, cost, iterations, trials, tuple(history), reason)

    if not math.isfinite(cost):
        return stop(LMStatus.NON_FINITE, 0, "cost at the initial values is not finite")
    damping = _Damping(params.mu_min, shared)
    for iteration in range(params.max_iterations):
        # The first iteration uses Gauss–Newton even in 'exact' mode: far from a minimum the
        # Gauss–Newton model of the chordal cost predicts better (sphere2500 from the chordal
        # initialisation: F 1687.86 after a Gauss–Newton step, 1707.8 after an exact one).
        exact = params.hessian == "exact" and iteration > 0
        lin = linearize(graph, plan, poses, exact)
        g = np.concatenate([lin.g_x, lin.g_y])
        if not np.all(np.isfinite(g)) or not np.all(np.isfinite(lin.A.data)):
            return stop(LMStatus.NON_FINITE, iteration, "non-finite gradient or Hessian")
        if g.size == 0 or np.max(np.abs(g)) <= params.gradient_tol:
            return stop(LMStatus.CONVERGED, iteration, "gradient below gradient_tol")
        if damping.mu_gn is None:
            diag = np.concatenate([lin.A.diagonal(), np.diag(lin.B)])
            damping.start(max(params.mu_init * float(np.max(diag)), params.mu_min))
        accepted = False
        solved_any = False
        pred = math.inf
        for _ in range(params.max_trials):
            trials += 1
            mu = damping.mu(exact)
            try:
                u, v = schur_step(
                    lin.A, lin.B, lin.C, lin.g_x, lin.g_y, mu, factorize, exact and not shared
                )
            except LinearSolveError as exc:
                log.debug("damped solve failed at mu=%g: %s", mu, exc)
                if exact:
                    # Not convex at μ_N: a property of this point, not of the step length, so
                    # μ_N stays (raising it here cost parking-garage an iteration); the
                    # Gauss–Newton model, convex by construction, takes this iteration.
                    lin, exact = linearize(graph, plan, poses, False), False
                else:
                    damping.reject(False)
                continue
            solved_any = True
            step = np.concatenate([u, v])
            pred = 0.5 * float(mu * step @ step - g @ step)  # model decrease, from M step = −g
            new_poses = retract(plan, poses, u, v)
            new_cost = evaluate_cost(graph, new_poses)
            actual = cost - new_cost
            log.debug(
                "iteration %d %s mu=%.3g predicted %.6g actual %.6g",
                iteration, "newton" if exact else "gauss-newton", mu, pred, actual,
            )
            if math.isfinite(new_cost) and actual > 0.0:
                damping.accept(exact, actual / pred if pred > 0 else 0.0)
                accepted = True
                break
            damping.reject(exact)
            if exact:  # the Newton step failed: Gauss–Newton for this iteration
                lin, exact = linearize(graph, plan, poses, False), False
        if not accepted:
            if not solved_any:
                return stop(
                    LMStatus.LINEAR_SOLVE_FAILED,
                    iteration,
                    "every damped system failed to factorise",
                )
            if pred <= params.cost_tol * cost:
                return stop(
                    LMStatus.CONVERGED,
                    iteration,
                    "no decreasing step; predicted decrease below cost_tol",
                )
            return stop(
                LMStatus.STALLED,
                iteration,
                f"no decreasing step after {params.max_trials} damping trials",
            )
        rel = actual / cost
        poses, cost = new_poses, new_cost
        history.append(cost)
        if callback is not None:
            callback(iteration + 1, cost, damping.mu(exact))
        if rel < params.cost_tol:
            return stop(LMStatus.CONVERGED, iteration + 1, "relative cost decrease below cost_tol")
        if float(np.linalg.norm(step)) < params.step_tol:
            return stop(LMStatus.CONVERGED, iteration + 1, "step norm below step_tol")
    return stop(LMStatus.MAX_ITERATIONS, params.max_iterations, "reached max_iterations")
