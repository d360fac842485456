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

**Loops into the past** (``archive_size``, on by default; :mod:`dran_edge.robot.archive`). A node
that is marginalised leaves its estimate, relative to what it is known best against (an object,
or the world near the gauge), and that pose's covariance (given its factors and the prior) in a
bounded archive, and its loops become factors between their other ends and that reference
instead of being re-anchored (the re-anchored loops piled up on the window's oldest node and
each got a tiny share of one bridge). A loop that arrives later and refers to an archived
keyframe becomes such a factor on its current node too. Relative to an object rather than in
the world wherever that is more certain: the map's placement error of the keyframe's time is
then not counted again by every entry. The loops into one archived keyframe use its marginal's
information at most once in total — but that information is also in the dense prior, so it is
counted up to twice: not conservative (module :mod:`dran_edge.robot.archive`). A graph without
the gauge prior (a fleet robot that is not the gauge anchor: its frame comes from object
consensus) archives nothing and re-anchors as before.
Optionally (``skeleton_fraction``, off by default) a share of the nodes is kept as a skeleton
spread over the whole mission (:mod:`dran_edge.robot.skeleton`).

Where the code is: this module turns events into nodes and factors and hands the graph to the
solver; :mod:`dran_edge.robot.factor_store` holds the factors and removes nodes
(composition, marginalisation, the prior's sparsified form); :mod:`dran_edge.robot.factor_algebra`
has the factor kinds and the compose/invert/fuse algebra.

Pure: numpy/scipy only, no clock, no I/O. SE(3) only (the VIO is 3-D).

Size: over ~500 lines because the graph's event handling and solver hand-off (its factor store
and algebra are in their own modules); over 500 only by ruff format's layout.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from dran_edge import geometry as geo
from dran_edge.config import AgentConfig
from dran_edge.events import Keyframe, LoopClosure, ObservationBatch, OdometrySample, VioReset
from dran_edge.robot.factor_algebra import (  # noqa: F401  (re-exported: callers' names)
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
    diag_covariance,
    fuse,
    invert_cov,
    split_weights,
)
from dran_edge.robot.factor_store import (  # noqa: F401
    FactorStore,
    MarginalPrior,
    _blockdiag_bound,
    _dense_normal_equations,
)
from dran_edge.robot.archive import PoseArchive, nearest_in_time
from dran_edge.robot.segments import Segmenter
from dran_edge.robot.skeleton import Skeleton
from dran_edge.solver.graph import PoseGraph, VariableKind

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


class KeyframeGraph(FactorStore):
    """The bounded local graph of one robot (see module docstring)."""

    def __init__(self, config: AgentConfig, *, anchor_first: bool = True, marginalize: bool = True):
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
        self._init_factors()
        self.skeleton = Skeleton(int(self.bounds.skeleton_fraction * self.bounds.max_nodes))
        # archived estimates are absolute: only a graph that carries the gauge has them (a
        # gauge-free graph's marginals are singular but for the linearised prior's round-off)
        self.archive = PoseArchive(self.bounds.archive_size if marginalize and anchor_first else 0)
        # buffers
        self.odo_stamps: deque[int] = deque(maxlen=ODOMETRY_BUFFER)
        self.odo_poses: deque[np.ndarray] = deque(maxlen=ODOMETRY_BUFFER)
        self.odo_segments: deque[int] = deque(maxlen=ODOMETRY_BUFFER)
        # stamp -> (segment, T_odom, path m, turn rad)
        self.kf_buffer: dict[int, tuple[int, np.ndarray, float, float]] = {}
        self.kf_order: deque[int] = deque()
        self.pending_obs: deque[ObservationBatch] = deque(maxlen=PENDING_OBSERVATIONS)
        self.counters: dict[str, int] = {}
        self._odo_cov_base = np.diag(
            [config.odometry_noise.sigma_translation_m**2] * 3
            + [config.odometry_noise.sigma_rotation_rad**2] * 3
        )

    # ------------------------------------------------------------------ small helpers
    def odometry_covariance(
        self, Z: np.ndarray, path_m: float | None = None, turn_rad: float | None = None
    ) -> np.ndarray:
        """Σ of VIO relative motion Z (configured noise model), growing with the distance
        travelled ``path_m`` and angle turned ``turn_rad`` (default: those of Z itself)."""
        n = self.config.odometry_noise
        dt = float(np.linalg.norm(Z[:3, 3])) if path_m is None else path_m
        dr = float(geo.so3_angle(Z[:3, :3])) if turn_rad is None else turn_rad
        st = n.sigma_translation_m + n.per_metre * dt
        sr = n.sigma_rotation_rad + n.per_radian * dr
        return np.diag([st * st] * 3 + [sr * sr] * 3)

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
            cum = (
                prev_kf[2] + float(np.linalg.norm(D[:3, 3])),
                prev_kf[3] + float(geo.so3_angle(D[:3, :3])),
            )
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
            ang = float(geo.so3_angle(Z[:3, :3]))
            dt_s = (ev.stamp_ns - self.node_stamp[last]) * 1e-9
            if (
                dist < b.keyframe_min_distance_m
                and ang < b.keyframe_min_angle_rad
                and dt_s < b.keyframe_max_interval_s
            ):
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
            S = self.odometry_covariance(
                Z, cum[0] - self.node_cum[last][0], cum[1] - self.node_cum[last][1]
            )
            self._add_factor(last, node, Z, S, KIND_ODOMETRY)
        else:
            prev = max(self.node_est) if self.node_est else None
            # A new segment starts where the robot last was (VIO restarts near the origin).
            self.node_est[node] = T.copy() if prev is None else self.node_est[prev].copy()
            if prev is None and self.anchor_first:
                self._add_factor(
                    NONE,
                    node,
                    self.node_est[node].copy(),
                    np.diag([GAUGE_SIGMA[0] ** 2] * 3 + [GAUGE_SIGMA[1] ** 2] * 3),
                    KIND_PRIOR,
                )
        self.last_node_of_segment[seg] = node
        stamps, nodes = self.seg_nodes.setdefault(seg, ([], []))
        stamps.append(int(ev.stamp_ns))
        nodes.append(node)
        self._count("nodes_added")
        self._enforce_bounds()
        return True

    def _attach(
        self,
        stamp_ns: int,
        T_odom_body: np.ndarray | None,
        seg: int,
        cum: tuple[float, float] | None = None,
    ) -> tuple[int, np.ndarray, np.ndarray] | None:
        """(node, T_node_body, Σ) for a body pose at ``stamp_ns`` in segment ``seg``, via the
        nearest kept node of that segment and the VIO relative motion."""
        stamps, nodes = self.seg_nodes.get(seg, ([], []))
        if not stamps:
            return None
        j = nearest_in_time(stamps, stamp_ns)
        best = nodes[j]
        if best is None or T_odom_body is None:
            return None
        if stamps[j] == stamp_ns:
            return best, geo.se3_between(self.node_odom[best], T_odom_body), np.zeros((6, 6))
        return best, *self._vio_motion(self.node_odom[best], self.node_cum[best], T_odom_body, cum)

    def _vio_motion(
        self,
        T_odom_from: np.ndarray,
        cum_from: tuple[float, float],
        T_odom_to: np.ndarray,
        cum: tuple[float, float] | None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(Z, Σ): the VIO motion between two body poses and its drift covariance, which grows
        with the path travelled and the turn (``cum`` and ``cum_from``: (path_m, turn_rad))
        where the target's is known, else with the straight line."""
        Z = geo.se3_between(T_odom_from, T_odom_to)
        if cum is None:
            return Z, self.odometry_covariance(Z)
        return Z, self.odometry_covariance(Z, abs(cum[0] - cum_from[0]), abs(cum[1] - cum_from[1]))

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
        T, _ = geo.se3_interpolate(
            stamps[lo : hi + 1],
            np.stack([self.odo_poses[lo], self.odo_poses[hi]]),
            np.array([stamp_ns]),
        )
        return self.odo_segments[lo], T[0]

    def _loop(self, ev: LoopClosure) -> bool:
        ends: list[tuple[int, np.ndarray, np.ndarray]] = []
        # the current end first: the old end may take a share of an archived keyframe's
        # information (_attach_archived), which only a loop that is added should spend
        for stamp in (ev.stamp_cur_ns, ev.stamp_old_ns):
            kf = self._keyframe_pose(stamp)
            att = None if kf is None else self._attach(stamp, kf[1], kf[0], kf[2])
            if ends and kf is not None:  # the old end: a marginalised keyframe nearer?
                att = self._attach_archived(stamp, kf[1], kf[0], kf[2], att)
            if att is None:
                self._count("loops_unattachable")
                return False
            ends.append(att)
        (b, Z_b_cur, S_b), (a, Z_a_old, S_a) = ends
        if a == b:
            self._count("loops_within_one_node")
            return False
        # T_a⁻¹ T_b = Z_a_old · T_old_cur · Z_b_cur⁻¹ (the archive: a = an object, or NONE with
        # T_a = I)
        Z, S = compose_cov(Z_a_old, S_a, ev.T_old_cur, diag_covariance(self.config.loop_noise))
        Zi, Si = invert_cov(Z_b_cur, S_b)
        Z, S = compose_cov(Z, S, Zi, Si)
        self._add_factor(a, b, Z, S, KIND_LOOP)
        self._count("loops_added" if NONE < a < OBJ else "loops_to_archived_keyframes")
        self._enforce_bounds()
        return True

    def _attach_archived(
        self,
        stamp_ns: int,
        T_odom_body: np.ndarray,
        seg: int,
        cum: tuple[float, float] | None,
        att: tuple[int, np.ndarray, np.ndarray] | None,
    ) -> tuple[int, np.ndarray, np.ndarray] | None:
        """``(ref, T̂_ref_body, Σ)`` at ``stamp_ns`` from the nearest archived keyframe of
        ``seg`` (:mod:`dran_edge.robot.archive`; ``ref`` its reference: an object's key, or
        ``NONE`` for the world) when it is nearer in VIO path than the kept node of ``att`` (or
        there is none); else ``att``."""
        entry = self.archive.nearest(seg, stamp_ns)
        if entry is None:
            return att
        Z, S_vio = self._vio_motion(
            entry.T_odom_body, (entry.path_m, entry.turn_rad), T_odom_body, cum
        )
        if att is not None:  # the kept node wins when it is at most as far (VIO path)
            if cum is not None:
                d_arch, d_node = abs(cum[0] - entry.path_m), abs(cum[0] - self.node_cum[att[0]][0])
            else:
                d_arch, d_node = (
                    float(np.linalg.norm(Z[:3, 3])),
                    float(np.linalg.norm(att[1][:3, 3])),
                )
            if d_node <= d_arch:
                return att
        return (
            entry.ref_key,
            *compose_cov(entry.T_ref_body, entry.covariance / entry.take(), Z, S_vio),
        )

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
        poses = (
            np.concatenate([self.T_world_body(), self.T_world_object()])
            if len(keys)
            else np.zeros((0, 4, 4))
        )
        kinds = np.concatenate(
            [
                np.full(len(nodes), VariableKind.PRIVATE, np.int8),
                np.full(len(objs), VariableKind.PUBLIC, np.int8),
            ]
        )
        blocks = self._blocks(self.factor_arrays(include_prior=False), keys, residual)
        if self.prior is not None:
            blocks.append(self._prior_block(keys))
        return PoseGraph(3, kinds, tuple(blocks)), poses, keys

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
            "node_odom": np.stack([self.node_odom[k] for k in nodes.tolist()])
            if len(nodes)
            else np.zeros((0, 4, 4)),
            "node_est": self.T_world_body(),
            "objects": self.object_ids(),
            "obj_est": self.T_world_object(),
            "protected": np.array(sorted(self.protected), np.int64),
            "last_node_of_segment": [
                [int(s), int(n)]
                for s, n in self.last_node_of_segment.items()
                if n in self.node_stamp
            ],
            "factors": fa,
            "odo_stamps": np.array(self.odo_stamps, np.int64),
            "odo_poses": np.stack(self.odo_poses) if self.odo_poses else np.zeros((0, 4, 4)),
            "odo_segments": np.array(self.odo_segments, np.int64),
            "kf_stamps": np.array(self.kf_order, np.int64),
            "kf_segments": np.array([self.kf_buffer[s][0] for s in self.kf_order], np.int64),
            "kf_poses": np.stack([self.kf_buffer[s][1] for s in self.kf_order])
            if self.kf_order
            else np.zeros((0, 4, 4)),
            "kf_cum": np.array([self.kf_buffer[s][2:] for s in self.kf_order], np.float64).reshape(
                -1, 2
            ),
            "kf_last": [
                [int(sg), int(v[0]), v[1], float(v[2]), float(v[3])]
                for sg, v in self.kf_last.items()
            ],
            "node_cum": np.array([self.node_cum[k] for k in nodes.tolist()], np.float64).reshape(
                -1, 2
            ),
            "segmenter": self.segmenter.to_state(),
            "counters": dict(self.counters),
            "prior": self.prior,
            "prior_clean": self.prior_clean,
            "skeleton": self.skeleton.to_state(),
            "archive": self.archive.to_state(),
        }

    @classmethod
    def from_state(
        cls, config: AgentConfig, state: dict, *, anchor_first: bool = True
    ) -> KeyframeGraph:
        g = cls(config, anchor_first=anchor_first)
        g.next_node = int(state["next_node"])
        for i, k in enumerate(np.asarray(state["nodes"]).tolist()):
            g.node_stamp[k] = int(state["node_stamp"][i])
            g.node_segment[k] = int(state["node_segment"][i])
            g.node_odom[k] = np.array(state["node_odom"][i])
            g.node_est[k] = np.array(state["node_est"][i])
            d_m, r_rad = (float(v) for v in state["node_cum"][i])
            g.node_cum[k] = (d_m, r_rad)
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
            g._add_factor(
                int(fa["p"][i]),
                int(fa["q"][i]),
                np.array(fa["Z"][i]),
                np.array(fa["S"][i]),
                int(fa["kind"][i]),
            )
        for s, T, sg in zip(
            np.asarray(state["odo_stamps"]).tolist(),
            state["odo_poses"],
            np.asarray(state["odo_segments"]).tolist(),
        ):
            g.odo_stamps.append(s)
            g.odo_poses.append(np.array(T))
            g.odo_segments.append(sg)
        for s, sg, T, c in zip(
            np.asarray(state["kf_stamps"]).tolist(),
            np.asarray(state["kf_segments"]).tolist(),
            state["kf_poses"],
            np.asarray(state["kf_cum"]).tolist(),
        ):
            g.kf_buffer[s] = (sg, np.array(T), float(c[0]), float(c[1]))
            g.kf_order.append(s)
        g.kf_last = {
            int(sg): (int(st), np.array(T), float(d), float(r))
            for sg, st, T, d, r in state["kf_last"]
        }
        g.segmenter = Segmenter.from_state(config.graph, state["segmenter"])
        g.counters = {str(k): int(v) for k, v in state["counters"].items()}
        g.skeleton = Skeleton.from_state(g.skeleton.capacity, state.get("skeleton"))
        g.archive = PoseArchive.from_state(g.archive.capacity, state.get("archive"))
        for name in ("prior", "prior_clean"):
            pr = state.get(name)
            setattr(
                g,
                name,
                None if pr is None else {k: np.asarray(pr[k]) for k in ("keys", "T_lin", "W", "e")},
            )
        return g
