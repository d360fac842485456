"""Configuration of the pure core: noise models, graph bounds and the agent (``AgentConfig``).

Stdlib only, so the core (solver, dran, robot) can use it (docs/config.md)."""

from __future__ import annotations

from dataclasses import dataclass

from dran_edge.config.fields import Residual, RobustKernel, _Checked, _f
from dran_edge.errors import ConfigError


@dataclass(frozen=True)
class NoiseModel(_Checked):
    """Isotropic-per-block noise of one measurement kind (VINS-Mono gives no covariances)."""

    sigma_translation_m: float = _f(0.05, lo=0.0, lo_open=True)
    """Standard deviation of each translation component, metres."""
    sigma_rotation_rad: float = _f(0.02, lo=0.0, lo_open=True)
    """Standard deviation of each rotation component (tangent), radians."""


@dataclass(frozen=True)
class OdometryNoise(_Checked):
    """Noise of an odometry edge between two kept keyframes, growing with the motion between them.

    sigma_t = sigma_translation_m + per_metre * |dt|;
    sigma_r = sigma_rotation_rad + per_radian * |dr|.
    """

    sigma_translation_m: float = _f(0.01, lo=0.0, lo_open=True)
    """Translation standard deviation of any odometry edge, metres."""
    sigma_rotation_rad: float = _f(0.005, lo=0.0, lo_open=True)
    """Rotation standard deviation of any odometry edge, radians."""
    per_metre: float = _f(0.02, lo=0.0)
    """Added translation standard deviation per metre travelled (VIO drift), m/m."""
    per_radian: float = _f(0.01, lo=0.0)
    """Added rotation standard deviation per radian turned, rad/rad."""


@dataclass(frozen=True)
class GraphBounds(_Checked):
    """Keyframe selection, segmenting and the hard size cap of the bounded local graph."""

    keyframe_min_distance_m: float = _f(0.3, lo=0.0)
    """A VIO keyframe becomes a graph node once it is this far from the last node, metres."""
    keyframe_min_angle_rad: float = _f(0.26, lo=0.0)
    """... or has turned this much since the last node, radians."""
    keyframe_max_interval_s: float = _f(5.0, lo=0.0, lo_open=True)
    """... or this much time has passed since the last node, seconds."""
    max_nodes: int = _f(400, lo=8, hi=1_000_000)
    """Hard cap on trajectory nodes; over it the oldest removable nodes are marginalised."""
    max_edges: int = _f(1600, lo=8, hi=10_000_000)
    """Hard cap on factors (odometry, loop, object, prior) in the local graph."""
    skeleton_fraction: float = _f(0.0, lo=0.0, hi=0.9)
    """Share of ``max_nodes`` (and of ``max_edges`` for their factors) kept as a skeleton of old
    nodes spread evenly over the whole mission, so that loops into the distant past attach at
    short range (docs/notes/solve-and-bounded-graph.md, section 4); 0 (the default): only the
    recent window — the skeleton made ATE worse where it was measured."""
    archive_size: int = _f(4096, lo=0, hi=1_000_000)
    """Marginalised keyframes whose last estimate and covariance are kept, so that a loop into
    the distant past becomes a prior on its current node instead of a long VIO attachment
    (docs/notes/solve-and-bounded-graph.md, section 5); thinned by half when full; 0: off."""
    segment_gap_s: float = _f(1.0, lo=0.0, lo_open=True)
    """An odometry stamp gap longer than this starts a new segment, seconds (VINS restarts on 1 s)."""
    segment_jump_m: float = _f(1.0, lo=0.0, lo_open=True)
    """A position jump between consecutive odometry samples above this starts a new segment, metres."""
    segment_jump_rad: float = _f(0.8, lo=0.0, lo_open=True)
    """A rotation jump between consecutive odometry samples above this starts a new segment, rad."""
    observation_max_dt_s: float = _f(0.5, lo=0.0, lo_open=True)
    """An observation is attached to a keyframe only if odometry brackets it within this, seconds."""

    def _check(self) -> None:
        if self.max_edges < self.max_nodes:
            raise ConfigError(
                f"max_edges: expected >= max_nodes ({self.max_nodes}), got {self.max_edges}"
            )


@dataclass(frozen=True)
class AgentConfig(_Checked):
    """Parameters of one robot's DRAN agent (paper Sec. 4, Alg. 1; defaults from Sec. 5)."""

    robot_id: int = _f(0, lo=0, hi=65535)
    """This robot's id (copied from ``robot.id`` by the loader)."""
    neighbours: tuple[int, ...] = _f((), lo=0, hi=65535)
    """Ids of the communication neighbours (copied from ``neighbours`` by the loader)."""
    dim: int = _f(3, choices=(2, 3))
    """2 for SE(2), 3 for SE(3)."""
    residual: Residual = _f(Residual.GEODESIC, choices=tuple(Residual))
    """Residual of eq. 2: geodesic Log(T~^-1 Tp^-1 Tq) or chordal."""
    beta: float = _f(250.0, lo=0.0, lo_open=True)
    """Penalty parameter beta of the augmented Lagrangian (eq. 4). It has the units of the
    factors' information (DRAN is invariant under information x s, beta x s; docs/dran.md):
    about 0.05 x the information of a typical tag observation along its weakest axis. 250
    suits the robot's tag observations (median 5e3 per m^2 in translation); the paper's 1.0
    is for unit information (bench objects uses it)."""
    eta: float = _f(0.1, lo=0.0, lo_open=True)
    """Dual step eta of eq. 5b."""
    alpha: float = _f(1.0, lo=0.0, lo_open=True, hi=1.0)
    """Step size on the public variables v (objects): y <- Retr_y(alpha v) (Alg. 1 line 13)."""
    gamma: float = _f(1.0, lo=0.0, lo_open=True, hi=1.0)
    """Step size on the private variables u (trajectory): x <- Retr_x(gamma u) (Alg. 1 line 13)."""
    sor_omega: float = _f(1.0, lo=0.0, lo_open=True, hi=1.99)
    """Over-relaxation omega of the inter-robot iteration on the trajectory: after the accepted
    local step x <- Retr_x(gamma u) the robot keeps Retr_x(omega gamma u) instead (1: plain
    Alg. 1). With a colour schedule this is block SOR (docs/dran.md); the robot's first local
    step is always plain. Needs every neighbour's newest values each round (the synchronous,
    lossless Table 1 bench): with 30 % datagram loss it diverged (CSAIL F/F* 22 856), so bench
    g2o runs lossy links with 1, check-fleet refuses other values and the daemon warns."""
    colours: int = _f(1, lo=1, hi=256)
    """Update schedule: the robot runs its local step only in rounds k with
    (k - 1) mod colours == colour; 1 is the paper's every-round (parallel) schedule, more give a
    Gauss-Seidel-like order when neighbours have different colours (docs/dran.md)."""
    colour: int = _f(0, lo=0, hi=255)
    """This robot's colour in the schedule (0 <= colour < colours)."""
    dual_momentum: float = _f(0.0, lo=0.0, hi=0.95)
    """Heavy-ball momentum theta on the dual update (eq. 5b), a schedule without a shared round:
    lambda_ij <- lambda_ij + eta beta w_ij phi + theta (lambda_ij - lambda_ij before its last
    update), on the pairs the anti-windup lets integrate. Needs no shared round; both ends of a
    pair apply the same linear recurrence to antisymmetric increments. 0: off, the paper's eq.
    5b (measured: faster on small fleets and the demo replay, not on the paper-size object
    simulation, and worse with lossy links; docs/dran.md, "Acceleration without a shared
    round")."""
    eps_u: float = _f(1e-2, lo=0.0)
    """Terminate when the private step norm |u| < eps_u."""
    eps_v: float = _f(1e-1, lo=0.0)
    """... and the public step norm |v| < eps_v."""
    eps_phi: float = _f(1e-1, lo=0.0)
    """... and the consensus error |phi| < eps_phi."""
    eps_cost_rel: float = _f(0.0, lo=0.0)
    """Also optimal when the round's local step lowered L̂_i by at most this fraction of it
    (0: off, the paper's ε_u/ε_v rule alone). Steps that no longer pay stop the traffic of a
    slowly converging tail (docs/dran.md)."""
    stop_rule: str = _f("steps", choices=("tail", "steps"))
    """Which local test feeds the stop (docs/notes/stopping-rule.md). "tail": the remaining
    decrease of L̂_i predicted from the local Newton decrement (the Schur-reduced gradient in the
    metric of the local Hessian) and its observed contraction rate, relative to L̂_i, at most
    stop_tol, with the consensus penalty energy also at most stop_tol × L̂_i; a robot reports
    convergence only once its done counter (propagated as the minimum over its neighbours)
    reaches stop_rounds; the done counter rides in every neighbour message (one byte).
    "steps" (default, the robot daemon's): the paper's eps_u/eps_v (and eps_cost_rel) test
    alone; the daemon never stops on it, it only reports it. The benchmarks that stop on the
    rule (bench g2o, bench objects) use "tail"."""
    stop_tol: float = _f(1e-3, lo=0.0, lo_open=True)
    """"tail" rule: bound on the predicted remaining relative decrease of L̂_i."""
    stop_window: int = _f(20, lo=4, hi=1000)
    """"tail" rule: own local steps over which the contraction rate is estimated (the test
    needs this many steps of history)."""
    stop_rounds: int = _f(10, lo=1, hi=255)
    """"tail" rule: done counter needed to report convergence. The counter is 0 while the local
    test fails, else one more than the smallest of its own last value and the neighbours'
    counters; so it reaches this only when every robot within (this − 1) hops has passed its
    local test for the last rounds. Set above the communication graph's diameter."""
    k_max: int = _f(500, lo=1, hi=1_000_000)
    """Maximum number of local steps (DRAN iterations) of one optimisation."""
    mu_init: float = _f(1e-4, lo=0.0, lo_open=True)
    """Initial Levenberg-Marquardt damping mu of M = J^T J + mu I (eq. 7)."""
    robust_kernel: RobustKernel = _f(RobustKernel.HUBER, choices=tuple(RobustKernel))
    """Robust kernel on loop and object residuals (whitened)."""
    robust_threshold: float = _f(1.345, lo=0.0, lo_open=True)
    """Kernel width on the whitened residual norm (1.345: 95 % efficiency for Huber)."""
    object_robust_threshold: float = _f(0.0, lo=0.0)
    """Kernel width on object observations alone (0: robust_threshold). Loops want a tight
    kernel (a false loop is wrong by metres and must not pull); an observation that passed the
    gates wants a wider one, or the kernel also holds back the right ones while the
    trajectories still drift (docs/dran.md, robustness)."""
    dual_max_phi2: float = _f(0.1, lo=0.0)
    """Anti-windup of eq. 5b: a dual λ_ij is updated only while φ²(y_i, y_j) is at most this
    (squared geodesic distance, same units as eps_phi; default = the paper's eps_phi)."""
    object_gate_m: float = _f(2.0, lo=0.0)
    """Consistency gate: an object observation whose predicted object position is farther than
    this from the medoid of the robot's predictions of that object is dropped (0: off), metres."""
    object_min_views: int = _f(1, lo=1, hi=100)
    """An own object observation is used only when at least this many own observations of that
    object (itself included) agree within object_gate_m, or a neighbour's copy lies within
    object_gate_m of it (1: every observation that passes the gate; 2 rejects lone wrong ids)."""
    object_exclusion_m: float = _f(0.5, lo=0.0)
    """Spatial exclusion for lone observations (object_min_views > 1): a lone observation whose
    predicted object position is farther than this from every own observation of another object
    is used at once instead of waiting for a neighbour's corroboration. Two objects do not occupy
    one place, so a wrong id (a second label on something seen there) lies within it of the
    right one's views. By the same rule an observation within it of another object's views, with
    no more views of its own object there than that object has, waits however many views it has
    (a tag misread the same way from several keyframes). 0: off, every lone observation waits
    and repeated ones are used. Metres."""
    corroboration_ratio: float = _f(2.0, lo=0.0)
    """A held-back observation (object_min_views > 1) is also corroborated when a neighbour's
    copy of its object lies within association_gate_m of its prediction and this many times
    nearer than any copy of another object (a ratio test: the view's stretch of trajectory may
    have drifted past object_gate_m, but a wrong id lies where the seen object's copies are).
    0: off, corroboration within object_gate_m only."""
    association_gate_m: float = _f(8.0, lo=0.0)
    """Cross-robot association check: an own object observation predicting the object farther
    than this from the evidence-weighted medoid of the copies (one vote per observing robot,
    weighted by its number of observations; docs/dran.md) is dropped as a wrong association
    (0: off), metres."""
    centre_reach_m: float = _f(16.0, lo=0.0)
    """With a robust kernel and association_gate_m > 0: a neighbour's copy farther than this
    from the association check's centre for its object (the copy the votes side with,
    ``ObjectAssociation.check``) is in conflict whatever its origin, and its consensus term
    gets the Cauchy kernel. A copy built from a lone wrong view in the first rounds is dropped
    by the check within a round or two, but least squares has by then averaged it into the
    relays around it, which carry the right origin and vouch for the dragged value. 16 m, like
    conflict_reach_m: a drifted copy and a centre each within association_gate_m of the object
    are at most that far apart; at 8 m the kernel also held honestly drifted copies apart (one
    simulation seed's 20 % outlier run fell 15-26 % behind the outlier-free one; docs/dran.md,
    robustness). 0: off. Metres."""
    conflict_reach_m: float = _f(16.0, lo=0.0)
    """With a robust kernel: a neighbour's copy from another observing robot that lies farther
    than this from ours stands for another hypothesis (a wrong id), and its consensus term gets
    the Cauchy kernel (``ObjectAssociation.conflicts``); closer copies pull as least squares. Two copies
    each within association_gate_m (8 m) of the object are at most twice that apart. The first
    rounds' drift can exceed it (drifted copies up to 21.5 m apart on simulation seeds 0 and
    5), and a wider reach lets nearer wrong hypotheses pull (docs/dran.md, robustness). 0: off
    (with centre_reach_m also 0 every consensus term is least squares). Metres."""
    send_threshold: float = _f(1e-4, lo=0.0)
    """A separator/object entry is re-sent to a neighbour only when an element of its pose matrix
    moved by more than this since it was last sent to that neighbour (metres / unitless)."""
    resend_period_rounds: int = _f(20, lo=1, hi=1_000_000)
    """... or when it was last sent this many rounds ago (recovers from lost datagrams)."""
    relay_max_hops: int = _f(3, lo=0, hi=32)
    """Object estimates learned from others are relayed at most this many hops (Sec. 4.2.2)."""
    init_max_iterations: int = _f(50, lo=1, hi=10_000)
    """Iterations of each stage of the distributed chordal initialisation (Sec. 4.2.1)."""
    seed: int = _f(0, lo=0)
    """Seed of any randomness inside the agent (determinism)."""
    odometry_noise: OdometryNoise = _f(OdometryNoise())
    """Noise model of odometry edges."""
    loop_noise: NoiseModel = _f(NoiseModel(0.1, 0.05))
    """Noise model of DBoW2 loop closures (relative pose T_old_cur)."""
    object_noise: NoiseModel = _f(NoiseModel(0.05, 0.05))
    """Noise of tag observations when perception gives no covariance."""
    inter_robot_noise: NoiseModel = _f(NoiseModel(0.1, 0.05))
    """Noise of inter-robot relative-pose measurements (object-free mode)."""
    graph: GraphBounds = _f(GraphBounds())
    """The bounded local graph."""

    @property
    def object_kernel_width(self) -> float:
        """The kernel width in use on object observations (object_robust_threshold, or else
        robust_threshold)."""
        return self.object_robust_threshold or self.robust_threshold

    def _check(self) -> None:
        if self.robot_id in self.neighbours:
            raise ConfigError(f"neighbours: a robot cannot neighbour itself (id {self.robot_id})")
        if len(set(self.neighbours)) != len(self.neighbours):
            raise ConfigError(f"neighbours: expected distinct ids, got {list(self.neighbours)}")
        if self.colour >= self.colours:
            raise ConfigError(
                f"colour: expected a value < colours ({self.colours}), got {self.colour}"
            )
