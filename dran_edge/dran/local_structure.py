"""The local pose graph of L̂_i (eq. 6) for one topology, as the agent's local step solves it.

Variables, in this order: the own poses x_i (private), the own object copies y_i (public), the
neighbours' separators held as anchors and the neighbours' object copies y_j (both fixed).
Factors: f_intra, f_inter, the pose priors and f_obj (:meth:`LocalProblem.factors`) and the
consensus terms ``(β/2)‖w_ij φ(y_i, y_j) + λ_ij/β‖²`` (:func:`consensus_factors`; rebuilt every
round, they carry the duals). A :class:`LocalStructure` and its solver plan stay valid while the
topology (which copies, anchors, pairs and observations) does not change (docs/dran.md).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from dran_edge.config import AgentConfig
from dran_edge.dran.association import BoolArray, NeighbourCopy, PairKey
from dran_edge.dran.consensus import ConsensusFactors, phi_dim
from dran_edge.dran.problem import LocalProblem
from dran_edge.solver.factors import Cauchy, make_kernel
from dran_edge.solver.graph import PoseGraph, kinds_array
from dran_edge.solver.plan import StructurePlan, build_plan
from dran_edge.solver.schur import Factorize, cholesky_factorizer

AnchorKey = tuple[int, int]
"""(owner robot, keyframe id) of a neighbour's separator held as an anchor."""
StructureKey = tuple[tuple[int, ...], tuple[AnchorKey, ...], tuple[PairKey, ...], bytes]
"""(object ids, anchor keys, consensus pairs, bytes of the used-observation mask)."""


@dataclass(frozen=True, eq=False)
class LocalStructure:
    """The local PoseGraph of one topology and its structure plan (rebuilt when it changes)."""

    key: StructureKey
    n_poses: int
    graph: PoseGraph
    """Every factor block but the consensus terms."""
    plan: StructurePlan
    """Of ``graph`` with the consensus terms."""
    obj_ids: tuple[int, ...]
    anchor_keys: tuple[AnchorKey, ...]
    pair_keys: tuple[PairKey, ...]  # (neighbour, object id) for each consensus factor
    #: supernodal Cholesky of A + μI, analysed once for this structure
    factorize: Factorize | None

    @property
    def object_slot(self) -> dict[int, int]:
        """object id -> its variable."""
        return {oid: self.n_poses + i for i, oid in enumerate(self.obj_ids)}

    @property
    def consensus_base(self) -> int:
        """The variable of the first neighbour copy y_j (one per pair, in ``pair_keys`` order)."""
        return self.n_poses + len(self.obj_ids) + len(self.anchor_keys)

    def neighbour_copies(self, copies: Mapping[PairKey, NeighbourCopy]) -> np.ndarray:
        """(c, D, D) the neighbours' copies y_j of the consensus pairs, in pair order."""
        return np.stack([copies[k].T_world_object for k in self.pair_keys])

    def poses(
        self,
        x: np.ndarray,
        y: Mapping[int, np.ndarray],
        anchors: Mapping[AnchorKey, np.ndarray],
        copies: Mapping[PairKey, NeighbourCopy],
    ) -> np.ndarray:
        """The values of every variable, stacked in variable order."""
        parts = [x]
        D = x.shape[-1]
        if self.obj_ids:
            parts.append(np.stack([y[o] for o in self.obj_ids]))
        if self.anchor_keys:
            parts.append(np.stack([anchors[k] for k in self.anchor_keys]))
        if self.pair_keys:
            parts.append(self.neighbour_copies(copies))
        return np.concatenate(parts) if len(parts) > 1 else x.reshape(-1, D, D).copy()


def build_structure(
    problem: LocalProblem,
    config: AgentConfig,
    key: StructureKey,
    obs_ok: BoolArray,
    consensus: Callable[[dict[int, int], int], tuple[ConsensusFactors, ...]],
) -> LocalStructure:
    """The structure of ``key`` (its object ids, anchors and pairs; ``obs_ok``: the own
    observations in use); ``consensus(object_slot, consensus_base)`` gives the consensus
    terms, whose pattern the plan includes."""
    p = problem
    obj_ids, anchor_keys, pair_keys = key[0], key[1], key[2]
    n, n_o, n_a, n_c = p.n, len(obj_ids), len(anchor_keys), len(pair_keys)
    o_base, a_base, c_base = n, n + n_o, n + n_o + n_a
    obj_slot = {oid: o_base + i for i, oid in enumerate(obj_ids)}
    anc_slot = {k: a_base + i for i, k in enumerate(anchor_keys)}
    kinds = kinds_array(
        n + n_o + n_a + n_c, public=np.arange(o_base, a_base), fixed=np.arange(a_base, c_base + n_c)
    )
    c = config
    blocks = p.factors(
        anc_slot,
        obj_slot,
        obs_ok,
        make_kernel(c.robust_kernel, c.robust_threshold),
        make_kernel(c.robust_kernel, c.object_kernel_width),
    )
    graph = PoseGraph(dim=p.dim, kinds=kinds, factors=blocks)
    plan = build_plan(graph.with_factors(*consensus(obj_slot, c_base)))
    return LocalStructure(
        key, n, graph, plan, obj_ids, anchor_keys, pair_keys, cholesky_factorizer(plan)
    )


def consensus_factors(
    config: AgentConfig,
    pair_keys: tuple[PairKey, ...],
    object_slot: Mapping[int, int],
    consensus_base: int,
    lam: Mapping[PairKey, np.ndarray],
    w: Mapping[int, float],
    conflicts: Callable[[tuple[PairKey, ...]], BoolArray],
) -> tuple[ConsensusFactors, ...]:
    """The consensus terms of ``pair_keys`` (duals ``lam``, weights ``w`` per neighbour):
    pair i joins its object's copy y_i to the variable ``consensus_base + i`` holding y_j.

    With a robust kernel configured, a Cauchy kernel bounds the pull of a neighbour's copy
    that stands for another hypothesis: built from a wrong tag association, it lies far
    away and would otherwise drag every copy to it. Its scale puts the half-weight point
    at φ = object_gate_m. Only conflicting pairs get it (``conflicts``); every other
    pair stays least squares (infinite scale), so copies that differ by drift within the
    reaches pull fully (docs/dran.md, robustness)."""
    if not pair_keys:
        return ()
    c = config
    var = np.array([[object_slot[oid], consensus_base + i] for i, (j, oid) in enumerate(pair_keys)])
    r = phi_dim(c.residual, c.dim)
    lam_k = np.stack([lam.get(k, np.zeros(r)) for k in pair_keys])
    w_k = np.array([w[j] for j, _ in pair_keys])
    kernel = None
    if (
        c.robust_kernel != "none"
        and c.object_gate_m > 0
        and (c.conflict_reach_m > 0 or c.centre_reach_m > 0)
    ):
        conflict = conflicts(pair_keys)
        if conflict.any():
            scale = float(np.sqrt(c.beta) * np.mean(w_k) * c.object_gate_m)
            kernel = Cauchy(np.where(conflict, scale, np.inf))
    return (ConsensusFactors(var, w_k, lam_k, c.beta, c.residual, kernel),)
