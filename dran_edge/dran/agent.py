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
           [+ θ (λ_ij − λ_ij before its last update): dual_momentum θ > 0, off by default]
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

The local problem comes from a :class:`~dran_edge.dran.problem.LocalProblem` (docs/dran.md),
built from a prebuilt partition (``LocalProblem.from_partition``; bench g2o, simulations) or by
the daemon from the bounded online graph; the agent keeps estimates by keyframe id across
``set_problem`` calls. Which object observations and copies to trust (gating, the cross-robot
association check, hop counts and provenance) is :mod:`dran_edge.dran.association`'s job
(``Agent.objects``); the local pose graph of L̂_i is assembled by
:mod:`dran_edge.dran.local_structure`; what the agent counts is an
:class:`~dran_edge.dran.counters.AgentCounters`.

Size: over ~500 lines because Algorithm 1 and its stopping tests (association, the local
structure and the problem are in their own modules); over 500 only by ruff format's layout.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.config import AgentConfig
from dran_edge.dran.association import ObjectAssociation, PairKey
from dran_edge.dran.consensus import ConsensusFactors, consensus_error, dual_update, phi, phi_dim
from dran_edge.dran.counters import AgentCounters
from dran_edge.dran.local_structure import LocalStructure as _Structure
from dran_edge.dran.local_structure import AnchorKey, build_structure, consensus_factors
from dran_edge.dran.problem import LocalProblem
from dran_edge.events import (
    EstimateUpdate,
    Health,
    NeighbourData,
    Outgoing,
    Output,
    Tick,
)
from dran_edge.solver.damping import AGENT_DAMPING, DampingState, damped_step
from dran_edge.solver.factors import Cauchy
from dran_edge.solver.graph import PoseGraph
from dran_edge.solver.lm import (
    StructurePlan,
    evaluate_cost,
    linearize,
    retract,
    schur_step,
)
from dran_edge.messages import NeighbourMessage, ObjectEntry, SeparatorEntry

__all__ = ["Agent", "LocalProblem"]  # LocalProblem lives in dran_edge.dran.problem

log = logging.getLogger(__name__)


def _log_rate(h: np.ndarray) -> float:
    """Contraction rate per step of the positive sequence ``h``: exp of the least-squares slope
    of log h (a geometric sequence gives its ratio; a noisy one its trend)."""
    k = np.arange(h.size, dtype=np.float64)
    k -= k.mean()
    return float(np.exp(np.dot(k, np.log(h)) / np.dot(k, k)))


SentKey = tuple[int, str, int]
"""(neighbour, "s" or "o", keyframe or object id) of a value last sent."""


class Agent:
    """Robot ``config.robot_id``'s DRAN agent (see the module docstring)."""

    def __init__(
        self,
        config: AgentConfig,
        problem: LocalProblem | None = None,
        weights: dict[int, float] | None = None,
    ):
        self.config = config
        self.id = int(config.robot_id)
        self.neighbours = tuple(int(q) for q in config.neighbours)
        deg = len(self.neighbours)
        #: w_ij per neighbour (MH); without the neighbours' degrees we assume equal degrees.
        self.w = {
            q: (float(weights[q]) if weights and q in weights else 1.0 / (1.0 + deg))
            for q in self.neighbours
        }
        self.problem = (
            problem if problem is not None else LocalProblem.empty(config.dim, config.residual)
        )
        self.x = self.problem.x0.copy()
        self.k = 0
        self.mu: float | None = None
        self.counters = AgentCounters()
        #: the object copies y_i, the neighbours' copies and which own observations are used
        self.objects = ObjectAssociation(self.id, config, self.counters)
        #: (owner, keyframe id) -> the neighbour's separator pose and the round it was sent in
        self.anchors: dict[AnchorKey, np.ndarray] = {}
        self.anchor_round: dict[AnchorKey, int] = {}
        #: (neighbour, object id) -> λ_ij, the dual of that consensus pair
        self.lam: dict[PairKey, np.ndarray] = {}
        #: (neighbour, object id) -> λ_ij before the last dual update (dual_momentum > 0)
        self.lam_prev: dict[PairKey, np.ndarray] = {}
        self.last_sent: dict[SentKey, tuple[np.ndarray, int]] = {}
        #: (neighbour, "o", object id) -> (origin, hop, support) last sent with that copy
        self.last_sent_provenance: dict[SentKey, tuple[int, int, int]] = {}
        self.converged = False
        self.last_norms = (math.inf, math.inf, math.inf)
        self.last_cost = math.nan
        self.last_decrease = math.inf  # decrease of L̂_i by the last local step
        self._cost_at_start = math.nan  # L̂_i before the last local step
        #: the stopping rule (docs/notes/stopping-rule.md): local Newton decrements ½gᵀM⁻¹g of
        #: the last own steps, this robot's done counter, the neighbours' (value, round)
        self.decrements: list[float] = []
        self.last_decrement = math.inf
        self.done_count = 0
        self.nbr_done: dict[int, tuple[int, int]] = {}
        self.last_sent_done: dict[int, int] = {}
        self.stop_reason: str | None = None  # "criterion" or "k_max" once converged
        self.last_stop_test: dict[str, float] = {}
        self._structure: _Structure | None = None
        self.objects.reset(self.problem, self.x)

    @property
    def y(self) -> dict[int, np.ndarray]:
        """This robot's object copies y_i (object id -> T_world_object; ``objects.y``)."""
        return self.objects.y

    # ----------------------------------------------------------------- inputs
    def handle(self, event: object) -> list[Output]:
        """The only way in: absorb one event, return the outputs it causes."""
        if isinstance(event, NeighbourData):
            self._absorb(event.message)
            return []
        if isinstance(event, Tick):
            return self._round(int(event.stamp_ns))
        self.counters.unhandled_events += 1
        return [Health(getattr(event, "stamp_ns", 0), {"unhandled": type(event).__name__})]

    def set_problem(self, problem: LocalProblem) -> None:
        """Replace the local problem (the online graph changed); estimates kept by keyframe id."""
        old = {int(k): i for i, k in enumerate(self.problem.pose_ids.tolist())}
        x = problem.x0.copy()
        for i, k in enumerate(problem.pose_ids.tolist()):
            if k in old:
                x[i] = self.x[old[k]]
        self.problem, self.x, self._structure = problem, x, None
        self.objects.reset(problem, x)

    def _absorb(self, msg: NeighbourMessage) -> None:
        j, rnd = int(msg.sender_id), int(msg.round)
        if msg.done_count is not None and self.nbr_done.get(j, (0, -1))[1] <= rnd:
            self.nbr_done[j] = (int(msg.done_count), rnd)
        for e in msg.separators:
            key = (int(e.owner_robot), int(e.keyframe_id))
            if self.anchor_round.get(key, -1) > rnd:
                self.counters.stale_dropped += 1
                continue
            self.anchors[key] = np.asarray(e.T_world_body, dtype=np.float64)
            self.anchor_round[key] = rnd
        for o in msg.objects:
            self.objects.absorb(j, o, rnd)

    # ----------------------------------------------------------------- one round
    def _structure_for(self) -> _Structure:
        p, objects = self.problem, self.objects
        anchor_keys = tuple(
            sorted(
                {
                    (int(o), int(a))
                    for o, a in zip(p.inter_owner, p.inter_anchor_id)
                    if (int(o), int(a)) in self.anchors
                }
            )
        )
        pair_keys = tuple(
            sorted(k for k in objects.neighbour_copies if k[1] in self.y and k[0] in self.w)
        )
        key = (tuple(sorted(self.y)), anchor_keys, pair_keys, objects.obs_ok.tobytes())
        if self._structure is None or self._structure.key != key:
            self._structure = build_structure(
                p,
                self.config,
                key,
                objects.obs_ok,
                lambda slot, base: self._consensus_blocks(slot, base, pair_keys),
            )
        return self._structure

    def _consensus_blocks(
        self, obj_slot: dict[int, int], c_base: int, pair_keys: tuple[PairKey, ...]
    ) -> tuple[ConsensusFactors, ...]:
        return consensus_factors(
            self.config, pair_keys, obj_slot, c_base, self.lam, self.w, self.objects.conflicts
        )

    def _poses(self, s: _Structure) -> np.ndarray:
        return s.poses(self.x, self.y, self.anchors, self.objects.neighbour_copies)

    def _round(self, stamp_ns: int) -> list[Output]:
        c = self.config
        self.k += 1
        self.counters.rounds += 1
        if (self.k - 1) % c.colours != c.colour:
            # not this robot's turn in the colour schedule: keep absorbing, send nothing
            self.counters.idle_rounds += 1
            return [self._estimate(stamp_ns, self.last_norms[2])]
        self.objects.adopt_unknown()
        self.objects.check(self.x)
        self.objects.update_provenance()
        s = self._structure_for()
        # Dual update, eq. 5b, with the newest copies of both ends.
        if s.pair_keys:
            y_i = np.stack([self.y[o] for _, o in s.pair_keys])
            y_j = s.neighbour_copies(self.objects.neighbour_copies)
            r = phi_dim(c.residual, c.dim)
            lam = np.stack([self.lam.get(k, np.zeros(r)) for k in s.pair_keys])
            w = np.array([self.w[j] for j, _ in s.pair_keys])
            p_ij = phi(y_i, y_j, c.residual)
            # Anti-windup: integrate only pairs already near consensus (docs/dran.md); far apart
            # copies (first rounds, sparse graphs) made the duals overshoot and diverge.
            near = consensus_error(y_i, y_j) <= c.dual_max_phi2
            new = dual_update(lam, p_ij, w, c.beta, c.eta)
            if c.dual_momentum > 0.0:  # heavy ball on eq. 5b (docs/dran.md, acceleration)
                prev = np.stack([self.lam_prev.get(k, l) for k, l in zip(s.pair_keys, lam)])
                new = new + c.dual_momentum * (lam - prev)
                for key, value in zip(s.pair_keys, lam):
                    self.lam_prev[key] = value
            lam = np.where(near[:, None], new, lam)
            for key, value in zip(s.pair_keys, lam):
                self.lam[key] = value
        cons = self._consensus_blocks(s.object_slot, s.consensus_base, s.pair_keys)
        graph = s.graph.with_factors(*cons)
        kernel = cons[0].kernel if cons else None
        if isinstance(kernel, Cauchy):  # pairs under the kernel (conflicts) this round
            self.counters.consensus_conflicts += int(np.isfinite(kernel.scale).sum())
        poses = self._poses(s)
        x_k = self.x.copy()
        accepted_before = self.counters.accepted
        norm_u, norm_v = self._local_step(graph, s, poses)
        if c.sor_omega != 1.0 and accepted_before > 0 and self.counters.accepted > accepted_before:
            # block SOR on the trajectory: x_k ⊕ ω (z ⊖ x_k), z the round's local solution;
            # kept only while it does not raise L̂_i above its value at x_k (nonlinear safeguard)
            z = self.x
            self.x = geo.retract(x_k, c.sor_omega * geo.log(geo.between(x_k, z)))
            if evaluate_cost(graph, self._poses(s)) > self._cost_at_start:
                self.x = z
                self.counters.sor_rejected += 1
        phi2 = 0.0
        if s.pair_keys:
            y_i = np.stack([self.y[o] for _, o in s.pair_keys])
            y_j = s.neighbour_copies(self.objects.neighbour_copies)
            phi2 = float(np.max(consensus_error(y_i, y_j)))
        self.last_norms = (norm_u, norm_v, phi2)
        iterations = self.counters.rounds - self.counters.idle_rounds
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
        if c.eps_cost_rel > 0 and self.last_decrease <= c.eps_cost_rel * max(
            self.last_cost, 1e-300
        ):
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
            rate = max(_log_rate(h), _log_rate(h[W // 2 :]))
        test["rate"] = float(rate)
        if not rate < 1.0:
            return False
        test["tail_rel"] = d / (1.0 - rate) / L
        if s.pair_keys:
            y_i = np.stack([self.y[o] for _, o in s.pair_keys])
            y_j = s.neighbour_copies(self.objects.neighbour_copies)
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

    def _local_step(
        self, graph: PoseGraph, s: _Structure, poses: np.ndarray
    ) -> tuple[float, float]:
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
            self.counters.linear_fail += out.solve_failures
        if out.accepted:
            assert out.u is not None and out.v is not None and out.candidate is not None
            self.counters.accepted += 1
            self.last_decrease = cost - out.cost
            self.last_cost = out.cost
            self._store(plan, out.candidate)
            return float(np.linalg.norm(c.gamma * out.u)), float(np.linalg.norm(c.alpha * out.v))
        self.last_decrease = math.inf  # no step taken: not evidence of convergence
        self.counters.rejected += 1
        self.last_cost = cost
        return 0.0, 0.0

    def _store(self, plan: StructurePlan, poses: np.ndarray) -> None:
        n = self.problem.n
        self.x = poses[:n].copy()
        for i, oid in enumerate(sorted(self.y)):
            self.y[oid] = poses[n + i].copy()

    # ----------------------------------------------------------------- outputs
    def _changed(self, key: SentKey, T: np.ndarray, force: bool) -> bool:
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
            seps: list[SeparatorEntry] = []
            for i in p.separators_for.get(q, np.zeros(0, np.int64)).tolist():
                key = (q, "s", int(p.pose_ids[i]))
                if self._changed(key, self.x[i], False):
                    seps.append(
                        SeparatorEntry(
                            self.id, int(p.pose_ids[i]), int(p.pose_stamps_ns[i]), self.x[i].copy()
                        )
                    )
                    self.last_sent[key] = (self.x[i].copy(), self.k)
            objs: list[ObjectEntry] = []
            for oid, T in objects:
                key = (q, "o", oid)
                # beyond relay_max_hops a copy is not offered to new neighbours, but one that
                # was sent to q before keeps being updated there: else q would hold our last
                # value (and its provenance) for good, e.g. a phantom we have since dropped
                pv = self.objects.provenance_of(oid)
                if pv.hop >= self.config.relay_max_hops and key not in self.last_sent:
                    continue
                prov = (pv.origin, pv.hop, pv.support)
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
                        out.append(
                            Outgoing(
                                NeighbourMessage(self.id, self.k, stamp_ns, done_count=done), (q,)
                            )
                        )
                        continue
            if seps or objs:
                msg = NeighbourMessage(
                    self.id, self.k, stamp_ns, tuple(seps), tuple(objs), done_count=done
                )
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
            stamp_ns=stamp_ns,
            round=self.k,
            keyframe_stamps_ns=p.pose_stamps_ns.copy(),
            T_world_body=self.x.copy(),
            object_ids=tuple(o for o, _ in objects),
            T_world_object=(np.stack([T for _, T in objects]) if objects else np.zeros((0, D, D))),
            cost=float(self.last_cost),
            step_norm_u=self.last_norms[0],
            step_norm_v=self.last_norms[1],
            consensus_error=phi2,
            converged=self.converged,
        )

    # ----------------------------------------------------------------- checkpoints
    def to_state(self) -> dict[str, Any]:
        """Everything needed to resume (plain dicts, lists and numpy arrays)."""
        obj = self.objects.to_state()
        return {
            "problem": self.problem.to_dict(),
            "x": self.x.copy(),
            "k": self.k,
            "mu": self.mu,
            "y": obj["y"],
            "hops": obj["hops"],
            "origin": obj["origin"],
            "anchors": {k: v.copy() for k, v in self.anchors.items()},
            "anchor_round": dict(self.anchor_round),
            "nbr_obj": obj["nbr_obj"],
            "nbr_origin": obj["nbr_origin"],
            "nbr_support": obj["nbr_support"],
            "support": obj["support"],
            "lam": {k: v.copy() for k, v in self.lam.items()},
            "lam_prev": {k: v.copy() for k, v in self.lam_prev.items()},
            "w": dict(self.w),
            "counters": self.counters.to_dict(),
            "decrements": list(self.decrements),
            "done_count": self.done_count,
            "nbr_done": dict(self.nbr_done),
            "last_sent_done": dict(self.last_sent_done),
        }

    @classmethod
    def from_state(cls, config: AgentConfig, state: dict[str, Any]) -> Agent:
        agent = cls(config, LocalProblem.from_dict(state["problem"]), weights=state["w"])
        agent.x = np.asarray(state["x"], np.float64).copy()
        agent.k, agent.mu = int(state["k"]), state["mu"]
        agent.objects.load_state(state)
        agent.anchors = {_key2(k): np.asarray(v) for k, v in state["anchors"].items()}
        agent.anchor_round = {_key2(k): int(v) for k, v in state["anchor_round"].items()}
        agent.lam = {_key2(k): np.asarray(v) for k, v in state["lam"].items()}
        agent.lam_prev = {_key2(k): np.asarray(v) for k, v in state.get("lam_prev", {}).items()}
        agent.counters.update(state["counters"])
        agent.decrements = [float(d) for d in state.get("decrements", [])]
        agent.done_count = int(state.get("done_count", 0))
        agent.nbr_done = {
            int(k): (int(v[0]), int(v[1])) for k, v in state.get("nbr_done", {}).items()
        }
        agent.last_sent_done = {int(k): int(v) for k, v in state.get("last_sent_done", {}).items()}
        return agent

    # ----------------------------------------------------------------- reporting
    def local_objects(self) -> dict[int, np.ndarray]:
        return {k: v.copy() for k, v in self.y.items()}

    def local_cost(self) -> float:
        """L̂_i (eq. 6) at the current estimates, with the duals and neighbour copies held now."""
        s = self._structure_for()
        cons = self._consensus_blocks(s.object_slot, s.consensus_base, s.pair_keys)
        return evaluate_cost(s.graph.with_factors(*cons), self._poses(s))


def _key2(key: Any) -> tuple[int, int]:
    a, b = key
    return int(a), int(b)
