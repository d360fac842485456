"""Exact distributed Levenberg–Marquardt refinement by substructuring (docs/dran.md, "Exact
Gauss–Newton refinement"): the condensation of ``dran_edge.dran.substructure`` applied to the
Gauss–Newton system of the whole pose-graph problem.

Objective: the chordal SE-Sync cost DRAN minimises (paper eq. 2), ``F = Σ_e κ_e‖R_j − R_i R̃_e‖²
+ τ_e‖t_j − t_i − R_i t̃_e‖²``, as ``½F = Σ ½‖W_e r_e‖²`` (``solver.factors``, chordal residual,
isotropic whitening). Robot r's share takes its own edges and its inter-robot edges at half
weight, so ``H = Σ_r H⁽ʳ⁾``, ``g = Σ_r g⁽ʳ⁾`` and ``½F = Σ_r f_r`` (``solver.lm`` linearisation
per edge block: ``H⁽ʳ⁾ = J_rᵀJ_r``, Gauss–Newton). One iteration, over the BFS tree of the robot
graph (2 × height rounds):

1. every robot linearises its share at its current poses (own vertices and anchors), damps it
   with Marquardt's ``μ diag(H⁽ʳ⁾)`` (the robots' damping terms sum to ``μ diag(H)``: one
   consistent global damping), condenses ``(H⁽ʳ⁾ + μ diag H⁽ʳ⁾) δ = −g⁽ʳ⁾`` onto its boundary
   and sends it up (``REFINE_SCHUR``) with its cost share f_r at those poses and the decrease
   its share's model predicted for the step that led there, ``ℓ_r = −g⁽ʳ⁾ᵀδ − ½ δᵀH⁽ʳ⁾δ``
   (each as a float32 pair hi + lo, ~1e-14 relative), and whether its interior block was
   positive definite (``RefineParams.hessian`` "exact" can make it indefinite);
2. the root sums ``F = 2 Σ f_r`` and decides (the rule below); when it takes a step it solves
   the interface system;
3. down the tree: the boundary steps (``REFINE_STEP``, every robot's boundary, float32) and the
   decision (``REFINE_CONTROL``: flags accepted / stop / step / exact Hessian next, and μ for
   the next condensation);
4. every robot back-substitutes its interior step and retracts ``T ⊕ δ`` (own vertices and
   anchors: the copies of a vertex stay identical, the root rounds its own values to float32
   like everybody's).

Accept / damping rule (the root's, Nielsen's update as in ``solver.lm``): the first gather is
the start point. A trial point is accepted when ``F`` fell: ``ρ = (F_acc − F) / (2 Σ ℓ_r) > 0``;
then ``μ ← μ max(1/3, 1 − (2ρ − 1)³)`` (≥ ``mu_min``), ν = 2; else μ ← μ ν, ν ← 2ν and every
robot returns to its accepted poses and condenses there again with the new μ (a rejection costs
one more round trip). The μ the root announces is used from the robots' next condensation on
(a step is always damped with the μ announced before it). Stop: ``max_steps`` gathers after the
first, or an accepted step whose relative decrease ``(F_acc − F)/F_acc`` is below ``rel_tol``,
or μ above ``mu_max`` (no step lowers F). The last scatter carries only the decision.

Frozen steps (``RefineParams.frozen``, chord Newton; off by default): a gather costs the dense
condensed systems (|B_r|² per robot), a step's right-hand side only |B_r|. After a full gather
whose step was taken the root may announce (``REFINE_CONTROL`` flag 16) that the next gather
is *frozen*: every robot keeps its interior factor of ``H⁽ʳ⁾ + μ diag H⁽ʳ⁾`` (and ``H⁽ʳ⁾`` of
that model, for ℓ_r), linearises only its gradient at its new poses and sends
``g_r = −g⁽ʳ⁾_B + H_BI H_II⁻¹ g⁽ʳ⁾_I`` (``Condensed.with_rhs``: |B_r|·dof floats, then the same
five scalars) as ``REFINE_SCHUR`` chunks; the root solves with its kept factor of ``Σ S_r``
(``substructure.Interface``), scatters the boundary steps as above and the robots
back-substitute with the kept factor. The fixed point is ``g = 0`` whatever the frozen matrix
(its float32 rounding on the wire included: it changes the contraction, not the optimum).
A frozen step leaves μ as it was (it was damped with the frozen factor's μ; rejected, the
factor was stale, not the damping too weak). The root announces a full gather instead after a
rejected trial, when its rule changes the model (Gauss–Newton → exact) or when a frozen step
decreased F by more than ``frozen_rate`` times the previous step of the same factor (linear
contraction too slow) or below ``rel_tol`` (the stop is decided on a full step's decrease, as
without frozen steps: a frozen step's is smaller where the model is poor, e.g. Gauss–Newton on
large residuals; a full step rejected right after a frozen step below ``rel_tol`` stops too).

Iterative interface solve (``RefineParams.interface="pcg"``, ``dran_edge.dran.interface_pcg``):
every gather is a gradient gather as a frozen one (S_r stays with its robot) and the root solves
the interface system by preconditioned conjugate gradients over the tree to ``pcg_eta``; not
with frozen steps. ``newton_first``: the exact Hessian from the first step until a trial is
rejected (the polish after DRAN's rounds, ``experiments.fleet.run_g2o_dran(polish=...)``).

When (``RefineParams.mode="auto"``): if one step's condensed systems (``direct_floats`` with
block size dof) cost at most ``step_budget`` rounds' worth of separator poses
(``iteration_floats``), i.e. where DRAN's own rounds are the more expensive way to converge.
Synchronous and lossless only (the tree protocol needs every message, as the substructured
init); the asynchronous daemon does not run it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import cast

import numpy as np
import scipy.sparse as sp

from dran_edge import geometry as geo
from dran_edge.dran import interface_pcg, substructure
from dran_edge.dran.dist_init import Exchange
from dran_edge.dran.partition import Partition, RobotPart
from dran_edge.messages import InitEntry, InitStage
from dran_edge.solver.factors import BetweenFactors, Factor, isotropic_whitening
from dran_edge.solver.linearize import block_normal_equations


@dataclass(frozen=True)
class RefineParams:
    """Parameters of the exact distributed refinement (module docstring)."""

    mode: str = "auto"
    """"auto" (refine when ``step_budget`` allows), "always" or "never"."""
    max_steps: int = 200
    """Gathers after the first (accepted or rejected trials) at most: a safety cap; the run
    stops on ``rel_tol``. Gauss–Newton converges linearly (rate ~0.9) on large-residual graphs
    (the suite's noisy3d chains needed 48 to over 100 steps; 20, the earlier cap, left them at
    1.0012–1.09 F*)."""
    rel_tol: float = 1e-5
    """Stop after an accepted step that lowered F by less than this fraction."""
    mu_init: float = 1e-6
    """Initial Marquardt μ (relative: the damping is μ diag(H))."""
    mu_min: float = 1e-12
    mu_max: float = 1e8
    step_budget: float = 100.0
    """"auto": one step may send at most this many rounds' worth of separator values."""
    hessian: str = "gauss_newton"
    """"gauss_newton" (H⁽ʳ⁾ = J_rᵀJ_r) or "exact": the chordal residual's second-order terms
    added (``solver.factors.BetweenFactors.second_order``, damped Newton), used once an accepted
    step lowered F by less than ``newton_switch`` (near the optimum, where Gauss–Newton
    converges linearly on large residuals); a system that is not positive definite (a robot's
    interior or the root's interface) takes no step, raises μ and falls back to Gauss–Newton
    until the next such step. Measured (docs/notes/generalisation.md): no faster on noisy3d
    (Newton steps rejected there, as in the centralized LM), 8 instead of 11 steps to 1e-7 on
    a car3d chain."""
    newton_switch: float = 1e-2
    """See ``hessian``; ``inf``: the exact Hessian from the first step."""
    newton_first: bool = False
    """With ``hessian`` "exact": the exact Hessian from the first step, until a trial is
    rejected or a system is not positive definite; then ``newton_switch`` decides (a start near
    the optimum, e.g. the polish after DRAN; far from it, on large residuals, Newton steps are
    mostly rejected and Gauss–Newton goes first)."""
    frozen: bool = False
    """Chord (frozen-Hessian) steps (module docstring, "Frozen steps"): after a full gather
    whose step was taken, the robots send only their gradients condensed with the frozen
    interior factors and the root solves with its frozen interface factor, until a step is
    rejected, the model changes (Gauss–Newton → exact) or the contraction is slower than
    ``frozen_rate``."""
    frozen_rate: float = 0.5
    """Frozen steps go on while an accepted step's decrease of F is at most this fraction of
    the previous accepted step's (linear contraction of the chord iteration) and at least
    ``rel_tol`` (relative)."""
    interface: str = "dense"
    """How the root solves the interface system: "dense" (every robot's condensed S_r gathered
    and factorised) or "pcg" (``dran_edge.dran.interface_pcg``: S_r stays with its robot; the
    gathers carry only the condensed gradients, then preconditioned CG over the tree to the
    relative residual ``pcg_eta``). Not with ``frozen``."""
    pcg_eta: float = 0.1
    """"pcg": relative residual of the interface system at which CG stops (an inexact Newton
    step: it leaves about this share of the step's error; on sphere2500 from DRAN's estimate
    0.1 reached 9e-10 in two steps for 2.04 MB of floats, 0.01 1.6e-11 for 2.44 MB)."""
    pcg_mode_tol: float = 1e-3
    """"pcg": a robot's coarse modes are the eigenvectors of S_r against its block diagonal
    with eigenvalue below this (``interface_pcg.soft_modes``)."""
    pcg_max_modes: int = 60
    """"pcg": coarse modes per robot at most."""
    pcg_max_iter: int = 200
    """"pcg": CG iterations per step at most."""


@dataclass
class RefineResult:
    poses: np.ndarray
    """(n, D, D) merged: every vertex as its owner holds it after the last accepted step."""
    used: bool
    rounds: int = 0
    steps: int = 0
    """Accepted steps."""
    trials: int = 0
    """Gathers after the first."""
    F_history: list[float] = field(default_factory=list)
    """F (SE-Sync) at the start and after every accepted step, as the root summed it."""
    F_rounds: list[int] = field(default_factory=list)
    """The rounds (exchanges so far) at which the root knew each ``F_history`` value."""
    mu_history: list[float] = field(default_factory=list)
    reason: str = ""
    indefinite: int = 0
    """Gathers whose (exact-Hessian) system was not positive definite (no step taken)."""
    converged: bool = False
    """Stopped on ``rel_tol`` (an accepted step lowered F by less than that fraction)."""
    ratio_floats: float = 0.0
    """One step's floats over one round's separator values (``step_budget``'s test)."""
    frozen_steps: int = 0
    """Steps taken from a frozen factorisation (``RefineParams.frozen``)."""
    pcg_iterations: list[int] = field(default_factory=list)
    """CG iterations of every interface solve (``RefineParams.interface`` "pcg")."""


def step_ratio(
    partition: Partition, dim: int, gauge: int = 0, tree: substructure.RobotTree | None = None
) -> float:
    """Floats of one refinement step over one round in which every separator pose travels."""
    b = geo.dof(dim)
    tree = tree or substructure.robot_tree(partition)
    return substructure.direct_floats(partition, b, 1, gauge, tree) / max(
        substructure.iteration_floats(partition, b, 1), 1
    )


def scatter_blocks(
    H_blocks: np.ndarray, g_blocks: np.ndarray, variables: np.ndarray, n: int, b: int
) -> tuple[sp.csr_matrix, np.ndarray]:
    """Per-factor normal-equation blocks ((m, k·b, k·b), (m, k·b), factor ``variables`` (m, k))
    summed into the n·b square H and the gradient g."""
    m, k = variables.shape
    idx = substructure.expand(variables.reshape(-1), b).reshape(m, k * b)
    rows = np.repeat(idx, k * b, axis=1).ravel()
    cols = np.tile(idx, (1, k * b)).ravel()
    H = sp.csr_matrix((H_blocks.ravel(), (rows, cols)), shape=(n * b, n * b))
    return H, np.bincount(idx.ravel(), weights=g_blocks.ravel(), minlength=n * b)


def share(
    part: RobotPart,
    n: int,
    dim: int,
    edges: np.ndarray,
    measurements: np.ndarray,
    W: np.ndarray,
    poses: np.ndarray,
    exact: bool = False,
) -> tuple[sp.csr_matrix, np.ndarray, float, np.ndarray]:
    """Robot's share (H⁽ʳ⁾, g⁽ʳ⁾, f_r, diag J_rᵀJ_r) at ``poses``: n·dof square, its edges with
    the inter-robot ones at half weight (``W`` the (m, r) whitening of all edges); ``exact``
    adds the second-order terms to H⁽ʳ⁾ (not to the returned diagonal, the damping's scale)."""
    b = geo.dof(dim)
    eidx = np.concatenate([part.intra_edges, part.inter_edges]).astype(np.int64)
    scale = np.concatenate([np.ones(part.intra_edges.size), np.full(part.inter_edges.size, 0.5)])
    block = BetweenFactors(
        edges[eidx], measurements[eidx], W[eidx] * np.sqrt(scale)[:, None], residual="chordal"
    )
    Hb, gb, cost = block_normal_equations(cast(Factor, block), poses)
    H, g = scatter_blocks(Hb, gb, edges[eidx], n, b)
    D = H.diagonal()
    if exact:
        H2 = block.second_order(poses)
        assert H2 is not None  # the chordal residual has them
        H = H + scatter_blocks(H2, np.zeros(gb.shape), edges[eidx], n, b)[0]
    return H, g, cost, D


#: ``share_of(part, poses, exact) -> (H⁽ʳ⁾, g⁽ʳ⁾, f_r, damping diagonal)``: a robot's share of
#: the Gauss–Newton system (``share`` for the chordal pose graph), own vertices and anchors only.
ShareFn = Callable[
    [RobotPart, np.ndarray, bool], tuple[sp.csr_matrix, np.ndarray, float, np.ndarray]
]


#: Scalars after every REFINE_SCHUR vector: f_r and ℓ_r as float32 pairs (``_split``), then
#: 1.0 when the robot's interior block was positive definite.
NSCALARS = 5


def _split(x: float) -> list[float]:
    """x as a float32 pair (hi, lo) with hi + lo ≈ x to ~1e-14 relative."""
    hi = float(np.float32(x))
    return [hi, float(np.float32(x - hi))]


def _scalars(cost: float, pred: float, positive_definite: bool) -> list[float]:
    """The ``NSCALARS`` values after a robot's REFINE_SCHUR vector."""
    return _split(cost) + _split(pred) + [float(positive_definite)]


@dataclass
class _Robot:
    T_acc: np.ndarray  # accepted poses (own vertices and anchors meaningful)
    T: np.ndarray  # current (trial) poses
    mu: float
    pred: float = 0.0
    exact: bool = False  # model of the next condensation (the root's word)
    frozen: bool = False  # the next gather sends only the condensed gradient (the root's word)
    loc: substructure.Condensed | None = None  # the kept (frozen) condensation
    H: sp.csr_matrix | None = None  # its model's (undamped) Hessian share, for ℓ_r


class LMRule:
    """The root's accept / damping rule (module docstring): ``decide`` once per gathered
    point, in order."""

    def __init__(self, p: RefineParams, wire_dtype: type | None = np.float32):
        self.p, self.mu, self.nu, self.wire_dtype = p, p.mu_init, 2.0, wire_dtype
        self.F_acc = np.inf
        self.trial = False  # the gathered point is a trial (else the accepted point)
        self.last_rel = np.inf  # relative decrease of the last accepted trial
        self.newton_ok = p.newton_first  # Newton until a rejection or an indefinite system
        self.exact = self._model()  # next model
        self.last_dec = np.inf  # decrease of F by the last accepted trial
        self.slow = False  # the last accepted trial decreased F by > frozen_rate of the one before
        self.small_frozen: float | None = None  # its rel. decrease, a frozen step's < rel_tol

    def decide(
        self, F: float, pred: float, trials: int, frozen: bool = False
    ) -> tuple[bool, bool, str]:
        """(accepted, stop, reason) for the point just gathered; updates μ. ``frozen``: the
        trial was a frozen step, its decrease is compared with the previous one's (of the same
        factor); a slow one, or one below ``rel_tol``, does not stop the run (a full step
        decides: its decrease below ``rel_tol``, or its rejection after a frozen step below
        ``rel_tol``, stops); μ stays (the step was damped with the frozen factor's μ; a
        rejected one means the factor, not the damping, was stale: a full gather follows)."""
        p = self.p
        rel = None
        accept = not self.trial or F < self.F_acc
        if self.trial:
            rel = (self.F_acc - F) / self.F_acc
            if accept:
                dec = self.F_acc - F
                # a frozen step's decrease is no optimality test (the full step's is)
                self.slow = frozen and (dec > p.frozen_rate * self.last_dec or rel < p.rel_tol)
                self.last_dec = dec
                self.small_frozen = rel if frozen and rel < p.rel_tol else None
            elif not frozen and self.small_frozen is not None:  # no full step gains: optimal
                small, self.small_frozen = self.small_frozen, None
                return (
                    False,
                    True,
                    f"relative decrease {small:.1e} < {p.rel_tol:g} (a frozen step; "
                    "the full step after it rejected)",
                )
            if not frozen:  # a frozen step's damping was the frozen factor's: μ stays
                if accept:
                    rho = (self.F_acc - F) / pred if pred > 0 else 1.0
                    self.mu = max(self.mu * max(1 / 3, 1 - (2 * rho - 1) ** 3), p.mu_min)
                    self.nu = 2.0
                else:
                    self.mu, self.nu = self.mu * self.nu, self.nu * 2
        if self.wire_dtype is not None:  # what every robot receives
            self.mu = float(self.wire_dtype(self.mu))
        if accept:
            self.F_acc = F
            if rel is not None:
                self.last_rel = rel
        elif not frozen:
            self.newton_ok = False
        self.trial = accept
        self.exact = self._model()
        if accept and rel is not None and rel < p.rel_tol and not self.slow:
            return accept, True, f"relative decrease {rel:.1e} < {p.rel_tol:g}"
        if trials >= p.max_steps:
            return accept, True, f"{p.max_steps} steps"
        if self.mu > p.mu_max:
            return accept, True, f"mu {self.mu:.1e} > {p.mu_max:g}"
        return accept, False, ""

    def _model(self) -> bool:
        """Whether the next condensation uses the exact Hessian (``RefineParams.hessian``)."""
        p = self.p
        return p.hessian == "exact" and (self.newton_ok or self.last_rel <= p.newton_switch)

    def indefinite(self) -> None:
        """The gathered (accepted) point's system is not positive definite: no step; more
        damping, and Gauss–Newton for the next condensation."""
        self.mu, self.nu = self.mu * self.nu, self.nu * 2
        if self.wire_dtype is not None:
            self.mu = float(self.wire_dtype(self.mu))
        self.trial, self.exact, self.last_rel = False, False, np.inf
        self.newton_ok = False


def _step_entry(owner: np.ndarray, d: int, b: int) -> Callable[[int, np.ndarray], InitEntry]:
    def to_entry(v: int, step: np.ndarray) -> InitEntry:
        value = np.zeros(d * d)
        value[:b] = step.ravel()
        return InitEntry(InitStage.REFINE_STEP, int(owner[v]), v, value.reshape(d, d))

    return to_entry


def refine(
    dim: int,
    n: int,
    edges: np.ndarray,
    measurements: np.ndarray,
    kappa: np.ndarray,
    tau: np.ndarray,
    partition: Partition,
    poses: np.ndarray,
    exchange: Exchange,
    params: RefineParams = RefineParams(),
    gauge: int = 0,
    wire_dtype: type | None = np.float32,
) -> RefineResult:
    """Refine ``poses`` (every robot starts from them) by exact distributed LM steps on the
    chordal pose graph (module docstring); every value crosses ``exchange``
    (``dist_init.Exchange``). ``wire_dtype``: the value type the exchange delivers (the
    codec's float32), applied to the root's own copy of the steps and μ so that every copy of
    a vertex moves alike; None for a float64 in-memory exchange (``dist_init.direct_exchange``,
    tests)."""
    W = isotropic_whitening(kappa, tau, "chordal", dim)

    def share_of(
        part: RobotPart, T: np.ndarray, exact: bool
    ) -> tuple[sp.csr_matrix, np.ndarray, float, np.ndarray]:
        return share(part, n, dim, edges, measurements, W, T, exact)

    return refine_shares(dim, n, partition, share_of, poses, exchange, params, gauge, wire_dtype)


def refine_shares(
    dim: int,
    n: int,
    partition: Partition,
    share_of: ShareFn,
    poses: np.ndarray,
    exchange: Exchange,
    params: RefineParams = RefineParams(),
    gauge: int = 0,
    wire_dtype: type | None = np.float32,
    tree: substructure.RobotTree | None = None,
) -> RefineResult:
    """``refine`` for any objective whose robot shares ``share_of`` gives (``ShareFn``; F in
    the results is 2 Σ f_r), over ``tree`` (default: the BFS tree of the partition's robot
    graph); ``gauge`` < 0: no gauge vertex (priors fix it). A loop over gather → decide →
    scatter → retract, one pass per iteration, hence its length."""
    # Long: one loop of the refinement protocol (gather, root decision, scatter, retract) whose
    # steps share the per-robot state; each step is a few lines and commented.
    if params.mode not in ("auto", "always", "never"):
        raise ValueError(f"RefineParams.mode must be auto, always or never, got {params.mode!r}")
    if params.interface not in ("dense", "pcg"):
        raise ValueError(f"RefineParams.interface must be dense or pcg, got {params.interface!r}")
    if params.interface == "pcg" and params.frozen:
        raise ValueError("RefineParams: frozen steps need the dense interface, not pcg")
    poses = np.asarray(poses, np.float64)
    if params.mode == "never" or partition.num_robots < 2:
        return RefineResult(poses.copy(), False, reason="off")
    tree = tree or substructure.robot_tree(partition)
    ratio = step_ratio(partition, dim, gauge, tree)
    if params.mode == "auto" and ratio > params.step_budget:
        return RefineResult(
            poses.copy(), False, reason=f"a step costs {ratio:.0f} rounds", ratio_floats=ratio
        )
    b, d = geo.dof(dim), dim
    mu0 = params.mu_init if wire_dtype is None else float(wire_dtype(params.mu_init))
    root = LMRule(params, wire_dtype)
    robots = [_Robot(poses.copy(), poses.copy(), mu0, exact=root.exact) for _ in partition.parts]
    res = RefineResult(poses, True, ratio_floats=ratio)
    to_entry = _step_entry(partition.owner, d, b)
    no_boundary = [np.zeros(0, np.int64)] * len(robots)
    iface: substructure.Interface | None = None  # the root's last factorised interface
    model_exact = root.exact  # the model of the last full gather (the robots' word)
    stepped_frozen = False  # the last step was solved with a frozen factor
    pcg = params.interface == "pcg"  # S_r stays with its robot, CG over the tree
    while True:
        frozen = robots[tree.root].frozen  # the root's own word (every robot has it)
        locs, shares, packed = [], [], []
        for part, rob in zip(partition.parts, robots):  # 1. linearise, damp, condense
            loc, H, g, flat = _condense_share(part, partition, share_of, rob, b, gauge, pcg)
            locs.append(loc)
            shares.append((H, g))
            packed.append(flat)
        bundle, res.rounds = substructure.gather(
            tree, packed, d, exchange, InitStage.REFINE_SCHUR, res.rounds
        )
        if frozen or pcg:  # the root's frozen factor, or CG: the right-hand sides only
            assert iface is not None or pcg
            scalars = np.array([bundle[o][-NSCALARS:] for o in sorted(bundle)])
            gs = {o: bundle[o][:-NSCALARS].reshape(-1, 1) for o in sorted(bundle)}
            pd = True
        else:
            model_exact = robots[tree.root].exact
            iface, gs, scalars = substructure.factor_interface(bundle, b, 1, NSCALARS)
            pd = iface.positive_definite
        F, pred = 2 * float(scalars[:, :2].sum()), 2 * float(scalars[:, 2:4].sum())
        was_trial = root.trial
        # 2. the root's rule (the trial was a frozen step: the last step came from a frozen gather)
        accept, stop, reason = root.decide(F, pred, res.trials, stepped_frozen)
        if accept and (was_trial or not res.F_history):
            res.F_history.append(F)
            res.F_rounds.append(res.rounds)
            res.mu_history.append(root.mu)
        step = accept and not stop
        if step and not (pd and scalars[:, 4].all()):
            step = False
            root.indefinite()
            res.indefinite += 1
        # frozen next: a step from a factor of the model the rule wants next, not slowing down
        frozen_next = (
            params.frozen and step and root.exact == model_exact and not (frozen and root.slow)
        )
        res.frozen_steps += int(step and frozen)
        stepped_frozen = step and frozen
        values: dict[int, np.ndarray] = {}
        if step and pcg:  # CG over the tree (S_r stays with robot r)
            sides = [
                interface_pcg.RobotSide.of(loc, b, params.pcg_mode_tol, params.pcg_max_modes)
                for loc in locs
            ]
            sol = interface_pcg.solve(
                tree,
                sides,
                {o: gv[:, 0] for o, gv in gs.items()},
                exchange,
                res.rounds,
                b,
                d,
                params.pcg_eta,
                params.pcg_max_iter,
            )
            res.rounds = sol.rounds
            res.pcg_iterations.append(sol.iterations)
            values = sol.values
            if not sol.positive_definite:  # curvature ≤ 0: no step, as an indefinite system
                step, values = False, {}
                root.indefinite()
                res.indefinite += 1
        elif step and iface is not None:
            values = iface.solve(gs)
        flags = int(accept) | int(stop) << 1 | int(step) << 2 | int(root.exact) << 3
        flags |= int(frozen_next) << 4
        control = InitEntry(
            InitStage.REFINE_CONTROL,
            tree.root,
            0,
            np.resize(np.array([flags, root.mu] + [0.0] * (d * d - 2)), (d, d)),
        )
        if step and wire_dtype is not None:  # what the other robots receive
            values = {v: x.astype(wire_dtype).astype(np.float64) for v, x in values.items()}
        known, extra, res.rounds = substructure.scatter(  # 3. steps and decision down
            tree,
            [loc.B for loc in locs] if step else no_boundary,
            values if step else {},
            exchange,
            InitStage.REFINE_STEP,
            to_entry,
            lambda e: np.asarray(e.value, float).ravel()[:b].reshape(b, 1),
            res.rounds,
            [control],
        )
        for r, (part, rob, loc) in enumerate(zip(partition.parts, robots, locs)):
            ctl = [e for e in extra[r] if InitStage(e.stage) == InitStage.REFINE_CONTROL]
            if not ctl:
                substructure.missing(f"robot {r} did not receive the root's decision")
            flags_f, mu = np.asarray(ctl[0].value, float).ravel()[:2]
            flags = int(round(flags_f))
            acc, stepping = flags & 1, flags & 4
            rob.mu, rob.exact, rob.frozen = float(mu), bool(flags & 8), bool(flags & 16)
            if rob.frozen and not frozen:  # keep this gather's factor and model
                rob.loc, rob.H = loc, shares[r][0]
            if acc:
                rob.T_acc = rob.T.copy()
            rob.T, rob.pred = rob.T_acc.copy(), 0.0
            if not stepping:
                continue
            delta = np.zeros(n * b)  # 4. back-substitute, predicted decrease, retract
            X_B = substructure.boundary_values(loc, known[r], 1)
            delta[substructure.expand(loc.B, b)] = X_B[:, 0]
            if loc.I.size:
                delta[substructure.expand(loc.I, b)] = loc.back_substitute(X_B)[:, 0]
            H, g = shares[r]
            rob.pred = float(-g @ delta - 0.5 * delta @ (H @ delta))
            moved = np.concatenate([loc.I, loc.B])
            rob.T[moved] = geo.retract(rob.T_acc[moved], delta.reshape(n, b)[moved])
        if stop:
            res.reason, res.converged = reason, reason.startswith("relative decrease")
            break
        res.trials += 1
    res.steps = len(res.F_history) - 1
    res.poses = poses.copy()
    for part, rob in zip(partition.parts, robots):
        res.poses[part.vertices] = rob.T_acc[part.vertices]
    return res


def _condense_share(
    part: RobotPart,
    partition: Partition,
    share_of: ShareFn,
    rob: _Robot,
    b: int,
    gauge: int,
    gradient_only: bool = False,
) -> tuple[substructure.Condensed, sp.csr_matrix, np.ndarray, np.ndarray]:
    """Step 1 for one robot: (condensed system, H⁽ʳ⁾ of the model, g⁽ʳ⁾, packed vector). A full
    gather condenses the damped share at the robot's poses; a frozen one only the new gradient,
    with the kept interior factor, and sends that boundary vector and the scalars alone.
    ``gradient_only`` (the "pcg" interface): condensed in full, but only the condensed gradient
    and the scalars travel (S_r stays with the robot)."""
    if rob.frozen:
        assert rob.loc is not None and rob.H is not None
        _, g, cost, _ = share_of(part, rob.T, False)
        loc = rob.loc.with_rhs(-g[:, None])
        return loc, rob.H, g, np.concatenate([loc.g.ravel(), _scalars(cost, rob.pred, True)])
    H, g, cost, D = share_of(part, rob.T, rob.exact)
    loc = substructure.condense(
        part, partition, H + rob.mu * sp.diags(D), -g[:, None], b, gauge, np.zeros((b, 1))
    )
    scalars = _scalars(cost, rob.pred, loc.positive_definite)
    if gradient_only:
        return loc, H, g, np.concatenate([loc.g.ravel(), scalars])
    return loc, H, g, substructure.pack(loc, b, scalars)
