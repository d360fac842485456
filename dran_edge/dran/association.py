r"""Object data association of one robot's DRAN agent: which object copies and observations to trust.

Alg. 1 (docs/dran.md) assumes every tag id names one object. Tags are misread, so before each
local step the agent asks this module which of its own object observations to use (f_obj)
and which value each public object copy y_i starts from. :class:`ObjectAssociation` owns

- the own copies ``y`` (object id -> ``T_world_object``) and their :class:`Provenance` (hop
  count, origin robot, support: what the copy stands for when it is sent);
- the neighbours' latest copies, :class:`NeighbourCopy` per (neighbour, object id);
- the masks over the own observations: ``obs_ok`` (used this round), ``obs_pending`` (held
  back until a neighbour's copy corroborates them) and ``obs_ok_gate`` (passed the gate at
  :meth:`~ObjectAssociation.reset`);
- the association check's centres of the round (read by the consensus conflict kernel).

One round of the agent calls, in this order::

    adopt_unknown()          Alg. 1 lines 3–8: objects first heard of from a neighbour
    check(x)                 cross-robot association check (votes weighted by evidence)
    update_provenance()      what every own copy stands for when it is next sent

and :meth:`~ObjectAssociation.reset` whenever the local problem changes (own-observation
gating). :meth:`~ObjectAssociation.conflicts` tells the consensus term which neighbour copies
stand for another hypothesis. Counters (``obs_*``, ``objects_adopted``, ``stale_dropped``)
go to the agent's :class:`~dran_edge.dran.counters.AgentCounters`. Pure: no clock, no I/O.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from dran_edge.config import AgentConfig
from dran_edge.dran.counters import AgentCounters
from dran_edge.messages import ObjectEntry

if TYPE_CHECKING:
    from dran_edge.dran.agent import LocalProblem

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

PairKey = tuple[int, int]
"""(neighbour robot id, object id): one neighbour's copy of one object (a consensus pair)."""

_SUPPORT_MAX = 0xFFFF  # support goes on the wire as a u16


@dataclass
class Provenance:
    """What this robot's copy of an object stands for when it is sent (an ``ObjectEntry``)."""

    hop: int
    """0: built from own observations; else a relay, one hop more than the copy it follows."""
    origin: int
    """The robot whose observations the copy comes from."""
    support: int
    """Own observations the origin uses (its weight as a vote); 0: a bare estimate, no vote."""


@dataclass(frozen=True, eq=False)
class NeighbourCopy:
    """A neighbour's newest copy of an object, as last received."""

    T_world_object: FloatArray
    hop: int
    round: int
    """The sender's round when it sent the copy (an older one is dropped as stale)."""
    origin: int
    support: int


Votes = dict[int, tuple[FloatArray, FloatArray]]
"""object id -> (positions (m, 3), weights (m,)) of the independent votes on it."""


class ObjectAssociation:
    """Robot ``robot_id``'s object copies, neighbour copies and observation masks (module docstring)."""

    def __init__(self, robot_id: int, config: AgentConfig, counters: AgentCounters) -> None:
        self.id = robot_id
        self.config = config
        self.counters = counters
        #: object id -> this robot's copy y_i (T_world_object), in order of first appearance
        self.y: dict[int, FloatArray] = {}
        #: object id -> what that copy stands for (set together with ``y``)
        self.provenance: dict[int, Provenance] = {}
        #: (neighbour, object id) -> that neighbour's newest copy
        self.neighbour_copies: dict[PairKey, NeighbourCopy] = {}
        #: object id -> the association check's centre (a position) this round
        self.centres: dict[int, FloatArray] = {}
        self.obs_ok: BoolArray = np.zeros(0, bool)
        self.obs_pending: BoolArray = np.zeros(0, bool)
        self.obs_ok_gate: BoolArray = np.zeros(0, bool)
        self._problem: LocalProblem | None = None
        #: object id -> indices of its own observations (fixed for one problem)
        self._obs_groups: dict[int, IntArray] = {}

    @property
    def problem(self) -> LocalProblem:
        if self._problem is None:
            raise RuntimeError("ObjectAssociation.reset() has not been called")
        return self._problem

    def provenance_of(self, oid: int) -> Provenance:
        """The provenance of copy ``oid`` (an own observed copy if none is recorded)."""
        return self.provenance.get(oid) or Provenance(0, self.id, 1)

    # ----------------------------------------------------------------- own observations
    def reset(self, problem: LocalProblem, x: FloatArray) -> None:
        """Gate the own observations of ``problem`` (trajectory ``x``), then initialise unknown
        objects from them.

        Consistency gating (wrong tag associations): every observation predicts the object's
        position ``x_p T̃`` from the current trajectory. Per object, with three or more
        observations, those farther than ``object_gate_m`` from the medoid prediction are
        dropped (``obs_gated``). With ``object_min_views`` = k > 1, an observation is also used
        only when at least k own observations of the object (itself included) predict it
        within the gate (a tag is seen from several keyframes in a row; a wrong id is usually
        a lone observation); lone ones wait (``obs_pending``) until a neighbour's copy
        corroborates them (:meth:`check`), except where no own observation of another object
        lies within ``object_exclusion_m`` (a wrong id is a second label on something seen
        there, so it lies next to that object's views). By the same exclusion, a view that
        shares its place with another object's views, and has no more views of its own object
        there than that object has, waits too, however many views it has (``obs_shadowed``):
        a tag misread the same way from several keyframes would otherwise start a phantom copy
        where the object it misreads is. An unknown object starts at the medoid of its usable
        observations (Alg. 1 uses the first).
        """
        self._problem = p = problem
        cfg, counters = self.config, self.counters
        gate = cfg.object_gate_m
        self.obs_ok = np.ones(p.obs_object.size, bool)
        self.obs_pending = np.zeros(p.obs_object.size, bool)
        self.obs_ok_gate = self.obs_ok.copy()
        self._obs_groups = {}
        counters.obs_exclusion_clear = counters.obs_shadowed = 0
        if p.obs_object.size == 0:
            return
        pred = x[p.obs_own] @ p.obs_T
        pos_all = pred[:, :-1, -1]
        order = np.argsort(p.obs_object, kind="stable")
        ids, starts = np.unique(p.obs_object[order], return_index=True)
        self._obs_groups = {int(o): g for o, g in zip(ids.tolist(), np.split(order, starts[1:]))}
        dists = {
            oid: np.linalg.norm(pos_all[idx][:, None] - pos_all[idx][None], axis=-1)
            for oid, idx in self._obs_groups.items()
        }
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
                lone = n_near[idx] < cfg.object_min_views
                if cfg.object_exclusion_m > 0:
                    # spatial exclusion: a lone view that no view of another object shares
                    # its place with cannot be a second label of something seen there
                    clear = lone & ~collides[idx]
                    counters.obs_exclusion_clear += int(clear.sum())
                    counters.obs_shadowed += int((shadowed[idx] & ~lone).sum())
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
                self.provenance[oid] = Provenance(0, self.id, min(int(ok.sum()), _SUPPORT_MAX))
        counters.obs_gated = int((~self.obs_ok & ~self.obs_pending).sum())
        counters.obs_pending = int(self.obs_pending.sum())
        self.obs_ok_gate = self.obs_ok.copy()

    def _exclusion(self, pos: FloatArray, n_near: IntArray) -> tuple[BoolArray, BoolArray]:
        """Per own view: does an own view of another object lie within ``object_exclusion_m``
        of it (``collides``), and does one of those have at least as many views of its object
        near it as this view has of its own (``shadowed``)? Both all False unless
        ``object_min_views`` > 1 (the plain agent holds nothing back)."""
        p, cfg = self.problem, self.config
        collides = np.zeros(p.obs_object.size, bool)
        shadowed = collides.copy()
        excl = cfg.object_exclusion_m
        if excl <= 0 or cfg.object_min_views <= 1 or cfg.object_gate_m <= 0:
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

    # ----------------------------------------------------------------- neighbours' copies
    def absorb(self, neighbour: int, entry: ObjectEntry, round_: int) -> bool:
        """Keep neighbour ``neighbour``'s copy ``entry`` sent in its round ``round_`` (the
        newest wins); False (and ``stale_dropped`` counted) when an older one arrived late."""
        key = (neighbour, int(entry.object_id))
        prev = self.neighbour_copies.get(key)
        if prev is not None and prev.round > round_:
            self.counters.stale_dropped += 1
            return False
        self.neighbour_copies[key] = NeighbourCopy(
            np.asarray(entry.T_world_object, np.float64),
            int(entry.hop_count),
            round_,
            int(entry.origin_robot),
            int(entry.support),
        )
        return True

    def adopt_unknown(self) -> None:
        """Alg. 1 lines 3–8: an object first heard of from a neighbour starts at its value
        (the copy with the fewest hops below ``relay_max_hops``; relayed with one hop more)."""
        best: dict[int, tuple[int, int, NeighbourCopy]] = {}
        for (j, oid), c in self._sorted_copies():
            if oid in self.y or c.hop >= self.config.relay_max_hops:
                continue
            if oid not in best or c.hop < best[oid][0]:
                best[oid] = (c.hop, j, c)
        for oid, (hop, _j, c) in best.items():
            self.y[oid] = c.T_world_object.copy()
            self.provenance[oid] = Provenance(hop + 1, c.origin, c.support)
            self.counters.objects_adopted += 1

    def _sorted_copies(self) -> list[tuple[PairKey, NeighbourCopy]]:
        return sorted(self.neighbour_copies.items(), key=lambda kv: kv[0])

    def _copies_from_others(self) -> Iterator[tuple[int, NeighbourCopy]]:
        """(object id, copy) of every neighbour copy, in neighbour order, except those whose
        origin is this robot (its own estimate echoed back) and bare estimates (support 0: no
        observation behind them, :meth:`update_provenance`)."""
        for (_j, oid), c in self._sorted_copies():
            if c.origin != self.id and c.support > 0:
                yield oid, c

    def votes(self) -> Votes:
        """Per object: the neighbours' copies as independent votes, positions (m, 3) and weights.

        A copy counts once per robot whose observations it comes from (its origin) and weighs
        that robot's ``support`` (how many own observations of the object it uses): relays
        repeat their origin's estimate, so several neighbours relaying one robot's copy are one
        vote, and copies that come from this robot itself (its own estimate echoed back) or
        carry no support (bare estimates) are none. Per origin, the copy with the fewest hops."""
        best: dict[tuple[int, int], tuple[int, FloatArray, int]] = {}
        for oid, c in self._copies_from_others():
            if (oid, c.origin) not in best or c.hop < best[(oid, c.origin)][0]:
                best[(oid, c.origin)] = (c.hop, c.T_world_object[:-1, -1], c.support)
        votes: dict[int, tuple[list[FloatArray], list[int]]] = {}
        for (oid, _origin), (_hop, t, n) in sorted(best.items(), key=lambda kv: kv[0]):
            P, w = votes.setdefault(oid, ([], []))
            P.append(t)
            w.append(n)
        return {oid: (np.array(P), np.array(w, float)) for oid, (P, w) in votes.items()}

    # ----------------------------------------------------------------- the association check
    def check(self, x: FloatArray) -> None:
        """Cross-robot association check at trajectory ``x``, weighted by evidence.

        Per object, the candidates are the neighbours' votes (:meth:`votes`) and, while this
        robot uses own observations of it, its own copy weighted by their number. The centre is
        the weighted medoid of the candidates (the one with the least support-weighted distance
        to the others; a tie keeps the own copy). Own observations whose predicted object
        position is farther than ``association_gate_m`` from the centre are treated as wrong tag
        associations and dropped (``obs_rejected``): two keyframes' worth of a wrong id lose to
        another robot's five correct views, whichever robot got its copy out first. A copy
        left without own observations that is farther than the gate from the centre (built
        from the wrong observations, or a relay that sided with the weaker hypothesis)
        restarts there, also when the centre is a lone vote; a copy within the gate is left to
        consensus (restarting it every round kept undoing the local steps and the duals, and
        the fleet's estimate slid away over hundreds of rounds: docs/dran.md). The centres are
        kept for the round's consensus kernel (``centres``, ``centre_reach_m``). Re-evaluated
        every round, so a dropped observation comes back once the estimates agree with it."""
        gate = self.config.association_gate_m
        p = self.problem
        if gate <= 0:
            return
        votes = self.votes()
        self.centres = {}
        # held-back views in use: corroborated before and not rejected since (see below)
        latched = self.obs_pending & self.obs_ok
        if not votes:
            self.obs_ok = self.obs_ok_gate | latched
            self.counters.obs_rejected = self.counters.obs_corroborated = 0
            return
        n_obs = p.obs_object.size
        # predicted object positions x_p t̃ (rotation times translation, no 4x4 products)
        xo = x[p.obs_own]
        pred = (xo[:, :-1, :-1] @ p.obs_T[:, :-1, -1:])[..., 0] + xo[:, :-1, -1]
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
            self.centres[oid] = centre
            in_use = (self.obs_ok_gate[idx] | corroborated[idx] | latched[idx]) & ~rejected[idx]
            if (
                oid in self.y
                and not in_use.any()
                and np.linalg.norm(self.y[oid][:-1, -1] - centre) > gate
            ):
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
        self.counters.obs_rejected = int(rejected.sum())
        self.counters.obs_corroborated = int(corroborated.sum())

    def _corroborated(self, pred: FloatArray, votes: Votes) -> BoolArray:
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
        d = np.linalg.norm(
            pred[pend][:, None] - np.vstack([P for P, _w in votes.values()])[None], axis=-1
        )
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

    def update_provenance(self) -> None:
        """Hop count, origin and support of every copy: 0, this robot and the number of own
        observations in use while there are any; otherwise a relay of the nearest neighbour's
        copy (fewest hops) that has support, lies within ``association_gate_m`` of it and does
        not come from this robot, one hop more, with that copy's origin and support; otherwise
        a bare estimate (support 0, no vote anywhere). A robot whose own observations were all
        rejected thus stops passing its copy off as evidence, on its own behalf or on a former
        source's (before, such a copy kept its last support for good)."""
        gate = self.config.association_gate_m
        nearest: dict[int, tuple[int, int, int]] = {}
        for oid, c in self._copies_from_others():
            if oid not in self.y:
                continue
            if gate > 0 and np.linalg.norm(c.T_world_object[:-1, -1] - self.y[oid][:-1, -1]) > gate:
                continue
            if oid not in nearest or c.hop < nearest[oid][0]:
                nearest[oid] = (c.hop, c.origin, c.support)
        for oid in self.y:
            idx = self._obs_groups.get(oid)
            n_own = int(self.obs_ok[idx].sum()) if idx is not None else 0
            if n_own:
                self.provenance[oid] = Provenance(0, self.id, min(n_own, _SUPPORT_MAX))
            elif oid in nearest:
                hop, origin, support = nearest[oid]
                self.provenance[oid] = Provenance(hop + 1, origin, support)
            else:  # a bare estimate now: it no longer stands for evidence
                self.provenance.setdefault(oid, Provenance(0, self.id, 1)).support = 0

    # ----------------------------------------------------------------- consensus conflicts
    def conflicts(self, pair_keys: tuple[PairKey, ...]) -> BoolArray:
        """Per consensus pair (j, object): does j's copy stand for another hypothesis than ours?

        Yes when it lies more than ``centre_reach_m`` from the association check's centre for
        the object (``centres``, whatever its origin: a relay dragged by a phantom carries the
        right origin), or when it comes from another observing robot (origin) and lies more
        than ``conflict_reach_m`` from our copy: two drifted estimates of one object lie closer,
        so beyond it at least one of them is something else; a relay of our own copy is never a
        conflict by that rule. Both reaches 0 turn the conflict kernel off (the agent then does
        not ask). Counted per pair and round in ``AgentCounters.consensus_conflicts``."""
        reach = self.config.conflict_reach_m
        out = np.zeros(len(pair_keys), bool)
        centre_reach = self.config.centre_reach_m
        centres = self.centres if centre_reach > 0 else {}
        for i, (j, oid) in enumerate(pair_keys):
            t_j = self.neighbour_copies[(j, oid)].T_world_object[:-1, -1]
            if oid in centres and np.linalg.norm(t_j - centres[oid]) > centre_reach:
                out[i] = True
                continue
            if reach <= 0:
                continue
            if self.neighbour_copies[(j, oid)].origin == self.provenance_of(oid).origin:
                continue
            out[i] = np.linalg.norm(t_j - self.y[oid][:-1, -1]) > reach
        return out

    # ----------------------------------------------------------------- checkpoints
    def to_state(self) -> dict[str, Any]:
        """The checkpointed part (the agent's ``y``, ``hops``, ``origin``, ``nbr_obj``,
        ``nbr_origin``, ``nbr_support`` and ``support`` entries); the masks are not stored, they
        come from :meth:`reset` of the restored problem."""
        prov, nbr = self.provenance, self.neighbour_copies
        return {
            "y": {int(k): v.copy() for k, v in self.y.items()},
            "hops": {k: p.hop for k, p in prov.items()},
            "origin": {k: p.origin for k, p in prov.items()},
            "nbr_obj": {k: (c.T_world_object.copy(), c.hop, c.round) for k, c in nbr.items()},
            "nbr_origin": {k: c.origin for k, c in nbr.items()},
            "nbr_support": {k: c.support for k, c in nbr.items()},
            "support": {k: p.support for k, p in prov.items()},
        }

    def load_state(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`to_state` wrote (also checkpoints without ``nbr_origin``,
        ``nbr_support`` or ``support``: a neighbour's copy then came from it with support 1)."""
        self.y = {int(k): np.asarray(v, np.float64) for k, v in state["y"].items()}
        hops = {int(k): int(v) for k, v in state["hops"].items()}
        origin = {int(k): int(v) for k, v in state["origin"].items()}
        support = {int(k): int(v) for k, v in state.get("support", {}).items()}
        self.provenance = {
            k: Provenance(h, origin.get(k, self.id), support.get(k, 1)) for k, h in hops.items()
        }
        nbr_origin = {_pair(k): int(v) for k, v in state.get("nbr_origin", {}).items()}
        nbr_support = {_pair(k): int(v) for k, v in state.get("nbr_support", {}).items()}
        self.neighbour_copies = {}
        for k, v in state["nbr_obj"].items():
            key = _pair(k)
            self.neighbour_copies[key] = NeighbourCopy(
                np.asarray(v[0]),
                int(v[1]),
                int(v[2]),
                nbr_origin.get(key, key[0]),
                nbr_support.get(key, 1),
            )


def _pair(key: Any) -> PairKey:
    j, oid = key
    return int(j), int(oid)
