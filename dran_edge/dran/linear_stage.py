"""One linear least-squares stage of the distributed initialisation, solved by block iterations
over a partition (the solver that ``dran_edge.dran.dist_init`` and the DGS baseline,
``dran_edge.experiments.dgs``, share).

A stage minimises ``Σ_e w_e ‖X_j − M_e X_i − c_e‖²`` over the vertex values X_v (b × ncol
blocks; ``dist_init``'s module docstring gives M_e, c_e and b of the rotation and translation
stages). Normal equations (``Q X = Bv``): ``Q_ii += w M_eᵀM_e``, ``Q_jj += w I``,
``Q_ij += −w M_eᵀ``, ``Q_ji += −w M_e``, ``Bv_i += −w M_eᵀ c_e``, ``Bv_j += w c_e``.

Robot r's block update (Jacobi, or Gauss–Seidel over a colouring, with successive
over-relaxation ω as in Choudhary et al. 2017):

    X_r ← (1 − ω) X_r + ω Q_rr⁻¹ (Bv_r − Q_rk X_k)       (k: its anchors, the neighbours' separators)

``Q_rr`` is factorised once per stage and reused. Values travel between robots through an
:data:`Exchange` (the harness encodes them with the wire codec, so rounds and bytes are
counted exactly like the optimisation's).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from dran_edge.dran.partition import Partition
from dran_edge.messages import InitEntry, InitStage

Outgoing = dict[int, list[tuple[int, list[InitEntry]]]]
"""robot -> [(neighbour, entries it sends that neighbour)] of one exchange."""
Incoming = dict[int, list[InitEntry]]
"""robot -> the entries it received in one exchange."""
Exchange = Callable[[InitStage, int, Outgoing], Incoming]
"""``exchange(stage, iteration, outgoing) -> incoming``: one round of messages."""


@dataclass
class _Block:
    """One robot's share of one linear stage."""

    own: np.ndarray  # global positions of unknown own vertices
    known: np.ndarray  # global positions of anchors (+ the gauge if it is ours)
    lu: spla.SuperLU
    Q_rk: sp.csr_matrix
    Bv: np.ndarray
    X: np.ndarray  # (len(own)*b, ncol)
    updated: bool = False  # has made a block update in this stage


def normal_equations(
    n: int, b: int, edges: np.ndarray, M: np.ndarray, c: np.ndarray, w: np.ndarray
) -> tuple[sp.csr_matrix, np.ndarray]:
    """(Q, Bv) of ``Σ_e w_e ‖X_j − M_e X_i − c_e‖²`` (see the module docstring), vectorised.

    ``M`` is (m, b, b), ``c`` is (m, b, ncol), ``w`` (m,); Q is (n b, n b), Bv (n b, ncol).
    """
    m = edges.shape[0]
    i, j = edges[:, 0], edges[:, 1]
    ar = np.arange(b)
    I = np.broadcast_to(np.eye(b), (m, b, b))
    MtM = np.swapaxes(M, 1, 2) @ M
    blocks = [
        (i, i, w[:, None, None] * MtM),
        (j, j, w[:, None, None] * I),
        (i, j, -w[:, None, None] * np.swapaxes(M, 1, 2)),
        (j, i, -w[:, None, None] * M),
    ]
    rows, cols, vals = [], [], []
    for p, q, val in blocks:
        rows.append((p[:, None, None] * b + ar[None, :, None] + 0 * ar[None, None, :]).ravel())
        cols.append((q[:, None, None] * b + ar[None, None, :] + 0 * ar[None, :, None]).ravel())
        vals.append(val.ravel())
    Q = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n * b, n * b)
    )
    ncol = c.shape[-1]
    Bv = np.zeros((n * b, ncol))
    Mtc = -w[:, None, None] * (np.swapaxes(M, 1, 2) @ c)
    np.add.at(Bv, (i[:, None] * b + ar[None]).ravel(), Mtc.reshape(-1, ncol))
    np.add.at(Bv, (j[:, None] * b + ar[None]).ravel(), (w[:, None, None] * c).reshape(-1, ncol))
    return Q, Bv


def block_rows(positions: np.ndarray, b: int) -> np.ndarray:
    """Rows of the b-row blocks of vertices ``positions`` (in that order) in a stacked X."""
    rows: np.ndarray = (positions[:, None] * b + np.arange(b)[None]).ravel()
    return rows


def greedy_colouring(partition: Partition) -> np.ndarray:
    """(R,) colour of each robot so that neighbours differ (DGS's ordering, Choudhary 2017)."""
    colour = -np.ones(partition.num_robots, dtype=np.int64)
    for p in sorted(partition.parts, key=lambda p: -len(p.neighbours)):
        used = {int(colour[q]) for q in p.neighbours}
        colour[p.robot_id] = next(c for c in range(partition.num_robots + 1) if c not in used)
    return colour


@dataclass(frozen=True, eq=False)
class _SegmentFrame:
    """What one robot's frame updates (``LinearStage.frame_update``) read: its solo-segment
    values and its inter-robot edges seen from its side."""

    fixed: bool  # holds the gauge: its segment never moves
    X_hat: np.ndarray  # (n_r, b, ncol) the segment solved alone, at ``verts``
    verts: np.ndarray  # its vertices
    mine_j: np.ndarray  # per inter-robot edge: its own end is j
    own: np.ndarray  # per inter-robot edge: its own end
    other: np.ndarray  # per inter-robot edge: the neighbour's end
    M: np.ndarray
    c: np.ndarray
    w: np.ndarray


class LinearStage:
    """One distributed linear least-squares stage over a partition (rotations or translations)."""

    def __init__(
        self,
        partition: Partition,
        n: int,
        b: int,
        edges: np.ndarray,
        M: np.ndarray,
        c_of: Callable[[int], np.ndarray],
        w: np.ndarray,
        gauge: int,
        X_gauge: np.ndarray,
        X0: np.ndarray,
    ):
        """``c_of(r)`` gives robot r's (m, b, ncol) constants (they may use r's own knowledge)."""
        self.partition, self.b = partition, b
        self.X_known = X0.copy()  # each robot's view is taken from here per robot below
        self.views: list[np.ndarray] = []
        self.blocks: list[_Block] = []
        self.frames: list[_SegmentFrame] = []
        for part in partition.parts:
            eidx = np.concatenate([part.intra_edges, part.inter_edges])
            Q, Bv = normal_equations(n, b, edges[eidx], M[eidx], c_of(part.robot_id)[eidx], w[eidx])
            own = part.vertices[part.vertices != gauge]
            known = part.anchors
            if np.any(part.vertices == gauge):
                known = np.concatenate([known, [gauge]])
            ro, rk = block_rows(own, b), block_rows(known, b)
            Q = Q.tocsr()
            Q_rr = sp.csc_matrix(Q[ro][:, ro])
            lu = spla.splu(
                Q_rr,
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
            view = X0.copy()
            view[block_rows(np.array([gauge]), b)] = X_gauge
            # Warm start: the segment solved alone (intra edges, its first vertex as gauge).
            ei = part.intra_edges
            Qi, Bi = normal_equations(n, b, edges[ei], M[ei], c_of(part.robot_id)[ei], w[ei])
            first = int(part.vertices[0])
            loc = part.vertices[part.vertices != first]
            rl, rf = block_rows(loc, b), block_rows(np.array([first]), b)
            Qi = Qi.tocsr()
            X_first = X_gauge if first == gauge else X0[rf]
            X_hat = X0.copy()
            X_hat[rf] = X_first
            if loc.size:
                # A segment may fall apart into pieces (interleaved splits); a tiny pull
                # towards X0 keeps the pieces without the local gauge defined.
                Qs = sp.csc_matrix(Qi[rl][:, rl])
                eps = 1e-9 * max(float(np.abs(Qs.diagonal()).max(initial=0.0)), 1.0)
                X_hat[rl] = spla.spsolve(
                    Qs + eps * sp.identity(rl.size, format="csc"),
                    Bi[rl] - Qi[rl][:, rf] @ X_first + eps * X0[rl],
                ).reshape(-1, X0.shape[1])
            view[block_rows(part.vertices, b)] = X_hat[block_rows(part.vertices, b)]
            self.views.append(view)
            self.blocks.append(
                _Block(own, known, lu, Q[ro][:, rk].tocsr(), Bv[ro], view[ro].copy())
            )
            ex = edges[part.inter_edges]
            mine_j = partition.owner[ex[:, 1]] == part.robot_id
            self.frames.append(
                _SegmentFrame(
                    fixed=bool(np.any(part.vertices == gauge)),
                    X_hat=X_hat[block_rows(part.vertices, b)].reshape(part.vertices.size, b, -1),
                    verts=part.vertices,
                    mine_j=mine_j,
                    own=np.where(mine_j, ex[:, 1], ex[:, 0]),
                    other=np.where(mine_j, ex[:, 0], ex[:, 1]),
                    M=M[part.inter_edges],
                    c=c_of(part.robot_id)[part.inter_edges],
                    w=w[part.inter_edges],
                )
            )
        self.heard = [np.zeros(n, bool) for _ in partition.parts]
        self.multiplicative = b > 1
        #: per robot: the neighbours' separator values as last received (the solo-segment
        #: values X̂ during the frame phase), the base that a frame entry transforms
        self.base = [np.zeros((n, b, X0.shape[1])) for _ in partition.parts]
        #: per robot: its last frame (G, or the offset s) from ``frame_update``
        self.frame: list[np.ndarray | None] = [None for _ in partition.parts]

    def update(self, r: int, sor: float) -> float:
        """Robot r's block update from its current view; returns the max abs change.

        The robot's first block update of the stage is a plain one (ω = 1): it carries the
        large correction from the aligned solo segments to the coupled solution, and
        over-relaxing that one overshoots (parking-garage: F_init 3.24 instead of 1.46, with the
        1e-4 translation send threshold)."""
        blk, view = self.blocks[r], self.views[r]
        rhs = blk.Bv - blk.Q_rk @ view[block_rows(blk.known, self.b)]
        omega = sor if blk.updated else 1.0
        blk.updated = True
        X_new = (1.0 - omega) * blk.X + omega * blk.lu.solve(rhs)
        change = float(np.max(np.abs(X_new - blk.X), initial=0.0))
        blk.X = X_new
        view[block_rows(blk.own, self.b)] = X_new
        return change

    def frame_update(self, r: int) -> float:
        """Align robot r's whole segment to the anchors heard so far: ``X_v = X̂_v G`` (rotation
        stage, G d×d) or ``X_v = X̂_v + s`` (translation stage), least squares over its
        inter-robot edges. A segment solved alone is right up to such a transform, so a few of
        these small steps remove the slow rigid modes before the block updates; returns the
        max abs change of the segment."""
        f, view, b = self.frames[r], self.views[r], self.b
        if f.fixed:
            return 0.0
        sel = self.heard[r][f.other]
        if not sel.any():
            return 0.0
        pos = {int(v): k for k, v in enumerate(f.verts.tolist())}
        own_k = np.array([pos[int(v)] for v in f.own[sel]])
        Xh = f.X_hat[own_k]  # (e, b, ncol)
        Xo = view.reshape(-1, b, view.shape[1])[f.other[sel]]
        M, c, w, mj = f.M[sel], f.c[sel], f.w[sel], f.mine_j[sel]
        if self.multiplicative:
            # own j: X̂_j G − (M X_i + c);  own i: M X̂_i G − (X_j − c)
            P = np.where(mj[:, None, None], Xh, M @ Xh)
            Qm = np.where(mj[:, None, None], M @ Xo + c, Xo - c)
            lhs = np.einsum("e,eab,eac->bc", w, P, P)
            G = np.linalg.solve(lhs, np.einsum("e,eab,eac->bc", w, P, Qm))
            X_new = f.X_hat @ G
            self.frame[r] = G
        else:
            # own j: X̂_j + s − X_i − c;  own i: s − (X_j − X̂_i − c)
            Qm = np.where(mj[:, None, None], Xo + c - Xh, Xo - Xh - c)
            s_off = np.einsum("e,eab->ab", w, Qm) / w.sum()
            X_new = f.X_hat + s_off
            self.frame[r] = s_off
        idx = block_rows(f.verts, b)
        change = float(np.max(np.abs(X_new.reshape(-1, view.shape[1]) - view[idx])))
        view[idx] = X_new.reshape(-1, view.shape[1])
        blk = self.blocks[r]
        blk.X = view[block_rows(blk.own, b)].copy()
        return change

    def own_value(self, r: int, v: int) -> np.ndarray:
        return self.views[r][v * self.b : (v + 1) * self.b]

    def solo_values(self, r: int, vs: np.ndarray) -> np.ndarray:
        """Robot r's solo-segment values X̂ at its vertices ``vs`` (what its frames transform)."""
        f = self.frames[r]
        order = np.argsort(f.verts)
        X_hat: np.ndarray = f.X_hat[order[np.searchsorted(f.verts, vs, sorter=order)]]
        return X_hat

    def receive(self, r: int, v: int, X_v: np.ndarray) -> None:
        self.views[r][v * self.b : (v + 1) * self.b] = X_v
        self.heard[r][v] = True
        self.base[r][v] = X_v

    def receive_frame(self, r: int, owner: int, F: np.ndarray) -> None:
        """A neighbour's frame: every separator of ``owner`` that robot r holds a base for
        becomes ``X̂_v G`` (rotation stage) or ``X̂_v + s`` (translation stage)."""
        sel = self.heard[r] & (self.partition.owner == owner)
        X = self.base[r][sel]
        view = self.views[r].reshape(self.base[r].shape)
        view[sel] = X @ F if self.multiplicative else X + F
