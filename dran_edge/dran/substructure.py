"""Exact distributed solve of one linear stage of the initialisation by substructuring
(static condensation over the robot graph): the direct alternative to the block iterations of
``dran_edge.dran.dist_init``.

The stage is the least squares ``Σ_e w_e ‖X_j − M_e X_i − c_e‖²`` of ``dist_init`` (normal
equations ``Q X = Bv``). Split every inter-robot edge's weight half to each of its two robots;
robot r's share ``Q⁽ʳ⁾`` then involves its own vertices and its anchors only, and
``Q = Σ_r Q⁽ʳ⁾``. Its own vertices without inter-robot edges (the *interior* I_r) appear in no
other share, so eliminating them is local (Schur complement onto its *boundary* B_r = its
separators ∪ its anchors):

    S_r = Q⁽ʳ⁾_BB − Q⁽ʳ⁾_BI (Q⁽ʳ⁾_II)⁻¹ Q⁽ʳ⁾_IB,    g_r = Bv⁽ʳ⁾_B − Q⁽ʳ⁾_BI (Q⁽ʳ⁾_II)⁻¹ Bv⁽ʳ⁾_I

and the separators solve ``(Σ_r S_r) X_B = Σ_r g_r`` — exactly the stage's solution restricted
to them. Protocol over a BFS spanning tree of the robot graph rooted at a centre:

1. gather (height rounds): each robot sends (B_r ids, g_r, upper triangle of S_r) to its
   parent, forwarding its children's; packed float values travel as ``*_SCHUR`` init entries
   (``keyframe_id`` = chunk index, ``owner_robot`` = the robot whose S_r it is);
2. the root assembles and solves the interface system;
3. scatter (height rounds): each link carries the separator values its subtree needs, as the
   stage's own value entries (ROTATION / TRANSLATION);
4. each robot back-substitutes its interior: ``X_I = (Q⁽ʳ⁾_II)⁻¹ (Bv_I − Q_IB X_B)``.

Exact up to the wire's float32 values, in 2 × height rounds per stage. Bytes grow with
|B_r|² (a dense S_r per robot), so ``dist_init`` uses it where it costs no more than a number
of block iterations would (``direct_floats`` against ``iteration_floats``): chain-like graphs
with few loops, where the block iterations converge slowest, have small boundaries.

The steps are generic in the share: ``condense`` takes any robot share ``Q⁽ʳ⁾ X = rhs⁽ʳ⁾``
(block size b, SPD interior block, non-zero blocks only on the robot's edges), ``pack`` /
``gather`` / ``solve_interface`` / ``scatter`` move and solve it, optionally with scalars that
travel with the condensed system and entries the root adds to the scatter. ``solve_direct``
composes them for an init stage, ``dran_edge.dran.exact_gn`` for Gauss–Newton steps.

Size: over ~500 lines because the condensation protocol's four steps share its packed layout
and the kept factors of a frozen-Hessian refinement step (``Condensed.with_rhs``,
``Interface``) reuse them.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from dran_edge.messages import InitEntry, InitStage
from dran_edge.dran.linear_stage import block_rows
from dran_edge.dran.partition import Partition


@dataclass(frozen=True)
class RobotTree:
    """BFS spanning tree of the robot graph: ``parent[root] = -1``."""

    root: int
    parent: np.ndarray
    depth: np.ndarray
    children: tuple[tuple[int, ...], ...]

    @property
    def height(self) -> int:
        return int(self.depth.max(initial=0))

    def subtree(self, r: int) -> list[int]:
        out, stack = [], [r]
        while stack:
            q = stack.pop()
            out.append(q)
            stack.extend(self.children[q])
        return out


def _bfs(adj: list[Any], root: int) -> np.ndarray:
    depth = np.full(len(adj), -1)
    depth[root] = 0
    queue = deque([root])
    while queue:
        r = queue.popleft()
        for q in adj[r]:
            if depth[q] < 0:
                depth[q] = depth[r] + 1
                queue.append(q)
    return depth


def robot_tree(partition: Partition, adjacency: Sequence[Iterable[int]] | None = None) -> RobotTree:
    """BFS tree rooted at a centre of the robot graph (least eccentricity; among those the
    robot with the most boundary vertices, whose condensed system then does not travel;
    then the lowest id). ``adjacency`` (per robot its neighbours): the links to use instead of
    the partition's (robots sharing an edge), e.g. a communication graph; the protocol needs
    only a spanning tree, since every condensed system is forwarded to the root and every
    boundary value comes down from it (a factor between two robots that are no neighbours
    travels over the tree's path, counted on the links it crosses)."""
    R = partition.num_robots
    adj = (
        [sorted(p.neighbours) for p in partition.parts]
        if adjacency is None
        else [sorted(int(q) for q in a) for a in adjacency]
    )
    ecc = np.array([int(_bfs(adj, r).max()) for r in range(R)])
    size = np.array([np.union1d(p.separators, p.anchors).size for p in partition.parts])
    root = int(np.lexsort((np.arange(R), -size, ecc))[0])
    depth = _bfs(adj, root)
    if np.any(depth < 0):
        raise ValueError("the robot graph is not connected")
    parent = np.full(R, -1)
    for r in range(R):
        if r != root:
            parent[r] = min(q for q in adj[r] if depth[q] == depth[r] - 1)
    children = tuple(tuple(int(c) for c in np.flatnonzero(parent == r)) for r in range(R))
    return RobotTree(root, parent, depth, children)


def boundary(part: Any, gauge: int) -> np.ndarray:
    """Robot's boundary vertices B_r: its separators and anchors, without the gauge."""
    B: np.ndarray = np.union1d(part.separators, part.anchors)
    out: np.ndarray = B[B != gauge]
    return out


@dataclass(frozen=True)
class _Structure:
    """Which blocks of a robot's condensed system can be non-zero (from the graph alone)."""

    B: np.ndarray  # boundary vertex positions (sorted)
    I: np.ndarray  # interior vertex positions (sorted)
    pairs: np.ndarray  # (p, 2) boundary-local (i ≤ j) pairs joined by an edge, and (i, i)
    comps: tuple[
        tuple[np.ndarray, np.ndarray], ...
    ]  # per connected piece C of the interior: (C local rows into I, N(C) into B)


def _structure(part: Any, partition: Partition, gauge: int) -> _Structure:
    """S_r = Q_BB − Σ_C Q_BC Q_CC⁻¹ Q_CB: Q_BB has a block per boundary edge and the diagonal;
    each connected piece C of the interior fills a dense block on its boundary neighbours N(C)
    and nothing else (the pieces are independent), so only those blocks travel."""
    from scipy.sparse.csgraph import connected_components

    B = boundary(part, gauge)
    I = np.setdiff1d(part.vertices, np.concatenate([part.separators, [gauge]]))
    e = partition.edges[np.concatenate([part.intra_edges, part.inter_edges])]
    e = e[(e != gauge).all(axis=1)]
    inB, inI = np.isin(e, B), np.isin(e, I)
    bb = np.sort(np.searchsorted(B, e[inB.all(axis=1)]), axis=1)
    diag = np.repeat(np.arange(B.size)[:, None], 2, axis=1)
    pairs = np.unique(np.concatenate([diag, bb]), axis=0)
    ii = np.searchsorted(I, e[inI.all(axis=1)])
    adj = sp.coo_matrix((np.ones(len(ii)), (ii[:, 0], ii[:, 1])), shape=(I.size, I.size))
    ncomp, label = connected_components(adj, directed=False) if I.size else (0, np.zeros(0, int))
    ib = e[inI.any(axis=1) & inB.any(axis=1)]
    i_end = np.where(np.isin(ib[:, 0], I), ib[:, 0], ib[:, 1])
    b_end = np.where(np.isin(ib[:, 0], I), ib[:, 1], ib[:, 0])
    comp_of_edge = label[np.searchsorted(I, i_end)]
    comps = []
    for c in range(ncomp):
        N = np.unique(np.searchsorted(B, b_end[comp_of_edge == c]))
        comps.append((np.flatnonzero(label == c), N))
    return _Structure(B, I, pairs, tuple(comps))


def _structure_floats(st: _Structure, b: int, ncol: int) -> int:
    """Floats of ``_pack``: header, ids, right-hand side, Q_BB blocks, interior-piece blocks."""
    n = 4 + st.B.size * (1 + b * ncol) + len(st.pairs) * (2 + b * b)
    for _, N in st.comps:
        k = N.size * b
        n += 1 + N.size + k * (k + 1) // 2
    return n


def direct_floats(partition: Partition, b: int, ncol: int, gauge: int, tree: RobotTree) -> int:
    """Floats the direct solve sends: each robot's condensed system times its depth (forwarded
    up the tree), plus the separator values scattered down."""
    total = 0
    for part in partition.parts:
        depth = int(tree.depth[part.robot_id])
        if depth:
            total += depth * _structure_floats(_structure(part, partition, gauge), b, ncol)
    for r in range(partition.num_robots):
        if r == tree.root:
            continue
        need = np.unique(
            np.concatenate([boundary(partition.parts[q], gauge) for q in tree.subtree(r)])
        )
        total += need.size * b * ncol
    return total


def iteration_floats(partition: Partition, b: int, ncol: int) -> int:
    """Floats of one block iteration in which every separator is sent to every neighbour."""
    return sum(v.size for p in partition.parts for v in p.separators_for.values()) * b * ncol


# The rows of the b-row blocks of vertices ``positions`` in a stacked X (one definition, the
# linear stages'): ``expand(positions, b)``.
expand = block_rows


def _positive_pivots(lu: Any) -> bool:
    """A SuperLU factor (no pivoting, symmetric mode) of an SPD matrix: all pivots positive;
    None (an empty block) counts as positive definite."""
    return lu is None or bool(np.all(lu.U.diagonal() > 0))


@dataclass
class Condensed:
    """One robot's share of a block-sparse SPD system condensed onto its boundary."""

    st: _Structure
    lu: Any  # scipy SuperLU of the interior block, None without an interior
    Q_IB: sp.csr_matrix
    rhs_I: np.ndarray
    Q_BB: np.ndarray  # (p, b, b) blocks at st.pairs
    pieces: list[np.ndarray]  # per interior piece: dense −Q_NC Q_CC⁻¹ Q_CN on N(C)
    g: np.ndarray

    @property
    def B(self) -> np.ndarray:
        return self.st.B

    @property
    def I(self) -> np.ndarray:
        return self.st.I

    @property
    def positive_definite(self) -> bool:
        """The interior block's LU pivots (no pivoting, symmetric mode) are all positive."""
        return _positive_pivots(self.lu)

    def back_substitute(self, X_B: np.ndarray) -> np.ndarray:
        """Interior values ``X_I = (Q⁽ʳ⁾_II)⁻¹ (rhs_I − Q_IB X_B)`` for boundary values X_B."""
        if not self.I.size:
            return self.rhs_I
        X_I: np.ndarray = self.lu.solve(self.rhs_I - self.Q_IB @ X_B)
        return X_I

    def with_rhs(self, rhs: np.ndarray) -> Condensed:
        """The same (frozen) interior factor with a new right-hand side ``rhs`` (n·b rows, the
        gauge held at zero): ``g_r = rhs_B − Q_BI (Q_II)⁻¹ rhs_I``, no new factorisation."""
        b = self.Q_BB.shape[-1]  # (p, b, b), also with no pairs
        rb, ri = expand(self.B, b), expand(self.I, b)
        g = rhs[rb].copy()
        if ri.size:
            g -= self.Q_IB.T @ self.lu.solve(rhs[ri])
        return replace(self, rhs_I=rhs[ri], g=g)


def condense(
    part: Any,
    partition: Partition,
    Q: sp.spmatrix,
    rhs: np.ndarray,
    b: int,
    gauge: int,
    X_gauge: np.ndarray,
) -> Condensed:
    """Robot's share ``Q⁽ʳ⁾ X = rhs⁽ʳ⁾`` (n·b square, its own and anchor vertices only; block
    size b) condensed onto its boundary, the gauge vertex held at ``X_gauge``. The interior
    block must be positive definite (no pivoting)."""
    Q = sp.csr_matrix(Q)
    rhs = rhs - Q[:, expand(np.array([gauge]), b)] @ X_gauge
    st = _structure(part, partition, gauge)
    rb, ri = expand(st.B, b), expand(st.I, b)
    Q_B = Q[rb][:, rb]
    Q_BB = (
        np.stack([Q_B[i * b : (i + 1) * b][:, j * b : (j + 1) * b].toarray() for i, j in st.pairs])
        if len(st.pairs)
        else np.zeros((0, b, b))
    )
    g, lu, Q_IB, pieces = rhs[rb].copy(), None, sp.csr_matrix((ri.size, rb.size)), []
    if ri.size:
        lu = spla.splu(
            sp.csc_matrix(Q[ri][:, ri]),
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
        Q_IB = Q[ri][:, rb].tocsr()
        Y = lu.solve(np.column_stack([Q_IB.toarray(), rhs[ri]]))
        for C, N in st.comps:  # Y is zero outside each piece's own rows and neighbours
            rc, rn = expand(C, b), expand(N, b)
            Qc = Q_IB[rc][:, rn].toarray()
            P = -Qc.T @ Y[rc][:, rn]
            pieces.append(0.5 * (P + P.T))
            g[rn] -= Qc.T @ Y[rc, rb.size :]
    return Condensed(st, lu, Q_IB, rhs[ri], Q_BB, pieces, g)


def _stage_share(
    part: Any, n: int, b: int, edges: np.ndarray, M: np.ndarray, c: np.ndarray, w: np.ndarray
) -> tuple[sp.csr_matrix, np.ndarray]:
    """Robot's share of a linear init stage: its edges, inter-robot ones at half weight."""
    from dran_edge.dran.linear_stage import normal_equations

    eidx = np.concatenate([part.intra_edges, part.inter_edges])
    scale = np.concatenate([np.ones(part.intra_edges.size), np.full(part.inter_edges.size, 0.5)])
    Q, Bv = normal_equations(n, b, edges[eidx], M[eidx], c[eidx], w[eidx] * scale)
    return Q.tocsr(), Bv


def pack(loc: Condensed, b: int, scalars: Any = ()) -> np.ndarray:
    """The condensed system as one float vector (docs/wire-format.md, SCHUR stages), followed
    by ``scalars`` (values that travel with it, e.g. the robot's cost share)."""
    st = loc.st
    out = [[st.B.size], st.B.astype(float), loc.g.ravel(), [len(st.pairs)]]
    for (i, j), blk in zip(st.pairs, loc.Q_BB):
        out += [[i, j], blk.ravel()]
    out.append([len(st.comps)])
    for (_, N), P in zip(st.comps, loc.pieces):
        out += [[N.size], N.astype(float), P[np.triu_indices(P.shape[0])]]
    out.append(np.asarray(scalars, float))
    return np.concatenate([np.asarray(x, float) for x in out])


def _unpack(
    flat: np.ndarray, b: int, ncol: int, nscalars: int = 0
) -> tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
    """(B ids, g, pieces, scalars): the condensed system as (boundary-local indices, dense
    block) terms, and the ``nscalars`` values after it."""
    pos = 0

    def take(k: int) -> np.ndarray:
        nonlocal pos
        pos += k
        if pos > flat.size:
            raise ValueError("truncated condensed system")
        return flat[pos - k : pos]

    nb = int(round(take(1)[0]))
    B = np.rint(take(nb)).astype(np.int64)
    g = take(nb * b * ncol).reshape(nb * b, ncol)
    pieces: list[tuple[np.ndarray, np.ndarray]] = []
    for _ in range(int(round(take(1)[0]))):
        i, j = np.rint(take(2)).astype(np.int64)
        blk = take(b * b).reshape(b, b)
        if i == j:
            pieces.append((np.array([i]), blk))
        else:
            pieces.append(
                (np.array([i, j]), np.block([[np.zeros((b, b)), blk], [blk.T, np.zeros((b, b))]]))
            )
    for _ in range(int(round(take(1)[0]))):
        nn = int(round(take(1)[0]))
        N = np.rint(take(nn)).astype(np.int64)
        k = nn * b
        P = np.zeros((k, k))
        P[np.triu_indices(k)] = take(k * (k + 1) // 2)
        pieces.append((N, P + np.triu(P, 1).T))
    return B, g, pieces, take(nscalars).copy()


def missing(what: str) -> None:
    raise RuntimeError(
        f"substructured solve: {what} (a lost datagram?); it needs every "
        "message delivered: over lossy links send it through a reliable exchange "
        "(selective-repeat ARQ) or use InitParams(direct='never')"
    )


def _chunks(flat: np.ndarray, d: int) -> list[np.ndarray]:
    """The packed vector, prefixed by its length, cut into d×d chunks (the last zero-padded)."""
    flat = np.concatenate([[flat.size], flat])
    size = d * d
    pad = np.zeros(-(-flat.size // size) * size)
    pad[: flat.size] = flat
    return list(pad.reshape(-1, d, d))


def unchunk(entries: Iterable[Any], kind: InitStage, where: str) -> dict[int, np.ndarray]:
    """The packed vectors (``_chunks``) that ``entries`` of stage ``kind`` carry, by
    ``owner_robot``; a duplicated datagram repeats a chunk (keyed by its index), a missing one
    raises (``missing``: ``where`` names the receiver)."""
    parts: dict[int, dict[int, np.ndarray]] = {}
    for e in entries:
        if InitStage(e.stage) == kind:
            parts.setdefault(int(e.owner_robot), {})[int(e.keyframe_id)] = np.asarray(
                e.value, float
            ).ravel()
    out = {}
    for o, by_index in parts.items():
        chunks = sorted(by_index.items())
        flat = np.concatenate([v for _, v in chunks])
        if [k for k, _ in chunks] != list(range(len(chunks))) or flat.size < 1 + int(
            round(flat[0])
        ):
            missing(f"the vector of robot {o} ({kind.name}) reached {where} incomplete")
        out[o] = flat[1 : 1 + int(round(flat[0]))]
    return out


def gather(
    tree: RobotTree, packed: list[np.ndarray], d: int, exchange: Any, kind: InitStage, rounds: int
) -> tuple[dict[int, np.ndarray], int]:
    """Step 1 (module docstring): every robot's packed vector travels up the tree as ``kind``
    chunks (d × d); returns the root's ``{origin robot: packed vector}`` and the rounds count."""
    R = len(packed)
    bundles = [{r: packed[r]} for r in range(R)]
    for level in range(tree.height, 0, -1):
        outgoing: dict[int, list[Any]] = {}
        for r in np.flatnonzero(tree.depth == level):
            entries = [
                InitEntry(kind, int(o), k, ch)
                for o, flat in sorted(bundles[r].items())
                for k, ch in enumerate(_chunks(flat, d))
            ]
            outgoing[int(r)] = [(int(tree.parent[r]), entries)]
        incoming = exchange(kind, rounds, outgoing)
        rounds += 1
        for q, entries in incoming.items():
            for o, flat in unchunk(entries, kind, f"robot {q}").items():
                bundles[q][o] = flat
    if len(bundles[tree.root]) != R:
        missing(
            f"the root (robot {tree.root}) lacks the condensed systems of robots "
            f"{sorted(set(range(R)) - set(bundles[tree.root]))}"
        )
    return bundles[tree.root], rounds


@dataclass
class Interface:
    """The root's assembled interface system ``Σ S_r`` (factorised once), kept so that later
    right-hand sides ``Σ g_r`` solve with the same factor (a frozen-Hessian step)."""

    Bglob: np.ndarray  # every boundary vertex (sorted)
    at: dict[int, np.ndarray]  # per origin robot: its B's positions in Bglob
    lu: Any  # scipy SuperLU of Σ S_r, None without a boundary
    b: int

    @property
    def positive_definite(self) -> bool:
        """Its LU pivots (no pivoting, symmetric mode) are all positive."""
        return _positive_pivots(self.lu)

    def solve(self, gs: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """``{boundary vertex: (b, ncol) value}`` of ``(Σ S_r) X_B = Σ g_r``, ``gs`` the
        (|B_r|·b, ncol) right-hand sides by origin robot."""
        b, ncol = self.b, next(iter(gs.values())).shape[1]
        g_glob = np.zeros((self.Bglob.size * b, ncol))
        for o, g in gs.items():
            np.add.at(g_glob, expand(self.at[o], b), g)
        X_B = self.lu.solve(g_glob) if self.lu is not None else g_glob
        X_B = X_B.reshape(self.Bglob.size, b, ncol)
        return {int(v): X_B[k] for k, v in enumerate(self.Bglob.tolist())}


def factor_interface(
    bundle: dict[int, np.ndarray], b: int, ncol: int, nscalars: int = 0
) -> tuple[Interface, dict[int, np.ndarray], np.ndarray]:
    """Step 2's assembly: the root's ``Σ S_r`` factorised from the gathered vectors; returns it,
    the right-hand sides ``g_r`` by origin robot and the (R, nscalars) scalars by robot."""
    unpacked = {o: _unpack(bundle[o], b, ncol, nscalars) for o in sorted(bundle)}
    Bglob = np.unique(np.concatenate([u[0] for u in unpacked.values()]))
    at = {o: np.searchsorted(Bglob, u[0]) for o, u in unpacked.items()}
    rows, cols, vals = [], [], []
    for o, (_, _, pieces, _) in unpacked.items():
        for loc_idx, P in pieces:
            idx = expand(at[o][loc_idx], b)
            rows.append(np.repeat(idx, idx.size))
            cols.append(np.tile(idx, idx.size))
            vals.append(P.ravel())
    lu = None
    if Bglob.size:
        S_glob = sp.csc_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(Bglob.size * b,) * 2,
        )
        lu = spla.splu(
            S_glob,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
    scalars = np.array([u[3] for u in unpacked.values()]).reshape(len(unpacked), nscalars)
    gs = {o: u[1] for o, u in unpacked.items()}
    return Interface(Bglob, at, lu, b), gs, scalars


def solve_interface(
    bundle: dict[int, np.ndarray], b: int, ncol: int, nscalars: int = 0
) -> tuple[dict[int, np.ndarray], np.ndarray, bool]:
    """Step 2: the root assembles ``Σ S_r``, ``Σ g_r`` from the gathered vectors and solves;
    returns ``{boundary vertex: (b, ncol) value}``, the (R, nscalars) scalars by robot and
    whether ``Σ S_r`` is positive definite (its LU pivots, no pivoting, all positive)."""
    iface, gs, scalars = factor_interface(bundle, b, ncol, nscalars)
    return iface.solve(gs), scalars, iface.positive_definite


def scatter(
    tree: RobotTree,
    boundaries: list[np.ndarray],
    root_values: dict[int, np.ndarray],
    exchange: Any,
    kind: InitStage,
    to_entry: Callable[..., InitEntry],
    from_entry: Callable[[InitEntry], np.ndarray],
    rounds: int,
    extra: list[Any] | None = None,
) -> tuple[list[dict[int, np.ndarray]], list[list[Any]], int]:
    """Step 3: each link carries the boundary values its subtree needs as ``kind`` entries
    (``to_entry(v, X_v)`` / ``from_entry(entry)``), plus the root's ``extra`` entries (which
    every robot receives). Returns per robot ``{vertex: value}`` and its extra entries."""
    R = len(boundaries)
    known: list[dict[int, np.ndarray]] = [dict() for _ in range(R)]
    known[tree.root] = dict(root_values)
    others: list[dict[Any, Any]] = [
        dict() for _ in range(R)
    ]  # keyed: a duplicated datagram repeats
    others[tree.root] = {
        (int(e.stage), int(e.owner_robot), int(e.keyframe_id)): e for e in extra or []
    }
    for level in range(1, tree.height + 1):
        outgoing: dict[int, list[Any]] = {}
        for c in np.flatnonzero(tree.depth == level):
            p = int(tree.parent[c])
            need = np.unique(np.concatenate([boundaries[q] for q in tree.subtree(int(c))]))
            outgoing.setdefault(p, []).append(
                (
                    int(c),
                    [to_entry(int(v), known[p][int(v)]) for v in need.tolist()]
                    + list(others[p].values()),
                )
            )
        incoming = exchange(kind, rounds, outgoing)
        rounds += 1
        for q, entries in incoming.items():
            for e in entries:
                if InitStage(e.stage) == kind:
                    known[q][int(e.keyframe_id)] = from_entry(e)
                else:
                    others[q][(int(e.stage), int(e.owner_robot), int(e.keyframe_id))] = e
    for r, B in enumerate(boundaries):
        lost = [int(v) for v in B.tolist() if int(v) not in known[r]]
        if lost:
            missing(f"robot {r} did not receive the boundary values {lost[:5]}")
    return known, [list(o.values()) for o in others], rounds


def boundary_values(loc: Condensed, known: dict[int, np.ndarray], ncol: int) -> np.ndarray:
    """The (|B|·b, ncol) stacked values of the robot's boundary from ``known``."""
    return (
        np.concatenate([known[int(v)] for v in loc.B.tolist()])
        if loc.B.size
        else np.zeros((0, ncol))
    )


def solve_direct(
    partition: Partition,
    n: int,
    b: int,
    d: int,
    edges: np.ndarray,
    M: np.ndarray,
    c_of: Callable[[int], np.ndarray],
    w: np.ndarray,
    gauge: int,
    X_gauge: np.ndarray,
    exchange: Any,
    schur_kind: InitStage,
    value_kind: InitStage,
    to_entry: Callable[..., InitEntry],
    from_entry: Callable[[InitEntry], np.ndarray],
    X0: np.ndarray,
    tree: RobotTree | None = None,
) -> tuple[list[np.ndarray], int]:
    """Solve the stage exactly (module docstring). Returns each robot's view ((n·b, ncol):
    its own vertices and anchors solved, the rest ``X0``) and the rounds used. ``to_entry(v,
    X_v)`` / ``from_entry(entry)`` convert one separator value to / from its init entry."""
    ncol = X0.shape[1]
    tree = tree or robot_tree(partition)
    locs = []
    for p in partition.parts:
        Q, rhs = _stage_share(p, n, b, edges, M, c_of(p.robot_id), w)
        locs.append(condense(p, partition, Q, rhs, b, gauge, X_gauge))
    bundle, rounds = gather(tree, [pack(loc, b) for loc in locs], d, exchange, schur_kind, 0)
    root_values, _, _ = solve_interface(bundle, b, ncol)
    known, _, rounds = scatter(
        tree,
        [loc.B for loc in locs],
        root_values,
        exchange,
        value_kind,
        to_entry,
        from_entry,
        rounds,
    )
    views = []  # 4. back-substitution of each robot's interior
    for r, loc in enumerate(locs):
        view = X0.copy()
        view[expand(np.array([gauge]), b)] = X_gauge
        Xb = boundary_values(loc, known[r], ncol)
        view[expand(loc.B, b)] = Xb
        if loc.I.size:
            view[expand(loc.I, b)] = loc.back_substitute(Xb)
        views.append(view)
    return views, rounds
