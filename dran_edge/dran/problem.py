"""One robot's local problem (the measurements behind L̂_i, eq. 6) and its factor blocks.

:class:`LocalProblem` is the interface between graph sources and the DRAN agent
(docs/dran.md): built from a prebuilt partition (``LocalProblem.from_partition``; bench g2o,
simulations) or by the online core from the bounded keyframe graph. :meth:`LocalProblem.factors`
turns it into the factor blocks f_intra, f_inter, the pose priors and f_obj of the agent's local
pose graph (the consensus terms are the agent's: they carry its duals).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from dran_edge.config import Residual
from dran_edge.dran.partition import Partition
from dran_edge.solver.factors import (
    BetweenFactors,
    Factor,
    Kernel,
    PriorFactors,
    isotropic_whitening,
)

IntArray = npt.NDArray[np.int64]


class EdgeGraph(Protocol):
    """What :meth:`LocalProblem.from_partition` reads of a pose graph (e.g. a ``G2oGraph``)."""

    @property
    def dim(self) -> int: ...
    @property
    def num_vertices(self) -> int: ...
    @property
    def edges(self) -> np.ndarray: ...
    @property
    def measurements(self) -> np.ndarray: ...


@dataclass(frozen=True, eq=False)
class LocalProblem:
    """Robot i's measurements, in its own terms (the interface between graph sources and the agent).

    Poses are ``T_world_body`` in the fleet's common frame; indices ``own`` are positions into
    ``pose_ids``. Whitening ``W`` has ``WᵀW = Ω`` in the coordinates of ``residual`` (diagonal
    ``(m, r)`` or full ``(m, r, r)``).
    """

    dim: int
    residual: str
    """'geodesic' or 'chordal' (eq. 2) for every factor of this problem."""
    pose_ids: np.ndarray
    """(n,) int64 keyframe ids of the own poses (x_i); unique."""
    pose_stamps_ns: np.ndarray
    """(n,) int64 keyframe stamps."""
    x0: np.ndarray
    """(n, D, D) initial T_world_body."""
    between: np.ndarray
    """(m, 2) own indices (p, q) of odometry / intra-robot loop factors (f_intra)."""
    between_T: np.ndarray
    between_W: np.ndarray
    between_robust: np.ndarray
    """(m,) bool: apply the robust kernel (loops yes, odometry no)."""
    inter_own: np.ndarray
    """(k,) own index of each inter-robot factor (f_inter)."""
    inter_owner: np.ndarray
    """(k,) robot owning the other end (the anchor)."""
    inter_anchor_id: np.ndarray
    """(k,) keyframe id of the anchor in its owner's trajectory."""
    inter_own_is_p: np.ndarray
    """(k,) bool: the measurement is T̃ = T_own⁻¹ T_anchor (else T_anchor⁻¹ T_own)."""
    inter_T: np.ndarray
    inter_W: np.ndarray
    inter_robust: np.ndarray
    prior_own: np.ndarray
    """(p,) own indices with a pose prior (known start pose, gauge)."""
    prior_T: np.ndarray
    prior_W: np.ndarray
    obs_own: np.ndarray
    """(o,) own index of the observing keyframe of each object observation (f_obj)."""
    obs_object: np.ndarray
    """(o,) object id."""
    obs_T: np.ndarray
    """(o, D, D) T_body_object measured."""
    obs_W: np.ndarray
    separators_for: dict[int, IntArray] = field(default_factory=dict)
    """neighbour id -> (s,) own indices it needs as anchors."""
    prior_robust: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    """(p,) bool: apply the robust kernel to that prior (a loop into the robot's archive of
    past keyframes, dran_edge/robot/archive.py); empty: none."""

    @property
    def n(self) -> int:
        return int(self.pose_ids.shape[0])

    def to_dict(self) -> dict[str, Any]:
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "separators_for"}
        out["separators_for"] = {int(k): np.asarray(v) for k, v in self.separators_for.items()}
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LocalProblem:
        kw = dict(data)
        kw["separators_for"] = {
            int(k): np.asarray(v, np.int64) for k, v in data["separators_for"].items()
        }
        return cls(**kw)

    @classmethod
    def empty(cls, dim: int, residual: str) -> LocalProblem:
        D, r = dim + 1, (6 if dim == 3 else 3) if residual == Residual.GEODESIC else dim * dim + dim
        z = np.zeros(0, np.int64)
        T, W = np.zeros((0, D, D)), np.zeros((0, r))
        return cls(
            dim,
            residual,
            z,
            z,
            T,
            np.zeros((0, 2), np.int64),
            T,
            W,
            np.zeros(0, bool),
            z,
            z,
            z,
            np.zeros(0, bool),
            T,
            W,
            np.zeros(0, bool),
            z,
            T,
            W,
            z,
            z,
            T,
            W,
            {},
        )

    @classmethod
    def from_partition(
        cls,
        graph: EdgeGraph,
        partition: Partition,
        robot: int,
        x0: np.ndarray,
        kappa: np.ndarray,
        tau: np.ndarray,
        residual: str = "chordal",
    ) -> LocalProblem:
        """Robot ``robot``'s problem from a partitioned g2o graph (Table 1, object-free mode);
        keyframe ids are vertex positions; SE-Sync isotropic weights (κ, τ)."""
        part = partition.parts[robot]
        dim = graph.dim
        W = isotropic_whitening(kappa, tau, residual, dim)
        local = np.full(graph.num_vertices, -1, np.int64)
        local[part.vertices] = np.arange(part.vertices.size)
        e_in = graph.edges[part.intra_edges]
        e_x = graph.edges[part.inter_edges]
        own_is_p = partition.owner[e_x[:, 0]] == robot
        own_end = np.where(own_is_p, e_x[:, 0], e_x[:, 1])
        other = np.where(own_is_p, e_x[:, 1], e_x[:, 0])
        z = np.zeros(0, np.int64)
        D = dim + 1
        gauge = 0 if robot == int(partition.owner[0]) else None
        prior_own = np.array([local[0]], np.int64) if gauge is not None else z
        prior_T = x0[prior_own] if gauge is not None else np.zeros((0, D, D))
        prior_W = np.full((prior_own.size, W.shape[1]), 1e4 * float(np.sqrt(np.max(kappa))))
        return cls(
            dim=dim,
            residual=residual,
            pose_ids=part.vertices.astype(np.int64),
            pose_stamps_ns=part.vertices.astype(np.int64),
            x0=x0[part.vertices].copy(),
            between=local[e_in],
            between_T=graph.measurements[part.intra_edges],
            between_W=W[part.intra_edges],
            between_robust=np.zeros(e_in.shape[0], bool),
            inter_own=local[own_end],
            inter_owner=partition.owner[other].astype(np.int64),
            inter_anchor_id=other.astype(np.int64),
            inter_own_is_p=own_is_p,
            inter_T=graph.measurements[part.inter_edges],
            inter_W=W[part.inter_edges],
            inter_robust=np.zeros(e_x.shape[0], bool),
            prior_own=prior_own,
            prior_T=prior_T,
            prior_W=prior_W,
            obs_own=z,
            obs_object=z,
            obs_T=np.zeros((0, D, D)),
            obs_W=np.zeros((0, W.shape[1])),
            separators_for={q: local[v] for q, v in part.separators_for.items()},
        )

    def factors(
        self,
        anchor_slot: Mapping[tuple[int, int], int],
        object_slot: Mapping[int, int],
        obs_ok: np.ndarray,
        kernel: Kernel | None,
        object_kernel: Kernel | None,
    ) -> tuple[Factor, ...]:
        """The factor blocks of L̂_i but the consensus terms: f_intra (odometry without a
        kernel, loops with ``kernel``), f_inter against the neighbours' separators held as
        fixed anchors (only those in ``anchor_slot``: (owner, keyframe id) -> variable), the
        pose priors, and f_obj over the own observations in ``obs_ok`` (object id -> variable
        in ``object_slot``, ``object_kernel``). Own poses are variables 0..n−1."""
        blocks: list[Factor] = []
        if self.between.shape[0]:
            rob = self.between_robust
            for mask, ker, label in ((~rob, None, "intra"), (rob, kernel, "intra-loop")):
                if mask.any():
                    blocks.append(
                        BetweenFactors(
                            self.between[mask],
                            self.between_T[mask],
                            self.between_W[mask],
                            self.residual,
                            ker,
                            label,
                        )
                    )
        if self.inter_own.size:
            ends = list(zip(self.inter_owner, self.inter_anchor_id))
            keep = np.array([(int(o), int(a)) in anchor_slot for o, a in ends])
            if keep.any():
                a_idx = np.array([anchor_slot.get((int(o), int(a)), -1) for o, a in ends])[keep]
                own, is_p = self.inter_own[keep], self.inter_own_is_p[keep]
                var = np.stack([np.where(is_p, own, a_idx), np.where(is_p, a_idx, own)], axis=1)
                for m, ker in ((~self.inter_robust[keep], None), (self.inter_robust[keep], kernel)):
                    if m.any():
                        blocks.append(
                            BetweenFactors(
                                var[m],
                                self.inter_T[keep][m],
                                self.inter_W[keep][m],
                                self.residual,
                                ker,
                                "inter",
                            )
                        )
        if self.prior_own.size:
            rob = np.zeros(self.prior_own.size, bool)
            rob[: self.prior_robust.size] = self.prior_robust
            for mask, ker in ((~rob, None), (rob, kernel)):
                if mask.any():
                    blocks.append(
                        PriorFactors(
                            self.prior_own[mask][:, None],
                            self.prior_T[mask],
                            self.prior_W[mask],
                            self.residual,
                            ker,
                        )
                    )
        ok = obs_ok
        if ok.any():
            var = np.stack(
                [self.obs_own[ok], np.array([object_slot[int(o)] for o in self.obs_object[ok]])],
                axis=1,
            )
            blocks.append(
                BetweenFactors(
                    var, self.obs_T[ok], self.obs_W[ok], self.residual, object_kernel, "object"
                )
            )
        return tuple(blocks)
