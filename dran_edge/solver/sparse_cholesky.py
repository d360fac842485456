"""Supernodal multifrontal Cholesky for the block-sparse SPD matrices of pose graphs.

scipy has no sparse Cholesky (CHOLMOD lives in scikit-sparse, which the core may not use), and
SuperLU factorises an SPD matrix as a general LU at roughly twice the work and without level-3
BLAS on its supernodes. This module factorises ``A + μI`` with dense LAPACK/BLAS kernels on
frontal matrices (Liu, "The multifrontal method for sparse matrix solution", SIAM Review 1992;
Davis, "Direct Methods for Sparse Linear Systems", ch. 4 and 9):

- analysis (once per sparsity pattern): a minimum-degree ordering of the *block* graph (one node
  per pose variable; SuperLU's MMD on AᵀA+A), the elimination tree and column structures by
  symbolic factorisation, a postorder with leaf children last, and relaxed supernodes
  (amalgamation, Ashcraft & Grimes, "The influence of relaxed supernode partitions on the
  multifrontal method", ACM TOMS 1989: chains of the tree, and leaf siblings together with
  their parent, merged while the explicit zeros they add stay small); then, per supernode, index
  maps for assembling A's entries and for the extend-add of its update matrix into its parent's
  front;
- numeric factorisation (once per μ): per supernode in postorder, assemble the front
  ``F = [[F11, ·], [F21, F22]]``, ``L11 = chol(F11 + μI)``, ``L21 = F21 L11⁻ᵀ``, and add
  ``F22 − L21 L21ᵀ`` into the parent's front. Fronts hold only lower triangles, in three
  segments that LAPACK/BLAS (potrf, trtrs, syrk) overwrite in place (:func:`_front_pos`); the
  extend-add moves lower triangles only, with ``np.add.at`` (numpy ≥ 1.25);
- solves with any number of right-hand sides by forward and backward substitution over the
  supernodes.

Measured alternatives that lost (tools/bench/bench_cholesky.py, docs/benchmarks.md): nested
dissection (George, "Nested dissection of a regular finite element mesh", SIAM J. Numer. Anal.
1973) with BFS level-set or Fiedler-vector separators gave 19–44 % more fill and 16–79 % more
flops than the minimum degree order on sphere2500 and torus3D; COLAMD and MMD on AᵀA more than
twice the flops.

Python loops run over supernodes (hundreds), never over entries or poses.

Size: over ~500 lines because one algorithm (symbolic analysis, supernode assembly and the
numeric factorisation share their private layout), kept in one file on purpose.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.linalg.blas import dsyrk
from scipy.linalg.lapack import dpotrf, dtrtrs


class NotPositiveDefinite(ArithmeticError):
    """A frontal pivot block was not positive definite."""


def _add_at_fancy(F: np.ndarray, idx: np.ndarray, values: np.ndarray) -> None:
    F[idx] += values  # idx has no repeats: one update matrix's positions are distinct


# Extend-add F[rel] += U: ufunc.at is about 2x faster than fancy indexing from numpy 1.25 on (its
# indexed loops), and many times slower before.
_scatter_add = (
    np.add.at if tuple(int(x) for x in np.__version__.split(".")[:2]) >= (1, 25) else _add_at_fancy
)


@lru_cache(maxsize=256)
def _tril_flat(m: int) -> np.ndarray:
    """C-order flat positions of the lower triangle (i ≥ j, diagonal included, row by row) of
    an m×m matrix."""
    i, j = np.tril_indices(m)
    flat: np.ndarray = i * m + j
    return flat


def _front_pos(
    r: np.ndarray, c: np.ndarray, k: int | np.ndarray, f: int | np.ndarray
) -> np.ndarray:
    """Flat position of entry (r, c), r ≥ c, of an f×f front with k pivot columns, stored as
    three C-order segments ``[F11 (k×k) | F21 (m×k) | F22 (m×m)]`` (m = f − k). Each segment
    read as a column-major array is the transpose of its block, whose upper triangle (lower
    triangle of the block) LAPACK/BLAS factorise and update in place, without copies."""
    m = f - k
    pos: np.ndarray = np.where(
        r < k,
        r * k + c,
        np.where(c < k, k * k + (r - k) * k + c, k * k + m * k + (r - k) * m + (c - k)),
    )
    return pos


def _update_positions(loc: np.ndarray, k: np.ndarray, f: np.ndarray) -> np.ndarray:
    """:func:`_front_pos` of the lower triangles (order of :func:`_tril_flat`) of N update
    matrices at once: ``loc`` (N, m) ascending local rows in the parents' fronts, ``k``/``f``
    (N, 1) the parents' pivot columns and sizes. Uses that the position is separable:
    r·k + c for c < k, (k·k − k + r·m) + c for c ≥ k (then r ≥ c ≥ k)."""
    n, m = loc.shape
    full = np.where(
        (loc < k)[:, None, :], (loc * k)[:, :, None], (loc * (f - k) + (k * k - k))[:, :, None]
    )
    full += loc[:, None, :]
    out: np.ndarray = full.reshape(n, m * m)[:, _tril_flat(m)]
    return out


def _block_order(nb: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Minimum-degree elimination order of the block graph: order[k] = block eliminated k-th."""
    if nb <= 2:
        return np.arange(nb)
    pattern = sp.csc_matrix((np.ones(rows.size), (rows, cols)), shape=(nb, nb))
    pattern = sp.csc_matrix(pattern + sp.identity(nb) * (nb + 1.0))
    lu = spla.splu(
        pattern, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
    )
    return np.argsort(lu.perm_c)


def _etree(nb: int, rows: np.ndarray, cols: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Elimination tree of the block graph eliminated in ``order`` (Liu's algorithm with path
    compression; Davis, "Direct Methods for Sparse Linear Systems", sec. 4.1)."""
    pos = np.empty(nb, dtype=np.int64)
    pos[order] = np.arange(nb)
    pr, pc = pos[rows], pos[cols]
    upper = pr < pc
    key = np.unique(pc[upper] * nb + pr[upper])  # column k, rows i < k, ascending
    kc, kr = (key // nb).tolist(), (key % nb).tolist()
    parent = [-1] * nb
    ancestor = [-1] * nb
    for k, i in zip(kc, kr):
        while i != -1 and i < k:
            nxt = ancestor[i]
            ancestor[i] = k
            if nxt == -1:
                parent[i] = k
            i = nxt
    return np.asarray(parent, dtype=np.int64)


@dataclass(frozen=True, eq=False)
class _Supernode:
    c0: int
    """First scalar column (in the permuted order)."""
    c1: int
    rows: np.ndarray
    """Scalar row indices (permuted order) below the pivot block, ascending."""
    parent: int
    """Index of the parent supernode, −1 for a root."""
    rel: np.ndarray
    """Flat positions in the parent's front of the lower triangle of this supernode's update
    matrix (in the order of :func:`_tril_flat`). Only lower triangles are ever read: the fronts'
    row orders are ascending, so a child's lower triangle lands in its parent's."""
    a_src: np.ndarray
    """Positions in A's CSC data of the entries assembled into this front."""
    a_dst: np.ndarray
    """Their flat positions in the front: a plain C-order f×f square for a leaf (batched, see
    _LeafGroup), the segmented layout of :func:`_front_pos` otherwise."""
    diag: np.ndarray
    """Flat positions of the pivot block's diagonal in the front (for the shift μ)."""


def _symbolic(
    nb: int, rows: np.ndarray, cols: np.ndarray, order: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""Symbolic Cholesky of the block graph eliminated in ``order`` (Davis, ch. 4):
    struct[k] = adj_below(k) ∪ ⋃_{children c} struct[c] \ {k}, parent[k] = min struct[k].
    Returns (rows below the diagonal of each column, ascending and concatenated; column
    pointers; parent) in the permuted numbering."""
    pos = np.empty(nb, dtype=np.int64)
    pos[order] = np.arange(nb)
    pr, pc = pos[rows], pos[cols]
    lo, hi = np.maximum(pr, pc), np.minimum(pr, pc)
    key = np.unique(hi[lo > hi] * nb + lo[lo > hi])
    kc, kr = key // nb, key % nb
    starts = np.searchsorted(kc, np.arange(nb + 1)).tolist()
    kr_list = kr.tolist()
    struct: list[list[int]] = []
    pending: list[set[int]] = [set() for _ in range(nb)]
    parent = np.full(nb, -1, dtype=np.int64)
    for k in range(nb):
        st = pending[k]
        st.update(kr_list[starts[k] : starts[k + 1]])
        st.discard(k)
        srt = sorted(st)
        struct.append(srt)
        pending[k] = set()
        if srt:
            p = srt[0]
            parent[k] = p
            pending[p].update(srt[1:])
    ptr = np.zeros(nb + 1, dtype=np.int64)
    ptr[1:] = np.cumsum([len(x) for x in struct])
    flat = np.fromiter((r for x in struct for r in x), dtype=np.int64, count=int(ptr[-1]))
    return flat, ptr, parent


def _block_pattern(
    indptr: np.ndarray, indices: np.ndarray, nb: int, block: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The block pattern, from one representative (top-left) entry per stored block: the entries
    of each block column's first scalar column whose row starts a block. Returns (their positions
    in A's CSC data, block row, block column)."""
    first = np.arange(nb, dtype=np.int64) * block
    lens = indptr[first + 1] - indptr[first]
    rep_pos = np.repeat(indptr[first] - np.concatenate([[0], np.cumsum(lens)[:-1]]), lens)
    rep_pos += np.arange(int(lens.sum()))
    rep_pos = rep_pos[indices[rep_pos] % block == 0]
    brow = indices[rep_pos] // block
    bcol = np.searchsorted(indptr[first], rep_pos, side="right") - 1
    return rep_pos, brow, bcol


def _postorder(parent: np.ndarray) -> np.ndarray:
    """A postorder of the elimination tree (same fill; every chain of the tree becomes
    contiguous, so that it can form a supernode), leaf children last, right before their parent,
    so that they can join it."""
    nb = parent.size
    children: list[list[int]] = [[] for _ in range(nb)]
    for k, p in enumerate(parent.tolist()):
        if p >= 0:
            children[p].append(k)
    post: list[int] = []
    for root in np.flatnonzero(parent < 0).tolist():
        stack = [(root, False)]
        while stack:
            node, done = stack.pop()
            if done:
                post.append(node)
                continue
            stack.append((node, True))
            kids = sorted(children[node], key=lambda c: not children[c])
            stack.extend((c, False) for c in reversed(kids))
    return np.asarray(post, dtype=np.int64)


def _amalgamate(
    parent: np.ndarray, counts: np.ndarray, max_cols: int, relax_zeros: float, small_cols: int
) -> np.ndarray:
    """Relaxed supernodes (amalgamation, Ashcraft & Grimes 1989): the column bounds of the
    supernodes. Column k joins the current supernode [a, k) when k is the parent of each of its
    roots (the columns whose parent lies outside it) and the explicit zeros stay few; leaf
    siblings of the tree gather while they wait for their parent, and are split again if it does
    not join them."""
    nb = parent.size
    is_leaf_col = np.ones(nb, dtype=bool)
    is_leaf_col[parent[parent >= 0]] = False
    parent_l = parent.tolist()
    bounds = [0]
    actual = 0
    roots: list[int] = []

    def close(a: int, k: int) -> None:
        if len(roots) > 1:  # leaf siblings without their parent: singletons
            bounds.extend(range(a + 1, k))
        bounds.append(k)

    for k in range(nb):
        a = bounds[-1]
        if k > a and k - a + 1 <= max_cols:
            cols = k - a + 1
            if all(parent_l[r] == k for r in roots):
                new_ideal = cols * (cols - 1) // 2 + cols * int(counts[k])
                new_actual = actual + int(counts[k])
                if new_ideal - new_actual <= relax_zeros * new_ideal or cols <= small_cols:
                    actual, roots = new_actual, [k]
                    continue
            elif (
                is_leaf_col[k]
                and parent_l[k] == parent_l[roots[0]]
                and all(is_leaf_col[r] for r in roots)
            ):
                actual += int(counts[k])
                roots.append(k)
                continue
        if k > a:
            close(a, k)
        actual, roots = int(counts[k]), [k]
    close(bounds[-1], nb)
    return np.unique(np.asarray(bounds, dtype=np.int64))


@dataclass
class _Fronts:
    """The supernodal structure: a supernode is a chain k → k+1 → … → b−1 of the elimination
    tree, and struct[k] ⊂ {k+1} ∪ struct[k+1] along a chain, so its rows below are exactly those
    of its last column. Fronts are (pivot columns, rows below) in block indices."""

    bounds: np.ndarray
    owner: np.ndarray
    rows_b: list[np.ndarray]
    parent: np.ndarray
    children: list[list[int]]
    sizes: np.ndarray
    ncols: np.ndarray
    is_leaf: np.ndarray
    start: np.ndarray
    keys: np.ndarray
    """Sorted keys s·nb + block row of every front's rows, for one search per lookup."""


def _fronts(
    bounds: np.ndarray, s_rows: np.ndarray, s_ptr: np.ndarray, nb: int, block: int
) -> _Fronts:
    nsn = bounds.size - 1
    owner = np.repeat(np.arange(nsn), np.diff(bounds))
    rows_b = [s_rows[s_ptr[b - 1] : s_ptr[b]] for b in bounds[1:].tolist()]
    parent = np.array([owner[rb[0]] if rb.size else -1 for rb in rows_b], dtype=np.int64)
    children: list[list[int]] = [[] for _ in range(nsn)]
    for s_, p_ in enumerate(parent.tolist()):
        if p_ >= 0:
            children[p_].append(s_)
    fronts_b = [
        np.concatenate([np.arange(bounds[s], bounds[s + 1]), rows_b[s]]) for s in range(nsn)
    ]
    sizes = np.array([fb.size for fb in fronts_b], dtype=np.int64)
    return _Fronts(
        bounds=bounds,
        owner=owner,
        rows_b=rows_b,
        parent=parent,
        children=children,
        sizes=sizes,
        ncols=np.diff(bounds) * block,
        is_leaf=np.array([not c for c in children], dtype=bool),
        start=np.concatenate([[0], np.cumsum(sizes)]),
        keys=np.repeat(np.arange(nsn), sizes) * nb + np.concatenate(fronts_b),
    )


def _assembly(
    fr: _Fronts,
    indptr: np.ndarray,
    indices: np.ndarray,
    rep_pos: np.ndarray,
    brow: np.ndarray,
    bcol: np.ndarray,
    pos: np.ndarray,
    nb: int,
    block: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each stored entry of A goes: the front of the supernode owning its column, when its
    row is at or below that supernode's first column (the rest is the transpose). Returns
    (source positions in A's data, flat destinations in the fronts, per-supernode pointers)."""
    prb, pcb = pos[brow], pos[bcol]
    s_of = fr.owner[pcb]
    sel = np.flatnonzero(prb >= fr.bounds[s_of])
    sel = sel[np.argsort(s_of[sel], kind="stable")]
    s_b = s_of[sel]
    lrow_b = np.searchsorted(fr.keys, s_b * nb + prb[sel]) - fr.start[s_b]
    lcol_b = pcb[sel] - fr.bounds[s_b]
    # every stored block is dense and the scalar columns of a block column share their rows,
    # so element (r, c) of the block whose top-left entry is at p0 sits at
    # indptr[col0 + c] + (p0 − indptr[col0]) + r
    rr, cc = np.divmod(np.arange(block * block), block)
    col0 = bcol[sel] * block
    src = indptr[col0[:, None] + cc] + (rep_pos[sel] - indptr[col0])[:, None] + rr
    if rep_pos.size * block * block != indices.size or not np.array_equal(
        indices[src], (brow[sel] * block)[:, None] + rr
    ):
        raise ValueError("the pattern is not made of dense block×block blocks")
    f_b = (fr.sizes[s_b] * block)[:, None]
    # A's entries lie in the pivot columns (c < k), where _front_pos is r·k + c
    row_len = np.where(fr.is_leaf[s_b][:, None], f_b, fr.ncols[s_b][:, None])
    a_dst = ((lrow_b[:, None] * block + rr) * row_len + lcol_b[:, None] * block + cc).ravel()
    sn_ptr = np.searchsorted(s_b, np.arange(fr.parent.size + 1)) * (block * block)
    return src.ravel(), a_dst, sn_ptr


def _parent_positions(
    fr: _Fronts, nb: int, block: int
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Where each supernode's rows sit in its parent's front: (scalar rows per supernode, the
    parent-front positions of each update matrix's lower triangle), vectorised over the
    supernodes with the same number of rows."""
    nsn = fr.parent.size
    ar = np.arange(block)
    lens = np.array([rb.size for rb in fr.rows_b], dtype=np.int64)
    par_rep = np.repeat(fr.parent, lens)
    all_rows = np.concatenate(fr.rows_b) if nsn else np.zeros(0, np.int64)
    loc_all = np.zeros(all_rows.size, dtype=np.int64)
    has_par = par_rep >= 0
    loc_all[has_par] = (
        np.searchsorted(fr.keys, par_rep[has_par] * nb + all_rows[has_par])
        - fr.start[par_rep[has_par]]
    )
    cuts = np.cumsum(lens * block)[:-1]
    rows_split = np.split((all_rows[:, None] * block + ar).ravel(), cuts)
    loc_sc = (loc_all[:, None] * block + ar).ravel()
    loc_start = np.concatenate([[0], np.cumsum(lens * block)])
    m_s = lens * block
    rel_of: list[np.ndarray] = [np.zeros(0, dtype=np.int64)] * nsn
    for m in np.unique(m_s[fr.parent >= 0]).tolist():
        members = np.flatnonzero((m_s == m) & (fr.parent >= 0))
        loc = loc_sc[loc_start[members][:, None] + np.arange(m)]
        par = fr.parent[members][:, None]
        rel = _update_positions(loc, fr.ncols[par], fr.sizes[par] * block)
        for i, s_ in enumerate(members.tolist()):
            rel_of[s_] = rel[i]
    return rows_split, rel_of


def _leaf_groups(supernodes: list[_Supernode], children: list[list[int]]) -> list[_LeafGroup]:
    """Leaves (most supernodes of a pose graph: single poses of odometry chains) depend on
    nothing; those of one shape are factorised together as a batch, one numpy call each."""
    shapes: dict[tuple[int, int], list[int]] = {}
    for s, sn in enumerate(supernodes):
        if not children[s]:
            shapes.setdefault((sn.c1 - sn.c0, sn.rows.size), []).append(s)
    groups = []
    for (k, m), members in sorted(shapes.items()):
        f = k + m
        base = np.arange(len(members)) * f * f
        sns = [supernodes[s] for s in members]
        groups.append(
            _LeafGroup(
                k=k,
                m=m,
                cols=np.stack([np.arange(sn.c0, sn.c1) for sn in sns]),
                rows=np.stack([sn.rows for sn in sns]),
                src=np.concatenate([sn.a_src for sn in sns]),
                dst=np.concatenate([b + sn.a_dst for b, sn in zip(base, sns)]),
                diag=np.concatenate([b + sn.diag for b, sn in zip(base, sns)]),
                parents=[sn.parent for sn in sns],
                rels=[sn.rel for sn in sns],
            )
        )
    return groups


class SymbolicCholesky:
    """The analysis of one block-structured sparsity pattern (see the module docstring)."""

    def __init__(
        self,
        indptr: np.ndarray,
        indices: np.ndarray,
        n: int,
        block: int,
        max_cols: int = 64,
        relax_zeros: float = 0.3,
        small_cols: int = 8,
    ):
        """``indptr``/``indices``: CSC pattern of a symmetric matrix stored in full, with every
        diagonal entry present; ``block``: size of the dense diagonal blocks (pose dof).
        Supernodes have at most ``max_cols`` block columns; a chain is merged while the explicit
        zeros stay below ``relax_zeros`` of the supernode's entries or it has ≤ ``small_cols``."""
        if n % block:
            raise ValueError(f"n = {n} is not a multiple of the block size {block}")
        self.n, self.block = n, block
        nb = n // block
        indptr = np.asarray(indptr, dtype=np.int64)
        indices = np.asarray(indices, dtype=np.int64)
        rep_pos, brow, bcol = _block_pattern(indptr, indices, nb, block)
        order = _block_order(nb, brow, bcol)
        order = order[_postorder(_etree(nb, brow, bcol, order))]
        s_rows, s_ptr, parent = _symbolic(nb, brow, bcol, order)
        bounds = _amalgamate(parent, np.diff(s_ptr), max_cols, relax_zeros, small_cols)
        fr = _fronts(bounds, s_rows, s_ptr, nb, block)
        pos = np.empty(nb, dtype=np.int64)
        pos[order] = np.arange(nb)
        take, a_dst, sn_ptr = _assembly(fr, indptr, indices, rep_pos, brow, bcol, pos, nb, block)
        rows_split, rel_of = _parent_positions(fr, nb, block)
        # diagonal of each pivot block in its front: i·(f + 1) in a leaf's square front,
        # i·(k + 1) in the F11 segment of the others, for i < k
        ncols = fr.ncols
        kk = np.arange(int(ncols.sum())) - np.repeat(np.cumsum(ncols) - ncols, ncols)
        stride = np.where(fr.is_leaf, fr.sizes * block, ncols) + 1
        diag_split = np.split(kk * np.repeat(stride, ncols), np.cumsum(ncols)[:-1])
        self._supernodes = [
            _Supernode(
                c0=a_ * block,
                c1=b_ * block,
                rows=rows_split[s_],
                parent=p_,
                rel=rel_of[s_],
                a_src=take[sn_ptr[s_] : sn_ptr[s_ + 1]],
                a_dst=a_dst[sn_ptr[s_] : sn_ptr[s_ + 1]],
                diag=diag_split[s_],
            )
            for s_, (a_, b_, p_) in enumerate(
                zip(bounds[:-1].tolist(), bounds[1:].tolist(), fr.parent.tolist())
            )
        ]
        self._perm = (order[:, None] * block + np.arange(block)).ravel()  # permuted -> original
        self.num_supernodes = bounds.size - 1
        self._leaf_groups = _leaf_groups(self._supernodes, fr.children)
        self._internal = [s for s in range(self.num_supernodes) if fr.children[s]]

    def factorize(self, data: np.ndarray, shift: float = 0.0) -> NumericCholesky:
        """Factorise the matrix with the analysed pattern and values ``data`` (CSC order), plus
        ``shift`` on the diagonal. Raises NotPositiveDefinite."""
        data = np.asarray(data, dtype=np.float64)
        pending: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in self._supernodes]
        leaf_factors: list[tuple[np.ndarray, np.ndarray | None]] = []
        for grp in self._leaf_groups:
            k, m = grp.k, grp.m
            f = k + m
            N = grp.cols.shape[0]
            F = np.zeros(N * f * f)
            F[grp.dst] = data[grp.src]
            F[grp.diag] += shift
            F = F.reshape(N, f, f)
            try:
                L11 = np.linalg.cholesky(F[:, :k, :k])
            except np.linalg.LinAlgError:
                raise NotPositiveDefinite(f"a pivot block of {N} leaf supernodes") from None
            L21T: np.ndarray | None = None
            if m:
                L21T = np.linalg.solve(L11, np.swapaxes(F[:, k:, :k], 1, 2))
                U = (F[:, k:, k:] - np.swapaxes(L21T, 1, 2) @ L21T).reshape(N, m * m)
                U = U[:, _tril_flat(m)]
                for i, p in enumerate(grp.parents):
                    pending[p].append((grp.rels[i], U[i]))
            leaf_factors.append((L11, L21T))
        factors: list[tuple[np.ndarray, np.ndarray]] = []
        for s in self._internal:
            sn = self._supernodes[s]
            k = sn.c1 - sn.c0
            m = sn.rows.size
            # the front in the segmented layout of _front_pos; only lower triangles are valid
            # (see _Supernode.rel), i.e. the upper ones of the column-major views below
            F = np.zeros(k * k + m * k + m * m)
            F[sn.a_dst] = data[sn.a_src]
            F[sn.diag] += shift
            for rel, U in pending[s]:
                _scatter_add(F, rel, U)
            pending[s] = []
            # R = L11ᵀ (upper, column-major) in place of F11: F11 = R^T R
            R, info = dpotrf(F[: k * k].reshape(k, k).T, lower=0, clean=0, overwrite_a=1)
            if info != 0:
                raise NotPositiveDefinite(f"pivot block of columns {sn.c0}..{sn.c1} (info {info})")
            if m:
                # X = L21ᵀ = R⁻ᵀ F21ᵀ in place of F21, then F22 − XᵀX (rank-k update of the
                # triangle only) in place of F22: the update matrix passed to the parent
                X, info = dtrtrs(
                    R, F[k * k : k * k + m * k].reshape(m, k).T, lower=0, trans=1, overwrite_b=1
                )
                S = dsyrk(
                    -1.0,
                    X,
                    beta=1.0,
                    c=F[k * k + m * k :].reshape(m, m).T,
                    trans=1,
                    lower=0,
                    overwrite_c=1,
                )
                pending[sn.parent].append((sn.rel, S.T.reshape(-1)[_tril_flat(m)]))
            else:
                X = np.zeros((k, 0), order="F")
            factors.append((R, X))
        return NumericCholesky(self, leaf_factors, factors)


@dataclass(frozen=True, eq=False)
class _LeafGroup:
    k: int
    m: int
    cols: np.ndarray
    """(N, k) scalar pivot columns of each member."""
    rows: np.ndarray
    """(N, m) scalar rows below."""
    src: np.ndarray
    dst: np.ndarray
    """Flat positions in the stacked (N, f, f) fronts."""
    diag: np.ndarray
    parents: list[int]
    rels: list[np.ndarray]


class NumericCholesky:
    """L Lᵀ = P (A + μI) Pᵀ; :meth:`solve` handles (n,) or (n, r) right-hand sides."""

    def __init__(
        self,
        symbolic: SymbolicCholesky,
        leaf_factors: list[tuple[np.ndarray, np.ndarray | None]],
        factors: list[tuple[np.ndarray, np.ndarray]],
    ):
        self._sym = symbolic
        self._leaf_factors = leaf_factors
        self._factors = factors

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        rhs = np.asarray(rhs, dtype=np.float64)
        return self.backward(self.forward(rhs)).reshape(rhs.shape)

    def forward(self, rhs: np.ndarray) -> np.ndarray:
        """``L⁻¹ P rhs`` as (n, r) (in the factor's permuted order): ``A⁻¹ = Pᵀ L⁻ᵀ L⁻¹ P``, so
        ``bᵀ A⁻¹ c = forward(b)ᵀ forward(c)`` needs no back substitution."""
        sym = self._sym
        rhs = np.asarray(rhs, dtype=np.float64)
        y = np.array(rhs[sym._perm]).reshape(sym.n, -1)
        r = y.shape[1]
        sns = [sym._supernodes[s] for s in sym._internal]
        for grp, (L11, L21T) in zip(sym._leaf_groups, self._leaf_factors):
            ys = np.linalg.solve(L11, y[grp.cols])
            y[grp.cols] = ys
            if grp.m:
                assert L21T is not None
                upd = (np.swapaxes(L21T, 1, 2) @ ys).reshape(-1, r)
                np.subtract.at(y, grp.rows.ravel(), upd)
        for sn, (R, X) in zip(sns, self._factors):  # R = L11ᵀ, X = L21ᵀ
            ys, _ = dtrtrs(R, y[sn.c0 : sn.c1], lower=0, trans=1)
            y[sn.c0 : sn.c1] = ys
            if sn.rows.size:
                y[sn.rows] -= X.T @ ys
        return y

    def backward(self, y: np.ndarray) -> np.ndarray:
        """``Pᵀ L⁻ᵀ y`` for ``y`` from :meth:`forward` (or a combination of its columns);
        returns (n, r) in the original order."""
        sym = self._sym
        y = np.array(y, dtype=np.float64).reshape(sym.n, -1)
        sns = [sym._supernodes[s] for s in sym._internal]
        for sn, (R, X) in zip(reversed(sns), reversed(self._factors)):
            xs = y[sn.c0 : sn.c1]
            if sn.rows.size:
                xs = xs - X @ y[sn.rows]
            y[sn.c0 : sn.c1] = dtrtrs(R, xs, lower=0)[0]
        for grp, (L11, L21T) in zip(sym._leaf_groups, self._leaf_factors):
            xs = y[grp.cols]
            if grp.m:
                assert L21T is not None
                xs = xs - L21T @ y[grp.rows]
            y[grp.cols] = np.linalg.solve(np.swapaxes(L11, 1, 2), xs)
        out = np.empty_like(y)
        out[sym._perm] = y
        return out
