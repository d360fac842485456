r"""One robot's DRAN agent: the paper's Algorithm 1 as a pure state machine (docs/architecture.md, docs/dran.md).

``Agent.handle(event) -> list[Output]`` is the only way in. ``NeighbourData`` events are absorbed
(latest value wins; missing, duplicated or reordered messages are normal); a ``Tick`` runs one
round of Alg. 1 for this robot and returns the messages for its neighbours and an
``EstimateUpdate``. No clock, socket, thread, environment or global state; the same events give
the same outputs.

Notation (Sec. 3–4): private trajectory x_i (tangent u), public object copies y_i (tangent v),
neighbours' separators as fixed anchors (f_inter), duals λ_ij, MH weights w_ij, penalty β,
dual step η, step sizes α (public) and γ (private).

One round (Alg. 1, lines 3–13)::

    absorb neighbour data; initialise unknown objects from neighbours (lines 3–8)
    λ_ij ← λ_ij + η β w_ij φ(y_i, y_j)                                        (eq. 5b, line 9)
    L̂_i = f_intra + f_inter + f_obj + Σ_j (β/2)‖w_ij φ(y_i, y_j) + λ_ij/β‖²  (eq. 6)
    M = JᵀJ + μI = [[A, C], [Cᵀ, B]],  g = [g_x; g_y]                         (eq. 7)
    ĝ = g_y − Cᵀ A⁻¹ g_x,  Ĥ = B − Cᵀ A⁻¹ C                                   (eqs. 11, 12)
    v = −Ĥ⁻¹ ĝ,  u = −A⁻¹ (C v + g_x)                                        (line 11, eq. 8)
    y ← Retr_y(α v),  x ← Retr_x(γ u)                                         (line 13)

Sign convention: the paper writes both ``v = −Ĥ⁻¹ĝ`` and ``Retr(−αv)`` (Alg. 1) and
``Retr(+αξ)`` with ``ξ = −M⁻¹g`` (Sec. 5). We implement the descent step
``z⁺ = Retr_z(−α M⁻¹ g)``: (u, v) above are the minimiser of the model and are applied with ``+``.
A step is accepted only when L̂_i decreases; otherwise μ grows and the step is retried (a few
trials); if none decreases L̂_i the previous estimate is kept (docs/dran.md).

Termination (Sec. 4.2.3): ``converged`` when ``‖u‖ ≤ ε_u`` and ``‖v‖ ≤ ε_v`` (optimality) and the
largest ``φ²(y_i, y_j) ≤ ε_φ`` over the shared objects (feasibility; vacuous without objects), or
after K_max rounds. We require both (the paper says "either"): feasibility alone is vacuous in
object-free mode and optimality alone can hold while copies still disagree.

Dynamic map consensus (Sec. 4.2.2): every copy is sent with a hop count (0: observed by the
sender); a robot adopts an unknown object from a neighbour only when the entry's hop count is
below ``relay_max_hops`` and relays it with hop + 1, so maps travel diameter − 1 rounds.

The local problem comes from a :class:`LocalProblem` (docs/dran.md), built from a prebuilt
partition (``LocalProblem.from_partition``; bench g2o, simulations) or by the daemon from the
bounded online graph; the agent keeps estimates by keyframe id across ``set_problem`` calls.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, fields, replace

import numpy as np
from scipy.spatial import cKDTree

from dran_edge import geometry as geo
from dran_edge.config import AgentConfig, Residual
from dran_edge.dran.consensus import ConsensusFactors, consensus_error, dual_update, phi, phi_dim
from dran_edge.events import (
    EstimateUpdate,
    Health,
    NeighbourData,
    Outgoing,
    Output,
    Tick,
)
from dran_edge.solver.damping import AGENT_DAMPING, DampingState, damped_step
from dran_edge.solver.factors import BetweenFactors, Cauchy, PriorFactors, isotropic_whitening, make_kernel
from dran_edge.solver.graph import PoseGraph, kinds_array
from dran_edge.solver.lm import (
    build_plan,
    cholesky_factorizer,
    evaluate_cost,
    linearize,
    retract,
    schur_step,
)
from dran_edge.messages import NeighbourMessage, ObjectEntry, SeparatorEntry

log = logging.getLogger(__name__)


def _log_rate(h: np.ndarray) -> float:
    """Contraction rate per step of the positive sequence ``h``: exp of the least-squares slope
    of log h (a geometric sequence gives its ratio; a noisy one its trend)."""
    k = np.arange(h.size, dtype=np.float64)
    k -= k.mean()
    return float(np.exp(np.dot(k, np.log(h)) / np.dot(k, k)))


# --------------------------------------------------------------------------- the local problem
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
    separators_for: dict = field(default_factory=dict)
    """neighbour id -> (s,) own indices it needs as anchors."""

    @property
    def n(self) -> int:
        return int(self.pose_ids.shape[0])

    def to_dict(self) -> dict:
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "separators_for"}
        out["separators_for"] = {int(k): np.asarray(v) for k, v in self.separators_for.items()}
        return out

    @classmethod
    def from_dict(cls, data: dict) -> LocalProblem:
        kw = dict(data)
        kw["separators_for"] = {int(k): np.asarray(v, np.int64) for k, v in data["separators_for"].items()}
        return cls(**kw)

    @classmethod
    def empty(cls, dim: int, residual: str) -> LocalProblem:
        D, r = dim + 1, (6 if dim == 3 else 3) if residual == Residual.GEODESIC else dim * dim + dim
        z = np.zeros(0, np.int64)
        T, W = np.zeros((0, D, D)), np.zeros((0, r))
        return cls(dim, residual, z, z, T, np.zeros((0, 2), np.int64), T, W, np.zeros(0, bool),
                   z, z, z, np.zeros(0, bool), T, W, np.zeros(0, bool), z, T, W, z, z, T, W, {})

    @classmethod
    def from_partition(cls, graph, partition, robot: int, x0: np.ndarray, kappa: np.ndarray,
                       tau: np.ndarray, residual: str = "chordal") -> LocalProblem:
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
            dim=dim, residual=residual, pose_ids=part.vertices.astype(np.int64),
            pose_stamps_ns=part.vertices.astype(np.int64), x0=x0[part.vertices].copy(),
            between=local[e_in], between_T=graph.measurements[part.intra_edges],
            between_W=W[part.intra_edges], between_robust=np.zeros(e_in.shape[0], bool),
            inter_own=local[own_end], inter_owner=partition.owner[other].astype(np.int64),
            inter_anchor_id=other.astype(np.int64), inter_own_is_p=own_is_p,
            inter_T=graph.measurements[part.inter_edges], inter_W=W[part.inter_edges],
            inter_robust=np.zeros(e_x.shape[0], bool),
            prior_own=prior_own, prior_T=prior_T, prior_W=prior_W,
            obs_own=z, obs_object=z, obs_T=np.zeros((0, D, D)), obs_W=np.zeros((0, W.shape[1])),
            separators_for={q: local[v] for q, v in part.separators_for.items()},
        )


# --------------------------------------------------------------------------- the agent
@dataclass(frozen=True, eq=False)
class _Structure:
    """The local PoseGraph of one topology and its structure plan (rebuilt when it changes)."""

    key: tuple
    graph: PoseGraph
    plan: object
    obj_ids: tuple
    anchor_keys: tuple
    pair_keys: tuple  # (neighbour, object id) for each consensus factor
    factorize: object  # supernodal Cholesky of A + μI, analysed once for this structure


class Agent:
    """Robot ``config.robot_id``'s DRAN agent (see the module docstring)."""

    def __init__(self, config: AgentConfig, problem: LocalProblem | None = None,
                 weights: dict | None = None):
        self.config = config
        self.id = int(config.robot_id)
        self.neighbours = tuple(int(q) for q in config.neighbours)
        deg = len(self.neighbours)
        #: w_ij per neighbour (MH); without the neighbours' degrees we assume equal degrees.
        self.w = {q: (float(weights[q]) if weights and q in weights else 1.0 / (1.0 + deg))
                  for q in self.neighbours}
        self.problem = problem if problem is not None else LocalProblem.empty(config.dim, config.residual)
        self.x = self.problem.x0.copy()
        self.k = 0
        self.mu: float | None = None
        self.y: dict[int, np.ndarray] = {}
        self.hops: dict[int, int] = {}
        self.origin: dict[int, int] = {}
        self.anchors: dict[tuple[int, int], np.ndarray] = {}
        self.anchor_round: dict[tuple[int, int], int] = {}
        self.nbr_obj: dict[tuple[int, int], tuple[np.ndarray, int, int]] = {}
        #: (neighbour, object id) -> the robot whose observations that copy comes from
        self.nbr_origin: dict[tuple[int, int], int] = {}
        #: (neighbour, object id) -> its ``support`` (own observations its origin uses)
        self.nbr_support: dict[tuple[int, int], int] = {}
        #: object id -> support of this robot's copy (own usable observations, or the origin's)
        self.support: dict[int, int] = {}
        self.lam: dict[tuple[int, int], np.ndarray] = {}
        #: object id -> the association check's centre this round (``_check_associations``)
        self._centres: dict[int, np.ndarray] = {}
        self.last_sent: dict[tuple[int, str, int], tuple[np.ndarray, int]] = {}
        #: (neighbour, "o", object id) -> (origin, hop, support) last sent with that copy
        self.last_sent_provenance: dict[tuple[int, str, int], tuple[int, int, int]] = {}
        self.counters = {"rounds": 0, "accepted": 0, "rejected": 0, "linear_fail": 0,
                         "stale_dropped": 0, "objects_adopted": 0, "unhandled_events": 0,
                         "obs_gated": 0, "obs_rejected": 0, "consensus_conflicts": 0}
        self.converged = False
        self.last_norms = (math.inf, math.inf, math.inf)
        self.last_cost = math.nan
        self.last_decrease = math.inf  # decrease of L̂_i by the last local step
        #: the stopping rule (docs/notes/stopping-rule.md): local Newton decrements ½gᵀM⁻¹g of
        #: the last own steps, this robot's done counter, the neighbours' (value, round)
        self.decrements: list[float] = []
        self.last_decrement = math.inf
        self.done_count = 0
        self.nbr_done: dict[int, tuple[int, int]] = {}
        self.last_sent_done: dict[int, int] = {}
        self.stop_reason: str | None = None  # "criterion" or "k_max" once converged
        self.last_stop_test: dict = {}
        self.step_times: list = []
        self._structure: _Structure | None = None
        self._init_objects_from_observations()

    # ----------------------------------------------------------------- inputs
    def handle(self, event) -> list[Output]:
        """The only way in: absorb one event, return the outputs it causes."""
        if isinstance(event, NeighbourData):
            self._absorb(event.message)
            return []
        if isinstance(event, Tick):
            return self._round(int(event.stamp_ns))
        self.counters["unhandled_events"] += 1
        return [Health(getattr(event, "stamp_ns", 0), {"unhandled": type(event).__name__})]

    def set_problem(self, problem: LocalProblem) -> None:
        """Replace the local problem (the online graph changed); estimates kept by keyframe id."""
        old = {int(k): i for i, k in enumerate(self.problem.pose_ids.tolist())}
        x = problem.x0.copy()
        for i, k in enumerate(problem.pose_ids.tolist()):
            if k in old:
                x[i] = self.x[old[k]]
        self.problem, self.x, self._structure = problem, x, None
        self._init_objects_from_observations()

    def _absorb(self, msg: NeighbourMessage) -> None:
        j, rnd = int(msg.sender_id), int(msg.round)
        if msg.done_count is not None and self.nbr_done.get(j, (0, -1))[1] <= rnd:
            self.nbr_done[j] = (int(msg.done_count), rnd)
        for e in msg.separators:
            key = (int(e.owner_robot), int(e.keyframe_id))
            if self.anchor_round.get(key, -1) > rnd:
                self.counters["stale_dropped"] += 1
                continue
            self.anchors[key] = np.asarray(e.T_world_body, dtype=np.float64)
            self.anchor_round[key] = rnd
        for e in msg.objects:
            key = (j, int(e.object_id))
            prev = self.nbr_obj.get(key)
            if prev is not None and prev[2] > rnd:
                self.counters["stale_dropped"] += 1
                continue
            self.nbr_obj[key] = (np.asarray(e.T_world_object, np.float64), int(e.hop_count), rnd)
            self.nbr_origin[key] = int(e.origin_robot)
            self.nbr_support[key] = int(e.support)

    def _init_objects_from_observations(self) -> None:
        """Gate the own observations, then initialise unknown objects from them.

        Consistency gating (wrong tag associations): every observation predicts the object's
        position ``x_p T̃`` from the current trajectory. Per object, with three or more
        observations, those farther than ``object_gate_m`` from the medoid prediction are
        dropped (``obs_gated``). With ``object_min_views`` = k > 1, an observation is also used
        only when at least k own observations of the object (itself included) predict it
        within the gate (a tag is seen from several keyframes in a row; a wrong id is usually
        a lone observation); lone ones wait (``obs_pending``) until a neighbour's copy
        corroborates them (``_check_associations``), except where no own observation of another
        object lies within ``object_exclusion_m`` (a wrong id is a second label on something
        seen there, so it lies next to that object's views). By the same exclusion, a view that
        shares its place with another object's views, and has no more views of its own object
        there than that object has, waits too, however many views it has (``obs_shadowed``):
        a tag misread the same way from several keyframes would otherwise start a phantom copy
        where the object it misreads is. An unknown object starts at the medoid of its usable
        observations (Alg. 1 uses the first).
        """
        p = self.problem
        gate = self.config.object_gate_m
        self.obs_ok = np.ones(p.obs_object.size, bool)
        self.obs_pending = np.zeros(p.obs_object.size, bool)
        self.obs_ok_gate = self.obs_ok.copy()
        self._obs_groups: dict[int, np.ndarray] = {}
        self.counters["obs_exclusion_clear"] = self.counters["obs_shadowed"] = 0
        if p.obs_object.size == 0:
            return
        pred = self.x[p.obs_own] @ p.obs_T
        pos_all = pred[:, :-1, -1]
        order = np.argsort(p.obs_object, kind="stable")
        ids, starts = np.unique(p.obs_object[order], return_index=True)
        #: object id -> indices of its own observations (fixed for this problem)
        self._obs_groups = {int(o): g for o, g in zip(ids.tolist(), np.split(order, starts[1:]))}
        dists = {oid: np.linalg.norm(pos_all[idx][:, None] - pos_all[idx][None], axis=-1)
                 for oid, idx in self._obs_groups.items()}
        # views of its own object within the gate of each view (itself included)
        n_near = np.zeros(p.obs_object.size, np.int64)
        for oid, idx in self._obs_groups.items():
            n_near[idx] = (dists[oid] <= gate).sum(axis=1)
        collides, shadowed = self._exclusion(pos_all, n_near)
        for oid, idx in self._obs_groups.items():
            dist = dists[oid]
            med = int(np.argmin(dist.sum(axis=1)))
            ok = np.ones(idx.size, bool)
            if gate > 0:
                lone = n_near[idx] < self.config.object_min_views
                if self.config.object_exclusion_m > 0:
                    # spatial exclusion: a lone view that no view of another object shares
                    # its place with cannot be a second label of something seen there
                    clear = lone & ~collides[idx]
                    self.counters["obs_exclusion_clear"] += int(clear.sum())
                    self.counters["obs_shadowed"] += int((shadowed[idx] & ~lone).sum())
                    lone = (lone & ~clear) | shadowed[idx]
                ok = ~lone & ((dist[med] <= gate) if idx.size > 2 else True)
                self.obs_pending[idx[lone]] = True
                self.obs_ok[idx[~ok]] = False
            if ok.any():
                if oid not in self.y:
                    m = med
                    if not ok[med]:  # the medoid is a lone observation: medoid of the usable
                        usable = np.flatnonzero(ok)
                        m = usable[int(np.argmin(dist[np.ix_(usable, usable)].sum(axis=1)))]
                    self.y[oid] = pred[idx[m]].copy()
                self.hops[oid] = 0
                self.origin[oid] = self.id
                self.support[oid] = min(int(ok.sum()), 0xFFFF)
        self.counters["obs_gated"] = int((~self.obs_ok & ~self.obs_pending).sum())
        self.counters["obs_pending"] = int(self.obs_pending.sum())
        self.obs_ok_gate = self.obs_ok.copy()

    def _exclusion(self, pos: np.ndarray, n_near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per own view: does an own view of another object lie within ``object_exclusion_m``
        of it (``collides``), and does one of those have at least as many views of its object
        near it as this view has of its own (``shadowed``)? Both all False unless
        ``object_min_views`` > 1 (the plain agent holds nothing back)."""
        p = self.problem
        collides = np.zeros(p.obs_object.size, bool)
        shadowed = collides.copy()
        excl = self.config.object_exclusion_m
        if excl <= 0 or self.config.object_min_views <= 1 or self.config.object_gate_m <= 0:
            return collides, shadowed
        a, b = cKDTree(pos).query_pairs(excl, output_type="ndarray").T
        other = p.obs_object[a] != p.obs_object[b]
        a, b = a[other], b[other]
        collides[a] = collides[b] = True
        rival = np.zeros(p.obs_object.size, np.int64)  # best-seen other object sharing the place
        np.maximum.at(rival, a, n_near[b])
        np.maximum.at(rival, b, n_near[a])
        shadowed = collides & (n_near <= rival)
        return collides, shadowed

    # ----------------------------------------------------------------- one round
    def _adopt_unknown_objects(self) -> None:
        """Alg. 1 lines 3–8: an object first heard of from a neighbour starts at its value."""
        best: dict[int, tuple[int, int, np.ndarray]] = {}
        for (j, oid), (T, hop, _rnd) in sorted(self.nbr_obj.items()):
            if oid in self.y or hop >= self.config.relay_max_hops:
                continue
            if oid not in best or hop < best[oid][0]:
                best[oid] = (hop, j, T)
        for oid, (hop, j, T) in best.items():
            self.y[oid] = T.copy()
            self.hops[oid] = hop + 1
            self.origin[oid] = self.nbr_origin.get((j, oid), j)
            self.support[oid] = self.nbr_support.get((j, oid), 1)
            self.counters["objects_adopted"] += 1

    def _copies_from_others(self):
        """(object id, T, hop, origin, support) of every neighbour copy, in neighbour order,
        except those whose origin is this robot (its own estimate echoed back) and bare
        estimates (support 0: no observation behind them, ``_update_provenance``)."""
        for (j, oid), (T, hop, _rnd) in sorted(self.nbr_obj.items()):
            origin = self.nbr_origin.get((j, oid), j)
            support = self.nbr_support.get((j, oid), 1)
            if origin != self.id and support > 0:
                yield oid, T, hop, origin, support

    def _votes(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Per object: the neighbours' copies as independent votes, positions (m, 3) and weights.

        A copy counts once per robot whose observations it comes from (its origin) and weighs
        that robot's ``support`` (how many own observations of the object it uses): relays
        repeat their origin's estimate, so several neighbours relaying one robot's copy are one
        vote, and copies that come from this robot itself (its own estimate echoed back) or
        carry no support (bare estimates) are none. Per origin, the copy with the fewest hops."""
        best: dict[tuple[int, int], tuple[int, np.ndarray, int]] = {}
        for oid, T, hop, origin, support in self._copies_from_others():
            if (oid, origin) not in best or hop < best[(oid, origin)][0]:
                best[(oid, origin)] = (hop, T[:-1, -1], support)
        votes: dict[int, tuple[list, list]] = {}
        for (oid, _origin), (_hop, t, n) in sorted(best.items()):
            P, w = votes.setdefault(oid, ([], []))
            P.append(t)
            w.append(n)
        return {oid: (np.array(P), np.array(w, float)) for oid, (P, w) in votes.items()}

    def _check_associations(self) -> None:
        """Cross-robot association check, weighted by evidence.

        Per object, the candidates are the neighbours' votes (``_votes``) and, while this robot
        uses own observations of it, its own copy weighted by their number. The centre is the
        weighted medoid of the candidates (the one with the least support-weighted distance to
        the others; a tie keeps the own copy). Own observations whose predicted object position
        is farther than ``association_gate_m`` from the centre are treated as wrong tag
        associations and dropped (``obs_rejected``): two keyframes' worth of a wrong id lose to
        another robot's five correct views, whichever robot got its copy out first. A copy
        left without own observations that is farther than the gate from the centre (built
        from the wrong observations, or a relay that sided with the weaker hypothesis)
        restarts there, also when the centre is a lone vote; a copy within the gate is left to
        consensus (restarting it every round kept undoing the local steps and the duals, and
        the fleet's estimate slid away over hundreds of rounds: docs/dran.md). The centres are
        kept for the round's consensus kernel (``_centres``, ``centre_reach_m``). Re-evaluated
        every round, so a dropped observation comes back once the estimates agree with it."""
        gate = self.config.association_gate_m
        p = self.problem
        if gate <= 0:
            return
        votes = self._votes()
        self._centres = {}
        # held-back views in use: corroborated before and not rejected since (see below)
        latched = self.obs_pending & self.obs_ok
        if not votes:
            self.obs_ok = self.obs_ok_gate | latched
            self.counters["obs_rejected"] = self.counters["obs_corroborated"] = 0
            return
        n_obs = p.obs_object.size
        # predicted object positions x_p t̃ (rotation times translation, no 4x4 products)
        x = self.x[p.obs_own]
        pred = (x[:, :-1, :-1] @ p.obs_T[:, :-1, -1:])[..., 0] + x[:, :-1, -1]
        rejected = np.zeros(n_obs, bool)
        corroborated = self._corroborated(pred, votes)
        for oid, (P, w) in votes.items():
            idx = self._obs_groups.get(oid, np.zeros(0, np.int64))
            n_own = int((self.obs_ok_gate[idx] | corroborated[idx]).sum()) if idx.size else 0
            if n_own and oid in self.y:
                P = np.vstack([self.y[oid][:-1, -1], P])
                w = np.concatenate([[float(n_own)], w])
            if P.shape[0] < 2:
                # one vote and no own views to weigh it against: nothing is rejected, but a
                # copy that consensus dragged past the gate from its only source restarts there
                centre = P[0]
            else:
                spread = np.sqrt(((P[:, None] - P[None]) ** 2).sum(-1)) @ w
                centre = P[int(np.argmin(spread))]
                if idx.size:
                    rejected[idx] = np.linalg.norm(pred[idx] - centre, axis=1) > gate
            self._centres[oid] = centre
            in_use = (self.obs_ok_gate[idx] | corroborated[idx] | latched[idx]) & ~rejected[idx]
            if (oid in self.y and not in_use.any()
                    and np.linalg.norm(self.y[oid][:-1, -1] - centre) > gate):
                y = self.y[oid].copy()
                y[:-1, -1] = centre
                self.y[oid] = y
        # A corroborated view stays in use until the check rejects it. Once it is used this
        # robot is the origin of its copy, its neighbours (relaying the copy with the fewest
        # hops) echo that copy back, and an echo is no vote: without the latch the
        # corroboration vanished and the view went out and back in every other round
        # (docs/dran.md, robustness item 5).
        corroborated = (corroborated | latched) & ~rejected
        self.obs_ok = (self.obs_ok_gate | corroborated) & ~rejected
        self.counters["obs_rejected"] = int(rejected.sum())
        self.counters["obs_corroborated"] = int(corroborated.sum())

    def _corroborated(self, pred: np.ndarray, votes: dict) -> np.ndarray:
        """Held-back views (``obs_pending``) a neighbour's copy vouches for, as a mask over the
        own observations. A view of object k is corroborated when another robot's copy of k
        (``votes``) lies within ``object_gate_m`` of its prediction ``pred``, or, by the ratio
        test, within ``association_gate_m`` and ``corroboration_ratio`` times nearer than the
        nearest copy of any other object (the neighbours' and this robot's own). The ratio test
        is for a stretch of trajectory whose only object view is the held-back one: there the
        drift can exceed the object gate, and without the view it is never corrected (a right
        view whose twin was relabelled waited to the end of a run; docs/dran.md, robustness
        item 5). A wrong id lies where the seen object's copies are, so it fails the test."""
        p = self.problem
        ok = np.zeros(p.obs_object.size, bool)
        pend = np.flatnonzero(self.obs_pending)
        if not pend.size or not votes:
            return ok
        labels = np.concatenate([np.full(len(P), oid) for oid, (P, _w) in votes.items()])
        d = np.linalg.norm(pred[pend][:, None] - np.vstack([P for P, _w in votes.values()])[None],
                           axis=-1)
        same = labels[None] == p.obs_object[pend][:, None]
        d_own = np.where(same, d, np.inf).min(axis=1)
        hit = d_own <= self.config.object_gate_m
        ratio = self.config.corroboration_ratio
        if ratio > 0:
            d_other = np.where(same, np.inf, d).min(axis=1)
            if self.y:
                ids = np.fromiter(self.y, np.int64, len(self.y))
                Y = np.stack([T[:-1, -1] for T in self.y.values()])
                dy = np.linalg.norm(pred[pend][:, None] - Y[None], axis=-1)
                mine = ids[None] == p.obs_object[pend][:, None]
                d_other = np.minimum(d_other, np.where(mine, np.inf, dy).min(axis=1))
            hit |= (d_own <= self.config.association_gate_m) & (ratio * d_own < d_other)
        ok[pend[hit]] = True
        return ok

    def _update_provenance(self) -> None:
        """Hop count, origin and support of every copy: 0, this robot and the number of own
        observations in use while there are any; otherwise a relay of the nearest neighbour's
        copy (fewest hops) that has support, lies within ``association_gate_m`` of it and does
        not come from this robot, one hop more, with that copy's origin and support; otherwise
        a bare estimate (support 0, no vote anywhere). A robot whose own observations were all
        rejected thus stops passing its copy off as evidence, on its own behalf or on a former
        source's (before, such a copy kept its last support for good)."""
        gate = self.config.association_gate_m
        nearest: dict[int, tuple[int, int, int]] = {}
        for oid, T, hop, origin, support in self._copies_from_others():
            if oid not in self.y:
                continue
            if gate > 0 and np.linalg.norm(T[:-1, -1] - self.y[oid][:-1, -1]) > gate:
                continue
            if oid not in nearest or hop < nearest[oid][0]:
                nearest[oid] = (hop, origin, support)
        for oid in self.y:
            idx = self._obs_groups.get(oid)
            n_own = int(self.obs_ok[idx].sum()) if idx is not None else 0
            if n_own:
                self.hops[oid], self.origin[oid], self.support[oid] = 0, self.id, min(n_own, 0xFFFF)
            elif oid in nearest:
                hop, origin, support = nearest[oid]
                self.hops[oid], self.origin[oid], self.support[oid] = hop + 1, origin, support
            else:
                self.support[oid] = 0  # a bare estimate now: it no longer stands for evidence

    def _structure_for(self) -> _Structure:
        p = self.problem
        obj_ids = tuple(sorted(self.y))
        anchor_keys = tuple(sorted({(int(o), int(a)) for o, a in zip(p.inter_owner, p.inter_anchor_id)
                                    if (int(o), int(a)) in self.anchors}))
        pair_keys = tuple(sorted(k for k in self.nbr_obj if k[1] in self.y and k[0] in self.w))
        key = (obj_ids, anchor_keys, pair_keys, self.obs_ok.tobytes())
        if self._structure is not None and self._structure.key == key:
            return self._structure
        n, n_o, n_a, n_c = p.n, len(obj_ids), len(anchor_keys), len(pair_keys)
        o_base, a_base, c_base = n, n + n_o, n + n_o + n_a
        obj_slot = {oid: o_base + i for i, oid in enumerate(obj_ids)}
        anc_slot = {k: a_base + i for i, k in enumerate(anchor_keys)}
        kinds = kinds_array(n + n_o + n_a + n_c, public=np.arange(o_base, a_base),
                            fixed=np.arange(a_base, c_base + n_c))
        kernel = make_kernel(self.config.robust_kernel, self.config.robust_threshold)
        blocks = []
        if p.between.shape[0]:
            rob = p.between_robust
            for mask, ker, label in ((~rob, None, "intra"), (rob, kernel, "intra-loop")):
                if mask.any():
                    blocks.append(BetweenFactors(p.between[mask], p.between_T[mask], p.between_W[mask],
                                                 p.residual, ker, label))
        if p.inter_own.size:
            keep = np.array([(int(o), int(a)) in anc_slot for o, a in zip(p.inter_owner, p.inter_anchor_id)])
            if keep.any():
                a_idx = np.array([anc_slot.get((int(o), int(a)), -1)
                                  for o, a in zip(p.inter_owner, p.inter_anchor_id)])[keep]
                own, is_p = p.inter_own[keep], p.inter_own_is_p[keep]
                var = np.stack([np.where(is_p, own, a_idx), np.where(is_p, a_idx, own)], axis=1)
                for mask, ker in ((~p.inter_robust[keep], None), (p.inter_robust[keep], kernel)):
                    if mask.any():
                        blocks.append(BetweenFactors(var[mask], p.inter_T[keep][mask],
                                                     p.inter_W[keep][mask], p.residual, ker, "inter"))
        if p.prior_own.size:
            blocks.append(PriorFactors(p.prior_own[:, None], p.prior_T, p.prior_W, p.residual, None))
        ok = self.obs_ok
        if ok.any():
            var = np.stack([p.obs_own[ok], np.array([obj_slot[int(o)] for o in p.obs_object[ok]])], axis=1)
            blocks.append(BetweenFactors(var, p.obs_T[ok], p.obs_W[ok], p.residual,
                                         make_kernel(self.config.robust_kernel,
                                                     self.config.object_kernel_width), "object"))
        graph = PoseGraph(dim=p.dim, kinds=kinds, factors=tuple(blocks))
        plan = build_plan(graph.with_factors(*self._consensus_blocks(obj_slot, c_base, pair_keys)))
        self._structure = _Structure(key, graph, plan, obj_ids, anchor_keys, pair_keys,
                                     cholesky_factorizer(plan))
        return self._structure

    def _consensus_blocks(self, obj_slot: dict, c_base: int, pair_keys: tuple) -> tuple:
        if not pair_keys:
            return ()
        var = np.array([[obj_slot[oid], c_base + i] for i, (j, oid) in enumerate(pair_keys)])
        r = phi_dim(self.config.residual, self.config.dim)
        lam = np.stack([self.lam.get(k, np.zeros(r)) for k in pair_keys])
        w = np.array([self.w[j] for j, _ in pair_keys])
        c = self.config
        # With a robust kernel configured, a Cauchy kernel bounds the pull of a neighbour's copy
        # that stands for another hypothesis: built from a wrong tag association, it lies far
        # away and would otherwise drag every copy to it. Its scale puts the half-weight point
        # at φ = object_gate_m. Only conflicting pairs get it (``_conflicts``); every other
        # pair stays least squares (infinite scale), so copies that differ by drift within the
        # reaches pull fully (docs/dran.md, robustness).
        kernel = None
        if c.robust_kernel != "none" and c.object_gate_m > 0 and (
                c.conflict_reach_m > 0 or c.centre_reach_m > 0):
            conflict = self._conflicts(pair_keys)
            if conflict.any():
                scale = float(np.sqrt(c.beta) * np.mean(w) * c.object_gate_m)
                kernel = Cauchy(np.where(conflict, scale, np.inf))
        return (ConsensusFactors(var, w, lam, c.beta, c.residual, kernel),)

    def _conflicts(self, pair_keys: tuple) -> np.ndarray:
        """Per consensus pair (j, object): does j's copy stand for another hypothesis than ours?

        Yes when it lies more than ``centre_reach_m`` from the association check's centre for
        the object (``_centres``, whatever its origin: a relay dragged by a phantom carries the
        right origin), or when it comes from another observing robot (origin) and lies more
        than ``conflict_reach_m`` from our copy: two drifted estimates of one object lie closer,
        so beyond it at least one of them is something else; a relay of our own copy is never a
        conflict by that rule. Only called with a reach > 0 (both 0 turn the conflict kernel
        off). Counted per pair and round in ``counters['consensus_conflicts']``."""
        reach = self.config.conflict_reach_m
        out = np.zeros(len(pair_keys), bool)
        centre_reach = self.config.centre_reach_m
        centres = self._centres if centre_reach > 0 else {}
        for i, (j, oid) in enumerate(pair_keys):
            if oid in centres and np.linalg.norm(
                    self.nbr_obj[(j, oid)][0][:-1, -1] - centres[oid]) > centre_reach:
                out[i] = True
                continue
            if reach <= 0:
                continue
            if self.nbr_origin.get((j, oid), j) == self.origin.get(oid, self.id):
                continue
            d = np.linalg.norm(self.nbr_obj[(j, oid)][0][:-1, -1] - self.y[oid][:-1, -1])
            out[i] = d > reach
        return out

    def _poses(self, s: _Structure) -> np.ndarray:
        p = self.problem
        parts = [self.x]
        D = p.dim + 1
        if s.obj_ids:
            parts.append(np.stack([self.y[o] for o in s.obj_ids]))
        if s.anchor_keys:
            parts.append(np.stack([self.anchors[k] for k in s.anchor_keys]))
        if s.pair_keys:
            parts.append(np.stack([self.nbr_obj[k][0] for k in s.pair_keys]))
        return np.concatenate(parts) if len(parts) > 1 else self.x.reshape(-1, D, D).copy()

    def _round(self, stamp_ns: int) -> list[Output]:
        c = self.config
        self.k += 1
        self.counters["rounds"] += 1
        if (self.k - 1) % c.colours != c.colour:
            # not this robot's turn in the colour schedule: keep absorbing, send nothing
            self.counters["idle_rounds"] = self.counters.get("idle_rounds", 0) + 1
            return [self._estimate(stamp_ns, self.last_norms[2])]
        self._adopt_unknown_objects()
        self._check_associations()
        self._update_provenance()
        s = self._structure_for()
        # Dual update, eq. 5b, with the newest copies of both ends.
        if s.pair_keys:
            y_i = np.stack([self.y[o] for _, o in s.pair_keys])
            y_j = np.stack([self.nbr_obj[k][0] for k in s.pair_keys])
            r = phi_dim(c.residual, c.dim)
            lam = np.stack([self.lam.get(k, np.zeros(r)) for k in s.pair_keys])
            w = np.array([self.w[j] for j, _ in s.pair_keys])
            p_ij = phi(y_i, y_j, c.residual)
            # Anti-windup: integrate only pairs already near consensus (docs/dran.md); far apart
            # copies (first rounds, sparse graphs) made the duals overshoot and diverge.
            near = consensus_error(y_i, y_j) <= c.dual_max_phi2
            lam = np.where(near[:, None], dual_update(lam, p_ij, w, c.beta, c.eta), lam)
            for key, value in zip(s.pair_keys, lam):
                self.lam[key] = value
        n = self.problem.n
        obj_slot = {oid: n + i for i, oid in enumerate(s.obj_ids)}
        c_base = n + len(s.obj_ids) + len(s.anchor_keys)
        cons = self._consensus_blocks(obj_slot, c_base, s.pair_keys)
        graph = s.graph.with_factors(*cons)
        if cons and cons[0].kernel is not None:  # pairs under the kernel (conflicts) this round
            self.counters["consensus_conflicts"] += int(np.isfinite(cons[0].kernel.scale).sum())
        poses = self._poses(s)
        x_k = self.x.copy()
        accepted_before = self.counters["accepted"]
        norm_u, norm_v = self._local_step(graph, s, poses)
        if c.sor_omega != 1.0 and accepted_before > 0 and self.counters["accepted"] > accepted_before:
            # block SOR on the trajectory: x_k ⊕ ω (z ⊖ x_k), z the round's local solution;
            # kept only while it does not raise L̂_i above its value at x_k (nonlinear safeguard)
            z = self.x
            self.x = geo.retract(x_k, c.sor_omega * geo.log(geo.between(x_k, z)))
            if evaluate_cost(graph, self._poses(s)) > self._cost_at_start:
                self.x = z
                self.counters["sor_rejected"] = self.counters.get("sor_rejected", 0) + 1
        phi2 = 0.0
        if s.pair_keys:
            y_i = np.stack([self.y[o] for _, o in s.pair_keys])
            y_j = np.stack([self.nbr_obj[k][0] for k in s.pair_keys])
            phi2 = float(np.max(consensus_error(y_i, y_j)))
        self.last_norms = (norm_u, norm_v, phi2)
        iterations = self.counters["rounds"] - self.counters.get("idle_rounds", 0)
        if c.stop_rule == "tail":
            done = self._tail_test(s, phi2) and self._steps_test(norm_u, norm_v, phi2, eps=False)
            self._update_done_count(done)
            converged = self.done_count >= c.stop_rounds
        else:
            converged = self._steps_test(norm_u, norm_v, phi2, eps=True)
        self.converged = converged or iterations >= c.k_max
        if self.converged and self.stop_reason is None:
            self.stop_reason = "criterion" if converged else "k_max"
        elif not self.converged:
            self.stop_reason = None
        return self._outputs(stamp_ns, s, phi2)

    # ----------------------------------------------------------------- stopping rule
    def _steps_test(self, norm_u: float, norm_v: float, phi2: float, eps: bool) -> bool:
        """The paper's test (Sec. 4.2.3): ‖u‖ ≤ ε_u, ‖v‖ ≤ ε_v (``eps``; or the eps_cost_rel
        decrease test) and max φ² ≤ ε_φ. With ``eps`` False only the feasibility part."""
        c = self.config
        if phi2 > c.eps_phi:
            return False
        if not eps:
            return True
        optimal = norm_u <= c.eps_u and norm_v <= c.eps_v
        if c.eps_cost_rel > 0 and self.last_decrease <= c.eps_cost_rel * max(self.last_cost, 1e-300):
            optimal = True  # the local step no longer pays (docs/dran.md, termination)
        return optimal

    def _tail_test(self, s: _Structure, phi2: float) -> bool:
        """Local part of the "tail" rule (docs/notes/stopping-rule.md).

        δ_k = ½ gᵀ M⁻¹ g is the local Newton decrement at the start of the k-th own step (with
        the neighbours' newest separators and copies; ``gᵀM⁻¹g = g_xᵀA⁻¹g_x + ĝᵀĤ⁻¹ĝ``, the
        Schur-reduced gradient in the metric of the local Hessian). In a block iteration that
        converges linearly at rate ρ the decrements shrink by ρ per step, and the decrease still
        to come is about δ_k / (1 − ρ); ρ is estimated from the decrements of the last
        ``stop_window`` steps (the larger of the full- and half-window rates, so a slow mode that
        has just taken over counts). Passes when that remaining decrease is at most
        ``stop_tol`` × L̂_i and the consensus penalty energy (β/2) Σ w² ‖φ‖² too."""
        c = self.config
        d = self.last_decrement
        self.decrements.append(d)
        W = c.stop_window
        if len(self.decrements) > W + 1:
            del self.decrements[: len(self.decrements) - W - 1]
        L = max(self.last_cost, 1e-300)
        test = {"decrement_rel": d / L, "rate": math.nan, "tail_rel": math.inf, "penalty_rel": 0.0}
        self.last_stop_test = test
        if len(self.decrements) <= W or not all(map(math.isfinite, self.decrements)):
            return False
        h = np.asarray(self.decrements)
        if d <= 1e-14 * L:  # at the optimum of its block to rounding: nothing left here
            rate = 0.0
        elif np.any(h <= 0.0):
            return False
        else:
            rate = max(_log_rate(h), _log_rate(h[W // 2:]))
        test["rate"] = float(rate)
        if not rate < 1.0:
            return False
        test["tail_rel"] = d / (1.0 - rate) / L
        if s.pair_keys:
            y_i = np.stack([self.y[o] for _, o in s.pair_keys])
            y_j = np.stack([self.nbr_obj[k][0] for k in s.pair_keys])
            w = np.array([self.w[j] for j, _ in s.pair_keys])
            p = phi(y_i, y_j, c.residual)
            test["penalty_rel"] = 0.5 * c.beta * float(np.sum(w[:, None] ** 2 * p * p)) / L
        return test["tail_rel"] <= c.stop_tol and test["penalty_rel"] <= c.stop_tol

    def _update_done_count(self, done: bool) -> None:
        """c_i ← 0 if the local test fails, else 1 + min(c_i, min_j c_j) (capped at
        stop_rounds): c_i ≥ K only when every robot within K − 1 hops has passed its own test
        in its last rounds, so no robot reports convergence while another is far from it."""
        if not done:
            self.done_count = 0
            return
        nbr = [self.nbr_done.get(q, (0, -1))[0] for q in self.neighbours]
        self.done_count = min(self.config.stop_rounds, 1 + min([self.done_count, *nbr]))

    def _local_step(self, graph: PoseGraph, s: _Structure, poses: np.ndarray) -> tuple[float, float]:
        """One damped LM step with the Schur complement (eqs. 7–12); keeps x, y on rejection."""
        c = self.config
        plan = s.plan
        lin = linearize(graph, plan, poses)
        cost = self._cost_at_start = lin.cost
        if self.mu is None:
            diag = np.concatenate([lin.A.diagonal(), np.diag(lin.B)])
            self.mu = replace(AGENT_DAMPING, mu_init=c.mu_init).initial_mu(diag)
        g = np.concatenate([lin.g_x, lin.g_y])
        self.last_decrement = math.inf

        def solve_model(mu: float) -> tuple[np.ndarray, np.ndarray]:
            u, v = schur_step(lin.A, lin.B, lin.C, lin.g_x, lin.g_y, mu, s.factorize)
            if not math.isfinite(self.last_decrement):
                # local Newton decrement ½ gᵀ M⁻¹ g of this round's first solvable model
                self.last_decrement = max(-0.5 * float(g @ np.concatenate([u, v])), 0.0)
            return u, v

        def evaluate(u: np.ndarray, v: np.ndarray) -> tuple[float, np.ndarray]:
            new = retract(plan, poses, c.gamma * u, c.alpha * v)
            return evaluate_cost(graph, new), new

        out = damped_step(AGENT_DAMPING, DampingState(self.mu), solve_model, evaluate, cost, g)
        self.mu = out.state.mu
        if out.solve_failures:
            self.counters["linear_fail"] += out.solve_failures
        if out.accepted:
            assert out.u is not None and out.v is not None and out.candidate is not None
            self.counters["accepted"] += 1
            self.last_decrease = cost - out.cost
            self.last_cost = out.cost
            self._store(plan, out.candidate)
            return float(np.linalg.norm(c.gamma * out.u)), float(np.linalg.norm(c.alpha * out.v))
        self.last_decrease = math.inf  # no step taken: not evidence of convergence
        self.counters["rejected"] += 1
        self.last_cost = cost
        return 0.0, 0.0

    def _store(self, plan, poses: np.ndarray) -> None:
        n = self.problem.n
        self.x = poses[:n].copy()
        for i, oid in enumerate(sorted(self.y)):
            self.y[oid] = poses[n + i].copy()

    # ----------------------------------------------------------------- outputs
    def _changed(self, key: tuple, T: np.ndarray, force: bool) -> bool:
        prev = self.last_sent.get(key)
        c = self.config
        if prev is None or force or self.k - prev[1] >= c.resend_period_rounds:
            return True
        return float(np.max(np.abs(T - prev[0]))) > c.send_threshold

    def _outputs(self, stamp_ns: int, s: _Structure, phi2: float) -> list[Output]:
        p = self.problem
        out: list[Output] = []
        objects = sorted(self.y.items())
        for q in self.neighbours:
            seps = []
            for i in p.separators_for.get(q, np.zeros(0, np.int64)).tolist():
                key = (q, "s", int(p.pose_ids[i]))
                if self._changed(key, self.x[i], False):
                    seps.append(SeparatorEntry(self.id, int(p.pose_ids[i]), int(p.pose_stamps_ns[i]),
                                               self.x[i].copy()))
                    self.last_sent[key] = (self.x[i].copy(), self.k)
            objs = []
            for oid, T in objects:
                key = (q, "o", oid)
                # beyond relay_max_hops a copy is not offered to new neighbours, but one that
                # was sent to q before keeps being updated there: else q would hold our last
                # value (and its provenance) for good, e.g. a phantom we have since dropped
                if self.hops.get(oid, 0) >= self.config.relay_max_hops and key not in self.last_sent:
                    continue
                prov = (self.origin.get(oid, self.id), self.hops.get(oid, 0),
                        self.support.get(oid, 1))
                # a new origin, hop count or support goes out at once: it changes the votes
                if self._changed(key, T, self.last_sent_provenance.get(key) != prov):
                    objs.append(ObjectEntry(oid, T.copy(), *prov))
                    self.last_sent[key] = (T.copy(), self.k)
                    self.last_sent_provenance[key] = prov
            done = None
            if self.config.stop_rule == "tail":
                done = self.done_count
                if self.last_sent_done.get(q) != done:  # a new counter goes out at once
                    self.last_sent_done[q] = done
                    if not (seps or objs):  # alone: a header-only datagram
                        out.append(Outgoing(NeighbourMessage(self.id, self.k, stamp_ns,
                                                             done_count=done), (q,)))
                        continue
            if seps or objs:
                msg = NeighbourMessage(self.id, self.k, stamp_ns, tuple(seps), tuple(objs),
                                       done_count=done)
                out.append(Outgoing(msg, (q,)))
        out.append(self._estimate(stamp_ns, phi2))
        return out

    def current_estimate(self, stamp_ns: int) -> EstimateUpdate:
        """The estimate as the last round left it (e.g. of an agent restored from a checkpoint)."""
        return self._estimate(stamp_ns, self.last_norms[2])

    def _estimate(self, stamp_ns: int, phi2: float) -> EstimateUpdate:
        p = self.problem
        D = p.dim + 1
        objects = sorted(self.y.items())
        return EstimateUpdate(
            stamp_ns=stamp_ns, round=self.k, keyframe_stamps_ns=p.pose_stamps_ns.copy(),
            T_world_body=self.x.copy(), object_ids=tuple(o for o, _ in objects),
            T_world_object=(np.stack([T for _, T in objects]) if objects else np.zeros((0, D, D))),
            cost=float(self.last_cost), step_norm_u=self.last_norms[0],
            step_norm_v=self.last_norms[1], consensus_error=phi2, converged=self.converged)

    # ----------------------------------------------------------------- checkpoints
    def to_state(self) -> dict:
        """Everything needed to resume (plain dicts, lists and numpy arrays)."""
        return {
            "problem": self.problem.to_dict(), "x": self.x.copy(), "k": self.k, "mu": self.mu,
            "y": {int(k): v.copy() for k, v in self.y.items()}, "hops": dict(self.hops),
            "origin": dict(self.origin),
            "anchors": {k: v.copy() for k, v in self.anchors.items()},
            "anchor_round": dict(self.anchor_round),
            "nbr_obj": {k: (v[0].copy(), v[1], v[2]) for k, v in self.nbr_obj.items()},
            "nbr_origin": dict(self.nbr_origin), "nbr_support": dict(self.nbr_support),
            "support": dict(self.support),
            "lam": {k: v.copy() for k, v in self.lam.items()}, "w": dict(self.w),
            "counters": dict(self.counters),
            "decrements": list(self.decrements), "done_count": self.done_count,
            "nbr_done": dict(self.nbr_done), "last_sent_done": dict(self.last_sent_done),
        }

    @classmethod
    def from_state(cls, config: AgentConfig, state: dict) -> Agent:
        agent = cls(config, LocalProblem.from_dict(state["problem"]), weights=state["w"])
        agent.x = np.asarray(state["x"], np.float64).copy()
        agent.k, agent.mu = int(state["k"]), state["mu"]
        agent.y = {int(k): np.asarray(v, np.float64) for k, v in state["y"].items()}
        agent.hops = {int(k): int(v) for k, v in state["hops"].items()}
        agent.origin = {int(k): int(v) for k, v in state["origin"].items()}
        agent.anchors = {tuple(k): np.asarray(v) for k, v in state["anchors"].items()}
        agent.anchor_round = {tuple(k): int(v) for k, v in state["anchor_round"].items()}
        agent.nbr_obj = {tuple(k): (np.asarray(v[0]), int(v[1]), int(v[2])) for k, v in state["nbr_obj"].items()}
        agent.nbr_origin = {tuple(k): int(v) for k, v in state.get("nbr_origin", {}).items()}
        agent.nbr_support = {tuple(k): int(v) for k, v in state.get("nbr_support", {}).items()}
        agent.support = {int(k): int(v) for k, v in state.get("support", {}).items()}
        agent.lam = {tuple(k): np.asarray(v) for k, v in state["lam"].items()}
        agent.counters.update(state["counters"])
        agent.decrements = [float(d) for d in state.get("decrements", [])]
        agent.done_count = int(state.get("done_count", 0))
        agent.nbr_done = {int(k): (int(v[0]), int(v[1]))
                          for k, v in state.get("nbr_done", {}).items()}
        agent.last_sent_done = {int(k): int(v) for k, v in state.get("last_sent_done", {}).items()}
        return agent

    # ----------------------------------------------------------------- reporting
    def local_objects(self) -> dict[int, np.ndarray]:
        return {k: v.copy() for k, v in self.y.items()}
