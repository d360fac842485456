"""The bounded graph's factor store, and removing a node while keeping its information.

:class:`FactorStore` holds the factors (slot -> ``(p, q, Z, Σ, kind)``), their adjacency and the
dense marginalisation prior, and removes nodes over the caps as the module docstring of
:mod:`dran_edge.robot.keyframe_graph` explains: composition onto the most certain neighbour
for chain nodes, loop re-anchoring plus a Schur complement into the dense prior otherwise
(:class:`MarginalPrior`), and the prior's sparsified form for consumers without a dense-prior
factor. :class:`~dran_edge.robot.keyframe_graph.KeyframeGraph` is the subclass that owns the
node tables and turns events into factors. Pure: numpy only.

Size: over ~500 lines because node removal, the dense prior it feeds and the prior's sparsified
forms (for the agent, and a skeleton node leaving it) are one piece of algebra on one state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dran_edge import geometry as geo
from dran_edge.config import AgentConfig, GraphBounds
from dran_edge.robot.factor_algebra import (
    KIND_LOOP,
    KIND_NAMES,
    KIND_OBSERVATION,
    KIND_ODOMETRY,
    KIND_PRIOR,
    NONE,
    OBJ,
    _arrays,
    _whitening,
    compose_cov,
    fuse,
    invert_cov,
    split_weights,
)
from dran_edge.robot.archive import ArchivedPose, PoseArchive
from dran_edge.robot.skeleton import Skeleton
from dran_edge.solver.factors import BetweenFactors, PriorFactors, make_kernel

#: an archived pose whose variance exceeds this (m², rad²) carries no usable information
ARCHIVE_MAX_VARIANCE = 1e2
#: ... and one whose marginal information's smallest eigenvalue is below this share of its largest
ARCHIVE_MIN_EIGENVALUE = 1e-10

#: a factor: (p, q, Z, Σ, kind)
Factor = tuple[int, int, np.ndarray, np.ndarray, int]


@dataclass(frozen=True, eq=False)
class MarginalPrior:
    """Dense Gaussian on k variables left by marginalised nodes (a :class:`Factor` block, m = 1).

    Residual ``r = W δ + e`` with ``δ_i = Log(T_lin_i⁻¹ T_i)`` stacked [ρ, φ] per variable; its
    cost ½‖r‖² equals, to second order at ``T_lin``, the marginalised part of the problem
    (``WᵀW = H'``, ``Wᵀe = g'`` of the Schur complement). Jacobian of δ_i for the right
    perturbation: ``J_r⁻¹(δ_i)``.
    """

    variables: np.ndarray
    """(1, k) graph indices."""
    T_lin: np.ndarray
    """(k, 4, 4) linearisation points."""
    W: np.ndarray
    """(r, 6k)."""
    e: np.ndarray
    """(r,)."""
    kernel: None = None
    label: str = "marginal"

    def _delta(self, poses: np.ndarray) -> np.ndarray:
        return geo.se3_log(geo.se3_between(self.T_lin, poses[self.variables[0]]))

    def residuals(self, poses: np.ndarray) -> np.ndarray:
        return (self.W @ self._delta(poses).ravel() + self.e)[None]

    def linearize(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self._delta(poses)
        k, rdim = d.shape[0], self.W.shape[0]
        J = self.W.reshape(rdim, k, 6).transpose(1, 0, 2) @ geo.se3_right_jacobian_inv(d)
        return (self.W @ d.ravel() + self.e)[None], J[None]


def _blockdiag_bound(S: np.ndarray, block: int = 6) -> float:
    """The smallest c ≥ 1 with S ⪯ c·blockdiag(S) (6×6 blocks): the largest eigenvalue of
    D^-½ S D^-½, D = blockdiag(S); at most the number of blocks (Cauchy–Schwarz)."""
    k = S.shape[0] // block
    if k <= 1:
        return 1.0
    L = np.zeros_like(S)
    for i in range(k):
        sl = slice(block * i, block * i + block)
        lam, V = np.linalg.eigh(0.5 * (S[sl, sl] + S[sl, sl].T))
        L[sl, sl] = V @ np.diag(1.0 / np.sqrt(np.maximum(lam, 1e-300))) @ V.T
    return float(min(max(np.linalg.eigvalsh(L @ S @ L)[-1], 1.0), k))


def _dense_normal_equations(
    blocks: list, n_vars: int, poses: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Dense JᵀJ and Jᵀr (IRLS-weighted) of a few factor blocks over ``n_vars`` SE(3) variables."""
    H = np.zeros((6 * n_vars, 6 * n_vars))
    g = np.zeros(6 * n_vars)
    for block in blocks:
        r, J = block.linearize(poses)
        if block.kernel is not None:
            sw = np.sqrt(block.kernel.weight(np.sum(r * r, axis=1)))
            r, J = r * sw[:, None], J * sw[:, None, None, None]
        m, k, rd, _ = J.shape
        Jf = J.transpose(0, 2, 1, 3).reshape(m, rd, 6 * k)
        idx = (np.asarray(block.variables)[:, :, None] * 6 + np.arange(6)).reshape(m, 6 * k)
        np.add.at(H, (idx[:, :, None], idx[:, None, :]), np.swapaxes(Jf, 1, 2) @ Jf)
        np.add.at(g, idx, np.einsum("mrc,mr->mc", Jf, r))
    return H, g


def _from_archive(f: Factor) -> bool:
    """A factor the archive made: a loop turned into a factor between its new end and the
    archived keyframe's reference, an object (``(x, OBJ + id)``, the canonical order) or the
    world (unary, ``p = NONE``). Loops between nodes and objects are made by nothing else."""
    return f[4] == KIND_LOOP and (f[0] == NONE or f[1] >= OBJ)


def _is_node_loop(f: Factor) -> bool:
    """A loop between two kept nodes (one the archive can take over)."""
    return f[4] == KIND_LOOP and not _from_archive(f)


def _marginal_information(H: np.ndarray, sk: np.ndarray) -> np.ndarray | None:
    """The information of the entries ``sk`` of the normal equations ``H`` with the other
    entries eliminated (Schur complement, pseudo-inverse over their directions without
    information, which the entries ``sk`` must not touch); None when such a direction is coupled
    to them (their marginal is not finite)."""
    H = 0.5 * (H + H.T)
    sb = np.setdiff1d(np.arange(H.shape[0]), sk)
    Hkb = H[np.ix_(sk, sb)]
    lam_b, V = np.linalg.eigh(H[np.ix_(sb, sb)])
    null = lam_b <= ARCHIVE_MIN_EIGENVALUE * max(float(lam_b.max(initial=0.0)), 1e-300)
    coupled = np.linalg.norm(Hkb @ V[:, null], axis=0)
    if np.any(coupled > 1e-8 * max(float(np.linalg.norm(Hkb)), 1e-300)):
        return None
    Vr = V[:, ~null]
    M = H[np.ix_(sk, sk)] - (Hkb @ Vr) @ ((Hkb @ Vr) / lam_b[~null]).T
    return 0.5 * (M + M.T)


def _schur_out(
    keys: np.ndarray, poses: np.ndarray, H: np.ndarray, g: np.ndarray, i: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(keys, poses, H, g) with variable ``i`` Schur-complemented out."""
    sn = np.arange(6 * i, 6 * i + 6)
    sb = np.setdiff1d(np.arange(H.shape[0]), sn)
    Hnn = H[np.ix_(sn, sn)] + 1e-9 * np.eye(6)
    Hbn = H[np.ix_(sb, sn)]
    K = np.linalg.solve(Hnn, Hbn.T).T  # H_bn H_nn⁻¹
    return (
        np.delete(keys, i),
        np.delete(poses, i, axis=0),
        H[np.ix_(sb, sb)] - K @ Hbn.T,
        g[sb] - K @ g[sn],
    )


def _dense_prior(keys: np.ndarray, T_lin: np.ndarray, H: np.ndarray, g: np.ndarray) -> dict | None:
    """``½‖W δ + e‖²`` with ``WᵀW = H``, ``Wᵀe = g`` (null space dropped); None when H is 0."""
    lam, V = np.linalg.eigh(0.5 * (H + H.T))
    keep = lam > 1e-9 * max(float(lam.max(initial=0.0)), 1e-300)
    lam, V = lam[keep], V[:, keep]
    if not len(lam):
        return None
    return {
        "keys": keys,
        "T_lin": T_lin,
        "W": np.sqrt(lam)[:, None] * V.T,
        "e": (V.T @ g) / np.sqrt(lam),
    }


def _prior_without(prior: dict, key: int) -> dict | None:
    """A dense prior's exact marginal without variable ``key`` (Schur complement)."""
    W, e = prior["W"], prior["e"]
    i = int(np.searchsorted(prior["keys"], key))
    return _dense_prior(*_schur_out(prior["keys"], prior["T_lin"], W.T @ W, W.T @ e, i))


class FactorStore:
    """Factors, adjacency and the marginalisation prior of one bounded graph; node removal.

    The subclass sets the node tables annotated below and calls :meth:`_init_factors`."""

    config: AgentConfig
    bounds: GraphBounds
    marginalize: bool
    counters: dict[str, int]
    protected: set[int]
    node_stamp: dict[int, int]
    node_segment: dict[int, int]
    node_odom: dict[int, np.ndarray]
    node_est: dict[int, np.ndarray]
    node_cum: dict[int, tuple[float, float]]
    obj_est: dict[int, np.ndarray]
    last_node_of_segment: dict[int, int]
    seg_nodes: dict[int, tuple[list[int], list[int]]]
    skeleton: Skeleton
    archive: PoseArchive

    def _init_factors(self) -> None:
        # factors: slot -> (p, q, Z, S, kind); adjacency: key -> set of slots
        self.factors: dict[int, Factor] = {}
        self.adj: dict[int, set[int]] = {}
        self.pair_slot: dict[tuple[int, int, int], int] = {}
        self.special: dict[int, int] = {}  # key -> number of loop/observation factors
        self.next_slot = 0
        # the marginalisation prior: keys (k,), T_lin (k, 4, 4), W (r, 6k), e (r,)
        self.prior: dict | None = None
        # the same without the archive's factors (what an archived keyframe's covariance is
        # computed from, so that archive information does not feed later archive entries)
        self.prior_clean: dict | None = None

    def _count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + n

    @property
    def num_nodes(self) -> int:
        return len(self.node_stamp)

    @property
    def num_factors(self) -> int:
        return len(self.factors)

    # ------------------------------------------------------------------ factors
    def _add_factor(self, p: int, q: int, Z: np.ndarray, S: np.ndarray, kind: int) -> None:
        if p != NONE and p > q:  # canonical orientation p < q
            Z, S = invert_cov(Z, S)
            p, q = q, p
        key = (p, q, kind)
        slot = self.pair_slot.get(key)
        if slot is not None:
            _, _, Z0, S0, _ = self.factors[slot]
            Z, S = fuse(Z0, S0, Z, S)
            self.factors[slot] = (p, q, Z, S, kind)
            self._count("factors_fused")
            return
        slot = self.next_slot
        self.next_slot += 1
        self.factors[slot] = (p, q, Z, 0.5 * (S + S.T), kind)
        self.pair_slot[key] = slot
        for k in (p, q):
            if k != NONE:
                self.adj.setdefault(k, set()).add(slot)
                if kind in (KIND_LOOP, KIND_OBSERVATION):
                    self.special[k] = self.special.get(k, 0) + 1

    def _remove_factor(self, slot: int) -> tuple[int, int, np.ndarray, np.ndarray, int]:
        f = self.factors.pop(slot)
        p, q, _, _, kind = f
        self.pair_slot.pop((p, q, kind), None)
        for k in (p, q):
            if k != NONE:
                self.adj[k].discard(slot)
                if kind in (KIND_LOOP, KIND_OBSERVATION):
                    self.special[k] -= 1
        return f

    # ------------------------------------------------------------------ bounds
    def protect(self, node_keys) -> None:
        """Nodes to keep as long as possible (the agent's separators); replaces the set."""
        self.protected = {int(k) for k in node_keys if int(k) in self.node_stamp}

    def _removal_order(self) -> list[int]:
        newest = set(self.last_node_of_segment.values())

        def rank(node: int) -> tuple[int, int]:
            tier = 2 if node in self.protected else (1 if self.special.get(node, 0) else 0)
            return (tier, node)

        skeleton = self.skeleton
        return sorted(
            (n for n in self.node_stamp if n not in newest and n not in skeleton), key=rank
        )

    def _in_prior(self, n: int) -> bool:
        return self.prior is not None and n in self.prior["keys"]

    def _enforce_bounds(self) -> None:
        b = self.bounds
        if self.num_nodes <= b.max_nodes and self.num_factors <= b.max_edges:
            return
        skeleton = self.skeleton
        skeleton.capacity = int(b.skeleton_fraction * b.max_nodes)
        if self.num_factors > b.max_edges and len(skeleton) > 1:
            # the skeleton's factors get their share of max_edges too: halve it when over
            incident = sum(len(self.adj.get(k, ())) for k in skeleton.nodes)
            if incident > b.skeleton_fraction * b.max_edges:
                self._evict(skeleton.thin(len(skeleton) - 1))
        for node in self._removal_order():
            if self.num_nodes <= b.max_nodes and self.num_factors <= b.max_edges:
                break
            if node not in self.node_stamp:  # evicted from the skeleton meanwhile
                continue
            if skeleton.admits(node):
                self._evict(skeleton.add(node))  # kept (module skeleton); maybe others go
                continue
            self.remove_node(node)
        if self.num_factors > b.max_edges:  # only newest nodes left with dense factors
            self._count("bound_exceeded")

    def _evict(self, nodes: list[int]) -> None:
        """Remove nodes that left the skeleton (oldest first)."""
        for k in nodes:
            if k in self.node_stamp:
                self.remove_node(k)
                self._count("skeleton_evicted")

    def remove_node(self, n: int) -> None:
        """Remove node ``n`` keeping its information (module docstring)."""
        slots = sorted(self.adj.get(n, ()))
        self.skeleton.discard(n)
        chain = (
            len(slots) == 2
            and all(self.factors[s][4] == KIND_ODOMETRY for s in slots)
            and not self._in_prior(n)
        )
        if chain or not self.marginalize:
            self._compose_out(n, slots)
        else:
            self._marginalize_out(n, *self._loops_out(n, slots))
        seg = self.node_segment.get(n)
        stamps, nodes = self.seg_nodes.get(seg, ([], [])) if seg is not None else ([], [])
        if n in nodes:
            i = nodes.index(n)
            del stamps[i], nodes[i]
        for table in (
            self.node_stamp,
            self.node_segment,
            self.node_odom,
            self.node_est,
            self.node_cum,
        ):
            table.pop(n, None)
        self.adj.pop(n, None)
        self.special.pop(n, None)
        self.protected.discard(n)
        self._count("nodes_removed")

    def _loops_out(self, n: int, slots: list[int]) -> tuple[list[int], tuple | None, tuple | None]:
        """Take ``n``'s loops off before it is marginalised: into the archive when ``n``'s
        marginal is finite (:meth:`_loops_into_archive`), else re-anchored onto a neighbour
        (:meth:`_reanchor_loops`). Returns the slots left for the Schur complement, and its
        normal equations with and without the archive's factors when they were built on the
        way."""
        loops = [s for s in slots if _is_node_loop(self.factors[s])]
        if self.archive.capacity > 0:  # n's covariance from the system without archive factors
            rest = [s for s in slots if s not in loops]
            system = self._marginal_system(n, [self.factors[s] for s in rest])
            clean = self._marginal_system(
                n, [self.factors[s] for s in rest if not _from_archive(self.factors[s])], True
            )
            if self._loops_into_archive(n, loops, clean):
                return rest, system, clean
        return self._reanchor_loops(n, slots), None, None

    def _loops_into_archive(self, n: int, loops: list[int], system: tuple) -> bool:
        """Archive ``n`` (:meth:`_archive_node`) and turn each loop ``(x, n)`` into a factor
        between ``x`` and the entry's reference ``o`` (an object, or the world):
        ``T_o⁻¹ T_x ≈ T̂_o_n Z_nx`` with ``Σ = Ad(Z_nx⁻¹) (Σ_o_n / w) Ad(Z_nx⁻¹)ᵀ + Σ_nx``, where
        ``T̂_o_n`` is ``n`` in the reference's frame and ``Σ_o_n`` its covariance. The ``k``
        loops share half of that information, ``w = 1/(2k)``; later loops into the archived
        ``n`` take half of what is left each
        (:meth:`~dran_edge.robot.archive.ArchivedPose.take`), so all of them together use it at
        most once. False when ``n``'s marginal is not finite (nothing changed)."""
        keys_arr, poses, H, _ = system
        entry = self._archive_node(n, H, int(np.searchsorted(keys_arr, n)), keys_arr, poses)
        if entry is None:
            return False
        w = entry.take(len(loops)) if loops else 1.0
        for s in loops:
            p, q, Z, S, _ = self._remove_factor(s)
            x = p if q == n else q
            Z_nx, S_nx = (Z, S) if p == n else invert_cov(Z, S)
            Z_x, S_x = compose_cov(entry.T_ref_body, entry.covariance / w, Z_nx, S_nx)
            self._add_factor(entry.ref_key, x, Z_x, S_x, KIND_LOOP)
            self._count("loops_into_archive")
        return True

    def _reanchor_loops(self, n: int, slots: list[int]) -> list[int]:
        """Move ``n``'s loop factors onto its most certain odometry neighbour (composition).

        Marginalising a loop would put its far endpoint into the dense prior, and the prior
        would soon span the whole window. Each re-anchored loop and the marginalisation of the
        rest use the bridge edge ``(n, m)``; its information is split among them
        (:func:`split_weights`), so that it is counted once in total and the result is
        conservative (module docstring). Returns the slots left for marginalisation.
        """
        odo = [s for s in slots if self.factors[s][4] == KIND_ODOMETRY]
        loops = [s for s in slots if self.factors[s][4] == KIND_LOOP]
        if not odo or not loops:
            return slots
        bridge = min(odo, key=lambda s: float(np.trace(self.factors[s][3])))
        p, q, Z_b, S_b, kind_b = self.factors[bridge]
        m = q if p == n else p
        Z_nm, S_nm = (Z_b, S_b) if p == n else invert_cov(Z_b, S_b)
        rest = [s for s in slots if s not in loops]
        moved = []
        for s in loops:
            p, q, Z, S, _ = self._remove_factor(s)
            x = p if q == n else q
            if x == m:
                # a second n-m measurement: fused into the bridge (Ω₁ + Ω₂, independent)
                Z_nm, S_nm = fuse(Z_nm, S_nm, *((Z, S) if p == n else invert_cov(Z, S)))
                continue
            moved.append((x, *((Z, S) if q == n else invert_cov(Z, S))))
        # the marginalisation's own use of the bridge: the rest of n's factors and the prior
        a0 = sum(1.0 / float(np.trace(self.factors[s][3])) for s in rest if s != bridge)
        if self.prior is not None and n in self.prior["keys"]:
            i = int(np.flatnonzero(self.prior["keys"] == n)[0])
            Wn = self.prior["W"][:, 6 * i : 6 * i + 6]
            a0 += float(np.trace(Wn.T @ Wn)) / 36.0  # 1/tr(Σ) for Σ = σ²I ↔ tr(Ω)/36
        w0, ws = split_weights(a0, [S for _, _, S in moved])
        for (x, Z_xn, S_xn), w in zip(moved, ws):
            self._add_factor(x, m, *compose_cov(Z_xn, S_xn, Z_nm, S_nm / w), KIND_LOOP)
            self._count("loops_reanchored")
        self._remove_factor(bridge)
        if w0 > 0.0:
            self._add_factor(n, m, Z_nm, S_nm / w0, kind_b)
            rest = [s for s in rest if s != bridge] + [self.next_slot - 1]
        else:
            rest = [s for s in rest if s != bridge]
        return rest

    def _marginal_system(self, n: int, facs: list[Factor], clean: bool = False) -> tuple:
        """(keys, poses, H, g): the dense normal equations of factors ``facs`` of node ``n`` and
        the prior (``clean``: the prior without the archive's factors), over ``n``, the
        factors' other endpoints and the prior's variables."""
        prior = self.prior_clean if clean else self.prior
        keys = {n}
        for p, q, *_ in facs:
            keys.update(k for k in (p, q) if k != NONE)
        if prior is not None:
            keys.update(prior["keys"].tolist())
        keys_arr = np.array(sorted(keys), dtype=np.int64)
        poses = np.stack([self._estimate(k) for k in keys_arr.tolist()])
        blocks = self._blocks(_arrays(facs), keys_arr, self.config.residual)
        if prior is not None:
            blocks.append(self._prior_block(keys_arr, prior))
        H, g = _dense_normal_equations(blocks, len(keys_arr), poses)
        return keys_arr, poses, H, g

    def _marginalize_out(
        self, n: int, slots: list[int], system: tuple | None = None, clean: tuple | None = None
    ) -> None:
        """Schur-complement node ``n`` out of its factors and the prior into a new prior
        (``system``: their normal equations, :meth:`_marginal_system`, if already built)."""
        facs = [self._remove_factor(s) for s in slots]
        keys_arr, poses, H, g = system or self._marginal_system(n, facs)
        if self.archive.capacity > 0:  # the prior without the archive's factors, alike
            ck, cp, cH, cg = clean or self._marginal_system(
                n, [f for f in facs if not _from_archive(f)], True
            )
            ci = int(np.searchsorted(ck, n))
            crest, cT, cHp, cgp = _schur_out(ck, cp, cH, cg, ci)
            self.prior_clean = _dense_prior(crest, cT, cHp, cgp)
        i = int(np.searchsorted(keys_arr, n))
        rest, T_rest, Hp, gp = _schur_out(keys_arr, poses, H, g, i)
        if not self._set_prior(rest, T_rest, Hp, gp):
            return
        self._count("nodes_marginalised")
        in_prior = sorted(k for k in rest.tolist() if k in self.skeleton)
        for older, newer in zip(in_prior, in_prior[1:]):  # keep the newest skeleton node only
            if self.prior is not None:
                self._release_from_prior(older, newer)

    def _archive_node(
        self,
        n: int,
        H: np.ndarray,
        i: int,
        keys: np.ndarray | None = None,
        poses: np.ndarray | None = None,
    ) -> ArchivedPose | None:
        """Keep ``n``'s estimate and its covariance given the factors being marginalised and the
        prior, both without the archive's factors (``H`` of the clean system, :meth:`_loops_out`),
        in the archive (:mod:`dran_edge.robot.archive`): the inverse of ``n``'s Schur
        complement ``H_nn − H_nb H_bb⁺ H_bn`` (``[H⁻¹]_nn`` when ``H`` is regular; the
        pseudo-inverse drops directions of ``H_bb`` without information that ``n``'s factors do
        not touch, e.g. a node of a segment before a VIO reset left in the prior). Nothing when a
        direction without information is coupled to ``n``, when the complement is singular, or
        when the variance is too large to be of use. Given the system's ``keys`` and ``poses``,
        the entry is kept relative to what it is known best against, an object or the world
        (:meth:`_map_reference`); without them, in the world frame."""
        if self.archive.capacity <= 0:
            return None
        M = _marginal_information(H, np.arange(6 * i, 6 * i + 6))
        lam = np.linalg.eigvalsh(M) if M is not None else np.zeros(1)
        if (
            M is None
            or not np.all(np.isfinite(lam))
            or lam[0] <= ARCHIVE_MIN_EIGENVALUE * max(lam[-1], 1e-300)
        ):
            self._count("archive_singular")
            return None
        S = np.linalg.inv(M)
        S = 0.5 * (S + S.T)
        if float(np.max(np.diag(S))) > ARCHIVE_MAX_VARIANCE:
            self._count("archive_singular")
            return None
        d_m, r_rad = self.node_cum[n]
        T_n = self.node_est[n].copy()
        ref_key, T_ref_body = NONE, T_n
        if keys is not None and poses is not None:
            ref_key, T_ref_body, S = self._map_reference(H, i, keys, poses, T_n, S)
        entry = ArchivedPose(
            self.node_stamp[n],
            self.node_segment[n],
            T_n,
            S,
            self.node_odom[n].copy(),
            d_m,
            r_rad,
            ref_key=ref_key,
            T_ref_body=T_ref_body,
        )
        self.archive.add(entry)
        self._count("nodes_archived")
        return entry

    def _map_reference(
        self,
        H: np.ndarray,
        i: int,
        keys: np.ndarray,
        poses: np.ndarray,
        T_n: np.ndarray,
        S_n: np.ndarray,
    ) -> tuple[int, np.ndarray, np.ndarray]:
        """(ref_key, T̂_ref⁻¹ T̂_n, Σ): variable ``i`` of the system ``H`` (the node ``T_n``,
        world covariance ``S_n``) relative to what it is known best against: an object of the
        system, or the world (``NONE``, ``T_n``, ``S_n``).

        Why relative: a keyframe's world-frame estimate carries the map's placement error of
        its time (gauge, drift), which it shares with every entry of that time and with the
        objects the dense prior keeps. Loops into world-frame entries count that common error
        again per entry and pin the window to the past's placement
        (docs/notes/solve-and-bounded-graph.md, section 5c). The pose relative to an object,
        ``r = T_o⁻¹ T_n``, has the placement taken out: its covariance is ``J C Jᵀ`` with ``C``
        the joint marginal covariance of ``(n, o)`` and ``J = [I, −Ad(r⁻¹)]`` (right
        perturbations: ``δr = δn − Ad(r⁻¹) δo``). Of the world and the objects, the reference
        whose pose of ``n`` has the smallest log-determinant of covariance (a volume: the
        choice does not depend on units) is taken: of these candidate explanations of ``n``'s
        error, the one that leaves the least of it unexplained. Near the
        gauge that is the world (an early keyframe's world pose is more certain than its pose
        relative to any object); elsewhere an object."""
        objs = [j for j, k in enumerate(keys.tolist()) if k >= OBJ]
        if not objs:
            self._count("archive_world_frame")
            return NONE, T_n, S_n
        sk = np.concatenate([np.arange(6 * j, 6 * j + 6) for j in [i, *objs]])
        M = _marginal_information(H, sk)
        lam = np.linalg.eigvalsh(M) if M is not None else np.zeros(1)
        if M is None or lam[0] <= ARCHIVE_MIN_EIGENVALUE * max(lam[-1], 1e-300):
            self._count("archive_world_frame")  # an object's marginal is not finite
            return NONE, T_n, S_n
        C = np.linalg.inv(M)
        best = (float(np.linalg.slogdet(S_n)[1]), NONE, T_n, S_n)
        for a, j in enumerate(objs):
            r = geo.se3_between(poses[j], T_n)
            J = np.hstack([np.eye(6), -geo.se3_adjoint(geo.se3_inverse(r))])
            sel = np.r_[0:6, 6 + 6 * a : 12 + 6 * a]
            S = J @ C[np.ix_(sel, sel)] @ J.T
            S = 0.5 * (S + S.T)
            sign, logdet = np.linalg.slogdet(S)
            if sign > 0 and logdet < best[0]:
                best = (float(logdet), int(keys[j]), r, S)
        if best[1] == NONE:
            self._count("archive_world_frame")
        return best[1], best[2], best[3]

    def _release_from_prior(self, s: int, t: int) -> None:
        """Take skeleton node ``s`` out of the dense prior: the prior becomes its exact marginal
        on the other variables, times one relative factor ``(s, t)`` with the conditional of
        ``s`` given ``t`` in the prior's marginal on ``(s, t)`` — the Kullback–Leibler-optimal
        factorisation in which ``s`` depends on the prior's other variables only through ``t``
        (a Chow–Liu edge). So the dense prior never holds more than one skeleton node and stays
        small, while the chain between consecutive skeleton nodes keeps the information the
        prior had on it (docs/notes/solve-and-bounded-graph.md, section 4)."""
        prior = self.prior
        assert prior is not None
        keys = prior["keys"]
        W, e, T_lin = prior["W"], prior["e"], prior["T_lin"]
        H, g = W.T @ W, W.T @ e
        i, j = int(np.searchsorted(keys, s)), int(np.searchsorted(keys, t))
        si, sj = np.arange(6 * i, 6 * i + 6), np.arange(6 * j, 6 * j + 6)
        so = np.setdiff1d(np.arange(H.shape[0]), np.concatenate([si, sj]))
        # the prior's mode (min-norm where it has no gauge) for the relative measurement
        delta = -(np.linalg.pinv(H, rcond=1e-12, hermitian=True) @ g).reshape(-1, 6)
        T_mode = T_lin @ geo.se3_exp(delta)
        # conditional information of s given t in the marginal on (s, t)
        Hoo_inv_os = np.linalg.lstsq(H[np.ix_(so, so)], H[np.ix_(so, si)], rcond=None)[0]
        info_s = H[np.ix_(si, si)] - H[np.ix_(si, so)] @ Hoo_inv_os
        lam_s = np.linalg.eigvalsh(0.5 * (info_s + info_s.T))
        if lam_s[0] > 1e-9 * max(float(lam_s[-1]), 1e-300):
            Z = geo.se3_between(T_mode[i], T_mode[j])  # T_s⁻¹ T_t
            Ad = geo.se3_adjoint(geo.se3_inverse(Z))  # ε_t = -Ad(Z⁻¹) δ_s for t fixed
            self._add_factor(s, t, Z, Ad @ np.linalg.inv(info_s) @ Ad.T, KIND_ODOMETRY)
            self._count("skeleton_released_from_prior")
        # the prior's exact marginal without s (Schur complement), and the clean prior's alike
        self._set_prior(*_schur_out(keys, T_lin, H, g, i))
        if self.prior_clean is not None and s in self.prior_clean["keys"]:
            self.prior_clean = _prior_without(self.prior_clean, s)

    def _set_prior(self, keys: np.ndarray, T_lin: np.ndarray, H: np.ndarray, g: np.ndarray) -> bool:
        """The dense prior ``½‖W δ + e‖²`` with ``WᵀW = H``, ``Wᵀe = g`` (its null space
        dropped); None when ``H`` is zero. Returns whether a prior is left."""
        self.prior = _dense_prior(keys, T_lin, H, g)
        return self.prior is not None

    def _estimate(self, key: int) -> np.ndarray:
        return self.obj_est[key - OBJ] if key >= OBJ else self.node_est[key]

    def _prior_block(self, keys_arr: np.ndarray, prior: dict | None = None) -> MarginalPrior:
        prior = prior if prior is not None else self.prior
        assert prior is not None
        return MarginalPrior(
            np.searchsorted(keys_arr, prior["keys"])[None], prior["T_lin"], prior["W"], prior["e"]
        )

    def _blocks(self, fa: dict, keys: np.ndarray, residual: str) -> list:
        """Factor blocks (odometry, loop, observation, prior) over variables ``keys`` (sorted)."""
        if not len(fa["p"]):
            return []
        pi = np.searchsorted(keys, np.where(fa["p"] < 0, keys[0], fa["p"]))
        qi = np.searchsorted(keys, fa["q"])
        W = _whitening(fa["S"], residual)
        cfg = self.config
        kernels = {
            KIND_ODOMETRY: None,
            KIND_LOOP: make_kernel(cfg.robust_kernel, cfg.robust_threshold),
            KIND_OBSERVATION: make_kernel(cfg.robust_kernel, cfg.object_kernel_width),
        }
        blocks: list = []
        for kind in (KIND_ODOMETRY, KIND_LOOP, KIND_OBSERVATION):
            sel = (fa["kind"] == kind) & (fa["p"] >= 0)
            if np.any(sel):
                blocks.append(
                    BetweenFactors(
                        np.stack([pi[sel], qi[sel]], axis=1),
                        fa["Z"][sel],
                        W[sel],
                        residual,
                        kernels[kind],
                        label=KIND_NAMES[kind],
                    )
                )
        for kind in (KIND_PRIOR, KIND_LOOP):  # loops into the archive are unary too
            sel = (fa["p"] < 0) & (fa["kind"] == kind)
            if np.any(sel):
                blocks.append(
                    PriorFactors(
                        qi[sel][:, None],
                        fa["Z"][sel],
                        W[sel],
                        residual,
                        kernels.get(kind),
                        label=KIND_NAMES[kind],
                    )
                )
        return blocks

    def _compose_out(self, n: int, slots: list[int]) -> None:
        """Move ``n``'s factors onto a neighbour through the most certain factor."""
        binary = [s for s in slots if self.factors[s][0] != NONE]
        bridge = None
        if binary:
            # the most certain binary factor to another node (objects are never removed, so a
            # bridge to an object is fine too, but prefer nodes: odometry keeps the chain)
            def certainty(s: int) -> tuple[int, float]:
                p, q, _, S, _ = self.factors[s]
                other = q if p == n else p
                return (0 if other < OBJ else 1, float(np.trace(S)))

            bridge = min(binary, key=certainty)
        if bridge is None:
            for s in slots:
                self._remove_factor(s)  # nothing to carry their information onto
            return
        p, q, Z_b, S_b, bridge_kind = self._remove_factor(bridge)
        m = q if p == n else p
        Z_nm, S_nm = (Z_b, S_b) if p == n else invert_cov(Z_b, S_b)
        users = []
        for s in slots:
            if s == bridge:
                continue
            p, q, Z, S, kind = self._remove_factor(s)
            x = p if q == n else q
            if p != NONE and x == m:
                self._count("factors_dropped_cycle")  # a second n-m factor: fused into Σ_nm
                Z_nm, S_nm = fuse(Z_nm, S_nm, *((Z, S) if p == n else invert_cov(Z, S)))
                continue
            users.append((p, q, Z, S, kind))
        # every user composes with the bridge: split its information (counted once in total)
        _, ws = split_weights(0.0, [S for *_, S, _ in users])
        for (p, q, Z, S, kind), w in zip(users, ws):
            S_bridge = S_nm / w
            if p == NONE:  # prior on n -> prior on m (a loop into the archive stays a loop)
                Z2, S2 = compose_cov(Z, S, Z_nm, S_bridge)
                self._add_factor(NONE, m, Z2, S2, kind)
                continue
            x = p if q == n else q
            Z_xn, S_xn = (Z, S) if q == n else invert_cov(Z, S)
            Z2, S2 = compose_cov(Z_xn, S_xn, Z_nm, S_bridge)
            if m >= OBJ or x >= OBJ:
                new_kind = KIND_OBSERVATION
            elif kind == KIND_ODOMETRY and bridge_kind == KIND_ODOMETRY:
                new_kind = KIND_ODOMETRY
            else:
                new_kind = KIND_LOOP
            self._add_factor(x, m, Z2, S2, new_kind)

    def _sparsified_prior(self) -> dict:
        """The marginalisation prior as binary/unary factors, for consumers without a dense-prior
        factor (the DRAN agent's LocalProblem): a unary prior on the prior's oldest node (its
        marginal) and one relative factor from that root to each other variable of the prior with
        the conditional covariance given the root. Correlations between the non-root variables
        (e.g. object-object) are dropped; dropping alone would be over-confident wherever they
        are positively correlated, so every conditional covariance is inflated by the smallest
        c ≥ 1 with Σ_c ⪯ c·blockdiag(Σ_c) (Σ_c: their joint conditional covariance; c is the
        largest eigenvalue of the block-normalised Σ_c, at most their number) — conservative."""
        if self.prior is None:
            return _arrays([])
        keys = self.prior["keys"]
        nodes_in = [i for i, k in enumerate(keys.tolist()) if k < OBJ]
        if not nodes_in:
            self._count("prior_without_node")
            return _arrays([])
        W, e = self.prior["W"], self.prior["e"]
        H = W.T @ W
        Sigma = np.linalg.pinv(H, rcond=1e-12, hermitian=True)
        delta = -(Sigma @ (W.T @ e)).reshape(-1, 6)
        T_mean = self.prior["T_lin"] @ geo.se3_exp(delta)
        r = nodes_in[0]
        sr = slice(6 * r, 6 * r + 6)
        S_rr = 0.5 * (Sigma[sr, sr] + Sigma[sr, sr].T)
        lam = np.linalg.eigvalsh(0.5 * (H + H.T))
        # a prior of relative factors only (its gauge fixed elsewhere, e.g. on a skeleton node)
        # is singular: pinv's Σ is then no covariance — no unary factor, and the conditional
        # covariance from the conditional information H_oo instead
        full_rank = lam[0] > 1e-12 * max(float(lam[-1]), 1e-300)
        items = []
        if full_rank and np.all(np.diag(S_rr) < 1e6):
            items.append((NONE, int(keys[r]), T_mean[r], S_rr + 1e-12 * np.eye(6), KIND_PRIOR))
        S_rr_inv = np.linalg.pinv(S_rr, hermitian=True)
        T_r_inv = geo.se3_inverse(T_mean[r])
        others = [i for i in range(len(keys)) if i != r]
        so = (
            np.concatenate([np.arange(6 * i, 6 * i + 6) for i in others])
            if others
            else np.zeros(0, np.int64)
        )
        if full_rank:
            S_c = Sigma[np.ix_(so, so)] - Sigma[so, sr] @ S_rr_inv @ Sigma[sr, so]
        else:
            S_c = np.linalg.pinv(H[np.ix_(so, so)], rcond=1e-12, hermitian=True)
        S_c = 0.5 * (S_c + S_c.T) + 1e-12 * np.eye(len(so))
        c = _blockdiag_bound(S_c)
        for j, i in enumerate(others):
            k = int(keys[i])
            S_cond = c * S_c[6 * j : 6 * j + 6, 6 * j : 6 * j + 6]
            kind = KIND_OBSERVATION if k >= OBJ else KIND_ODOMETRY
            items.append((int(keys[r]), k, T_r_inv @ T_mean[i], S_cond, kind))
        return _arrays(items)
