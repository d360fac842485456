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

Each stage is solved by the block iterations of :mod:`dran_edge.dran.linear_stage` (normal
equations, Jacobi or Gauss–Seidel block updates with over-relaxation ω) or exactly by
substructuring (:mod:`dran_edge.dran.substructure`), whichever sends fewer values
(``InitParams.direct``). This module holds the two stages and the iteration protocol.

Each robot's first block update of a stage is plain (ω = 1), later ones use ω (default ``GS_SOR``
= 1.8 with Gauss–Seidel): plain block Gauss–Seidel with the old 1e-2 stopping tolerances stopped
after 4–18 iterations 2.5–38 % above the centralized chordal objective. Values travel as
``InitEntry`` messages through the caller's ``exchange`` (the harness encodes them with the wire
codec, so rounds and bytes are counted exactly like the optimisation's). The paper caps each
stage at 50 iterations.

Gauge: one vertex (``gauge``: position of the first vertex, owned by robot 0) is fixed to the
identity; robots without it are anchored through their neighbours.

Size: over ~500 lines because the two stages and their exchange protocol (the block solver is in
linear_stage.py); over 500 only by ruff format's layout.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dran_edge import geometry as geo
from dran_edge.dran import substructure
from dran_edge.dran.linear_stage import Exchange, Incoming, LinearStage, Outgoing, greedy_colouring
from dran_edge.dran.partition import Partition
from dran_edge.messages import InitEntry, InitStage

log = logging.getLogger(__name__)

__all__ = [
    "Exchange",
    "GS_SOR",
    "InitParams",
    "InitResult",
    "direct_exchange",
    "distributed_chordal_init",
]

HistoryEntry = tuple[str, int | str, float]
"""(stage name, iteration or "direct", largest change of the iteration or rounds used)."""


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
class InitResult:
    poses: np.ndarray
    """(n, D, D) initial poses ``T_world_vertex`` (the gauge vertex at the identity)."""
    rotation_iterations: int
    translation_iterations: int
    history: list[HistoryEntry] = field(default_factory=list)


@dataclass(frozen=True)
class _FrameCodec:
    """The frame entries of a stage's frame phase (``LinearStage.frame_update``)."""

    kind: InitStage
    to_entry: Callable[[int, np.ndarray], InitEntry]
    """(robot, its frame G or s) -> entry."""
    from_entry: Callable[[InitEntry], np.ndarray]


@dataclass(frozen=True)
class _ValueCodec:
    """A stage's separator values on the wire."""

    kind: InitStage
    to_entry: Callable[[int, int, np.ndarray], InitEntry]
    """(robot, vertex, X_v) -> entry."""
    from_entry: Callable[[InitEntry], np.ndarray]


class _Sender:
    """What robots send their neighbours in one stage: separator values that moved by more than
    ``send_tol`` since last sent, or during the frame phase the solo values X̂ once and then the
    frame whenever it changed (``frames``: None sends the separators then too)."""

    def __init__(
        self, stage: LinearStage, values: _ValueCodec, frames: _FrameCodec | None, send_tol: float
    ):
        self.stage, self.values, self.frames, self.send_tol = stage, values, frames, send_tol
        self.last_sent: dict[tuple[int, int], np.ndarray] = {}  # (robot, neighbour) -> values sent
        self.base_sent: set[tuple[int, int]] = set()  # (robot, neighbour): X̂ sent for the frames
        self.last_frame: dict[tuple[int, int], np.ndarray] = {}

    def sends(self, r: int, in_frames: bool) -> list[tuple[int, list[InitEntry]]]:
        stage, part = self.stage, self.stage.partition
        to_entry = self.values.to_entry
        sends = []
        view = stage.views[r].reshape(-1, stage.b, stage.views[r].shape[1])
        for q in part.parts[r].neighbours:
            vs = part.parts[r].separators_for[q]
            X = view[vs]
            if in_frames and self.frames is not None:
                entries = []
                if (r, q) not in self.base_sent:
                    Xh = stage.solo_values(r, vs)
                    entries = [to_entry(r, int(v), Xh[k]) for k, v in enumerate(vs.tolist())]
                    self.base_sent.add((r, q))
                F, F_prev = stage.frame[r], self.last_frame.get((r, q))
                if F is not None and (F_prev is None or np.max(np.abs(F - F_prev)) > self.send_tol):
                    entries.append(self.frames.to_entry(r, F))
                    self.last_frame[(r, q)] = F.copy()
                self.last_sent[(r, q)] = X.copy()  # what q rebuilds from X̂ and the frame
                if entries:
                    sends.append((q, entries))
                continue
            prev = self.last_sent.get((r, q))
            if prev is None:
                prev = np.full_like(X, np.nan)
                self.last_sent[(r, q)] = prev
            # NaN (never sent) compares False, so it is sent
            changed = ~(np.max(np.abs(X - prev), axis=(1, 2)) <= self.send_tol)
            entries = [
                to_entry(r, int(v), X[k])
                for k, v in zip(np.flatnonzero(changed), vs[changed].tolist())
            ]
            prev[changed] = X[changed]
            if entries:
                sends.append((q, entries))
        return sends

    def receive(self, incoming: Incoming) -> None:
        stage, frames = self.stage, self.frames
        for r, entries in incoming.items():
            for e in entries:
                if InitStage(e.stage) == self.values.kind:
                    stage.receive(r, int(e.keyframe_id), self.values.from_entry(e))
                elif frames is not None and InitStage(e.stage) == frames.kind:
                    stage.receive_frame(r, int(e.owner_robot), frames.from_entry(e))


def _run_stage(
    stage: LinearStage,
    values: _ValueCodec,
    exchange: Exchange,
    params: InitParams,
    tol: float,
    sor: float,
    send_tol: float,
    colour: np.ndarray | None,
    history: list[HistoryEntry],
    max_iterations: int,
    frames: _FrameCodec | None = None,
) -> int:
    """Iterate ``stage`` through ``exchange``; returns the iterations used.

    During the frame phase a robot sends each neighbour its solo-segment separator values X̂
    once, then only its frame (one ``frames.kind`` entry: G or s) whenever the frame changed;
    the neighbour rebuilds the separators as X̂ G or X̂ + s (``LinearStage.receive_frame``).
    Without ``frames`` the separators themselves are sent as in the block phase."""
    R = stage.partition.num_robots
    sender = _Sender(stage, values, frames, send_tol)
    groups = (
        [list(range(R))]
        if colour is None
        else [[r for r in range(R) if colour[r] == c] for c in np.unique(colour)]
    )
    iterations = 0
    frames_done = params.frame_iterations == 0
    for it in range(max_iterations):
        iterations = it + 1
        max_change = 0.0
        for group in groups:
            outgoing: Outgoing = {}
            for r in group:
                in_frames = it < params.frame_iterations and not frames_done
                if in_frames:
                    change = stage.frame_update(r)
                else:
                    change = stage.update(r, sor)
                max_change = max(max_change, change)
                outgoing[r] = sender.sends(r, in_frames)
            sender.receive(exchange(values.kind, it, outgoing))
        history.append((values.kind.name, it, max_change))
        if it < params.frame_iterations and not frames_done:
            if it > 0 and max_change < tol:
                frames_done = True  # segments aligned: switch to block updates
            continue
        if max_change < tol:
            break
    return iterations


@dataclass(frozen=True)
class _Setting:
    """What both stages share: the graph, its partition, the exchange and the schedule."""

    n: int
    d: int
    edges: np.ndarray
    partition: Partition
    exchange: Exchange
    tree_exchange: Exchange
    """The substructured stages' exchange (they need every message)."""
    params: InitParams
    gauge: int
    colour: np.ndarray | None
    """Gauss–Seidel colours, None for Jacobi."""
    sor: float
    """Over-relaxation when InitParams leaves it to the schedule (GS_SOR or 1)."""
    tree: substructure.RobotTree | None
    history: list[HistoryEntry]

    @property
    def m(self) -> int:
        return int(self.edges.shape[0])


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
    tree_exchange: Exchange | None = None,
) -> InitResult:
    """Two-stage distributed chordal initialisation; every value crosses ``exchange``, or
    for the substructured (direct) stages, which need every message, ``tree_exchange`` when
    given (a reliable one over lossy links, ``experiments.fleet.Fleet.reliable_exchange``)."""
    d, D = dim, dim + 1
    colour = greedy_colouring(partition) if params.gauss_seidel else None
    tree = substructure.robot_tree(partition) if partition.num_robots > 1 else None
    s = _Setting(
        n,
        d,
        edges,
        partition,
        exchange,
        tree_exchange or exchange,
        params,
        gauge,
        colour,
        GS_SOR if params.gauss_seidel else 1.0,
        tree,
        [],
    )
    R_views, it_rot = _rotation_stage(s, measurements[:, :d, :d], np.asarray(kappa, float))
    tr_views, it_tr = _translation_stage(s, R_views, measurements[:, :d, d], np.asarray(tau, float))
    poses = np.broadcast_to(np.eye(D), (n, D, D)).copy()
    for part in partition.parts:
        r, own = part.robot_id, part.vertices
        poses[own, :d, :d] = R_views[r][own]
        poses[own, :d, d] = tr_views[r][own]
    return InitResult(poses, it_rot, it_tr, s.history)


def _rotation_stage(
    s: _Setting, R_meas: np.ndarray, kappa: np.ndarray
) -> tuple[list[np.ndarray], int]:
    """Stage 1: relaxed rotations X_v = R_vᵀ (b = d), then each robot projects what it knows
    (own values and the neighbours' last relaxed values) to SO(d). Returns the (n, d, d)
    rotations each robot holds and the iterations (or rounds) used."""
    n, d, m, partition, params = s.n, s.d, s.m, s.partition, s.params
    I_d = np.eye(d)
    X0 = np.tile(I_d, (n, 1))  # X_v = R_vᵀ = I
    rot_M = np.swapaxes(R_meas, 1, 2)

    def rot_entry(r: int, v: int, X_v: np.ndarray) -> InitEntry:
        return InitEntry(InitStage.ROTATION, r, v, X_v.T.copy())

    def rot_value(e: InitEntry) -> np.ndarray:
        X_v: np.ndarray = np.asarray(e.value, float).T
        return X_v

    if _use_direct(params, partition, d, d, s.gauge, s.tree):
        owner = partition.owner
        rot_views, it_rot = substructure.solve_direct(
            partition,
            n,
            d,
            d,
            s.edges,
            rot_M,
            lambda r: np.zeros((m, d, d)),
            kappa,
            s.gauge,
            I_d,
            s.tree_exchange,
            InitStage.ROTATION_SCHUR,
            InitStage.ROTATION,
            lambda v, X: rot_entry(int(owner[v]), v, X),
            rot_value,
            X0,
            s.tree,
        )
        s.history.append((InitStage.ROTATION.name, "direct", it_rot))
    else:
        rot = LinearStage(
            partition,
            n,
            d,
            s.edges,
            np.swapaxes(R_meas, 1, 2),
            lambda r: np.zeros((m, d, d)),
            kappa,
            s.gauge,
            I_d,
            X0,
        )
        frames = _FrameCodec(
            InitStage.ROTATION_FRAME,
            lambda r, G: InitEntry(InitStage.ROTATION_FRAME, r, 0, G.copy()),
            lambda e: np.asarray(e.value, float),
        )
        it_rot = _run_stage(
            rot,
            _ValueCodec(InitStage.ROTATION, rot_entry, rot_value),
            s.exchange,
            params,
            params.rotation_tol,
            s.sor if params.sor is None else params.sor,
            params.send_tol,
            s.colour,
            s.history,
            params.max_iterations,
            frames if params.frame_entries else None,
        )
        rot_views = rot.views
    R_views = [
        geo.so3_project(v.reshape(n, d, d).swapaxes(1, 2))
        if d == 3
        else _so2_project(v.reshape(n, d, d).swapaxes(1, 2))
        for v in rot_views
    ]
    return R_views, it_rot


def _translation_stage(
    s: _Setting, R_views: list[np.ndarray], t_meas: np.ndarray, tau: np.ndarray
) -> tuple[list[np.ndarray], int]:
    """Stage 2: translations X_v = t_vᵀ (b = 1) with each robot's rotations fixed. Returns the
    (n, d) translations each robot holds and the iterations (or rounds) used."""
    n, d, m, partition, params = s.n, s.d, s.m, s.partition, s.params
    D, edges = d + 1, s.edges

    def c_of(r: int) -> np.ndarray:
        Ri = R_views[r][edges[:, 0]]
        c: np.ndarray = (Ri @ t_meas[:, :, None]).reshape(m, 1, d)
        return c

    def trans_entry(r: int, v: int, X_v: np.ndarray) -> InitEntry:
        T = np.eye(D)
        T[:d, :d], T[:d, d] = R_views[r][v], X_v[0]
        return InitEntry(InitStage.TRANSLATION, r, v, T)

    def trans_value(e: InitEntry) -> np.ndarray:
        return np.asarray(e.value, float)[:d, d][None]

    def offset_entry(r: int, s_off: np.ndarray) -> InitEntry:
        T = np.eye(D)
        T[:d, d] = s_off[0]
        return InitEntry(InitStage.TRANSLATION_FRAME, r, 0, T)

    if _use_direct(params, partition, 1, d, s.gauge, s.tree):

        def value_entry(v: int, X_v: np.ndarray) -> InitEntry:
            # the owner's rotation rides along (the pose layout needs one); receivers use t
            return trans_entry(int(partition.owner[v]), v, X_v)

        tr_views, it_tr = substructure.solve_direct(
            partition,
            n,
            1,
            d,
            edges,
            np.ones((m, 1, 1)),
            c_of,
            tau,
            s.gauge,
            np.zeros((1, d)),
            s.tree_exchange,
            InitStage.TRANSLATION_SCHUR,
            InitStage.TRANSLATION,
            value_entry,
            trans_value,
            np.zeros((n, d)),
            s.tree,
        )
        s.history.append((InitStage.TRANSLATION.name, "direct", it_tr))
    else:
        trans = LinearStage(
            partition,
            n,
            1,
            edges,
            np.ones((m, 1, 1)),
            c_of,
            tau,
            s.gauge,
            np.zeros((1, d)),
            np.zeros((n, d)),
        )
        frames = _FrameCodec(InitStage.TRANSLATION_FRAME, offset_entry, trans_value)
        it_tr = _run_stage(
            trans,
            _ValueCodec(InitStage.TRANSLATION, trans_entry, trans_value),
            s.exchange,
            params,
            params.translation_tol,
            s.sor if params.translation_sor is None else params.translation_sor,
            params.translation_send_tol,
            s.colour,
            s.history,
            params.max_iterations,
            frames if params.frame_entries else None,
        )
        tr_views = trans.views
    return tr_views, it_tr


def _use_direct(
    params: InitParams,
    partition: Partition,
    b: int,
    ncol: int,
    gauge: int,
    tree: substructure.RobotTree | None,
) -> bool:
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
    R: np.ndarray = geo.so2_exp(theta)
    return R


def direct_exchange(stage: InitStage, iteration: int, outgoing: Outgoing) -> Incoming:
    """Lossless in-memory exchange (tests, centralized checks); counts nothing."""
    incoming: Incoming = {}
    for sends in outgoing.values():
        for q, entries in sends:
            incoming.setdefault(q, []).extend(entries)
    return incoming
