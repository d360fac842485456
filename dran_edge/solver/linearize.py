"""Tier 2 of the Schur–LM (:mod:`dran_edge.solver.lm`): residuals and Jacobians of every factor
block scattered into the undamped normal equations ``[[A, C], [Cᵀ, B]]``, ``[g_x; g_y]`` of
paper eq. 7, once per iteration; the cost and the retraction ``x ⊕ u``, ``y ⊕ v``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from dran_edge import geometry as geo
from dran_edge.solver.factors import Factor, factor_cost
from dran_edge.solver.graph import PoseGraph
from dran_edge.solver.plan import StructurePlan


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
    out: np.ndarray = poses.copy()
    dof = plan.dof
    if plan.private_vars.size:
        out[plan.private_vars] = geo.retract(poses[plan.private_vars], u.reshape(-1, dof))
    if plan.public_vars.size:
        out[plan.public_vars] = geo.retract(poses[plan.public_vars], v.reshape(-1, dof))
    return out
