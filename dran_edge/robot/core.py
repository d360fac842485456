"""One robot's online core: the bounded local graph fed by ingest events, the DRAN agent on top.

``RobotCore.handle(event) -> list[Output]`` takes every event of :mod:`dran_edge.events`:

- VIO odometry, keyframes, loops, resets and tag observation batches go into the robot's
  :class:`~dran_edge.robot.keyframe_graph.KeyframeGraph` (keyframe selection, segments, bounded size);
- on a ``Tick`` whose graph changed since the last round, the graph is turned into the agent's
  :class:`~dran_edge.dran.agent.LocalProblem` (``problem_from_graph``) and handed over with
  ``Agent.set_problem`` (estimates are kept by keyframe id); then the tick runs one DRAN round;
- neighbour data goes to the agent unchanged.

Frames. The local graph works in the frame of the robot's first VIO segment. The fleet's
common world frame is ``T_world_odom``: with the paper's protocol each robot knows its initial
world-to-robot transform (from mocap at the start, mission.yaml ``T_world_odom``) and anchors
its first node there. Without it (a live robot), ``T_world_odom`` is the identity and, as in the
daemon, only the robot whose id is below all its neighbours' carries the gauge prior
(:func:`~dran_edge.robot.keyframe_graph.gauge_anchor`); the others are placed by object consensus. The problem handed to the agent is that
graph mapped into the world (``x = T_world_odom · x_graph``, priors likewise).

Write-back. After every round the agent's estimates are written back into the graph (mapped
back by ``T_world_odom⁻¹``) before the graph is touched again: before the next ingest event,
before a rebuild and before :meth:`RobotCore.to_state`. New keyframes are thus chained from
the optimised poses, marginalisation linearises at them, and a checkpoint holds them.

Pure core: numpy only, no clock, no I/O. ``to_state``/``from_state`` for checkpoints (the robot
daemon's checkpoint is this state plus its own journal position and counters). Ingest events
that make the local graph raise propagate to the caller; the daemon counts, logs and drops them.
"""

from __future__ import annotations

import numpy as np

from dran_edge import geometry as geo
from dran_edge.dran.agent import Agent, LocalProblem
from dran_edge.config import AgentConfig
from dran_edge.events import (
    Keyframe,
    LoopClosure,
    ObservationBatch,
    OdometrySample,
    Tick,
    VioReset,
)
from dran_edge.robot.keyframe_graph import (
    KIND_LOOP,
    KIND_OBSERVATION,
    KIND_ODOMETRY,
    KIND_PRIOR,
    OBJ,
    KeyframeGraph,
    _whitening,
    gauge_anchor,
)

INGEST_EVENTS = (OdometrySample, Keyframe, LoopClosure, VioReset, ObservationBatch)

#: version of :meth:`RobotCore.to_state`'s layout
STATE_FORMAT = 1


def problem_from_graph(
    graph: KeyframeGraph, residual: str, T_world_graph: np.ndarray | None = None
) -> LocalProblem:
    """The agent's :class:`LocalProblem` of ``graph``, mapped into the world by ``T_world_graph``.

    Odometry and loop factors between nodes become ``between`` (loops robust), node-object
    factors (observations, and loops into the archive kept relative to an object) become
    observations ``obs_*`` (``T_body_object`` measured from the node), unary priors become
    ``prior_*``. Whitening from each factor's covariance (``WᵀW = Σ⁻¹``).
    """
    G = np.eye(4) if T_world_graph is None else np.asarray(T_world_graph, dtype=np.float64)
    keys = graph.node_keys()
    stamps = graph.node_stamps_ns()
    x0 = G @ graph.T_world_body() if len(keys) else np.zeros((0, 4, 4))
    fa = graph.factor_arrays()
    p, q, kind = fa["p"], fa["q"], fa["kind"]
    W = _whitening(fa["S"], residual)
    node_p = (p >= 0) & (p < OBJ)
    node_q = (q >= 0) & (q < OBJ)
    idx = {int(k): i for i, k in enumerate(keys.tolist())}

    def index(a: np.ndarray) -> np.ndarray:
        return np.array([idx[int(k)] for k in a.tolist()], dtype=np.int64)

    btw = node_p & node_q & ((kind == KIND_ODOMETRY) | (kind == KIND_LOOP))
    # observations, and loops into the archive relative to an object (a remembered view of it)
    obs = node_p & (q >= OBJ) & ((kind == KIND_OBSERVATION) | (kind == KIND_LOOP))
    pri = (p < 0) & node_q & ((kind == KIND_PRIOR) | (kind == KIND_LOOP))  # loops into the archive
    z = np.zeros(0, np.int64)
    T0 = np.zeros((0, 4, 4))
    return LocalProblem(
        dim=3,
        residual=residual,
        pose_ids=keys.astype(np.int64),
        pose_stamps_ns=stamps.astype(np.int64),
        x0=x0,
        between=np.stack([index(p[btw]), index(q[btw])], axis=1).reshape(-1, 2),
        between_T=fa["Z"][btw],
        between_W=W[btw],
        between_robust=kind[btw] == KIND_LOOP,
        inter_own=z,
        inter_owner=z,
        inter_anchor_id=z,
        inter_own_is_p=np.zeros(0, bool),
        inter_T=T0,
        inter_W=W[:0],
        inter_robust=np.zeros(0, bool),
        prior_own=index(q[pri]),
        prior_T=G @ fa["Z"][pri],
        prior_W=W[pri],
        obs_own=index(p[obs]),
        obs_object=(q[obs] - OBJ).astype(np.int64),
        obs_T=fa["Z"][obs],
        obs_W=W[obs],
        separators_for={},
        prior_robust=kind[pri] == KIND_LOOP,
    )


class RobotCore:
    """See the module docstring. ``agent`` and ``local_graph`` are public for shells and tests."""

    def __init__(self, config: AgentConfig, T_world_odom: np.ndarray | None = None):
        self.config = config
        self.agent = Agent(config)
        self.T_world_odom = np.eye(4)
        # Without a known world frame, the daemon's rule: only the robot whose id is below all
        # its neighbours' carries the gauge prior; the others are placed by object consensus.
        self.local_graph = KeyframeGraph(config, anchor_first=gauge_anchor(config))
        if T_world_odom is not None:
            self.set_world_frame(T_world_odom)
        self._dirty = False
        #: the agent ran a round since its estimates were last written into the graph
        self._estimates_stale = False
        self.rebuilds = 0
        #: node key -> (stamp_ns, T_world_body by odometry alone, T_odom_body): the estimate
        #: before any optimisation (SR_ATE's ATE^0), chained like the local graph initialises
        #: nodes; kept for the graph's current nodes and the last node of each segment.
        self.dead_reckoning: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}
        self._dr_last_of_segment: dict[int, int] = {}
        self._dr_last: int | None = None

    def set_world_frame(self, T_world_odom: np.ndarray) -> None:
        """The robot's first VIO frame in the fleet's world (the paper's protocol); every robot
        that knows it anchors its first node there. Call it before the first keyframe."""
        if self.local_graph.num_nodes:
            raise ValueError("set_world_frame: the local graph already has nodes")
        self.T_world_odom = np.asarray(T_world_odom, dtype=np.float64)
        self.local_graph = KeyframeGraph(self.config, anchor_first=True)

    def handle(self, event) -> list:
        """One event in, the outputs it causes out (ingest events cause none)."""
        if isinstance(event, INGEST_EVENTS):
            self.write_back()
            self._dirty |= bool(self.local_graph.handle(event))
            return []
        if isinstance(event, Tick):
            if self._dirty:
                # Cleared first: a rebuild that raises is not retried on every later tick.
                self._dirty = False
                self._rebuild()
            self._estimates_stale = True
        return self.agent.handle(event)

    def write_back(self) -> None:
        """The agent's pose and object estimates -> the local graph, if a round ran since the
        last write-back (new nodes are chained from them; marginalisation linearises at them)."""
        if not self._estimates_stale:
            return
        a, g = self.agent, self.local_graph
        G_inv = geo.se3_inverse(self.T_world_odom)
        if a.problem.n:
            g.set_estimates(a.problem.pose_ids, G_inv @ a.x)
        if a.y:
            oids = np.array(sorted(a.y), dtype=np.int64)
            g.set_estimates(OBJ + oids, G_inv @ np.stack([a.y[int(o)] for o in oids]))
        self._estimates_stale = False

    def _track_dead_reckoning(self) -> None:
        g = self.local_graph
        for key in g.node_keys().tolist():
            if key in self.dead_reckoning:
                continue
            seg, T_odom = g.node_segment[key], g.node_odom[key]
            prev = self._dr_last_of_segment.get(seg)
            if prev is not None:
                _, T_prev, T_odom_prev = self.dead_reckoning[prev]
                T = T_prev @ geo.se3_between(T_odom_prev, T_odom)
            elif self._dr_last is None:
                T = self.T_world_odom @ T_odom
            else:  # a new segment starts where the robot last was (as the local graph does)
                T = self.dead_reckoning[self._dr_last][1].copy()
            self.dead_reckoning[key] = (int(g.node_stamp[key]), T, T_odom)
            self._dr_last_of_segment[seg] = key
            self._dr_last = key
        # Bounded like the graph: the current nodes and what new nodes are chained from.
        keep = set(g.node_keys().tolist()) | set(self._dr_last_of_segment.values())
        if len(keep) < len(self.dead_reckoning):
            self.dead_reckoning = {k: v for k, v in self.dead_reckoning.items() if k in keep}

    def initial_estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps_ns, T_world_body) of the current nodes by odometry alone (no optimisation)."""
        keys = [k for k in self.local_graph.node_keys().tolist() if k in self.dead_reckoning]
        if not keys:
            return np.zeros(0, np.int64), np.zeros((0, 4, 4))
        return (
            np.array([self.dead_reckoning[k][0] for k in keys], np.int64),
            np.stack([self.dead_reckoning[k][1] for k in keys]),
        )

    def _rebuild(self) -> None:
        self._track_dead_reckoning()
        self.write_back()
        self.agent.set_problem(
            problem_from_graph(self.local_graph, self.config.residual, self.T_world_odom)
        )
        self._dirty = False
        self.rebuilds += 1

    # ------------------------------------------------------------------ checkpoints
    def to_state(self) -> dict:
        """Everything needed to resume: ``{"agent", "graph", "online"}`` (plain dicts, lists and
        numpy arrays, as :mod:`dran_edge.daemon.checkpoint` stores them). Writes the agent's estimates
        back into the graph first, so the graph's state holds the optimised poses."""
        self.write_back()
        dr = sorted(self.dead_reckoning)
        return {
            "agent": self.agent.to_state(),
            "graph": self.local_graph.to_state(),
            "online": {
                "format": STATE_FORMAT,
                "T_world_odom": self.T_world_odom.copy(),
                "anchor_first": bool(self.local_graph.anchor_first),
                "dirty": bool(self._dirty),
                "rebuilds": int(self.rebuilds),
                "dr_keys": np.array(dr, np.int64),
                "dr_stamps_ns": np.array([self.dead_reckoning[k][0] for k in dr], np.int64),
                "dr_T_world_body": (
                    np.stack([self.dead_reckoning[k][1] for k in dr]) if dr else np.zeros((0, 4, 4))
                ),
                "dr_T_odom_body": (
                    np.stack([self.dead_reckoning[k][2] for k in dr]) if dr else np.zeros((0, 4, 4))
                ),
                "dr_last_of_segment": [
                    [int(sg), int(k)] for sg, k in self._dr_last_of_segment.items()
                ],
                "dr_last": None if self._dr_last is None else int(self._dr_last),
            },
        }

    @classmethod
    def from_state(cls, config: AgentConfig, state: dict) -> RobotCore:
        """The core :meth:`to_state` saved (``config`` as when it was saved)."""
        on = state["online"]
        if on.get("format") != STATE_FORMAT:
            raise ValueError(
                f"RobotCore.from_state: expected state format {STATE_FORMAT}, "
                f"got {on.get('format')!r}"
            )
        core = cls(config)
        core.T_world_odom = np.asarray(on["T_world_odom"], dtype=np.float64).copy()
        core.agent = Agent.from_state(config, state["agent"])
        core.local_graph = KeyframeGraph.from_state(
            config, state["graph"], anchor_first=bool(on["anchor_first"])
        )
        core._dirty = bool(on["dirty"])
        core.rebuilds = int(on["rebuilds"])
        for i, k in enumerate(np.asarray(on["dr_keys"]).tolist()):
            core.dead_reckoning[int(k)] = (
                int(on["dr_stamps_ns"][i]),
                np.array(on["dr_T_world_body"][i], np.float64),
                np.array(on["dr_T_odom_body"][i], np.float64),
            )
        core._dr_last_of_segment = {int(sg): int(k) for sg, k in on["dr_last_of_segment"]}
        core._dr_last = None if on["dr_last"] is None else int(on["dr_last"])
        return core
