"""Two-stage distributed chordal initialisation (paper Sec. 4.2.1) and the linear block solver
shared with the DGS baseline (``dran_edge.experiments.dgs``).

The centralized recipe is ``dran_edge.solver.chordal`` (Carlone et al. 2015). Here every robot owns its
vertices and solves only its block, holding the neighbours' separator values as known:

1. Rotations. Relax ``R_v`` to any ``d×d`` matrix and minimise ``Σ κ_e ‖R_j − R_i R̃_e‖²_F``.
   Row a of the residual is ``r_j^a − R̃_eᵀ r_i^a`` (``r^a`` the a-th row as a column), so with
   ``X_v = R_vᵀ`` (column a = row a of ``R_v``) every edge is the linear residual
   ``√w_e (X_j − M_e X_i − c_e)`` with ``M_e = R̃_eᵀ``, ``c_e = 0``, block size ``b = d`` and
   ``d`` right-hand-side columns. The result is projected to SO(d).
2. Translations. With the rotations fixed, ``Σ τ_e ‖t_j − t_i − R_i t̃_e‖²`` is the same form with
   ``b = 1``, ``M_e = 1``, ``c_e = (R_i t̃_e)ᵀ`` and ``X_v = t_vᵀ``.

Normal equations of that form (``Q X = Bv``): ``Q_ii += w M_eᵀM_e``, ``Q_jj += w I``,
``Q_ij += −w M_eᵀ``, ``Q_ji += −w M_e``, ``Bv_i += −w M_eᵀ c_e``, ``Bv_j += w c_e``.

Robot r's block update (Jacobi, or Gauss–Seidel over a colouring when ``colouring`` is given, with
successive over-relaxation ω as in Choudhary et al. 2017):

    X_r ← (1 − ω) X_r + ω Q_rr⁻¹ (Bv_r − Q_rk X_k)       (k: its anchors, the neighbours' separators)

Each robot's first block update of a stage is plain (ω = 1), later ones use ω (default ``GS_SOR``
= 1.8 with Gauss–Seidel): plain block Gauss–Seidel with the old 1e-2 stopping tolerances stopped
after 4–18 iterations 2.5–38 % above the centralized chordal objective. ``Q_rr`` is factorised
once per stage and reused. Values travel as ``InitEntry`` messages through
the caller's ``exchange`` (the harness encodes them with the wire codec, so rounds and bytes are
counted exactly like the optimisation's). The paper caps each stage at 50 iterations.

Gauge: one vertex (``gauge``: position of the first vertex, owned by robot 0) is fixed to the
identity; robots without it are anchored through their neighbours.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from dran_edge import geometry as geo
from dran_edge.dran import substructure
from dran_edge.messages import InitEntry, InitStage
from dran_edge.dran.partition import Partition

log = logging.getLogger(__name__)

#: exchange(stage, iteration, outgoing) -> incoming. ``outgoing[r]`` is a list of
#: (neighbour, entries) robot r sends; ``incoming[r]`` the entries robot r received.
Exchange = Callable[[InitStage, int, dict], dict]


#: Default over-relaxation of the Gauss–Seidel block updates (both stages). Measured on the
#: Table 1 graphs (docs/notes/benchmarks-history.md, "Distributed initialisation"): with it
#: (and the 1e-3 stage tolerances) the 50 + 50 iteration init lands 0.01–4.2 % above the
#: centralized chordal objective, where ω = 1 with 1e-2 tolerances left it 2.5–38 % above
#: (CSAIL 31.53 vs 31.48, was 34.30; parking-garage 1.47 vs 1.42, was 1.90).
GS_SOR = 1.8


@dataclass(frozen=True)
class InitParams:
    """Parameters of the distributed initialisation (Sec. 4.2.1; defaults from Sec. 6.1)."""

    max_iterations: int = 50
    """Cap on iterations (communication rounds) of each stage (the paper's 50)."""
    rotation_tol: float = 1e-3
    """Stage 1 stops when no robot's relaxed rotations change by more than this (max abs entry).
    (1e-2 stopped stage 1 after 4–11 iterations with rotations still up to 0.007–0.13 off.)"""
    translation_tol: float = 1e-3
    """Stage 2 stops when no robot's translations change by more than this, metres."""
    send_tol: float = 1e-4
    """Stage 1: a separator's relaxed rotation is re-sent only when an entry moved by more than
    this since last sent."""
    translation_send_tol: float = 1e-3
    """Stage 2: a separator's translation is re-sent only when it moved by more than this since
    last sent, metres (1 mm: a third fewer init bytes on parking-garage than 1e-4 for +0.8 %
    on F_init)."""
    sor: float | None = None
    """Successive over-relaxation ω of the rotation stage's block updates (1.0: plain
    Gauss–Seidel/Jacobi). None: ``GS_SOR`` with ``gauss_seidel``, 1.0 with Jacobi (block Jacobi
    can diverge for ω > 1)."""
    translation_sor: float | None = None
    """The same for the translation stage."""
    frame_iterations: int = 20
    """Of the ``max_iterations`` of a stage, at most this many align whole segments first
    (warm start, see ``LinearStage.frame_update``); 0 disables it."""
    frame_entries: bool = True
    """During the frame phase send one frame entry (G or s) per neighbour instead of every
    separator (the neighbour rebuilds them from the solo values X̂ it received once)."""
    gauss_seidel: bool = False
    """True: robots of one colour update per sub-step using the newest values (DGS);
    False: all robots update in parallel from last round's values (Jacobi)."""
    direct: str = "auto"
    """Per stage: "always" solves it exactly by substructuring (``dran_edge.dran.substructure``:
    each robot condenses its segment onto its separators, the robot tree's root solves the
    interface, 2 × tree height rounds); "never" runs the block iterations above; "auto" solves
    directly when that sends at most ``direct_budget`` block iterations' worth of values
    (``substructure.direct_floats`` against ``iteration_floats``) — the chain-like graphs
    with few separators, where the block iterations converge slowest."""
    direct_budget: float = 20.0
    """See ``direct``: the block-iteration count whose values the direct solve may cost. The
    generated suite needs 5–16, the Table 1 graphs 7.5–15 except sphere2500 (46) and torus3D
    (81), where the block iterations send fewer bytes (sphere2500: 0.89 MB direct against
    0.42 MB for an init within 0.4 % of the chordal one; docs/benchmarks.md)."""


@dataclass
class _Block:
    """One robot's share of one linear stage."""

    own: np.ndarray  # global positions of unknown own vertices
    known: np.ndarray  # global positions of anchors (+ the gauge if it is ours)
    lu: object
    Q_rk: sp.csr_matrix
    Bv: np.ndarray
    X: np.ndarray  # (len(own)*b, ncol)
    updated: bool = False  # has made a block update in this stage


@dataclass
class InitResult:
    poses: np.ndarray
    """(n, D, D) initial poses ``T_world_vertex`` (the gauge vertex at the identity)."""
    rotation_iterations: int
    translation_iterations: int
    history: list = field(default_factory=list)


def normal_equations(n: int, b: int, edges: np.ndarray, M: np.ndarray, c: np.ndarray,
                     w: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """(Q, Bv) of ``Σ_e w_e ‖X_j − M_e X_i − c_e‖²`` (see module docstring), vectorised.

    ``M`` is (m, b, b), ``c`` is (m, b, ncol), ``w`` (m,); Q is (n b, n b), Bv (n b, ncol).
    """
    m = edges.shape[0]
    i, j = edges[:, 0], edges[:, 1]
    ar = np.arange(b)
    I = np.broadcast_to(np.eye(b), (m, b, b))
    MtM = np.swapaxes(M, 1, 2) @ M
    blocks = [(i, i, w[:, None, None] * MtM), (j, j, w[:, None, None] * I),
              (i, j, -w[:, None, None] * np.swapaxes(M, 1, 2)), (j, i, -w[:, None, None] * M)]
    rows, cols, vals = [], [], []
    for p, q, val in blocks:
        rows.append((p[:, None, None] * b + ar[None, :, None] + 0 * ar[None, None, :]).ravel())
        cols.append((q[:, None, None] * b + ar[None, None, :] + 0 * ar[None, :, None]).ravel())
        vals.append(val.ravel())
    Q = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(n * b, n * b))
    ncol = c.shape[-1]
    Bv = np.zeros((n * b, ncol))
    Mtc = -w[:, None, None] * (np.swapaxes(M, 1, 2) @ c)
    np.add.at(Bv, (i[:, None] * b + ar[None]).ravel(), Mtc.reshape(-1, ncol))
    np.add.at(Bv, (j[:, None] * b + ar[None]).ravel(), (w[:, None, None] * c).reshape(-1, ncol))
    return Q, Bv


_expand = substructure.expand


def greedy_colouring(partition: Partition) -> np.ndarray:
    """(R,) colour of each robot so that neighbours differ (DGS's ordering, Choudhary 2017)."""
    colour = -np.ones(partition.num_robots, dtype=np.int64)
    for p in sorted(partition.parts, key=lambda p: -len(p.neighbours)):
        used = {int(colour[q]) for q in p.neighbours}
        colour[p.robot_id] = next(c for c in range(partition.num_robots + 1) if c not in used)
    return colour


class LinearStage:
    """One distributed linear least-squares stage over a partition (rotations or translations)."""

    def __init__(self, partition: Partition, n: int, b: int, edges: np.ndarray, M: np.ndarray,
                 c_of: Callable[[int], np.ndarray], w: np.ndarray, gauge: int,
                 X_gauge: np.ndarray, X0: np.ndarray):
        """``c_of(r)`` gives robot r's (m, b, ncol) constants (they may use r's own knowledge)."""
        self.partition, self.b = partition, b
        self.X_known = X0.copy()  # each robot's view is taken from here per robot below
        self.views: list[np.ndarray] = []
        self.blocks: list[_Block] = []
        self.frames: list[dict] = []
        for part in partition.parts:
            eidx = np.concatenate([part.intra_edges, part.inter_edges])
            Q, Bv = normal_equations(n, b, edges[eidx], M[eidx], c_of(part.robot_id)[eidx], w[eidx])
            own = part.vertices[part.vertices != gauge]
            known = part.anchors
            if np.any(part.vertices == gauge):
                known = np.concatenate([known, [gauge]])
            ro, rk = _expand(own, b), _expand(known, b)
            Q = Q.tocsr()
            Q_rr = sp.csc_matrix(Q[ro][:, ro])
            lu = spla.splu(Q_rr, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                           options={"SymmetricMode": True})
            view = X0.copy()
            view[_expand(np.array([gauge]), b)] = X_gauge
            # Warm start: the segment solved alone (intra edges, its first vertex as gauge).
            ei = part.intra_edges
            Qi, Bi = normal_equations(n, b, edges[ei], M[ei], c_of(part.robot_id)[ei], w[ei])
            first = int(part.vertices[0])
            loc = part.vertices[part.vertices != first]
            rl, rf = _expand(loc, b), _expand(np.array([first]), b)
            Qi = Qi.tocsr()
            X_first = X_gauge if first == gauge else X0[rf]
            X_hat = X0.copy()
            X_hat[rf] = X_first
            if loc.size:
                # A segment may fall apart into pieces (interleaved splits); a tiny pull
                # towards X0 keeps the pieces without the local gauge defined.
                Qs = sp.csc_matrix(Qi[rl][:, rl])
                eps = 1e-9 * max(float(np.abs(Qs.diagonal()).max(initial=0.0)), 1.0)
                X_hat[rl] = spla.spsolve(Qs + eps * sp.identity(rl.size, format="csc"),
                                         Bi[rl] - Qi[rl][:, rf] @ X_first + eps * X0[rl]
                                         ).reshape(-1, X0.shape[1])
            view[_expand(part.vertices, b)] = X_hat[_expand(part.vertices, b)]
            self.views.append(view)
            self.blocks.append(_Block(own, known, lu, Q[ro][:, rk].tocsr(), Bv[ro], view[ro].copy()))
            ex = edges[part.inter_edges]
            mine_j = partition.owner[ex[:, 1]] == part.robot_id
            self.frames.append({
                "fixed": bool(np.any(part.vertices == gauge)), "X_hat": X_hat[_expand(part.vertices, b)]
                .reshape(part.vertices.size, b, -1), "verts": part.vertices, "mine_j": mine_j,
                "own": np.where(mine_j, ex[:, 1], ex[:, 0]), "other": np.where(mine_j, ex[:, 0], ex[:, 1]),
                "M": M[part.inter_edges], "c": c_of(part.robot_id)[part.inter_edges], "w": w[part.inter_edges]})
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
        rhs = blk.Bv - blk.Q_rk @ view[_expand(blk.known, self.b)]
        omega = sor if blk.updated else 1.0
        blk.updated = True
        X_new = (1.0 - omega) * blk.X + omega * blk.lu.solve(rhs)
        change = float(np.max(np.abs(X_new - blk.X), initial=0.0))
        blk.X = X_new
        view[_expand(blk.own, self.b)] = X_new
        return change

    def frame_update(self, r: int) -> float:
        """Align robot r's whole segment to the anchors heard so far: ``X_v = X̂_v G`` (rotation
        stage, G d×d) or ``X_v = X̂_v + s`` (translation stage), least squares over its
        inter-robot edges. A segment solved alone is right up to such a transform, so a few of
        these small steps remove the slow rigid modes before the block updates; returns the
        max abs change of the segment."""
        f, view, b = self.frames[r], self.views[r], self.b
        if f["fixed"]:
            return 0.0
        sel = self.heard[r][f["other"]]
        if not sel.any():
            return 0.0
        pos = {int(v): k for k, v in enumerate(f["verts"].tolist())}
        own_k = np.array([pos[int(v)] for v in f["own"][sel]])
        Xh = f["X_hat"][own_k]  # (e, b, ncol)
        Xo = view.reshape(-1, b, view.shape[1])[f["other"][sel]]
        M, c, w, mj = f["M"][sel], f["c"][sel], f["w"][sel], f["mine_j"][sel]
        if self.multiplicative:
            # own j: X̂_j G − (M X_i + c);  own i: M X̂_i G − (X_j − c)
            P = np.where(mj[:, None, None], Xh, M @ Xh)
            Qm = np.where(mj[:, None, None], M @ Xo + c, Xo - c)
            lhs = np.einsum("e,eab,eac->bc", w, P, P)
            G = np.linalg.solve(lhs, np.einsum("e,eab,eac->bc", w, P, Qm))
            X_new = f["X_hat"] @ G
            self.frame[r] = G
        else:
            # own j: X̂_j + s − X_i − c;  own i: s − (X_j − X̂_i − c)
            Qm = np.where(mj[:, None, None], Xo + c - Xh, Xo - Xh - c)
            s_off = np.einsum("e,eab->ab", w, Qm) / w.sum()
            X_new = f["X_hat"] + s_off
            self.frame[r] = s_off
        idx = _expand(f["verts"], b)
        change = float(np.max(np.abs(X_new.reshape(-1, view.shape[1]) - view[idx])))
        view[idx] = X_new.reshape(-1, view.shape[1])
        blk = self.blocks[r]
        blk.X = view[_expand(blk.own, b)].copy()
        return change

    def own_value(self, r: int, v: int) -> np.ndarray:
        return self.views[r][v * self.b:(v + 1) * self.b]

    def solo_values(self, r: int, vs: np.ndarray) -> np.ndarray:
        """Robot r's solo-segment values X̂ at its vertices ``vs`` (what its frames transform)."""
        f = self.frames[r]
        order = np.argsort(f["verts"])
        return f["X_hat"][order[np.searchsorted(f["verts"], vs, sorter=order)]]

    def receive(self, r: int, v: int, X_v: np.ndarray) -> None:
        self.views[r][v * self.b:(v + 1) * self.b] = X_v
        self.heard[r][v] = True
        self.base[r][v] = X_v

    def receive_frame(self, r: int, owner: int, F: np.ndarray) -> None:
        """A neighbour's frame: every separator of ``owner`` that robot r holds a base for
        becomes ``X̂_v G`` (rotation stage) or ``X̂_v + s`` (translation stage)."""
        sel = self.heard[r] & (self.partition.owner == owner)
        X = self.base[r][sel]
        view = self.views[r].reshape(self.base[r].shape)
        view[sel] = X @ F if self.multiplicative else X + F


def _run_stage(stage: LinearStage, kind: InitStage, exchange: Exchange, params: InitParams,
               tol: float, sor: float, send_tol: float, colour: np.ndarray | None,
               to_entry: Callable, from_entry: Callable,
               history: list, max_iterations: int, frame_kind: InitStage | None = None,
               frame_to_entry: Callable | None = None,
               frame_from_entry: Callable | None = None) -> int:
    """Iterate ``stage`` through ``exchange``; returns the iterations used.

    During the frame phase a robot sends each neighbour its solo-segment separator values X̂
    once, then only its frame (one ``frame_kind`` entry: G or s) whenever the frame changed;
    the neighbour rebuilds the separators as X̂ G or X̂ + s (``LinearStage.receive_frame``).
    Without ``frame_kind`` the separators themselves are sent as in the block phase."""
    part = stage.partition
    R = part.num_robots
    last_sent: dict[tuple[int, int], np.ndarray] = {}  # (robot, neighbour) -> values sent
    base_sent: set[tuple[int, int]] = set()  # (robot, neighbour): X̂ sent for the frames
    last_frame: dict[tuple[int, int], np.ndarray] = {}
    groups = [list(range(R))] if colour is None else [
        [r for r in range(R) if colour[r] == c] for c in np.unique(colour)]
    iterations = 0
    frames_done = params.frame_iterations == 0
    for it in range(max_iterations):
        iterations = it + 1
        max_change = 0.0
        for group in groups:
            outgoing: dict[int, list] = {}
            for r in group:
                in_frames = it < params.frame_iterations and not frames_done
                if in_frames:
                    change = stage.frame_update(r)
                else:
                    change = stage.update(r, sor)
                max_change = max(max_change, change)
                sends = []
                view = stage.views[r].reshape(-1, stage.b, stage.views[r].shape[1])
                for q in part.parts[r].neighbours:
                    vs = part.parts[r].separators_for[q]
                    X = view[vs]
                    if in_frames and frame_kind is not None:
                        entries = []
                        if (r, q) not in base_sent:
                            Xh = stage.solo_values(r, vs)
                            entries = [to_entry(r, int(v), Xh[k]) for k, v in enumerate(vs.tolist())]
                            base_sent.add((r, q))
                        F, F_prev = stage.frame[r], last_frame.get((r, q))
                        if F is not None and (F_prev is None or np.max(np.abs(F - F_prev)) > send_tol):
                            entries.append(frame_to_entry(r, F))
                            last_frame[(r, q)] = F.copy()
                        last_sent[(r, q)] = X.copy()  # what q rebuilds from X̂ and the frame
                        if entries:
                            sends.append((q, entries))
                        continue
                    prev = last_sent.get((r, q))
                    if prev is None:
                        prev = np.full_like(X, np.nan)
                        last_sent[(r, q)] = prev
                    # NaN (never sent) compares False, so it is sent
                    changed = ~(np.max(np.abs(X - prev), axis=(1, 2)) <= send_tol)
                    entries = [to_entry(r, int(v), X[k]) for k, v in zip(np.flatnonzero(changed),
                                                                         vs[changed].tolist())]
                    prev[changed] = X[changed]
                    if entries:
                        sends.append((q, entries))
                outgoing[r] = sends
            incoming = exchange(kind, it, outgoing)
            for r, entries in incoming.items():
                for e in entries:
                    if InitStage(e.stage) == kind:
                        stage.receive(r, int(e.keyframe_id), from_entry(e))
                    elif frame_kind is not None and InitStage(e.stage) == frame_kind:
                        stage.receive_frame(r, int(e.owner_robot), frame_from_entry(e))
        history.append((kind.name, it, max_change))
        if it < params.frame_iterations and not frames_done:
            if it > 0 and max_change < tol:
                frames_done = True  # segments aligned: switch to block updates
            continue
        if max_change < tol:
            break
    return iterations


def distributed_chordal_init(
    dim: int,
    n: int,
    edges: np.ndarray,
    measurements: np.ndarray,
    kappa: np.ndarray,
    tau: np.ndarray,
    partition: Partition,
    exchange: Exchange,
    params: InitParams = InitParams(),
    gauge: int = 0,
) -> InitResult:
    """Two-stage distributed chordal initialisation; every value crosses ``exchange``."""
    d, D = dim, dim + 1
    m = edges.shape[0]
    colour = greedy_colouring(partition) if params.gauss_seidel else None
    default_sor = GS_SOR if params.gauss_seidel else 1.0
    sor_rot = default_sor if params.sor is None else params.sor
    sor_tr = default_sor if params.translation_sor is None else params.translation_sor
    history: list = []
    R_meas, t_meas = measurements[:, :d, :d], measurements[:, :d, d]
    I_d = np.eye(d)
    X0 = np.tile(I_d, (n, 1))  # X_v = R_vᵀ = I
    rot = _LazyStage(lambda: LinearStage(partition, n, d, edges, np.swapaxes(R_meas, 1, 2),
                                         lambda r: np.zeros((m, d, d)), np.asarray(kappa, float),
                                         gauge, I_d, X0))

    def rot_entry(r: int, v: int, X_v: np.ndarray) -> InitEntry:
        return InitEntry(InitStage.ROTATION, r, v, X_v.T.copy())

    frames = params.frame_entries
    tree = substructure.robot_tree(partition) if partition.num_robots > 1 else None
    rot_M = np.swapaxes(R_meas, 1, 2)
    if _use_direct(params, partition, d, d, gauge, tree):
        owner = partition.owner
        rot_views, it_rot = substructure.solve_direct(
            partition, n, d, d, edges, rot_M, lambda r: np.zeros((m, d, d)),
            np.asarray(kappa, float), gauge, I_d, exchange, InitStage.ROTATION_SCHUR,
            InitStage.ROTATION, lambda v, X: rot_entry(int(owner[v]), v, X),
            lambda e: np.asarray(e.value, float).T, X0, tree)
        history.append((InitStage.ROTATION.name, "direct", it_rot))
    else:
        it_rot = _run_stage(rot, InitStage.ROTATION, exchange, params, params.rotation_tol,
                            sor_rot, params.send_tol, colour, rot_entry,
                            lambda e: np.asarray(e.value, float).T, history,
                            params.max_iterations, InitStage.ROTATION_FRAME if frames else None,
                            lambda r, G: InitEntry(InitStage.ROTATION_FRAME, r, 0, G.copy()),
                            lambda e: np.asarray(e.value, float))
        rot_views = rot.views

    # Each robot projects what it knows (own values and the neighbours' last relaxed values).
    R_views = [geo.so3_project(v.reshape(n, d, d).swapaxes(1, 2)) if d == 3 else
               _so2_project(v.reshape(n, d, d).swapaxes(1, 2)) for v in rot_views]

    def c_of(r: int) -> np.ndarray:
        Ri = R_views[r][edges[:, 0]]
        return (Ri @ t_meas[:, :, None]).reshape(m, 1, d)

    trans = _LazyStage(lambda: LinearStage(partition, n, 1, edges, np.ones((m, 1, 1)), c_of,
                                           np.asarray(tau, float), gauge, np.zeros((1, d)),
                                           np.zeros((n, d))))

    def trans_entry(r: int, v: int, X_v: np.ndarray) -> InitEntry:
        T = np.eye(D)
        T[:d, :d], T[:d, d] = R_views[r][v], X_v[0]
        return InitEntry(InitStage.TRANSLATION, r, v, T)

    def offset_entry(r: int, s_off: np.ndarray) -> InitEntry:
        T = np.eye(D)
        T[:d, d] = s_off[0]
        return InitEntry(InitStage.TRANSLATION_FRAME, r, 0, T)

    if _use_direct(params, partition, 1, d, gauge, tree):
        def value_entry(v: int, X_v: np.ndarray) -> InitEntry:
            # the owner's rotation rides along (the pose layout needs one); receivers use t
            return trans_entry(int(partition.owner[v]), v, X_v)

        tr_views, it_tr = substructure.solve_direct(
            partition, n, 1, d, edges, np.ones((m, 1, 1)), c_of, np.asarray(tau, float), gauge,
            np.zeros((1, d)), exchange, InitStage.TRANSLATION_SCHUR, InitStage.TRANSLATION,
            value_entry, lambda e: np.asarray(e.value, float)[:d, d][None], np.zeros((n, d)),
            tree)
        history.append((InitStage.TRANSLATION.name, "direct", it_tr))
    else:
        it_tr = _run_stage(trans, InitStage.TRANSLATION, exchange, params,
                           params.translation_tol, sor_tr, params.translation_send_tol, colour,
                           trans_entry, lambda e: np.asarray(e.value, float)[:d, d][None],
                           history, params.max_iterations,
                           InitStage.TRANSLATION_FRAME if frames else None, offset_entry,
                           lambda e: np.asarray(e.value, float)[:d, d][None])
        tr_views = trans.views

    poses = np.broadcast_to(np.eye(D), (n, D, D)).copy()
    for part in partition.parts:
        r, own = part.robot_id, part.vertices
        poses[own, :d, :d] = R_views[r][own]
        poses[own, :d, d] = tr_views[r][own]
    return InitResult(poses, it_rot, it_tr, history)


class _LazyStage:
    """A ``LinearStage`` built on first use (the direct path never needs its factorisations)."""

    def __init__(self, build: Callable[[], LinearStage]):
        self._build, self._stage = build, None

    def __getattr__(self, name):
        if self._stage is None:
            self._stage = self._build()
        return getattr(self._stage, name)


def _use_direct(params: InitParams, partition: Partition, b: int, ncol: int, gauge: int,
                tree) -> bool:
    """``InitParams.direct`` for a stage with block size ``b`` and ``ncol`` columns."""
    if params.direct not in ("auto", "always", "never"):
        raise ValueError(f"InitParams.direct must be auto, always or never, got {params.direct!r}")
    if tree is None or params.direct == "never":
        return False
    if params.direct == "always":
        return True
    direct = substructure.direct_floats(partition, b, ncol, gauge, tree)
    return direct <= params.direct_budget * substructure.iteration_floats(partition, b, ncol)


def _so2_project(M: np.ndarray) -> np.ndarray:
    """Nearest rotation of (..., 2, 2) matrices."""
    theta = np.arctan2(M[..., 1, 0] - M[..., 0, 1], M[..., 0, 0] + M[..., 1, 1])
    return geo.so2_exp(theta)


def direct_exchange(stage: InitStage, iteration: int, outgoing: dict) -> dict:
    """Lossless in-memory exchange (tests, centralized checks); counts nothing."""
    incoming: dict[int, list] = {}
    for sends in outgoing.values():
        for q, entries in sends:
            incoming.setdefault(q, []).extend(entries)
    return incoming
