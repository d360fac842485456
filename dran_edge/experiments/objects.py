"""The Ego-like object simulation of the paper's Sec. 6.2 and its metrics.

21 robots and 60 objects with random poses in a box; each robot flies a trajectory through a few
objects (one pose per ``step_m`` metres, heading along the motion); it observes every object
within ``range_m`` (5 m) of a pose. Odometry and observations are corrupted by rotation noise
``Exp(ε)``, ``ε ~ N(0, σ_r² I)`` (the isotropic Gaussian-tangent stand-in for the paper's
Langevin noise, σ_r = 1°) and translation noise ``N(0, σ_t² I)`` (σ_t = 0.005 m). The start pose of
every robot is known (a strong prior: "world-to-robot transform known at start"); initial
trajectories compose the noisy odometry from it; objects start at their first observation.

Weights: ``weights='unit'`` (default) uses Ω = I for every factor — the PyPose default the paper's
costs suggest, and the scale at which the paper's β = 1 balances the consensus term;
``weights='noise'`` uses Ω = diag(1/σ_t², 1/σ_r²).

Outliers (``outlier_ratio`` p): each object observation is, with probability p, also reported
under a wrong object id (``outlier_ids='add'``, the default: the outlier run has every
observation of the outlier-free run plus the wrong ones, so comparing the two measures what the
outliers cost) or reported under a wrong id instead of its own (``'relabel'``, a misread tag:
the run also loses those observations); and p × (observations / robots) false intra-robot loop
closures per robot join random pose pairs with an identity measurement. The agent's robustness
settings (docs/dran.md, robustness) are what must absorb them.

Metrics (paper Sec. 6.2, ``dran_edge.evaluation.metrics``): SR_ATE, SR_cost against the centralized LM of the
solver core on the same factors (one copy per object), CE over the robots' object copies and
Bias of the copies against the ground truth. The distributed cost F^k is the centralized
objective at the robots' trajectories and the per-object mean of their copies (so disagreement
between copies costs).
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.evaluation import metrics
from dran_edge.dran.agent import Agent
from dran_edge.dran.problem import LocalProblem
from dran_edge.config import AgentConfig, RobustKernel
from dran_edge.errors import InputError
from dran_edge.solver.factors import BetweenFactors, PriorFactors, make_kernel
from dran_edge.solver.graph import PoseGraph, kinds_array
from dran_edge.solver.lm import LMParams, evaluate_cost, solve

if TYPE_CHECKING:
    from dran_edge.experiments.fleet import Fleet


@dataclass(frozen=True)
class SimParams:
    """Scenario parameters (defaults: the paper's Ego setting)."""

    num_robots: int = 21
    num_objects: int = 60
    box_m: tuple = (60.0, 60.0, 10.0)
    """Extent of the box objects and robots live in, metres."""
    goals_per_robot: int = 3
    """Objects each robot flies past (legs of its trajectory)."""
    step_m: float = 1.5
    """Distance between consecutive trajectory poses, metres."""
    range_m: float = 5.0
    """An object closer than this to a pose is observed."""
    sigma_rot_rad: float = float(np.deg2rad(1.0))
    sigma_trans_m: float = 0.005
    outlier_ratio: float = 0.0
    outlier_kinds: str = "both"
    """Which outliers ``outlier_ratio`` injects: 'ids' (wrong object ids), 'loops' (false loop
    closures) or 'both'."""
    outlier_ids: str = "add"
    """How a wrong id enters: 'add' (a second report of the observation under a wrong id; the
    right one stays) or 'relabel' (the wrong id replaces the right one)."""
    weights: str = "unit"
    seed: int = 0

    def __post_init__(self) -> None:
        checks = [  # the same form as simulate.SimParams
            ("outlier_ratio", 0.0 <= self.outlier_ratio < 1.0, "0 <= p < 1"),
            ("outlier_kinds", self.outlier_kinds in ("ids", "loops", "both"), "ids, loops or both"),
            ("outlier_ids", self.outlier_ids in ("add", "relabel"), "add or relabel"),
            ("weights", self.weights in ("unit", "noise"), "unit or noise"),
        ]
        for name, ok, expected in checks:
            if not ok:
                raise InputError(
                    f"SimParams.{name}: expected {expected}, got {getattr(self, name)!r}"
                )


@dataclass(frozen=True, eq=False)
class Scenario:
    params: SimParams
    gt_robots: list
    """Per robot (n_i, 4, 4) ground-truth T_world_body."""
    gt_objects: np.ndarray
    """(M, 4, 4) ground-truth T_world_object."""
    problems: list
    """Per robot :class:`LocalProblem` (geodesic residual)."""


def _noise(rng, n, sr, st):
    xi = np.concatenate([rng.normal(0, st, (n, 3)), rng.normal(0, sr, (n, 3))], axis=1)
    return geo.se3_exp(xi)


def _look_along(direction: np.ndarray) -> np.ndarray:
    """Rotations whose x axis is ``direction`` (n, 3), z up as far as possible."""
    x = direction / np.linalg.norm(direction, axis=1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0])
    y = np.cross(up, x)
    bad = np.linalg.norm(y, axis=1) < 1e-6
    y[bad] = np.array([0.0, 1.0, 0.0])
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    return np.stack([x, y, np.cross(x, y)], axis=2)


def make_scenario(params: SimParams = SimParams(), residual: str = "geodesic") -> Scenario:
    # Long: the scenario generator as the paper's Sec. 6.2 describes it, step by step.
    rng = np.random.default_rng(params.seed)
    # Outliers draw from their own stream, so a scenario with outliers has exactly the
    # trajectories, odometry and observation noise of the same seed without them (the
    # outlier-free run it is compared with).
    outlier_rng = np.random.default_rng([params.seed, 1])
    M = params.num_objects
    box = np.asarray(params.box_m)
    obj_t = rng.random((M, 3)) * box
    obj_R = geo.so3_exp(rng.normal(0, 1.0, (M, 3)))
    gt_objects = geo.se3_from_rt(obj_R, obj_t)
    sr, st = params.sigma_rot_rad, params.sigma_trans_m
    wr = 1.0 if params.weights == "unit" else 1.0 / sr
    wt = 1.0 if params.weights == "unit" else 1.0 / st
    W = np.concatenate([np.full(3, wt), np.full(3, wr)])
    gt_robots, problems = [], []
    for r in range(params.num_robots):
        start = rng.random(3) * box
        goals = obj_t[rng.choice(M, params.goals_per_robot, replace=False)] + rng.normal(
            0, 1.0, (params.goals_per_robot, 3)
        )
        way = np.vstack([start, goals])
        pts = []
        for a, b in itertools.pairwise(way):
            k = max(int(np.linalg.norm(b - a) / params.step_m), 1)
            pts.append(a + (b - a) * (np.arange(k) / k)[:, None])
        pts.append(way[-1:])
        P = np.vstack(pts)
        d = np.diff(P, axis=0)
        d = np.vstack([d, d[-1:]])
        T_gt = geo.se3_from_rt(_look_along(d + 1e-9), P)
        n = T_gt.shape[0]
        Z_odo = geo.se3_between(T_gt[:-1], T_gt[1:]) @ _noise(rng, n - 1, sr, st)
        chain = [T_gt[0]]
        for Z in Z_odo:
            chain.append(chain[-1] @ Z)
        x0 = np.stack(chain)
        dist = np.linalg.norm(P[:, None, :] - obj_t[None], axis=2)
        pi, oi = np.nonzero(dist < params.range_m)
        Z_obs = geo.se3_between(T_gt[pi], gt_objects[oi]) @ _noise(rng, pi.size, sr, st)
        obs_obj = oi.copy()
        between = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
        between_T, robust = Z_odo, np.zeros(n - 1, bool)
        if params.outlier_ratio > 0:
            n_obs = pi.size
            wrong = outlier_rng.random(n_obs) < params.outlier_ratio
            shift = outlier_rng.integers(1, M, wrong.sum())
            if params.outlier_kinds in ("ids", "both"):
                if params.outlier_ids == "relabel":
                    obs_obj[wrong] = (oi[wrong] + shift) % M
                else:  # the same detection once more, under a wrong id
                    pi = np.concatenate([pi, pi[wrong]])
                    obs_obj = np.concatenate([obs_obj, (oi[wrong] + shift) % M])
                    Z_obs = np.concatenate([Z_obs, Z_obs[wrong]])
            n_loops = round(params.outlier_ratio * max(n_obs, 1))
            if params.outlier_kinds == "ids":
                n_loops = 0
            if n_loops and n > 3:
                a = outlier_rng.integers(0, n, n_loops)
                b = (a + outlier_rng.integers(2, n, n_loops)) % n
                between = np.vstack([between, np.stack([a, b], 1)])
                between_T = np.concatenate([between_T, np.broadcast_to(np.eye(4), (n_loops, 4, 4))])
                robust = np.concatenate([robust, np.ones(n_loops, bool)])
        z = np.zeros(0, np.int64)
        E = np.zeros((0, 4, 4))
        problems.append(
            LocalProblem(
                dim=3,
                residual=residual,
                pose_ids=np.arange(n, dtype=np.int64),
                pose_stamps_ns=np.arange(n, dtype=np.int64) * 500_000_000,
                x0=x0,
                between=between.astype(np.int64),
                between_T=between_T,
                between_W=np.tile(W, (between.shape[0], 1)),
                between_robust=robust,
                inter_own=z,
                inter_owner=z,
                inter_anchor_id=z,
                inter_own_is_p=np.zeros(0, bool),
                inter_T=E,
                inter_W=np.zeros((0, 6)),
                inter_robust=np.zeros(0, bool),
                prior_own=np.array([0]),
                prior_T=T_gt[:1],
                prior_W=np.full((1, 6), 1e3 * max(wt, wr)),
                obs_own=pi.astype(np.int64),
                obs_object=obs_obj.astype(np.int64),
                obs_T=Z_obs,
                obs_W=np.tile(W, (pi.size, 1)),
                separators_for={},
            )
        )
        gt_robots.append(T_gt)
    return Scenario(params, gt_robots, gt_objects, problems)


def centralized(
    sc: Scenario, kernel=None, object_kernel=None
) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
    """The global graph (all trajectories + one copy per object), its initial values, offsets.

    ``kernel`` on the robust loops, ``object_kernel`` on the observations (None: least squares)."""
    sizes = [p.n for p in sc.problems]
    off = np.concatenate([[0], np.cumsum(sizes)])
    M = sc.params.num_objects
    N = off[-1] + M
    blocks: list[BetweenFactors | PriorFactors] = []
    x0 = [p.x0 for p in sc.problems]
    y0 = np.broadcast_to(np.eye(4), (M, 4, 4)).copy()
    seen = np.zeros(M, bool)
    for r, p in enumerate(sc.problems):
        o = off[r]
        rob = p.between_robust
        blocks.append(
            BetweenFactors(p.between[~rob] + o, p.between_T[~rob], p.between_W[~rob], p.residual)
        )
        if rob.any():
            blocks.append(
                BetweenFactors(
                    p.between[rob] + o, p.between_T[rob], p.between_W[rob], p.residual, kernel
                )
            )
        blocks.append(PriorFactors(p.prior_own[:, None] + o, p.prior_T, p.prior_W, p.residual))
        var = np.stack([p.obs_own + o, off[-1] + p.obs_object], axis=1)
        blocks.append(BetweenFactors(var, p.obs_T, p.obs_W, p.residual, object_kernel))
        for k in range(p.obs_object.size):
            oid = p.obs_object[k]
            if not seen[oid]:
                y0[oid] = p.x0[p.obs_own[k]] @ p.obs_T[k]
                seen[oid] = True
    # frozen factor dataclasses against Factor's settable attributes (solver/factors.py)
    graph = PoseGraph(3, kinds_array(N), tuple(blocks))  # type: ignore[arg-type]
    return graph, np.concatenate(x0 + [y0]), off


def bench_config(robust: bool, min_views: int | None = None) -> AgentConfig:
    """The agent settings of ``dran-edge bench objects``: least squares everywhere, or with
    ``robust`` the settings ``--outliers`` turns on (docs/dran.md, robustness): Cauchy 0.05 on
    the loops (unit information: 0.05 m / 0.05 rad), 1.0 on the object observations, and lone
    observations held back (min views 2) except where the spatial exclusion clears them, which
    also holds back repeated views that share their place with a better-seen object. The
    consensus-conflict kernel is off (``conflict_reach_m`` 0): with the exclusion all but one of
    the 1956 wrong views of scenario seeds 0-7 wait for corroboration, and on drifted copies of
    one object the kernel only slowed the fleet (seed 5: +24 % ATE where the run ended;
    docs/notes/benchmarks-history.md, "Tenth session"). The kernel on copies far from the association
    check's centre (``centre_reach_m``, 16 m, the agent default) stays on: a lone wrong view
    cleared by the exclusion can start a phantom in the first round, and least squares would
    average it into the relays before the check drops it ("Thirteenth session"). ``min_views``
    overrides the min views. β is the paper's 1: this simulation has unit information (β has
    the units of information; the daemon's default is for the robot's tag observations). The
    fleet stops on the "tail" rule (docs/notes/stopping-rule.md): the paper's ε_u/ε_v test let
    a run stop at K_max 27 % above F*."""
    return AgentConfig(
        beta=1.0,
        stop_rule="tail",
        robust_kernel=RobustKernel.CAUCHY if robust else RobustKernel.NONE,
        robust_threshold=0.05,
        object_robust_threshold=1.0,
        conflict_reach_m=0.0 if robust else 16.0,
        object_min_views=min_views if min_views is not None else 2 if robust else 1,
    )


@dataclasses.dataclass(frozen=True)
class _Reference:
    """The centralized reference of a scenario and the start's metrics (F_init, ATE_init)."""

    graph: PoseGraph
    init: np.ndarray
    off: np.ndarray
    """Robot r's poses are ``init[off[r]:off[r + 1]]``."""
    n_x: int
    """Number of robot poses (the rest of ``init`` are objects)."""
    gt_x: np.ndarray
    F_init: float
    F_star: float
    ate0: float
    ate_star: float


def _reference(sc: Scenario, config: AgentConfig) -> _Reference:
    """The reference (F*, ATE*): the centralized LM with the agents' kernels.

    With outliers it solves the same seed's scenario without them (same trajectories, noise
    and start; see make_scenario), so SR_cost and SR_ATE say how close the fleet gets, despite
    the outliers, to what a centralized solver gets without them. Over all factors the
    centralized LM has no gating, and the wrong ids drag it metres away (ATE* 3–23 m at 20 %,
    docs/notes/benchmarks-history.md).
    """
    ref_sc = sc
    if sc.params.outlier_ratio > 0:
        ref_sc = make_scenario(
            dataclasses.replace(sc.params, outlier_ratio=0.0), sc.problems[0].residual
        )
    graph, init, off = centralized(
        ref_sc,
        make_kernel(config.robust_kernel, config.robust_threshold),
        make_kernel(config.robust_kernel, config.object_kernel_width),
    )
    ref = solve(graph, init, LMParams(max_iterations=100))
    gt_x = np.concatenate(sc.gt_robots)
    n_x = int(off[-1])
    return _Reference(
        graph,
        init,
        off,
        n_x,
        gt_x,
        evaluate_cost(graph, init),
        ref.cost,
        metrics.ate_log_rmse(init[:n_x], gt_x),
        metrics.ate_log_rmse(ref.poses[:n_x], gt_x),
    )


def _snapshot(sc: Scenario, ref: _Reference, agents: list[Agent], fleet: Fleet) -> dict[str, Any]:
    """The paper's metrics of the fleet's current estimate (objects: the robots' mean)."""
    M = sc.params.num_objects
    Y = np.broadcast_to(np.eye(4), (len(agents), M, 4, 4)).copy()
    present = np.zeros((len(agents), M), bool)
    for i, a in enumerate(agents):
        for oid, T in a.y.items():
            Y[i, oid], present[i, oid] = T, True
    x = np.concatenate([a.x for a in agents])
    have = present.any(axis=0)
    y_mean = ref.init[ref.n_x :].copy()
    if have.any():
        y_mean[have] = metrics.object_mean(Y[:, have], present[:, have])
    F_k = evaluate_cost(ref.graph, np.concatenate([x, y_mean]))
    ate_k = metrics.ate_log_rmse(x, ref.gt_x)
    ce = metrics.consistency_error(Y[:, have], present[:, have])[0] if have.any() else 0.0
    bias = (
        metrics.object_bias(Y[:, have], present[:, have], sc.gt_objects[have])
        if have.any()
        else 0.0
    )
    return {
        "round": fleet.round,
        "F": F_k,
        "SR_cost": metrics.sr_cost(ref.F_init, F_k, ref.F_star),
        "F_over_Fstar": metrics.cost_ratio(F_k, ref.F_star),
        "ATE": ate_k,
        "SR_ATE": metrics.sr_ate(ref.ate0, ate_k, ref.ate_star),
        "ATE_over_ATEstar": metrics.ate_ratio(ate_k, ref.ate_star),
        "CE": float(ce),
        "Bias": float(bias),
        "bytes": fleet.traffic.bytes_total,
    }


def _refine(
    sc: Scenario, graph: PoseGraph, init: np.ndarray, off: np.ndarray, fleet, params, links
) -> dict:
    """``run_objects``' refinement over the fleet's bus ({} when ``params`` is None); the
    curve's and history's F are the root's 2 Σ f_r (halved by the caller)."""
    from dran_edge.experiments import object_refine
    from dran_edge.experiments.fleet import lossy_links, refine_over_fleet

    if params is None:
        return {}
    adjacency = [fleet.bus.neighbours(r) for r in fleet.ids]
    kernels = any(b.kernel is not None for b in graph.factors) or sc.params.outlier_ratio > 0
    return refine_over_fleet(
        fleet,
        params.mode,
        lambda exchange: object_refine.refine_objects(
            graph, off, init, adjacency, exchange, params
        ),
        reliable=lossy_links(links),
        skip="robust kernels or outliers: least squares only" if kernels else "",
    )


def run_objects(
    sc: Scenario,
    config: AgentConfig,
    comm_graph,
    links=None,
    max_rounds: int = 200,
    seed: int = 0,
    history_every: int = 0,
    progress=None,
    refine=None,
    stop: bool = True,
) -> dict:
    """DRAN on the scenario over the in-process bus, with the paper's metrics.

    ``comm_graph``: the communication graph as ``comms.bus.Bus`` takes it (undirected robot
    pairs or a ``round -> edges`` callable such as ``bus.random_connected_graph``); ``links``:
    the bus's ``BusParams`` (default lossless, next-round delivery); ``seed`` replaces
    ``links.seed``. ``history_every`` > 0: the metrics every that many rounds in ``history``;
    ``progress(round)``, if given, is called after every round (for progress output).
    SR_cost and SR_ATE are against the centralized LM; for a scenario with outliers, the LM of
    the same scenario without them (F, F_init and F* on that outlier-free graph).

    ``refine`` (an ``exact_gn.RefineParams``): before the first round, exact distributed LM
    steps on the centralized objective over the same bus (``experiments.object_refine``;
    over lossy links through the ARQ, ``Fleet.reliable_exchange``; least squares only, else
    not run; a link down too long ends it; ``refine_reason`` says why); the
    agents start from the refined trajectories and object copies. A refinement that stopped
    on its relative-decrease test ends the run there when ``stop`` (``stopped_by``
    "refine"). ``round`` and ``bytes`` count the refinement's exchanges too; ``rounds`` the
    DRAN rounds only."""
    from dran_edge.comms.bus import Bus, BusParams
    from dran_edge.experiments.fleet import Fleet, neighbour_weights, stop_rounds_for

    ref = _reference(sc, config)
    bus = Bus(
        range(len(sc.problems)),
        graph=comm_graph,
        params=dataclasses.replace(links or BusParams(), seed=seed),
    )
    W = neighbour_weights(bus)
    fleet = Fleet([], bus)
    refined = _refine(sc, ref.graph, ref.init, ref.off, fleet, refine, links)
    start = ref.init if refined.get("poses_refined") is None else refined.pop("poses_refined")
    off, n_x = ref.off, ref.n_x
    agents = []
    K = stop_rounds_for(bus, config)
    for r, p in enumerate(sc.problems):
        cfg = dataclasses.replace(
            config, robot_id=r, neighbours=tuple(sorted(W[r])), dim=3, stop_rounds=K
        )
        if refine is not None:
            p = dataclasses.replace(p, x0=start[off[r] : off[r + 1]].copy())
        agent = Agent(cfg, p, weights=W[r])
        if refine is not None:  # every copy of an observed object at the refined value
            for oid in agent.y:
                agent.y[oid] = start[n_x + oid].copy()
        agents.append(agent)
    fleet.agents, fleet.estimates = agents, [None] * len(agents)
    history = []

    def cb(k, _fleet):
        if history_every and k % history_every == 0:
            history.append(_snapshot(sc, ref, agents, fleet))
        if progress is not None:
            progress("rounds", k, max_rounds)

    if stop and refined.get("refine_converged"):  # the root's global test already held
        rounds, reasons = 0, ["refine"]
    else:
        rounds = fleet.run(max_rounds, callback=cb)
        reasons = sorted({a.stop_reason for a in agents if a.stop_reason})
    out = _snapshot(sc, ref, agents, fleet)
    if refined:
        refined["refine_curve"] = [(k, b, F / 2) for k, b, F in refined["refine_curve"]]
        refined["refine_F_history"] = [F / 2 for F in refined["refine_F_history"]]
    out.update(refined)
    out.update(
        {
            "rounds": rounds,
            "stopped_by": "+".join(reasons) if rounds < max_rounds else None,
            "F_init": ref.F_init,
            "F_star": ref.F_star,
            "ATE_init": ref.ate0,
            "ATE_star": ref.ate_star,
            "history": history,
            "local_step_ms_median": float(np.median(fleet.step_ms)) if fleet.step_ms else 0.0,
            "datagrams": fleet.traffic.datagrams,
            "dropped": fleet.traffic.dropped,
            "consensus_conflicts": sum(a.counters.consensus_conflicts for a in agents),
        }
    )
    return out
