"""Exact distributed solve of one linear stage of the initialisation by substructuring
(static condensation over the robot graph): the direct alternative to the block iterations of
``dran_edge.dist_init``.

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
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from dran_edge.messages import InitEntry, InitStage
from dran_edge.partition import Partition


@dataclass(frozen=True)
class RobotTree:
    """BFS spanning tree of the robot graph: ``parent[root] = -1``."""

    root: int
    parent: np.ndarray
    depth: np.ndarray
    children: tuple

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


def _bfs(adj: list, root: int) -> np.ndarray:
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


def robot_tree(partition: Partition) -> RobotTree:
    """BFS tree rooted at a centre of the robot graph (least eccentricity, lowest id)."""
    R = partition.num_robots
    adj = [sorted(p.neighbours) for p in partition.parts]
    ecc = [int(_bfs(adj, r).max()) for r in range(R)]
    root = int(np.argmin(ecc))
    depth = _bfs(adj, root)
    if np.any(depth < 0):
        raise ValueError("the robot graph is not connected")
    parent = np.full(R, -1)
    for r in range(R):
        if r != root:
            parent[r] = min(q for q in adj[r] if depth[q] == depth[r] - 1)
    children = tuple(tuple(int(c) for c in np.flatnonzero(parent == r)) for r in range(R))
    return RobotTree(root, parent, depth, children)


def boundary(part, gauge: int) -> np.ndarray:
    """Robot's boundary vertices B_r: its separators and anchors, without the gauge."""
    B = np.union1d(part.separators, part.anchors)
    return B[B != gauge]


def direct_floats(partition: Partition, b: int, ncol: int, gauge: int, tree: RobotTree) -> int:
    """Floats the direct solve sends: each S_r, g_r and id list times its depth (forwarded up
    the tree), plus the separator values scattered down."""
    total = 0
    for part in partition.parts:
        nb = boundary(part, gauge).size
        k = nb * b
        total += int(tree.depth[part.robot_id]) * (1 + nb + k * ncol + k * (k + 1) // 2)
    for r in range(partition.num_robots):
        if r == tree.root:
            continue
        need = np.unique(np.concatenate([boundary(partition.parts[q], gauge)
                                         for q in tree.subtree(r)]))
        total += need.size * b * ncol
    return total


def iteration_floats(partition: Partition, b: int, ncol: int) -> int:
    """Floats of one block iteration in which every separator is sent to every neighbour."""
    return sum(v.size for p in partition.parts for v in p.separators_for.values()) * b * ncol


def _expand(positions: np.ndarray, b: int) -> np.ndarray:
    return (positions[:, None] * b + np.arange(b)[None]).ravel()


@dataclass
class _Local:
    B: np.ndarray  # boundary vertex positions
    I: np.ndarray  # interior vertex positions
    lu: object
    Q_IB: sp.csr_matrix
    rhs_I: np.ndarray
    S: np.ndarray
    g: np.ndarray


def _local(part, partition: Partition, n: int, b: int, edges, M, c, w, gauge: int,
           X_gauge: np.ndarray) -> _Local:
    """Robot's share Q⁽ʳ⁾ (inter-robot edges at half weight) condensed onto its boundary."""
    from dran_edge.dist_init import normal_equations

    eidx = np.concatenate([part.intra_edges, part.inter_edges])
    scale = np.concatenate([np.ones(part.intra_edges.size), np.full(part.inter_edges.size, 0.5)])
    Q, Bv = normal_equations(n, b, edges[eidx], M[eidx], c[eidx], w[eidx] * scale)
    Q = Q.tocsr()
    g_rows = _expand(np.array([gauge]), b)
    rhs = Bv - Q[:, g_rows] @ X_gauge
    Bd = boundary(part, gauge)
    I = np.setdiff1d(part.vertices, np.concatenate([part.separators, [gauge]]))
    rb, ri = _expand(Bd, b), _expand(I, b)
    Q_BB = Q[rb][:, rb].toarray()
    S, g, lu, Q_IB = Q_BB, rhs[rb], None, sp.csr_matrix((ri.size, rb.size))
    if ri.size:
        Q_II = sp.csc_matrix(Q[ri][:, ri])
        lu = spla.splu(Q_II, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
        Q_IB = Q[ri][:, rb].tocsr()
        Y = lu.solve(np.column_stack([Q_IB.toarray(), rhs[ri]]))
        S = Q_BB - Q_IB.T @ Y[:, :rb.size]
        g = rhs[rb] - Q_IB.T @ Y[:, rb.size:]
    return _Local(Bd, I, lu, Q_IB, rhs[ri], 0.5 * (S + S.T), g)


def _pack(loc: _Local, b: int) -> np.ndarray:
    k = loc.B.size * b
    iu = np.triu_indices(k)
    return np.concatenate([[loc.B.size], loc.B.astype(float), loc.g.ravel(), loc.S[iu]])


def _unpack(flat: np.ndarray, b: int, ncol: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    nb = int(round(flat[0]))
    B = np.rint(flat[1:1 + nb]).astype(np.int64)
    k = nb * b
    g = flat[1 + nb:1 + nb + k * ncol].reshape(k, ncol)
    S = np.zeros((k, k))
    S[np.triu_indices(k)] = flat[1 + nb + k * ncol:1 + nb + k * ncol + k * (k + 1) // 2]
    return B, g, S + np.triu(S, 1).T


def _packed_size(nb: float, b: int, ncol: int) -> int:
    k = int(round(nb)) * b
    return 1 + int(round(nb)) + k * ncol + k * (k + 1) // 2


def _missing(what: str) -> None:
    raise RuntimeError(f"substructured init stage: {what} (a lost datagram?); it needs every "
                       "message delivered: over lossy links use InitParams(direct='never')")


def _chunks(flat: np.ndarray, d: int) -> list[np.ndarray]:
    size = d * d
    pad = np.zeros(-(-flat.size // size) * size)
    pad[:flat.size] = flat
    return list(pad.reshape(-1, d, d))


def solve_direct(partition: Partition, n: int, b: int, d: int, edges: np.ndarray,
                 M: np.ndarray, c_of: Callable[[int], np.ndarray], w: np.ndarray, gauge: int,
                 X_gauge: np.ndarray, exchange, schur_kind: InitStage, value_kind: InitStage,
                 to_entry: Callable, from_entry: Callable, X0: np.ndarray,
                 tree: RobotTree | None = None) -> tuple[list[np.ndarray], int]:
    """Solve the stage exactly (module docstring). Returns each robot's view ((n·b, ncol):
    its own vertices and anchors solved, the rest ``X0``) and the rounds used. ``to_entry(v,
    X_v)`` / ``from_entry(entry)`` convert one separator value to / from its init entry."""
    R = partition.num_robots
    ncol = X0.shape[1]
    tree = tree or robot_tree(partition)
    locs = [_local(p, partition, n, b, edges, M, c_of(p.robot_id), w, gauge, X_gauge)
            for p in partition.parts]
    rounds = 0
    # 1. gather: bundles[r] = {origin robot: packed floats} known at r
    bundles = [{r: _pack(locs[r], b)} for r in range(R)]
    for level in range(tree.height, 0, -1):
        outgoing: dict[int, list] = {}
        for r in np.flatnonzero(tree.depth == level):
            entries = [InitEntry(schur_kind, int(o), k, ch)
                       for o, flat in sorted(bundles[r].items())
                       for k, ch in enumerate(_chunks(flat, d))]
            outgoing[int(r)] = [(int(tree.parent[r]), entries)]
        incoming = exchange(schur_kind, rounds, outgoing)
        rounds += 1
        for q, entries in incoming.items():
            parts: dict[int, dict] = {}
            for e in entries:  # a duplicated datagram repeats a chunk: keyed by its index
                if InitStage(e.stage) == schur_kind:
                    parts.setdefault(int(e.owner_robot), {})[int(e.keyframe_id)] = \
                        np.asarray(e.value, float).ravel()
            for o, by_index in parts.items():
                chunks = sorted(by_index.items())
                flat = np.concatenate([v for _, v in chunks])
                if [k for k, _ in chunks] != list(range(len(chunks))) or \
                        flat.size < _packed_size(flat[0], b, ncol):
                    _missing(f"robot {o}'s condensed system reached robot {q} incomplete")
                bundles[q][o] = flat
    # 2. the root assembles Σ S_r, Σ g_r and solves
    root = tree.root
    if len(bundles[tree.root]) != R:
        _missing(f"the root (robot {tree.root}) lacks the condensed systems of robots "
                 f"{sorted(set(range(R)) - set(bundles[tree.root]))}")
    unpacked = [_unpack(bundles[root][o], b, ncol) for o in range(R)]
    Bglob = np.unique(np.concatenate([u[0] for u in unpacked]))
    rows, cols, vals = [], [], []
    g_glob = np.zeros((Bglob.size * b, ncol))
    for B, g, S in unpacked:
        idx = _expand(np.searchsorted(Bglob, B), b)
        rows.append(np.repeat(idx, idx.size))
        cols.append(np.tile(idx, idx.size))
        vals.append(S.ravel())
        np.add.at(g_glob, idx, g)
    X_B = np.zeros_like(g_glob)
    if Bglob.size:
        S_glob = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                               shape=(Bglob.size * b,) * 2)
        X_B = spla.splu(S_glob, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                        options={"SymmetricMode": True}).solve(g_glob)
    X_B = X_B.reshape(Bglob.size, b, ncol)
    # 3. scatter: known[r] = {vertex: value} the robot holds
    known = [dict() for _ in range(R)]
    known[root] = {int(v): X_B[k] for k, v in enumerate(Bglob.tolist())}
    for level in range(1, tree.height + 1):
        outgoing = {}
        for c in np.flatnonzero(tree.depth == level):
            p = int(tree.parent[c])
            need = np.unique(np.concatenate([locs[q].B for q in tree.subtree(int(c))]))
            outgoing.setdefault(p, []).append(
                (int(c), [to_entry(int(v), known[p][int(v)]) for v in need.tolist()]))
        incoming = exchange(value_kind, rounds, outgoing)
        rounds += 1
        for q, entries in incoming.items():
            for e in entries:
                if InitStage(e.stage) == value_kind:
                    known[q][int(e.keyframe_id)] = from_entry(e)
    # 4. back-substitution of each robot's interior
    views = []
    for r, loc in enumerate(locs):
        lost = [int(v) for v in loc.B.tolist() if int(v) not in known[r]]
        if lost:
            _missing(f"robot {r} did not receive the separator values {lost[:5]}")
        view = X0.copy()
        view[_expand(np.array([gauge]), b)] = X_gauge
        Xb = np.concatenate([known[r][int(v)] for v in loc.B.tolist()]) if loc.B.size else \
            np.zeros((0, ncol))
        view[_expand(loc.B, b)] = Xb
        if loc.I.size:
            view[_expand(loc.I, b)] = loc.lu.solve(loc.rhs_I - loc.Q_IB @ Xb)
        views.append(view)
    return views, rounds
