"""Tier 1 of the Schur–LM (:mod:`dran_edge.solver.lm`): the variable ordering and the scatter plans
that turn per-factor blocks into the sparse normal equations, once per graph topology.

The tangent of all non-fixed variables is split into private ``u`` (eliminated, paper eq. 8) and
public ``v``; :func:`build_plan` orders the private variables first and records where every
element of every factor block's ``JᵀJ`` and ``Jᵀr`` goes in ``A`` (sparse CSC), ``C`` (sparse
CSC), ``B`` (dense), ``g_x`` and ``g_y`` of eq. 7.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dran_edge.solver.graph import PoseGraph, VariableKind


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


def _block_csc_plan(
    brow: np.ndarray,
    bcol: np.ndarray,
    base: np.ndarray,
    stride: np.ndarray,
    nbr: int,
    nbc: int,
    dof: int,
    with_diag: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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


_SCATTER_KEYS = (
    *("A_r", "A_c", "A_s", "A_k"),  # A: block row, block column, source base, source stride
    *("C_r", "C_c", "C_s", "C_k"),  # C: the same
    *("B_r", "B_c", "B_s"),  # B: scalar row, scalar column, source
    *("gx_t", "gx_s", "gy_t", "gy_s"),  # g_x, g_y: target, source
)


def _scatter_sources(
    graph: PoseGraph, slot: np.ndarray
) -> tuple[dict[str, np.ndarray], list[int], list[int]]:
    """Where each element of the concatenated factor blocks goes: per key of ``_SCATTER_KEYS``
    the concatenated indices, and the offsets of each factor block's (m, kd, kd) Hessian and
    (m, kd) gradient blocks in the concatenated arrays (kd = k·dof for k-ary factors)."""
    dof = graph.dof
    kinds = graph.kinds
    rr, cc = np.divmod(np.arange(dof * dof), dof)
    ar = np.arange(dof)
    parts: dict[str, list[np.ndarray]] = {key: [] for key in _SCATTER_KEYS}
    H_offsets: list[int] = []
    g_offsets: list[int] = []
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
    return cat, H_offsets, g_offsets


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
    cat, H_offsets, g_offsets = _scatter_sources(graph, slot)
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
