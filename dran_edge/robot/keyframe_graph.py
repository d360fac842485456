r"""One robot's bounded local pose graph: keyframe nodes, objects, and factors with covariances.

What goes in (events of :mod:`dran_edge.events`): VIO odometry samples, VIO keyframes, DBoW2
loops, resets, tag observation batches. What comes out: trajectory nodes (``T_world_body``),
object copies (``T_world_object``) and binary relative-pose factors with 6x6 covariances, as a
:class:`~dran_edge.solver.graph.PoseGraph` for the Schur-LM solver (nodes PRIVATE, objects PUBLIC, as
paper Sec. 3.1) — the DRAN agent owns one and adds its consensus terms.

**Keyframe selection.** A VIO keyframe becomes a node when it is the first of its segment, or
has moved ``keyframe_min_distance_m`` / turned ``keyframe_min_angle_rad`` from the last node,
or ``keyframe_max_interval_s`` has passed. Keyframes not selected stay in a bounded buffer of
VIO poses so that loops referring to them can still be attached.

**Segments** (:mod:`dran_edge.robot.segments`): an odometry edge only joins nodes of one segment.

**Factors.** Every factor is ``(p, q, Z, Σ)``: the measurement ``Z ≈ T_p⁻¹ T_q`` with right
noise, ``T_p⁻¹ T_q = Z Exp(ε)``, ``ε ~ N(0, Σ)`` in the tangent order [ρ, φ]. Endpoints are
nodes or objects; a unary prior (the gauge) has ``p = NONE``. Odometry between kept keyframes:
``Z = (T^odom_p)⁻¹ T^odom_q`` with the configured per-edge + per-metre/per-radian noise (VINS
gives no covariances). Loops: ``T_old_cur`` with ``loop_noise``. Observations: the frame's body
pose is interpolated from odometry at the frame stamp (slerp/lerp) and composed with the
tag pose, ``Z = T_node_body(s) T_body_object``, covariance = observation ⊕ interpolation motion.

**Bounded.** At most ``max_nodes`` nodes and ``max_edges`` factors. Over either cap the
daemon removes nodes, oldest first, preferring plain chain nodes, then loop endpoints and object
anchors, then separators (:meth:`KeyframeGraph.protect`). Removing node ``n`` keeps its information
by composition with covariance propagation (Solà et al. 2018, eqs. 159-160 for the adjoint):
choose the most certain factor ``e = (n, m)`` as the bridge; every other factor ``(x, n)``
becomes ``(x, m)`` with

    Z_xm = Z_xn Z_nm,    Σ_xm = Ad(Z_nm⁻¹) Σ_xn Ad(Z_nm⁻¹)ᵀ + Σ_nm

(a unary prior on ``n`` likewise becomes a prior on ``m``). For a node with only its two
odometry edges this is exact marginalisation of the chain (to first order). When the bridge has
several uses (re-anchored factors, and for a node with loops the Schur complement of the rest)
its information is split among them, ``Σ_nm / w_i`` with ``Σ w_i = 1`` (:func:`split_weights`):
counted once in total, and conservative — the kept graph's information never exceeds the exact
marginal's (docs/notes/solve-and-bounded-graph.md). Factors that end up parallel (same
endpoints) are fused, ``Ω = Ω₁ + Ω₂``, ``Z = Z₁ Exp(Ω⁻¹ Ω₂ Log(Z₁⁻¹ Z₂))``, which is what keeps
the edge count bounded. Memory is O(max_nodes + max_edges + buffers) whatever the mission length.

Pure: numpy/scipy only, no clock, no I/O. SE(3) only (the VIO is 3-D).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from dran_edge import geometry as geo
from dran_edge.config import AgentConfig, NoiseModel, Residual
from dran_edge.events import Keyframe, LoopClosure, ObservationBatch, OdometrySample, VioReset
from dran_edge.solver.factors import (
    BetweenFactors,
    PriorFactors,
    make_kernel,
    whitening_from_information,
)
from dran_edge.solver.graph import PoseGraph, VariableKind
from dran_edge.robot.segments import Segmenter

OBJ = 1 << 40  # variable key of object k is OBJ + k; node keys are < OBJ
NONE = -1  # p of a unary prior

KIND_ODOMETRY, KIND_LOOP, KIND_OBSERVATION, KIND_PRIOR = 0, 1, 2, 3
KIND_NAMES = ("odometry", "loop", "observation", "prior")

GAUGE_SIGMA = (1e-4, 1e-4)  # metres, radians: the first node's prior (local gauge)
ODOMETRY_BUFFER = 4096  # recent odometry samples kept for interpolation
KEYFRAME_BUFFER = 20000  # recent VIO keyframe poses kept for late loops
PENDING_OBSERVATIONS = 256
KEYFRAME_MATCH_NS = 1_000_000  # a loop's keyframe stamp matches a buffered keyframe within 1 ms


def gauge_anchor(config: AgentConfig) -> bool:
    """Whether this robot's first node carries the gauge prior: exactly when its id is below
    all its neighbours' (a lone robot anchors; in a fleet the lowest id does, the others are
    placed by object consensus)."""
    return all(config.robot_id < q for q in config.neighbours)


def rotation_angle(R: np.ndarray) -> float:
    """|Log(R)| in radians (a cheap form for thresholds and noise models)."""
    return float(np.arccos(np.clip((np.trace(R) - 1.0) * 0.5, -1.0, 1.0)))


def diag_covariance(noise: NoiseModel) -> np.ndarray:
    return np.diag([noise.sigma_translation_m**2] * 3 + [noise.sigma_rotation_rad**2] * 3)


def _inv(T: np.ndarray) -> np.ndarray:
    """Inverse of one SE(3) matrix (unbatched fast path of geo.se3_inverse)."""
    out = np.eye(4)
    Rt = T[:3, :3].T
    out[:3, :3] = Rt
    out[:3, 3] = -Rt @ T[:3, 3]
    return out


def _adj(T: np.ndarray) -> np.ndarray:
    """Adj(T) of one SE(3) matrix, [[R, [t]x R], [0, R]] (unbatched geo.se3_adjoint)."""
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    out = np.zeros((6, 6))
    out[:3, :3] = R
    out[3:, 3:] = R
    out[:3, 3:] = tx @ R
    return out


def compose_cov(Z_ab: np.ndarray, S_ab: np.ndarray, Z_bc: np.ndarray, S_bc: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """(Z_ac, Σ_ac) of two chained measurements (right noise; independent)."""
    Ad = _adj(_inv(Z_bc))
    return Z_ab @ Z_bc, Ad @ S_ab @ Ad.T + S_bc


def invert_cov(Z_ab: np.ndarray, S_ab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Z_ba, Σ_ba): the same measurement seen from the other end."""
    Ad = _adj(Z_ab)
    return _inv(Z_ab), Ad @ S_ab @ Ad.T


def fuse(Z1: np.ndarray, S1: np.ndarray, Z2: np.ndarray, S2: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray]:
    """Information-weighted fusion of two measurements of the same relative pose."""
    O1, O2 = np.linalg.inv(S1), np.linalg.inv(S2)
    S = np.linalg.inv(O1 + O2)
    delta = S @ O2 @ geo.se3_log(geo.se3_between(Z1, Z2))
    return Z1 @ geo.se3_exp(delta), 0.5 * (S + S.T)


def split_weights(a0: float, covariances: list[np.ndarray]) -> tuple[float, list[float]]:
    """Shares (w₀, [w_i]) of one factor's information Ω among its uses, w₀ + Σ w_i = 1.

    Use i composes the shared factor with a factor of covariance ``covariances[i]``; use 0 (the
    marginalisation) has scalar information ``a0`` (0: no such use). Giving use i the copy
    ``w_i Ω`` counts Ω exactly once: the copies sum to the original factor, and eliminating the
    removed node separately in each use is the original elimination with the constraint "all
    copies of the node are equal" dropped — which can only lose information, so the result is
    conservative (the kept graph's information ⪯ the exact marginal's). The shares maximise the
    scalar information Σ 1/(s_i + b/w_i) of the uses (s_i = tr Σ_i, a0 = 1/s_0, b the shared
    factor's): w_i ∝ 1/s_i — a precise partner gets most of the shared factor.
    """
    a = [a0] + [1.0 / max(float(np.trace(S)), 1e-300) for S in covariances]
    total = sum(a)
    if total <= 0.0:
        k = len(covariances)
        return 0.0, [1.0 / k] * k
    return a[0] / total, [x / total for x in a[1:]]


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


class KeyframeGraph:
    """The bounded local graph of one robot (see module docstring)."""

    def __init__(self, config: AgentConfig, *, anchor_first: bool = True,
                 marginalize: bool = True):
        if config.dim != 3:
            raise ValueError("KeyframeGraph supports dim=3 only (VIO poses are SE(3))")
        self.config = config
        self.bounds = config.graph
        self.anchor_first = anchor_first
        self.marginalize = marginalize
        self.segmenter = Segmenter(self.bounds)
        # nodes: key -> row in these lists (compact dict-of-arrays kept small by the cap)
        self.next_node = 0
        self.node_stamp: dict[int, int] = {}
        self.node_segment: dict[int, int] = {}
        self.node_odom: dict[int, np.ndarray] = {}  # T_odom_body of the keyframe
        self.node_est: dict[int, np.ndarray] = {}  # T_world_body estimate
        self.node_cum: dict[int, tuple[float, float]] = {}  # VIO path length m, turn rad
        self.kf_last: dict[int, tuple[int, np.ndarray, float, float]] = {}  # seg -> last VIO kf
        self.obj_est: dict[int, np.ndarray] = {}  # object id -> T_world_object
        self.protected: set[int] = set()
        self.last_node_of_segment: dict[int, int] = {}
        self.seg_nodes: dict[int, tuple[list[int], list[int]]] = {}  # seg -> (stamps, nodes)
        # factors: slot -> (p, q, Z, S, kind); adjacency: key -> set of slots
        self.factors: dict[int, tuple[int, int, np.ndarray, np.ndarray, int]] = {}
        self.adj: dict[int, set[int]] = {}
        self.pair_slot: dict[tuple[int, int, int], int] = {}
        self.special: dict[int, int] = {}  # key -> number of loop/observation factors
        self.next_slot = 0
        # the marginalisation prior: keys (k,), T_lin (k, 4, 4), W (r, 6k), e (r,)
        self.prior: dict | None = None
        # buffers
        self.odo_stamps: deque[int] = deque(maxlen=ODOMETRY_BUFFER)
        self.odo_poses: deque[np.ndarray] = deque(maxlen=ODOMETRY_BUFFER)
        self.odo_segments: deque[int] = deque(maxlen=ODOMETRY_BUFFER)
        self.kf_buffer: dict[int, tuple[int, np.ndarray]] = {}  # stamp -> (segment, T_odom)
        self.kf_order: deque[int] = deque()
        self.pending_obs: deque[ObservationBatch] = deque(maxlen=PENDING_OBSERVATIONS)
        self.counters: dict[str, int] = {}
        self._odo_cov_base = np.diag([config.odometry_noise.sigma_translation_m**2] * 3
                                     + [config.odometry_noise.sigma_rotation_rad**2] * 3)

    # ------------------------------------------------------------------ small helpers
    def _count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + n

    @property
    def num_nodes(self) -> int:
        return len(self.node_stamp)

    @property
    def num_factors(self) -> int:
        return len(self.factors)

    def odometry_covariance(self, Z: np.ndarray, path_m: float | None = None,
                            turn_rad: float | None = None) -> np.ndarray:
        """Σ of VIO relative motion Z (configured noise model), growing with the distance
        travelled ``path_m`` and angle turned ``turn_rad`` (default: those of Z itself)."""
        n = self.config.odometry_noise
        dt = float(np.linalg.norm(Z[:3, 3])) if path_m is None else path_m
        dr = rotation_angle(Z[:3, :3]) if turn_rad is None else turn_rad
        st = n.sigma_translation_m + n.per_metre * dt
        sr = n.sigma_rotation_rad + n.per_radian * dr
        return np.diag([st * st] * 3 + [sr * sr] * 3)

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

    # ------------------------------------------------------------------ events
    def handle(self, event) -> bool:
        """Absorb one event; True if the graph's structure changed."""
        if isinstance(event, OdometrySample):
            return self._odometry(event)
        if isinstance(event, Keyframe):
            return self._keyframe(event)
        if isinstance(event, LoopClosure):
            return self._loop(event)
        if isinstance(event, VioReset):
            self.segmenter.reset(event.stamp_ns, event.reason)
            self._count("resets")
            return False
        if isinstance(event, ObservationBatch):
            return self._observations(event)
        return False

    def _odometry(self, ev: OdometrySample) -> bool:
        seg, reason = self.segmenter.odometry(ev.stamp_ns, ev.T_odom_body)
        if reason is None and self.odo_stamps and ev.stamp_ns <= self.odo_stamps[-1]:
            self._count("odometry_stale")
            return False
        if reason is not None and self.segmenter.next_id > 1:
            self._count("segments_detected")
        self.odo_stamps.append(int(ev.stamp_ns))
        self.odo_poses.append(np.asarray(ev.T_odom_body, dtype=np.float64))
        self.odo_segments.append(seg)
        changed = False
        while self.pending_obs and self.pending_obs[0].stamp_ns <= ev.stamp_ns:
            changed |= self._observations(self.pending_obs.popleft(), retry=True)
        return changed

    def _keyframe(self, ev: Keyframe) -> bool:
        seg = self.segmenter.segment_at(ev.stamp_ns)
        if seg < 0:
            seg = self.segmenter.reset(ev.stamp_ns, "first keyframe")
        T = np.asarray(ev.T_odom_body, dtype=np.float64)
        prev_kf = self.kf_last.get(seg)
        if prev_kf is not None and ev.stamp_ns > prev_kf[0]:
            D = geo.se3_between(prev_kf[1], T)
            cum = (prev_kf[2] + float(np.linalg.norm(D[:3, 3])),
                   prev_kf[3] + rotation_angle(D[:3, :3]))
        else:
            cum = (0.0, 0.0) if prev_kf is None else (prev_kf[2], prev_kf[3])
        if prev_kf is None or ev.stamp_ns > prev_kf[0]:
            self.kf_last[seg] = (int(ev.stamp_ns), T, cum[0], cum[1])
        if ev.stamp_ns not in self.kf_buffer:
            self.kf_buffer[ev.stamp_ns] = (seg, T, cum[0], cum[1])
            self.kf_order.append(ev.stamp_ns)
            while len(self.kf_order) > KEYFRAME_BUFFER:
                self.kf_buffer.pop(self.kf_order.popleft(), None)
        last = self.last_node_of_segment.get(seg)
        b = self.bounds
        if last is not None:
            if ev.stamp_ns <= self.node_stamp.get(last, -1):
                self._count("keyframes_out_of_order")
                return False
            Z = geo.se3_between(self.node_odom[last], T)
            dist = float(np.linalg.norm(Z[:3, 3]))
            ang = rotation_angle(Z[:3, :3])
            dt_s = (ev.stamp_ns - self.node_stamp[last]) * 1e-9
            if (dist < b.keyframe_min_distance_m and ang < b.keyframe_min_angle_rad
                    and dt_s < b.keyframe_max_interval_s):
                self._count("keyframes_skipped")
                return False
        node = self.next_node
        self.next_node += 1
        self.node_stamp[node] = int(ev.stamp_ns)
        self.node_segment[node] = seg
        self.node_odom[node] = T
        self.node_cum[node] = cum
        self.adj[node] = set()
        if last is not None:
            Z = geo.se3_between(self.node_odom[last], T)
            self.node_est[node] = self.node_est[last] @ Z
            S = self.odometry_covariance(Z, cum[0] - self.node_cum[last][0],
                                         cum[1] - self.node_cum[last][1])
            self._add_factor(last, node, Z, S, KIND_ODOMETRY)
        else:
            prev = max(self.node_est) if self.node_est else None
            # A new segment starts where the robot last was (VIO restarts near the origin).
            self.node_est[node] = T.copy() if prev is None else self.node_est[prev].copy()
            if prev is None and self.anchor_first:
                self._add_factor(NONE, node, self.node_est[node].copy(),
                                 np.diag([GAUGE_SIGMA[0] ** 2] * 3 + [GAUGE_SIGMA[1] ** 2] * 3),
                                 KIND_PRIOR)
        self.last_node_of_segment[seg] = node
        stamps, nodes = self.seg_nodes.setdefault(seg, ([], []))
        stamps.append(int(ev.stamp_ns))
        nodes.append(node)
        self._count("nodes_added")
        self._enforce_bounds()
        return True

    def _attach(self, stamp_ns: int, T_odom_body: np.ndarray | None, seg: int,
                cum: tuple[float, float] | None = None
                ) -> tuple[int, np.ndarray, np.ndarray] | None:
        """(node, T_node_body, Σ) for a body pose at ``stamp_ns`` in segment ``seg``, via the
        nearest kept node of that segment and the VIO relative motion."""
        stamps, nodes = self.seg_nodes.get(seg, ([], []))
        if not stamps:
            return None
        i = bisect.bisect_left(stamps, stamp_ns)
        cands = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
        j = min(cands, key=lambda j: abs(stamps[j] - stamp_ns))
        best, best_dt = nodes[j], abs(stamps[j] - stamp_ns)
        if best is None or T_odom_body is None:
            return None
        Z = geo.se3_between(self.node_odom[best], T_odom_body)
        if not best_dt:
            return best, Z, np.zeros((6, 6))
        if cum is not None:  # drift grows with the path travelled, not the straight line
            c = self.node_cum[best]
            S = self.odometry_covariance(Z, abs(cum[0] - c[0]), abs(cum[1] - c[1]))
        else:
            S = self.odometry_covariance(Z)
        return best, Z, S

    def _keyframe_pose(self, stamp_ns: int):
        """(segment, T_odom_body, (path_m, turn_rad) or None) of a VIO keyframe stamp."""
        hit = self.kf_buffer.get(stamp_ns)
        if hit is None and self.kf_order:
            # VINS-Mono keeps stamps as double seconds: a loop's stamp may differ from the
            # keyframe's header stamp by a few ns after conversions; match within 1 ms.
            stamps = np.fromiter(self.kf_order, dtype=np.int64, count=len(self.kf_order))
            i = int(np.argmin(np.abs(stamps - stamp_ns)))
            if abs(int(stamps[i]) - stamp_ns) <= KEYFRAME_MATCH_NS:
                hit = self.kf_buffer[int(stamps[i])]
        if hit is not None:
            return hit[0], hit[1], (hit[2], hit[3])
        T = self._interpolate(stamp_ns)
        return None if T is None else (T[0], T[1], None)

    def _interpolate(self, stamp_ns: int) -> tuple[int, np.ndarray] | None:
        """(segment, T_odom_body) at ``stamp_ns`` from buffered odometry, within one segment."""
        if not self.odo_stamps:
            return None
        stamps = np.fromiter(self.odo_stamps, dtype=np.int64, count=len(self.odo_stamps))
        i = int(np.searchsorted(stamps, stamp_ns))
        max_dt = int(self.bounds.observation_max_dt_s * 1e9)
        if i < len(stamps) and stamps[i] == stamp_ns:
            return self.odo_segments[i], self.odo_poses[i]
        if i == 0 or i == len(stamps):
            return None
        lo, hi = i - 1, i
        if self.odo_segments[lo] != self.odo_segments[hi] or stamps[hi] - stamps[lo] > max_dt:
            return None
        T, _ = geo.se3_interpolate(stamps[lo:hi + 1], np.stack([self.odo_poses[lo],
                                                                self.odo_poses[hi]]),
                                   np.array([stamp_ns]))
        return self.odo_segments[lo], T[0]

    def _loop(self, ev: LoopClosure) -> bool:
        ends = []
        for stamp in (ev.stamp_old_ns, ev.stamp_cur_ns):
            kf = self._keyframe_pose(stamp)
            att = None if kf is None else self._attach(stamp, kf[1], kf[0], kf[2])
            if att is None:
                self._count("loops_unattachable")
                return False
            ends.append(att)
        (a, Z_a_old, S_a), (b, Z_b_cur, S_b) = ends
        if a == b:
            self._count("loops_within_one_node")
            return False
        # T_a⁻¹ T_b = Z_a_old · T_old_cur · Z_b_cur⁻¹
        Z, S = compose_cov(Z_a_old, S_a, ev.T_old_cur, diag_covariance(self.config.loop_noise))
        Zi, Si = invert_cov(Z_b_cur, S_b)
        Z, S = compose_cov(Z, S, Zi, Si)
        self._add_factor(a, b, Z, S, KIND_LOOP)
        self._count("loops_added")
        self._enforce_bounds()
        return True

    def _observations(self, batch: ObservationBatch, retry: bool = False) -> bool:
        at = self._interpolate(batch.stamp_ns)
        if at is None:
            newest = self.odo_stamps[-1] if self.odo_stamps else None
            if not retry and (newest is None or batch.stamp_ns > newest):
                self.pending_obs.append(batch)  # odometry has not reached the frame yet
                return False
            self._count("observations_unattachable", len(batch.observations))
            return False
        seg, T_odom_body = at
        att = self._attach(batch.stamp_ns, T_odom_body, seg)
        if att is None:
            self._count("observations_unattachable", len(batch.observations))
            return False
        node, Z_nb, S_nb = att
        for obs in batch.observations:
            S_obs = np.asarray(obs.covariance, dtype=np.float64)
            if not np.all(np.isfinite(S_obs)) or np.any(np.diag(S_obs) <= 0):
                S_obs = diag_covariance(self.config.object_noise)
            Z, S = compose_cov(Z_nb, S_nb, obs.T_body_object, S_obs)
            key = OBJ + int(obs.object_id)
            if obs.object_id not in self.obj_est:
                self.obj_est[int(obs.object_id)] = self.node_est[node] @ Z
                self.adj.setdefault(key, set())
            self._add_factor(node, key, Z, S, KIND_OBSERVATION)
            self._count("observations_added")
        self._enforce_bounds()
        return True

    # ------------------------------------------------------------------ bounds
    def protect(self, node_keys) -> None:
        """Nodes to keep as long as possible (the agent's separators); replaces the set."""
        self.protected = {int(k) for k in node_keys if int(k) in self.node_stamp}

    def _removal_order(self) -> list[int]:
        newest = set(self.last_node_of_segment.values())

        def rank(node: int) -> tuple[int, int]:
            tier = 2 if node in self.protected else (1 if self.special.get(node, 0) else 0)
            return (tier, node)

        return sorted((n for n in self.node_stamp if n not in newest), key=rank)

    def _enforce_bounds(self) -> None:
        b = self.bounds
        if self.num_nodes <= b.max_nodes and self.num_factors <= b.max_edges:
            return
        order = self._removal_order()
        for node in order:
            if self.num_nodes <= b.max_nodes and self.num_factors <= b.max_edges:
                break
            self.remove_node(node)
        if self.num_factors > b.max_edges:  # only newest nodes left with dense factors
            self._count("bound_exceeded")

    def remove_node(self, n: int) -> None:
        """Remove node ``n`` keeping its information (module docstring)."""
        slots = sorted(self.adj.get(n, ()))
        chain = (len(slots) == 2 and all(self.factors[s][4] == KIND_ODOMETRY for s in slots)
                 and not (self.prior is not None and n in self.prior["keys"]))
        if chain or not self.marginalize:
            self._compose_out(n, slots)
        else:
            self._marginalize_out(n, self._reanchor_loops(n, slots))
        seg = self.node_segment.get(n)
        stamps, nodes = self.seg_nodes.get(seg, ([], []))
        if n in nodes:
            i = nodes.index(n)
            del stamps[i], nodes[i]
        for table in (self.node_stamp, self.node_segment, self.node_odom, self.node_est,
                      self.node_cum):
            table.pop(n, None)
        self.adj.pop(n, None)
        self.special.pop(n, None)
        self.protected.discard(n)
        self._count("nodes_removed")

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
            Wn = self.prior["W"][:, 6 * i:6 * i + 6]
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

    def _marginalize_out(self, n: int, slots: list[int]) -> None:
        """Schur-complement node ``n`` out of its factors and the prior into a new prior."""
        facs = [self._remove_factor(s) for s in slots]
        keys = {n}
        for p, q, *_ in facs:
            keys.update(k for k in (p, q) if k != NONE)
        if self.prior is not None:
            keys.update(self.prior["keys"].tolist())
        keys_arr = np.array(sorted(keys), dtype=np.int64)
        poses = np.stack([self._estimate(k) for k in keys_arr.tolist()])
        fa = _arrays(facs)
        blocks = self._blocks(fa, keys_arr, self.config.residual)
        if self.prior is not None:
            blocks.append(self._prior_block(keys_arr))
        H, g = _dense_normal_equations(blocks, len(keys_arr), poses)
        i = int(np.searchsorted(keys_arr, n))
        sn = np.arange(6 * i, 6 * i + 6)
        sb = np.setdiff1d(np.arange(H.shape[0]), sn)
        Hnn = H[np.ix_(sn, sn)] + 1e-9 * np.eye(6)
        Hbn = H[np.ix_(sb, sn)]
        K = np.linalg.solve(Hnn, Hbn.T).T  # H_bn H_nn⁻¹
        Hp = H[np.ix_(sb, sb)] - K @ Hbn.T
        gp = g[sb] - K @ g[sn]
        lam, V = np.linalg.eigh(0.5 * (Hp + Hp.T))
        keep = lam > 1e-9 * max(float(lam.max(initial=0.0)), 1e-300)
        lam, V = lam[keep], V[:, keep]
        rest = np.delete(keys_arr, i)
        if not len(lam):
            self.prior = None
            return
        self.prior = {
            "keys": rest,
            "T_lin": np.delete(poses, i, axis=0),
            "W": np.sqrt(lam)[:, None] * V.T,
            "e": (V.T @ gp) / np.sqrt(lam),
        }
        self._count("nodes_marginalised")

    def _estimate(self, key: int) -> np.ndarray:
        return self.obj_est[key - OBJ] if key >= OBJ else self.node_est[key]

    def _prior_block(self, keys_arr: np.ndarray) -> MarginalPrior:
        pk = self.prior["keys"]
        return MarginalPrior(np.searchsorted(keys_arr, pk)[None], self.prior["T_lin"],
                             self.prior["W"], self.prior["e"])

    def _blocks(self, fa: dict, keys: np.ndarray, residual: str) -> list:
        """Factor blocks (odometry, loop, observation, prior) over variables ``keys`` (sorted)."""
        if not len(fa["p"]):
            return []
        pi = np.searchsorted(keys, np.where(fa["p"] < 0, keys[0], fa["p"]))
        qi = np.searchsorted(keys, fa["q"])
        W = _whitening(fa["S"], residual)
        cfg = self.config
        kernels = {KIND_ODOMETRY: None,
                   KIND_LOOP: make_kernel(cfg.robust_kernel, cfg.robust_threshold),
                   KIND_OBSERVATION: make_kernel(cfg.robust_kernel, cfg.object_kernel_width)}
        blocks: list = []
        for kind in (KIND_ODOMETRY, KIND_LOOP, KIND_OBSERVATION):
            sel = (fa["kind"] == kind) & (fa["p"] >= 0)
            if np.any(sel):
                blocks.append(BetweenFactors(
                    np.stack([pi[sel], qi[sel]], axis=1), fa["Z"][sel], W[sel], residual,
                    kernels[kind], label=KIND_NAMES[kind]))
        sel = fa["p"] < 0
        if np.any(sel):
            blocks.append(PriorFactors(qi[sel][:, None], fa["Z"][sel], W[sel], residual,
                                       None, label="prior"))
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
            if p == NONE:  # prior on n -> prior on m
                Z2, S2 = compose_cov(Z, S, Z_nm, S_bridge)
                self._add_factor(NONE, m, Z2, S2, KIND_PRIOR)
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

    # ------------------------------------------------------------------ for the solver
    def node_keys(self) -> np.ndarray:
        return np.array(sorted(self.node_stamp), dtype=np.int64)

    def object_ids(self) -> np.ndarray:
        return np.array(sorted(self.obj_est), dtype=np.int64)

    def node_stamps_ns(self) -> np.ndarray:
        return np.array([self.node_stamp[k] for k in sorted(self.node_stamp)], dtype=np.int64)

    def T_world_body(self) -> np.ndarray:
        keys = sorted(self.node_est)
        return np.stack([self.node_est[k] for k in keys]) if keys else np.zeros((0, 4, 4))

    def T_world_object(self) -> np.ndarray:
        keys = sorted(self.obj_est)
        return np.stack([self.obj_est[k] for k in keys]) if keys else np.zeros((0, 4, 4))

    def factor_arrays(self, include_prior: bool = True) -> dict:
        """All factors as arrays: p, q (variable keys; p = -1 for unary priors), Z, Σ, kind.

        With ``include_prior`` the dense marginalisation prior is appended in sparsified form
        (:meth:`_sparsified_prior`), so a consumer that knows only binary and unary factors
        still gets the information of removed nodes; :meth:`problem` uses the exact dense prior.
        """
        fa = _arrays([self.factors[s] for s in sorted(self.factors)])
        if include_prior and self.prior is not None:
            extra = self._sparsified_prior()
            for key in ("p", "q", "Z", "S", "kind"):
                fa[key] = np.concatenate([fa[key], extra[key]])
        return fa

    def problem(self, residual: str | None = None) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
        """(graph, poses, keys): variables = nodes (PRIVATE) then objects (PUBLIC).

        ``keys[i]`` is the node key or ``OBJ + object_id`` of variable i. Loops and
        observations carry the configured robust kernel.
        """
        residual = residual or self.config.residual
        nodes = self.node_keys()
        objs = self.object_ids()
        keys = np.concatenate([nodes, OBJ + objs])
        poses = np.concatenate([self.T_world_body(), self.T_world_object()]) if len(keys) \
            else np.zeros((0, 4, 4))
        kinds = np.concatenate([np.full(len(nodes), VariableKind.PRIVATE, np.int8),
                                np.full(len(objs), VariableKind.PUBLIC, np.int8)])
        blocks = self._blocks(self.factor_arrays(include_prior=False), keys, residual)
        if self.prior is not None:
            blocks.append(self._prior_block(keys))
        return PoseGraph(3, kinds, tuple(blocks)), poses, keys

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
        items = []
        if np.all(np.diag(S_rr) < 1e6):
            items.append((NONE, int(keys[r]), T_mean[r], S_rr + 1e-12 * np.eye(6), KIND_PRIOR))
        S_rr_inv = np.linalg.pinv(S_rr, hermitian=True)
        T_r_inv = _inv(T_mean[r])
        others = [i for i in range(len(keys)) if i != r]
        so = np.concatenate([np.arange(6 * i, 6 * i + 6) for i in others]) if others else \
            np.zeros(0, np.int64)
        S_c = Sigma[np.ix_(so, so)] - Sigma[so, sr] @ S_rr_inv @ Sigma[sr, so]
        S_c = 0.5 * (S_c + S_c.T) + 1e-12 * np.eye(len(so))
        c = _blockdiag_bound(S_c)
        for j, i in enumerate(others):
            k = int(keys[i])
            S_cond = c * S_c[6 * j:6 * j + 6, 6 * j:6 * j + 6]
            kind = KIND_OBSERVATION if k >= OBJ else KIND_ODOMETRY
            items.append((int(keys[r]), k, T_r_inv @ T_mean[i], S_cond, kind))
        return _arrays(items)

    def set_estimates(self, keys: np.ndarray, poses: np.ndarray) -> None:
        """Write solver results back (variables by key, as returned by :meth:`problem`)."""
        for k, T in zip(np.asarray(keys).tolist(), np.asarray(poses)):
            if k >= OBJ:
                if (k - OBJ) in self.obj_est:
                    self.obj_est[k - OBJ] = T.copy()
            elif k in self.node_est:
                self.node_est[k] = T.copy()

    def solve(self, params=None):
        """Optimise the local graph alone (Schur-LM) and keep the result; returns the LMResult."""
        from dran_edge.solver import lm

        graph, poses, keys = self.problem()
        if not len(keys) or not graph.factors:
            return None
        result = lm.solve(graph, poses, params or lm.LMParams(max_iterations=20))
        if math.isfinite(result.cost):
            self.set_estimates(keys, result.poses)
        return result

    # ------------------------------------------------------------------ state
    def to_state(self) -> dict:
        fa = self.factor_arrays(include_prior=False)
        nodes = self.node_keys()
        return {
            "next_node": self.next_node,
            "nodes": nodes,
            "node_stamp": np.array([self.node_stamp[k] for k in nodes.tolist()], np.int64),
            "node_segment": np.array([self.node_segment[k] for k in nodes.tolist()], np.int64),
            "node_odom": np.stack([self.node_odom[k] for k in nodes.tolist()]) if len(nodes)
            else np.zeros((0, 4, 4)),
            "node_est": self.T_world_body(),
            "objects": self.object_ids(),
            "obj_est": self.T_world_object(),
            "protected": np.array(sorted(self.protected), np.int64),
            "last_node_of_segment": [[int(s), int(n)] for s, n in
                                     self.last_node_of_segment.items() if n in self.node_stamp],
            "factors": fa,
            "odo_stamps": np.array(self.odo_stamps, np.int64),
            "odo_poses": np.stack(self.odo_poses) if self.odo_poses else np.zeros((0, 4, 4)),
            "odo_segments": np.array(self.odo_segments, np.int64),
            "kf_stamps": np.array(self.kf_order, np.int64),
            "kf_segments": np.array([self.kf_buffer[s][0] for s in self.kf_order], np.int64),
            "kf_poses": np.stack([self.kf_buffer[s][1] for s in self.kf_order])
            if self.kf_order else np.zeros((0, 4, 4)),
            "kf_cum": np.array([self.kf_buffer[s][2:] for s in self.kf_order], np.float64
                               ).reshape(-1, 2),
            "kf_last": [[int(sg), int(v[0]), v[1], float(v[2]), float(v[3])]
                        for sg, v in self.kf_last.items()],
            "node_cum": np.array([self.node_cum[k] for k in nodes.tolist()], np.float64
                                 ).reshape(-1, 2),
            "segmenter": self.segmenter.to_state(),
            "counters": dict(self.counters),
            "prior": self.prior,
        }

    @classmethod
    def from_state(cls, config: AgentConfig, state: dict, *, anchor_first: bool = True
                   ) -> KeyframeGraph:
        g = cls(config, anchor_first=anchor_first)
        g.next_node = int(state["next_node"])
        for i, k in enumerate(np.asarray(state["nodes"]).tolist()):
            g.node_stamp[k] = int(state["node_stamp"][i])
            g.node_segment[k] = int(state["node_segment"][i])
            g.node_odom[k] = np.array(state["node_odom"][i])
            g.node_est[k] = np.array(state["node_est"][i])
            g.node_cum[k] = tuple(float(v) for v in state["node_cum"][i])
            g.adj[k] = set()
        for i, k in enumerate(np.asarray(state["objects"]).tolist()):
            g.obj_est[k] = np.array(state["obj_est"][i])
            g.adj[OBJ + k] = set()
        for k in sorted(g.node_stamp):
            stamps, nodes = g.seg_nodes.setdefault(g.node_segment[k], ([], []))
            stamps.append(g.node_stamp[k])
            nodes.append(k)
        g.protected = set(np.asarray(state["protected"]).tolist())
        g.last_node_of_segment = {int(s): int(n) for s, n in state["last_node_of_segment"]}
        fa = state["factors"]
        for i in range(len(fa["p"])):
            g._add_factor(int(fa["p"][i]), int(fa["q"][i]), np.array(fa["Z"][i]),
                          np.array(fa["S"][i]), int(fa["kind"][i]))
        for s, T, sg in zip(np.asarray(state["odo_stamps"]).tolist(), state["odo_poses"],
                            np.asarray(state["odo_segments"]).tolist()):
            g.odo_stamps.append(s)
            g.odo_poses.append(np.array(T))
            g.odo_segments.append(sg)
        for s, sg, T, c in zip(np.asarray(state["kf_stamps"]).tolist(),
                               np.asarray(state["kf_segments"]).tolist(), state["kf_poses"],
                               np.asarray(state["kf_cum"]).tolist()):
            g.kf_buffer[s] = (sg, np.array(T), c[0], c[1])
            g.kf_order.append(s)
        g.kf_last = {int(sg): (int(st), np.array(T), float(d), float(r))
                     for sg, st, T, d, r in state["kf_last"]}
        g.segmenter = Segmenter.from_state(config.graph, state["segmenter"])
        g.counters = {str(k): int(v) for k, v in state["counters"].items()}
        pr = state.get("prior")
        g.prior = (None if pr is None
                   else {k: np.asarray(pr[k]) for k in ("keys", "T_lin", "W", "e")})
        return g


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


def _dense_normal_equations(blocks: list, n_vars: int, poses: np.ndarray
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


def _arrays(items: list) -> dict:
    """Factor tuples (p, q, Z, Σ, kind) as arrays."""
    if not items:
        return {"p": np.zeros(0, np.int64), "q": np.zeros(0, np.int64),
                "Z": np.zeros((0, 4, 4)), "S": np.zeros((0, 6, 6)), "kind": np.zeros(0, np.int8)}
    return {"p": np.array([f[0] for f in items], np.int64),
            "q": np.array([f[1] for f in items], np.int64),
            "Z": np.stack([f[2] for f in items]), "S": np.stack([f[3] for f in items]),
            "kind": np.array([f[4] for f in items], np.int8)}


def _whitening(S: np.ndarray, residual: str) -> np.ndarray:
    """Whitening of covariances Σ (m, 6, 6) for the given residual."""
    if len(S) == 0:
        return np.zeros((0, 6, 6)) if residual == Residual.GEODESIC else np.zeros((0, 12))
    if residual == Residual.GEODESIC:
        return whitening_from_information(np.linalg.inv(S))
    # chordal: isotropic precisions from the mean variances (eq. 2 chordal form)
    tau = 3.0 / np.trace(S[:, :3, :3], axis1=1, axis2=2)
    kappa = 0.5 * 3.0 / np.trace(S[:, 3:, 3:], axis1=1, axis2=2)
    from dran_edge.solver.factors import isotropic_whitening

    return isotropic_whitening(kappa, tau, Residual.CHORDAL, 3)
