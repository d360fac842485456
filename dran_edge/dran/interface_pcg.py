r"""The refinement's interface system solved by conjugate gradients over the robot tree, instead of
gathering every robot's dense condensed system (``RefineParams.interface="pcg"``; docs/dran.md,
"Iterative interface solve").

The exact refinement (``dran_edge.dran.exact_gn``) needs ``δ_B`` of ``S δ_B = g_B`` with
``S = Σ_r R_rᵀ S_r R_r`` (R_r: restriction to robot r's boundary B_r). The dense gather sends
every S_r (|B_r|² floats; on sphere2500, 5 robots, ~2.8 MB a step). Here S_r stays with its robot
and the root runs preconditioned CG, each iteration two round trips of boundary vectors:

- ``q = S p``: down p restricted to B_r, up ``S_r p_r`` (the robot applies its own S_r);
- the preconditioner, balancing Neumann–Neumann (Mandel 1993) with a coarse space:

      M⁻¹ = Σ_r R_rᵀ D_r S_r⁻¹ D_r R_r        (one-level: down ``u_r``, up ``D_r S_r⁻¹ D_r u_r``)
      P   = Z E⁻¹ Zᵀ + (I − Z E⁻¹ Zᵀ S) M⁻¹ (I − S Z E⁻¹ Zᵀ),   E = Zᵀ S Z

  D_r the partition of unity (1 / the number of robots whose boundary holds the vertex, so
  ``Σ_r R_rᵀ D_r R_r = I``), and ``Z = [R_rᵀ D_r N_r]_r`` with ``N_r`` the eigenvectors of
  ``S_r`` against its own 6×6 (3×3) block diagonal whose eigenvalue is below ``mode_tol``, which
  each robot computes from its own S_r (the near-rigid motions of each floating piece of a
  robot's map, which S_r alone barely resists: a GenEO-style coarse space).

The root holds Z and ``S Z``, gathered once per linearisation: every robot sends its N_r up, the
root sends each robot D_r and the other robots' columns where they overlap B_r, and every robot
sends ``S_r R_r Z`` for the columns that touch B_r. In a round trip each tree link carries its
subtree's boundary vertices once: down the values, up their partial sums ``Σ R_qᵀ v_q`` (a robot
adds its children's to its own; ``_Links``). The coarse solve and the projections happen at the
root.

Measured centrally in float64 on sphere2500 (5 robots, exact damped Newton steps from the
chordal init; the probe of docs/notes/generalisation.md): with 6 modes per robot 4–13 iterations
to a relative residual of 0.1 and 10–16 to 0.01 at every step, against 40–103 and 78–125 with
the one-level preconditioner alone and 11–33 to 0.01 with the block-diagonal one plus the same
coarse space. The refinement is an inexact Newton method then: a step solved to ``η`` leaves
about ``η`` of the error, so the LM rule's accept / reject still decides (on F).

Pure numpy/scipy; every value crosses the ``exchange`` (``dist_init.Exchange``) as
``REFINE_PCG_UP`` / ``REFINE_PCG_DOWN`` chunks (docs/wire-format.md), so the bus counts its bytes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg as sla

from dran_edge.dran import substructure
from dran_edge.messages import InitEntry, InitStage


def dense_S(loc: substructure.Condensed, b: int) -> np.ndarray:
    """A robot's condensed matrix ``S_r`` on its boundary, dense (|B_r|·b square)."""
    m = loc.B.size * b
    S = np.zeros((m, m))
    for (i, j), blk in zip(loc.st.pairs.tolist(), loc.Q_BB):
        S[i * b : (i + 1) * b, j * b : (j + 1) * b] += blk
        if i != j:
            S[j * b : (j + 1) * b, i * b : (i + 1) * b] += blk.T
    for (_, N), P in zip(loc.st.comps, loc.pieces):
        rn = substructure.expand(N, b)
        S[np.ix_(rn, rn)] += P
    return S


def soft_modes(S: np.ndarray, b: int, tol: float, k_max: int) -> np.ndarray:
    """The eigenvectors of ``S z = λ blockdiag(S) z`` with ``λ < tol`` (at most ``k_max``, the
    softest): (m, k). One floating piece of a robot's map gives ~6 (3 in 2D) near-zero λ (its
    rigid motions, resisted only through the boundary), well apart from the rest (measured:
    λ ≤ 2e-4 for those, ≥ 1e-3 next, on sphere2500 and interleaved splits), so the count
    follows the number of floating pieces."""
    m = S.shape[0]
    k = min(k_max, m)
    if k == 0:
        return np.zeros((m, 0))
    # the 6×6 (3×3) diagonal blocks, made positive definite (|λ|, floored): with the exact
    # Hessian a block can be indefinite
    diag = np.stack([S[i : i + b, i : i + b] for i in range(0, m, b)])
    lam_d, V_d = np.linalg.eigh(0.5 * (diag + np.swapaxes(diag, 1, 2)))
    mag = np.abs(lam_d)
    mag = np.maximum(mag, 1e-12 * max(float(mag.max(initial=0.0)), 1e-300))
    blocks = np.zeros_like(S)
    for j, i in enumerate(range(0, m, b)):
        blocks[i : i + b, i : i + b] = (V_d[j] * mag[j]) @ V_d[j].T
    lam, V = sla.eigh(0.5 * (S + S.T), blocks, subset_by_index=[0, k - 1])
    return np.asarray(V[:, lam < tol])


@dataclass
class RobotSide:
    """What robot r keeps for the solve: its S_r, the factor of S_r for the Neumann solves and
    the coarse columns it applies S_r to."""

    B: np.ndarray
    S: np.ndarray
    lu: Any
    modes: np.ndarray

    @classmethod
    def of(cls, loc: substructure.Condensed, b: int, tol: float, k_max: int) -> RobotSide:
        S = dense_S(loc, b)
        lu = sla.lu_factor(S) if S.size else None
        return cls(loc.B, S, lu, soft_modes(S, b, tol, k_max))

    def neumann(self, u: np.ndarray) -> np.ndarray:
        return sla.lu_solve(self.lu, u) if self.lu is not None else u


@dataclass
class PCGResult:
    values: dict[int, np.ndarray]
    """{boundary vertex: (b, 1) step} as ``substructure.Interface.solve`` returns it."""
    rounds: int
    iterations: int = 0
    residual: float = np.inf
    """‖g_B − S δ_B‖ / ‖g_B‖ at the end."""
    positive_definite: bool = True
    """False when CG met a direction of non-positive curvature, or a preconditioned residual
    with ``rᵀPr ≤ 0`` (the robots' S_r indefinite): no step is taken."""
    history: list[float] = field(default_factory=list)


def _pack_up(vectors: list[Any]) -> np.ndarray:
    """One float vector of the arrays ``vectors`` (raveled, in order)."""
    return np.concatenate([np.asarray(v, float).ravel() for v in vectors])


def _link_exchange(
    kind: InitStage,
    sends: dict[int, list[tuple[int, int, np.ndarray]]],
    d: int,
    exchange: Any,
    rounds: int,
) -> dict[int, dict[int, np.ndarray]]:
    """One exchange of packed vectors over tree links: ``sends[sender]`` lists ``(receiver,
    key, vector)``; returns ``{receiver: {key: vector}}`` (``key``: ``owner_robot``)."""
    per_link: dict[tuple[int, int], list[InitEntry]] = {}  # one message per link
    for sender, items in sends.items():
        for receiver, key, vec in items:
            per_link.setdefault((sender, receiver), []).extend(
                InitEntry(kind, key, k, ch) for k, ch in enumerate(substructure._chunks(vec, d))
            )
    outgoing: dict[int, list[Any]] = {}
    for (sender, receiver), entries in per_link.items():
        outgoing.setdefault(sender, []).append((receiver, entries))
    incoming = exchange(kind, rounds, outgoing)
    return {r: substructure.unchunk(es, kind, f"robot {r}") for r, es in incoming.items()}


def down(
    tree: substructure.RobotTree,
    packed: dict[int, np.ndarray],
    d: int,
    exchange: Any,
    rounds: int,
) -> tuple[dict[int, np.ndarray], int]:
    """The mirror of ``substructure.gather``: the root's per-robot vectors travel down the tree
    (each link carries those of its subtree) as ``REFINE_PCG_DOWN`` chunks (``owner_robot`` the
    destination). Returns every robot's vector (the root's own without a message)."""
    have: list[dict[int, np.ndarray]] = [dict() for _ in range(tree.parent.size)]
    have[tree.root] = dict(packed)
    for level in range(1, tree.height + 1):
        sends: dict[int, list[tuple[int, int, np.ndarray]]] = {}
        for c in np.flatnonzero(tree.depth == level).tolist():
            p = int(tree.parent[c])
            sends.setdefault(p, []).extend(
                (c, q, have[p][q]) for q in sorted(tree.subtree(c)) if q in have[p]
            )
        got = _link_exchange(InitStage.REFINE_PCG_DOWN, sends, d, exchange, rounds)
        rounds += 1
        for r, by_robot in got.items():
            have[r].update(by_robot)
    out = {r: have[r][r] for r in packed if r in have[r]}
    if len(out) != len(packed):
        substructure.missing("a robot did not receive its vector from the root")
    return out, rounds


class _Links:
    """Boundary vectors over the tree, one value per vertex and link: the link above robot c
    carries the vertices of its subtree's boundaries (``union[c]``); down, a robot forwards
    what its children need; up, it adds its own and its children's sums (the root only needs
    ``Σ_r R_rᵀ v_r``)."""

    def __init__(self, tree: substructure.RobotTree, Bs: list[np.ndarray], b: int):
        self.tree, self.b = tree, b
        self.union = {
            r: np.unique(np.concatenate([Bs[q] for q in tree.subtree(r)])) for r in range(len(Bs))
        }
        self.B = Bs

    def rows(self, inner: np.ndarray, outer: np.ndarray) -> np.ndarray:
        """Rows of the vertices ``inner`` (⊆ ``outer``) in a vector over ``outer``."""
        return substructure.expand(np.searchsorted(outer, inner), self.b)

    def down(
        self, x: np.ndarray, Bglob: np.ndarray, d: int, exchange: Any, rounds: int
    ) -> tuple[list[np.ndarray], int]:
        """The global vector ``x`` (over ``Bglob``, at the root) restricted to every robot's
        boundary, as each robot receives it."""
        t = self.tree
        have = {t.root: x[self.rows(self.union[t.root], Bglob)]}
        for level in range(1, t.height + 1):
            sends: dict[int, list[tuple[int, int, np.ndarray]]] = {}
            for c in np.flatnonzero(t.depth == level).tolist():
                p = int(t.parent[c])
                v = have[p][self.rows(self.union[c], self.union[p])]
                sends.setdefault(p, []).append((c, c, v))
            got = _link_exchange(InitStage.REFINE_PCG_DOWN, sends, d, exchange, rounds)
            rounds += 1
            for items in sends.values():
                for c, _, _ in items:
                    if c not in got.get(c, {}):
                        substructure.missing(f"robot {c} did not receive its boundary vector")
                    have[c] = got[c][c]
        return [have[r][self.rows(B, self.union[r])] for r, B in enumerate(self.B)], rounds

    def up(
        self, parts: list[np.ndarray], Bglob: np.ndarray, d: int, exchange: Any, rounds: int
    ) -> tuple[np.ndarray, int]:
        """``Σ_r R_rᵀ parts[r]`` at the root (over ``Bglob``), summed on the way up."""
        t = self.tree
        acc = {r: np.zeros(self.union[r].size * self.b) for r in range(len(parts))}
        for r, v in enumerate(parts):
            acc[r][self.rows(self.B[r], self.union[r])] += v
        for level in range(t.height, 0, -1):
            sends: dict[int, list[tuple[int, int, np.ndarray]]] = {}
            for c in np.flatnonzero(t.depth == level).tolist():
                sends[c] = [(int(t.parent[c]), c, acc[c])]
            got = _link_exchange(InitStage.REFINE_PCG_UP, sends, d, exchange, rounds)
            rounds += 1
            for c, [(p, _, _)] in sends.items():
                if c not in got.get(p, {}):
                    substructure.missing(f"robot {c}'s partial sum did not reach robot {p}")
                acc[p][self.rows(self.union[c], self.union[p])] += got[p][c]
        out = np.zeros(Bglob.size * self.b)
        out[self.rows(self.union[t.root], Bglob)] = acc[t.root]
        return out, rounds


class _Root:
    """The root's view of the interface: where every robot's boundary sits, and D_r."""

    def __init__(self, Bs: dict[int, np.ndarray], b: int):
        self.b = b
        self.Bglob = np.unique(np.concatenate([B for B in Bs.values()])) if Bs else np.zeros(0)
        self.at = {r: np.searchsorted(self.Bglob, B) for r, B in Bs.items()}
        count = np.zeros(self.Bglob.size)
        for idx in self.at.values():
            count[idx] += 1
        self.weight = {r: np.repeat(1.0 / count[idx], b) for r, idx in self.at.items()}
        self.rows = {r: substructure.expand(idx, b) for r, idx in self.at.items()}
        self.n = self.Bglob.size * b

    def assemble(self, parts: dict[int, np.ndarray]) -> np.ndarray:
        """``Σ_r R_rᵀ parts[r]`` over the interface."""
        x = np.zeros(self.n)
        for r, v in parts.items():
            np.add.at(x, self.rows[r], v)
        return x


def _coarse_space(
    tree: substructure.RobotTree,
    sides: list[RobotSide],
    root: _Root,
    exchange: Any,
    rounds: int,
    d: int,
) -> tuple[np.ndarray, np.ndarray, int]:
    """(Z, S Z, rounds) at the root. Up: every robot's soft modes N_r. Down: to every robot its
    weights D_r and the other robots' columns where they overlap its boundary. Up: ``S_r`` times
    the columns touching its boundary (its own ``D_r N_r`` among them), in robot order."""
    b = root.b
    wire = [s.modes.astype(np.float32).astype(np.float64) for s in sides]  # N_r as it travels
    up = [_pack_up([np.array([N.shape[1]]), N]) for N in wire]
    bundle, rounds = substructure.gather(tree, up, d, exchange, InitStage.REFINE_PCG_UP, rounds)
    blocks: list[np.ndarray] = []  # Z's columns, robot by robot
    first: list[int] = []
    for r, s in enumerate(sides):
        k = int(round(bundle[r][0]))
        Zr = np.zeros((root.n, k))
        Zr[root.rows[r]] = root.weight[r][:, None] * bundle[r][1:].reshape(s.B.size * b, k)
        first.append(sum(blk.shape[1] for blk in blocks))
        blocks.append(Zr)
    Z = np.hstack(blocks) if blocks else np.zeros((root.n, 0))
    shared = {  # robot r -> [(q, positions in B_r of B_r ∩ B_q)]
        r: [
            (q, np.flatnonzero(np.isin(sides[r].B, sides[q].B)))
            for q in range(len(sides))
            if q != r and np.isin(sides[r].B, sides[q].B).any() and blocks[q].shape[1]
        ]
        for r in range(len(sides))
    }
    packed = {}
    for r, s in enumerate(sides):
        parts: list[np.ndarray] = [root.weight[r][::b]]
        for q, pos in shared[r]:
            rows = root.rows[r][substructure.expand(pos, b)]
            span = slice(first[q], first[q] + blocks[q].shape[1])
            parts += [np.array([q, blocks[q].shape[1], pos.size]), pos, Z[rows, span]]
        packed[r] = _pack_up(parts)
    got, rounds = down(tree, packed, d, exchange, rounds)
    mine = []
    for r, s in enumerate(sides):
        flat, nb = got[r], s.B.size
        w = np.repeat(flat[:nb], b)
        by_robot = {r: w[:, None] * wire[r]}
        at = nb
        while at < flat.size:  # [q, k, m, m positions, the m·b × k values]
            q, k, m = (int(round(v)) for v in flat[at : at + 3])
            pos = np.rint(flat[at + 3 : at + 3 + m]).astype(np.int64)
            Zq = np.zeros((nb * b, k))
            Zq[substructure.expand(pos, b)] = flat[at + 3 + m : at + 3 + m + m * b * k].reshape(
                m * b, k
            )
            by_robot[q] = Zq
            at += 3 + m + m * b * k
        qs = sorted(by_robot)
        mine.append((qs, s.S @ np.hstack([by_robot[q] for q in qs])))
    bundle, rounds = substructure.gather(
        tree, [SZr.ravel() for _, SZr in mine], d, exchange, InitStage.REFINE_PCG_UP, rounds
    )
    SZ = np.zeros_like(Z)
    for r, (qs, _) in enumerate(mine):
        idx = np.concatenate(
            [np.arange(first[q], first[q] + blocks[q].shape[1]) for q in qs]
        ).astype(np.int64)
        if idx.size:
            SZ[np.ix_(root.rows[r], idx)] += bundle[r].reshape(root.rows[r].size, idx.size)
    return Z, SZ, rounds


def solve(
    tree: substructure.RobotTree,
    sides: list[RobotSide],
    gs: dict[int, np.ndarray],
    exchange: Any,
    rounds: int,
    b: int,
    d: int,
    eta: float,
    max_iter: int,
) -> PCGResult:
    """``δ_B`` of ``(Σ S_r) δ_B = Σ g_r`` to the relative residual ``eta`` (module docstring).
    ``sides[r]`` is robot r's (held by robot r only), ``gs`` the root's gathered right-hand
    sides by robot. Setup: the soft modes up, D_r and the overlapping coarse columns down,
    ``S_r R_r Z`` up; then CG, two round trips per iteration (one to start)."""
    root = _Root({r: s.B for r, s in enumerate(sides)}, b)
    Z, SZ, rounds = _coarse_space(tree, sides, root, exchange, rounds, d)
    E = Z.T @ SZ
    Einv = np.linalg.pinv(0.5 * (E + E.T), rcond=1e-12) if E.size else E

    links = _Links(tree, [s.B for s in sides], b)

    def round_trip(x: np.ndarray, neumann: bool) -> np.ndarray:
        """Down ``x`` restricted to every boundary, up ``Σ_r R_rᵀ S_r x_r`` (or, ``neumann``,
        ``Σ_r R_rᵀ D_r S_r⁻¹ D_r x_r``: every robot knows its D_r)."""
        nonlocal rounds
        got, rounds = links.down(x, root.Bglob, d, exchange, rounds)
        back = [
            root.weight[r] * s.neumann(root.weight[r] * got[r]) if neumann else s.S @ got[r]
            for r, s in enumerate(sides)
        ]
        total, rounds = links.up(back, root.Bglob, d, exchange, rounds)
        return total

    def apply_P(res: np.ndarray) -> np.ndarray:
        """The balancing preconditioner (module docstring); one round trip."""
        a = Einv @ (Z.T @ res)
        y = round_trip(res - SZ @ a, neumann=True)
        out: np.ndarray = Z @ a + y - Z @ (Einv @ (SZ.T @ y))
        return out

    g = root.assemble(gs)
    out = PCGResult({}, rounds)
    x = np.zeros(root.n)
    g_norm = float(np.linalg.norm(g))
    if g_norm == 0.0:
        out.residual = 0.0
    else:
        res_vec = g.copy()
        z = apply_P(res_vec)
        p = z.copy()
        rz = float(res_vec @ z)
        for it in range(1, max_iter + 1):
            if not rz > 0.0:  # the preconditioner is not positive definite here (exact Hessian)
                out.positive_definite = False
                break
            q = round_trip(p, neumann=False)
            curvature = float(p @ q)
            if not curvature > 0.0:
                out.positive_definite = False
                break
            alpha = rz / curvature
            x += alpha * p
            res_vec -= alpha * q
            out.iterations = it
            out.residual = float(np.linalg.norm(res_vec)) / g_norm
            out.history.append(out.residual)
            if out.residual <= eta:
                break
            z = apply_P(res_vec)
            rz, rz_old = float(res_vec @ z), rz
            p = z + (rz / rz_old) * p
    out.rounds = rounds
    X = x.reshape(-1, b)
    out.values = {int(v): X[k].reshape(b, 1) for k, v in enumerate(root.Bglob.tolist())}
    return out
