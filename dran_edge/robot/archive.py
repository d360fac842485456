"""Where the robot was: the last estimates of marginalised keyframes, for loops into the past.

A DBoW2 loop may close to a keyframe anywhere in the mission's history, long after the bounded
graph removed it. Without this archive such a loop attaches to the kept node nearest in time
through VIO odometry whose covariance grows with the path, and the loops of a removed node are
re-anchored onto its neighbour: they pile up on the window's oldest node (tens per removal) and
each keeps a small share of one odometry edge — little is left of them. The archive keeps, for
every node the graph *marginalises* (plain chain nodes composed out are not archived), its
estimate at removal relative to a reference and the covariance of that relative pose given the
node's factors and the prior (:meth:`~dran_edge.robot.factor_store.FactorStore._archive_node`).
Then

- the node's loops ``(x, n)`` become factors between ``x`` and the reference ``o``,
  ``T_o⁻¹ T_x ≈ T̂_o_n Z_nx``, instead of being re-anchored
  (:meth:`~dran_edge.robot.factor_store.FactorStore._loops_into_archive`);
- a later loop whose old end is nearer (in VIO path) to an archived keyframe than to any kept
  node becomes such a factor on its current node: ``T_o⁻¹ T_b ≈ T̂_o_old · T_old_cur ·
  Z_b_cur⁻¹``, the archived covariance propagated through the VIO motion from the archived
  keyframe to the loop's stamp, plus the loop's own noise and the attachment.

**Relative to the map.** The reference is what the keyframe is known best against: of the
world and the objects, the one whose pose of the keyframe has the smallest covariance volume
(:meth:`~dran_edge.robot.factor_store.FactorStore._map_reference`) — an object, except near
the gauge early in the mission. A keyframe's world-frame estimate carries the map's placement
error of its time (gauge, drift), common to every entry of that time and to the objects the
dense prior keeps; with world-frame entries only, each loop into the archive counted that
common error again, and the window was pinned to the placement the map had when the entries
were made. Measured on six 10 000-keyframe missions, the window's mean position error then
differed from the unbounded graph's by 1.6–4.8 cm; with the reference, by 0.1–1.6 cm
(docs/notes/solve-and-bounded-graph.md, section 5c). In the DRAN agent's problem a loop into
the archive relative to an object is a view of that object (an observation).

**What it costs in consistency.** The archived relative pose was computed from information the
dense prior still holds (the objects' observations, the odometry before it): a loop into the
archive uses that shared part again. The loops into one archived keyframe share its
marginal's information: those made when it is marginalised get half of it, every later batch
half of what is left (:meth:`ArchivedPose.take`), so all of them together use it at most once,
and with the prior's copy it is counted at most twice — not conservative, but bounded; without
that budget a keyframe visited on every lap pinned the window to its frozen estimate with full
weight each time (docs/notes/solve-and-bounded-graph.md, section 5, has the measurements). The
covariance is the node's marginal given only its own factors and the prior, larger than its
marginal in the whole window, and both without the archive's own factors (``prior_clean``: the
prior the same marginalisations give without them), so archive information does not feed the
covariances of later entries (which compounded: each entry more certain than the last). A graph
without the gauge prior (a fleet robot that is not the gauge anchor: its frame comes from object
consensus and still moves) archives nothing: its
marginals have no absolute information but the round-off of the dense prior's linearisation,
which a numerical rank test cannot tell from weak information (forced on, 9 of the 79
marginalised nodes of tests/test_archive.py's mission pass it).

**Bounded.** At most ``capacity`` entries. Every marginalised keyframe gets a sequence number
and is archived when that number is a multiple of the current ``stride``; when the archive is
full the stride doubles and the entries off it are dropped (a dyadic thinning, as the skeleton
of :mod:`dran_edge.robot.skeleton`), so the archive covers the whole mission evenly at between
half and all of its capacity. Memory is O(capacity) whatever the mission's length. Pure: numpy
only, no clock.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np

from dran_edge.robot.factor_algebra import NONE


def nearest_in_time(stamps: list[int], stamp_ns: int) -> int:
    """Index of the stamp in the sorted, non-empty ``stamps`` nearest to ``stamp_ns`` (the
    earlier one on a tie)."""
    i = bisect.bisect_left(stamps, stamp_ns)
    return min(
        (j for j in (i - 1, i) if 0 <= j < len(stamps)), key=lambda j: abs(stamps[j] - stamp_ns)
    )


@dataclass
class ArchivedPose:
    """One marginalised keyframe."""

    stamp_ns: int
    segment: int
    T_world_body: np.ndarray
    """(4, 4) the estimate at removal."""
    covariance: np.ndarray
    """(6, 6) of ``T_ref_body``, [ρ, φ], right perturbation ``T = T̂ Exp(ε)``."""
    T_odom_body: np.ndarray
    """(4, 4) the keyframe's VIO pose."""
    path_m: float
    """VIO path length at the keyframe (its segment's), metres."""
    turn_rad: float
    """VIO accumulated turn at the keyframe, radians."""
    budget: float = 1.0
    """Share of the covariance's information not yet handed to loops."""
    ref_key: int = NONE
    """The variable the entry is relative to: an object's key (``OBJ + id``), or ``NONE`` for
    the world frame (module docstring, "Relative to the map")."""
    T_ref_body: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    """(4, 4) the estimate in the reference's frame, ``T̂_ref⁻¹ T̂_world_body`` (the world's:
    ``T_world_body``, the default)."""

    def __post_init__(self) -> None:
        if self.T_ref_body.size == 0:
            self.T_ref_body = self.T_world_body

    def take(self, uses: int = 1) -> float:
        """The share of the information for each of ``uses`` loops made now: half of what is
        left, split evenly (so all loops ever made into this keyframe get at most its
        information once in total)."""
        share = 0.5 * self.budget
        self.budget -= share
        return share / uses


class PoseArchive:
    """Marginalised keyframes per segment, in time order (module docstring)."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self._stamps: dict[int, list[int]] = {}
        self._entries: dict[int, list[ArchivedPose]] = {}
        self._seqs: dict[int, list[int]] = {}  # archive sequence numbers (module docstring)
        self.next_seq = 0
        self.stride = 1
        self.thinned = 0

    def __len__(self) -> int:
        return sum(len(v) for v in self._stamps.values())

    def add(self, entry: ArchivedPose) -> None:
        """Archive ``entry`` when its sequence number is on the current stride (see the class)."""
        if self.capacity <= 0:
            return
        seq = self.next_seq
        self.next_seq += 1
        if seq % self.stride:
            return
        stamps = self._stamps.setdefault(entry.segment, [])
        i = bisect.bisect_left(stamps, entry.stamp_ns)
        if i < len(stamps) and stamps[i] == entry.stamp_ns:
            self._entries[entry.segment][i] = entry
            self._seqs[entry.segment][i] = seq
            return
        stamps.insert(i, entry.stamp_ns)
        self._entries.setdefault(entry.segment, []).insert(i, entry)
        self._seqs.setdefault(entry.segment, []).insert(i, seq)
        while len(self) > self.capacity:
            self.stride *= 2
            for seg in list(self._stamps):
                keep = [j for j, q in enumerate(self._seqs[seg]) if q % self.stride == 0]
                self._stamps[seg] = [self._stamps[seg][j] for j in keep]
                self._entries[seg] = [self._entries[seg][j] for j in keep]
                self._seqs[seg] = [self._seqs[seg][j] for j in keep]
            self.thinned += 1

    def nearest(self, segment: int, stamp_ns: int) -> ArchivedPose | None:
        """The archived keyframe of ``segment`` nearest in time to ``stamp_ns``, if any."""
        stamps = self._stamps.get(segment)
        if not stamps:
            return None
        return self._entries[segment][nearest_in_time(stamps, stamp_ns)]

    def to_state(self) -> dict:
        entries = [e for seg in sorted(self._entries) for e in self._entries[seg]]
        return {
            "seqs": np.array([q for seg in sorted(self._seqs) for q in self._seqs[seg]], np.int64),
            "next_seq": self.next_seq,
            "stride": self.stride,
            "budget": np.array([e.budget for e in entries], np.float64),
            "stamps": np.array([e.stamp_ns for e in entries], np.int64),
            "segments": np.array([e.segment for e in entries], np.int64),
            "T_world_body": np.array([e.T_world_body for e in entries]).reshape(-1, 4, 4),
            "ref_key": np.array([e.ref_key for e in entries], np.int64),
            "T_ref_body": np.array([e.T_ref_body for e in entries]).reshape(-1, 4, 4),
            "covariance": np.array([e.covariance for e in entries]).reshape(-1, 6, 6),
            "T_odom_body": np.array([e.T_odom_body for e in entries]).reshape(-1, 4, 4),
            "cum": np.array([(e.path_m, e.turn_rad) for e in entries], np.float64).reshape(-1, 2),
            "thinned": self.thinned,
        }

    @classmethod
    def from_state(cls, capacity: int, state: dict | None) -> PoseArchive:
        a = cls(capacity)
        if not state:
            return a
        for i, s in enumerate(np.asarray(state["stamps"]).tolist()):
            seg = int(state["segments"][i])
            a._stamps.setdefault(seg, []).append(int(s))
            a._seqs.setdefault(seg, []).append(int(state["seqs"][i]))
            a._entries.setdefault(seg, []).append(
                ArchivedPose(
                    int(s),
                    seg,
                    np.array(state["T_world_body"][i]),
                    np.array(state["covariance"][i]),
                    np.array(state["T_odom_body"][i]),
                    float(state["cum"][i][0]),
                    float(state["cum"][i][1]),
                    float(state["budget"][i]),
                    # checkpoints written before relative entries hold world-frame ones
                    int(state["ref_key"][i]) if "ref_key" in state else NONE,
                    np.array(state["T_ref_body"][i]) if "T_ref_body" in state else np.zeros(0),
                )
            )
        a.thinned = int(state["thinned"])
        a.next_seq = int(state["next_seq"])
        a.stride = int(state["stride"])
        return a
