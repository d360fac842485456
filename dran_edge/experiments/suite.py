"""The generalisation suite: generated pose-graph families that DRAN was not tuned on, each
split over robots and solved by DRAN (Table 1 setup), the DGS baseline and the centralized LM.

Families (``FAMILIES``; generators in ``dran_edge.sim.graphgen``), several seeds each:

- ``car2d`` / ``car3d``: a vehicle on a grid of streets (20 m blocks, 3D over hills), one pose
  per metre, 1–3 % of the poses get a loop closure to an earlier visit (spread over the
  trajectory, as car datasets look);
- ``indoor2d``: the same in 6 m corridors, 0.5 m steps (long indoor datasets);
- ``city2d`` / ``city3d``: a random walk on a unit grid with loops at every second revisit
  (M3500 / city10000-like, dense);
- ``noisy3d``: ``car3d`` with 0.1 rad rotation noise per edge;
- ``aniso2d`` / ``aniso3d``: ``car*`` with per-edge correlated translation covariances whose
  axis standard deviations span a factor 10.

Per case (``run_case``): F* and ATE* of the centralized solver (``pgo.solve_g2o`` from the
chordal initialisation, exact Hessian, as ``dran-edge solve`` runs it, with an iteration cap of
``CENTRAL_MAX_ITERATIONS``; ``central_status`` says whether it converged), F of the centralized
chordal initialisation, then DRAN from the distributed initialisation over the in-process bus
with every byte counted (``multiagent.run_g2o_dran``, Table 1 setup, ``stop=False`` so it runs
all rounds while recording where every robot's stopping rule first held), and DGS from the same
initialisation (its init rounds and bytes are DRAN's). F is the SE-Sync objective; ATE the
translation RMSE after a rigid alignment to the ground truth. Nothing here is tuned per case.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

CHECKPOINTS = (50, 100, 200, 300, 500, 1000)
"""DRAN rounds (after the initialisation) at which F/F* is reported."""

CENTRAL_MAX_ITERATIONS = 1000
"""The centralized LM's iteration cap for F*: its default 100 is not enough on the noisy3d
chains (193 iterations on noisy3d-n4000-s3, F 0.35 % below its value after 100)."""


@dataclass(frozen=True)
class Family:
    dim: int
    kind: str  # "road" or "grid"
    sigma_r_rad: float = 0.01
    sigma_t_m: float = 0.05
    anisotropy: float = 1.0
    step_m: float = 1.0
    block_m: float = 20.0
    hills_m: float = 0.0


FAMILIES = {
    "car2d": Family(2, "road"),
    "car3d": Family(3, "road", hills_m=3.0),
    "indoor2d": Family(2, "road", step_m=0.5, block_m=6.0, sigma_t_m=0.02),
    "city2d": Family(2, "grid"),
    "city3d": Family(3, "grid"),
    "noisy3d": Family(3, "road", sigma_r_rad=0.1, hills_m=3.0),
    "aniso2d": Family(2, "road", anisotropy=10.0),
    "aniso3d": Family(3, "road", anisotropy=10.0, hills_m=3.0),
}


@dataclass(frozen=True)
class Case:
    family: str
    num_poses: int
    seed: int
    robots: int = 5
    split: str = "contiguous"  # or "interleaved"

    @property
    def loop_fraction(self) -> float:
        """1, 2 or 3 % by seed for the chain families (the grid families close every loop)."""
        return 0.01 * (1 + self.seed % 3)

    @property
    def name(self) -> str:
        return f"{self.family}-n{self.num_poses}-s{self.seed}-r{self.robots}-{self.split[:6]}"


def make_graph(case: Case):
    """(G2oGraph, true poses) of a case; deterministic in the case."""
    from dran_edge.sim import graphgen as gg

    fam = FAMILIES[case.family]
    n, seed = case.num_poses, case.seed
    if fam.kind == "road":
        blocks = max(3, int(np.sqrt(n * fam.step_m / (4 * fam.block_m))))
        T = gg.road_trajectory(
            fam.dim,
            n,
            seed,
            step_m=fam.step_m,
            block_m=fam.block_m,
            blocks=blocks,
            hills_m=fam.hills_m,
        )
        loops = gg.loop_pairs(
            T,
            1.5 * fam.step_m,
            int(2 * fam.block_m / fam.step_m),
            int(round(case.loop_fraction * n)),
            seed,
        )
    else:
        side = max(6, int(np.sqrt(n / 2)) if fam.dim == 2 else int((n / 2) ** (1 / 3)) + 4)
        T = gg.grid_walk_trajectory(fam.dim, n, seed, side=side)
        loops = gg.loop_pairs(T, 0.01, 4, int(0.5 * n), seed)
    g = gg.graph_from_trajectory(T, loops, fam.sigma_t_m, fam.sigma_r_rad, seed, fam.anisotropy)
    return g, T


def make_partition(case: Case, g):
    from dran_edge.dran.partition import contiguous_owner, interleaved_owner, partition_edges

    if case.split == "contiguous":
        owner = contiguous_owner(g.num_vertices, case.robots)
    elif case.split == "interleaved":
        owner = interleaved_owner(g.num_vertices, case.robots)
    else:
        raise ValueError(f"split must be contiguous or interleaved, got {case.split!r}")
    return partition_edges(g.edges, owner)


def ate_m(T_est: np.ndarray, T_true: np.ndarray) -> float:
    """Translation RMSE (m) after the least-squares rigid alignment of the positions."""
    from dran_edge.evaluation.align import umeyama

    d = T_est.shape[-1] - 1
    p, q = np.zeros((len(T_est), 3)), np.zeros((len(T_true), 3))
    p[:, :d], q[:, :d] = T_est[:, :d, d], T_true[:, :d, d]
    R, t, _ = umeyama(p, q)
    err = p @ R.T + t - q
    return float(np.sqrt(np.mean(np.sum(err * err, axis=1))))


def _first(curve: list, ratio: float, F_star: float):
    """(round, bytes) of the first point of ``curve`` at or below ratio × F*."""
    for k, b, F in curve:
        if F <= ratio * F_star:
            return k, b
    return None, None


class CurveRecorder:
    """The DRAN callback of :func:`run_case` (and of ``bench g2o --curve``): (round, bytes so
    far, F) per round in ``curve`` (round 0, the initialisation's end, filled in by the caller),
    and in ``rule`` the round where every robot had reported convergence for three rounds in a
    row (with F, bytes, ATE when ``T_true`` is given, and the agents' stop reasons).

    ``until_decided`` (with ``F_star``): return True, which ends the run (``Fleet.run``), once
    the questions the suite asks are decided — F ≤ ``target`` × F* reached and the run's own
    stop known: the refinement converged (``on_start`` told it) or the stopping rule fired.
    Rounds after that are not run, so nothing is "measured at round 1000" then."""

    def __init__(
        self,
        part: Any,
        shape: tuple[int, int, int],
        F: Callable[[np.ndarray], float],
        T_true: np.ndarray | None = None,
        F_star: float | None = None,
        until_decided: bool = False,
        target: float = 1.001,
    ):
        self.part, self.shape, self.F, self.T_true = part, shape, F, T_true
        self.F_star, self.until_decided, self.target = F_star, until_decided, target
        self.curve: list[tuple[int, Any, Any]] = []
        self.rule: dict[str, Any] = {"round": None}
        self.streak = 0
        self.refine_converged = False
        self.reached = False
        self.ended_early: int | None = None

    def on_start(self, refined: dict) -> None:
        """``run_g2o_dran``'s hook: whether the refinement already ended the run."""
        self.refine_converged = bool(refined.get("refine_converged"))

    def merged(self, fleet: Any) -> np.ndarray:
        T = np.zeros(self.shape)  # every vertex is some robot's
        for r, p in enumerate(self.part.parts):
            T[p.vertices] = fleet.agents[r].x
        return T

    def __call__(self, k: int, fleet: Any) -> bool:
        if k == 1:  # round 0: the initialisation's end (F filled in by the caller)
            self.curve.append((0, None, None))
        done = all(e is not None and e.converged for e in fleet.estimates)
        self.streak = self.streak + 1 if done else 0
        T = self.merged(fleet)
        # the bus round (the caller makes it relative to the init's end)
        self.curve.append((fleet.round, fleet.traffic.bytes_total, self.F(T)))
        if self.F_star is not None and self.curve[-1][2] <= self.target * self.F_star:
            self.reached = True
        if self.streak >= 3 and self.rule["round"] is None:
            self.rule.update(
                round=self.curve[-1][0],
                F=self.curve[-1][2],
                bytes=self.curve[-1][1],
                ate=None if self.T_true is None else ate_m(T, self.T_true),
                reasons=sorted({a.stop_reason for a in fleet.agents if a.stop_reason}),
            )
        decided = self.reached and (self.refine_converged or self.rule["round"] is not None)
        if self.until_decided and decided:
            self.ended_early = fleet.round
            return True
        return False


def _curve_numbers(
    curve: list[tuple[int, Any, Any]],
    stop: dict[str, Any],
    rule: dict[str, Any],
    F_star: float,
    rounds: int,
    checkpoints: Sequence[int],
) -> dict[str, Any]:
    """F/F* at the checkpoints the run reached, the run's stop and the stopping rule's first
    firing, and the first round and bytes within 1 % and 0.1 % of F*."""
    out: dict[str, Any] = {}
    for c in checkpoints:  # the last point at or before round c
        if c <= rounds and curve[-1][0] >= c:
            out[f"F_over_F_star_at_{c}"] = [f for k, _, f in curve if k <= c][-1] / F_star
    out["stop_round"], out["stopped_by"] = stop["round"], stop.get("by")
    if stop["round"] is not None:
        out.update(
            stop_F_over_F_star=stop["F"] / F_star, stop_bytes=stop["bytes"], stop_ATE_m=stop["ate"]
        )
    out["rule_round"] = rule["round"]
    if rule["round"] is not None:
        out.update(rule_F_over_F_star=rule["F"] / F_star, rule_reasons=rule["reasons"])
    for ratio, key in ((1.01, "1pct"), (1.001, "01pct")):
        k, b = _first(curve, ratio, F_star)
        out[f"round_at_{key}"], out[f"bytes_at_{key}"] = k, b
    return out


def curve_after_init(
    rec: CurveRecorder, res: dict[str, Any], rounds: int, refined: bool
) -> tuple[list[tuple[int, Any, Any]], dict[str, Any]]:
    """The recorder's curve and rule on the axis of rounds after the init: round 0 is the
    init's end; with a refinement, the root's F at each of its accepted points and at its end
    come first (their rounds count), then DRAN's rounds, cut at ``rounds``. Bytes are totals
    since the start, the init's included."""
    curve, rule = rec.curve, dict(rec.rule)
    curve[0] = (0, res["bytes_init"], res["objective_init"])
    r0 = res["init_rounds"]  # bus rounds -> rounds after the init
    curve[1:] = [(k - r0, b, f) for k, b, f in curve[1:] if k - r0 <= rounds]
    if refined:
        curve[1:1] = [(k, res["bytes_init"] + b, f) for k, b, f in res["refine_curve"][1:]] + [
            (
                res["refine_rounds"],
                res["bytes_init"] + res["refine_bytes"],
                res["objective_refined"],
            )
        ]
    if rule["round"] is not None:
        rule["round"] -= r0
    return curve, rule


def _run_stop(res: dict[str, Any], rule: dict[str, Any], ate_refined: float | None) -> dict:
    """Where the run would have ended with ``stop=True``: at the refinement's end when it
    converged (``run_g2o_dran``: no DRAN round then), else where the stopping rule fired."""
    if res.get("refine_converged"):
        return {
            "round": res["refine_rounds"],
            "F": res["objective_refined"],
            "bytes": res["bytes_init"] + res["refine_bytes"],
            "ate": ate_refined,
            "by": "refine",
        }
    if rule["round"] is None:
        return {"round": None}
    return {**rule, "by": "+".join(rule["reasons"]) or "rule"}


def run_case(
    case: Case,
    rounds: int = 1000,
    init_direct: str = "auto",
    dgs: bool = True,
    checkpoints=CHECKPOINTS,
    refine=None,
    stop_rule: str = "tail",
    until_decided: bool = False,
) -> dict:
    """Every number of one case (module docstring); ``curve`` holds (round, bytes so far, F)
    per round, round 0 being the initialisation's end. ``refine`` (``exact_gn.RefineParams``):
    exact LM steps after the init (``run_g2o_dran``); their rounds count on the same axis (the
    curve has a point where the root learnt F at each accepted point of the refinement, one at
    its end, then one per DRAN round, cut at ``rounds``), so the checkpoints and the 1 % / 0.1 %
    rounds and bytes compare like for like. ``stop_rule``: the agents' rule ("tail", as
    ``bench g2o``, or "steps", Table 1's). ``stop_*``: where the run would have stopped (the
    refinement's end when it converged, else the rule's first firing); ``rule_*``: the rule's
    first firing. ``until_decided``: end DRAN once F ≤ 1.001 F* and the stop are known
    (``CurveRecorder``); ``ended_round`` then says where, and the end values are at that round."""
    # Long: one suite case's numbers gathered into one record (module docstring).
    from dran_edge.experiments.dgs import run_g2o_dgs
    from dran_edge.dran.dist_init import InitParams
    from dran_edge.experiments.fleet import TABLE1_DELTA_EVERY, run_g2o_dran, table1_setup
    from dran_edge.solver.objective import sesync_objective, sesync_weights
    from dran_edge.solver.centralized import solve_g2o
    from dran_edge.solver.lm import Hessian, LMParams

    t0 = time.perf_counter()
    g, T_true = make_graph(case)
    part = make_partition(case, g)
    kappa, tau = sesync_weights(g.dim, g.information)

    def F(T):
        return sesync_objective(T, g.edges, g.measurements, kappa, tau)

    lm = LMParams(hessian=Hessian.EXACT, cost_tol=1e-8, max_iterations=CENTRAL_MAX_ITERATIONS)
    central = solve_g2o(g, "chordal", "chordal", "sesync", params=lm)
    F_star, F_chordal = central.objective_final, central.objective_init
    t_central = time.perf_counter() - t0
    cfg, run_kw = table1_setup(g.dim, stop=stop_rule)
    shape = (g.num_vertices, g.dim + 1, g.dim + 1)
    rec = CurveRecorder(part, shape, F, T_true, F_star, until_decided=until_decided)
    t1 = time.perf_counter()
    res = run_g2o_dran(
        g,
        case.robots,
        cfg,
        init_params=InitParams(gauss_seidel=True, direct=init_direct),
        max_rounds=rounds,
        callback=rec,
        partition=part,
        stop=False,
        refine=refine,
        on_start=rec.on_start,
        **run_kw,
    )
    t_dran = time.perf_counter() - t1
    F_init = res["objective_init"]
    curve, rule = curve_after_init(rec, res, rounds, refined=refine is not None)
    ate_refined = ate_m(res["poses_refined"], T_true) if refine is not None else None
    stop = _run_stop(res, rule, ate_refined)
    out = {
        "case": case.name,
        "family": case.family,
        "seed": case.seed,
        "dim": g.dim,
        "poses": g.num_vertices,
        "edges": g.num_edges,
        "robots": case.robots,
        "split": case.split,
        "loop_fraction": case.loop_fraction if FAMILIES[case.family].kind == "road" else None,
        "init_direct": init_direct,
        "F_star": F_star,
        "central_status": central.result.status.value,
        "central_iterations": central.result.iterations,
        "F_chordal": F_chordal,
        "ATE_star_m": ate_m(central.result.poses, T_true),
        "ATE_chordal_m": ate_m(central.poses_init, T_true),
        "F_init": F_init,
        "F_init_over_F_chordal": F_init / F_chordal,
        "init_rounds": res["init_rounds"],
        "init_bytes": res["bytes_init"],
        "ATE_init_m": ate_m(res["poses_init"], T_true),
        "dran_rounds": res["rounds"],
        "dran_bytes": res["bytes_total"],
        **{k: v for k, v in res.items() if k.startswith("refine_") or k == "objective_refined"},
        **({"ATE_refined_m": ate_refined} if refine is not None else {}),
        "stop_rule": stop_rule,
        # the last round on the curve: ``rounds``, or where ``until_decided`` ended the run
        "ended_round": curve[-1][0],
        "ended_early": rec.ended_early is not None,
        "dran_F_end": curve[-1][2],  # at ``ended_round`` (refine rounds count on that axis)
        "dran_F_end_over_F_star": curve[-1][2] / F_star,
        "dran_ATE_end_m": ate_m(res["poses"], T_true),
    }
    out.update(_curve_numbers(curve, stop, rule, F_star, rounds, checkpoints))
    if dgs:
        t2 = time.perf_counter()
        d = run_g2o_dgs(
            g,
            case.robots,
            initial_poses=res["poses_init"],
            partition=part,
            delta_every=TABLE1_DELTA_EVERY,
        )
        out.update(
            dgs_F_end_over_F_star=d["objective_final"] / F_star,
            dgs_rounds=res["init_rounds"] + d["rounds"],
            dgs_bytes=res["bytes_init"] + d["bytes_total"],
            dgs_ATE_end_m=ate_m(d["poses"], T_true),
            dgs_wall_s=time.perf_counter() - t2,
        )
    out.update(central_wall_s=t_central, dran_wall_s=t_dran, wall_s=time.perf_counter() - t0)
    out["curve"] = [(k, b, f / F_star) for k, b, f in curve]
    return out


def default_cases(quick: bool = False, seeds=(1, 2, 3)) -> list[Case]:
    """The suite. Quick: two small families, 3 robots, for the test and a smoke run."""
    if quick:
        return [
            Case("car2d", 240, 1, robots=3),
            Case("city3d", 150, 2, robots=3, split="interleaved"),
        ]
    cases = []
    for fam in FAMILIES:
        for k, seed in enumerate(seeds):
            n = 2000 + 1000 * ((seed + k) % 3) if FAMILIES[fam].kind == "road" else 2000
            cases.append(Case(fam, n, seed))
    for robots in (3, 10, 20):
        cases.append(Case("car2d", 3000, 1, robots=robots))
        cases.append(Case("car3d", 3000, 1, robots=robots))
    for fam in ("car2d", "car3d", "city2d"):
        cases.append(Case(fam, 3000, 1, robots=5, split="interleaved"))
    return cases


def select_cases(
    quick: bool = False,
    seeds: Sequence[int] = (1, 2, 3),
    families: Sequence[str] | None = None,
    robots: Sequence[int] | None = None,
    splits: Sequence[str] | None = None,
    poses: int | None = None,
) -> list[Case]:
    """The cases of ``bench suite``: without ``poses``, the suite's own cases (their pose
    counts) filtered by ``families`` / ``robots`` / ``splits``; with ``poses`` (or a quick run
    with a filter), every family × seed × robots × split at that size (default 5 robots,
    contiguous)."""
    if poses or (quick and (families or robots or splits)):
        return [
            Case(f, poses or (300 if quick else 3000), seed, r, split)
            for f in (families or sorted(FAMILIES))
            for seed in seeds
            for r in (robots or [5])
            for split in (splits or ["contiguous"])
        ]
    return [
        c
        for c in default_cases(quick, tuple(seeds))
        if (not families or c.family in families)
        and (not robots or c.robots in robots)
        and (not splits or c.split in splits)
    ]


def worst_by_family(rows: list[dict]) -> dict:
    """Per family the worst (largest) value of each ratio and the latest 1 % and 0.1 % rounds."""
    keys = [
        "F_init_over_F_chordal",
        "dran_F_end_over_F_star",
        "stop_F_over_F_star",
        "rule_F_over_F_star",
        "dgs_F_end_over_F_star",
    ] + [f"F_over_F_star_at_{c}" for c in CHECKPOINTS]
    out: dict = {}
    for r in rows:
        w = out.setdefault(r["family"], {"cases": 0})
        w["cases"] += 1
        for k in keys:
            if r.get(k) is not None:
                w[k] = max(w.get(k, -np.inf), r[k])
        for key in ("round_at_1pct", "round_at_01pct"):  # None: some case never got there
            k1 = r.get(key)
            w[key] = None if k1 is None or w.get(key, 0) is None else max(w.get(key, 0), k1)
    return out


def _fmt(v, spec=".4f") -> str:
    return "–" if v is None else format(v, spec)


def _at(r: dict, key: str) -> str:
    """ "round / kB" of the first point at ``key`` ("1pct", "01pct"), "–" if never."""
    k, b = r.get(f"round_at_{key}"), r.get(f"bytes_at_{key}")
    return "–" if k is None or b is None else f"{k} / {b / 1e3:.0f}"


def markdown_table(rows: list[dict]) -> str:
    """One line per case: the numbers of ``run_case`` (ratios to F*, bytes in kB). "end" is the
    last round run (``ended_round``: the cap, or where ``until_decided`` ended the run)."""
    # Long but flat: one cell per column.
    cps = [c for c in CHECKPOINTS if any(f"F_over_F_star_at_{c}" in r for r in rows)]
    head = (
        ["case", "F_init/F_chord", "init rnd/kB", "refine rnd/kB"]
        + [f"F/F* @{c}" for c in cps]
        + ["rnd/kB @1.01F*", "rnd/kB @1.001F*", "stop rnd (by)", "F/F* stop", "rule rnd, F/F*"]
        + ["end rnd", "F/F* end", "ATE end/ATE*", "DGS F/F*", "DGS kB"]
    )
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        refine = (
            f"{r['refine_rounds']}/{r['refine_bytes'] / 1e3:.0f}" if r.get("refine_used") else "–"
        )
        rule = (
            "–"
            if r.get("rule_round") is None
            else f"{r['rule_round']}, {r['rule_F_over_F_star']:.4f}"
        )
        cells = [
            r["case"],
            _fmt(r["F_init_over_F_chordal"]),
            f"{r['init_rounds']}/{r['init_bytes'] / 1e3:.0f}",
            refine,
        ]
        cells += [_fmt(r.get(f"F_over_F_star_at_{c}")) for c in cps]
        cells += [
            _at(r, "1pct"),
            _at(r, "01pct"),
            "–" if r["stop_round"] is None else f"{r['stop_round']} ({r.get('stopped_by')})",
            _fmt(r.get("stop_F_over_F_star")),
            rule,
            str(r.get("ended_round", "–")),
            _fmt(r["dran_F_end_over_F_star"], ".6f"),
            _fmt(r["dran_ATE_end_m"] / max(r["ATE_star_m"], 1e-12), ".3f"),
            _fmt(r.get("dgs_F_end_over_F_star")),
            _fmt(None if r.get("dgs_bytes") is None else r["dgs_bytes"] / 1e3, ".0f"),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(rows: list[dict], out_dir) -> list:
    """F/F* against DRAN rounds and against bytes, one line per case, one figure per family
    (PNG, matplotlib Agg); returns the written paths."""
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for fam in sorted({r["family"] for r in rows}):
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
        for r in rows:
            if r["family"] != fam:
                continue
            c = np.asarray(r["curve"], float)
            label = r["case"].removeprefix(fam + "-")
            axes[0].plot(c[:, 0], c[:, 2] - 1.0, label=label)
            axes[1].plot(c[:, 1] / 1e6, c[:, 2] - 1.0, label=label)
        labels = ("DRAN rounds after the initialisation", "MB sent (init included)")
        for ax, xl in zip(axes, labels):
            ax.set_yscale("log")
            ax.axhline(0.01, color="k", lw=0.6, ls="--")
            ax.axhline(0.001, color="k", lw=0.6, ls=":")
            ax.set_xlabel(xl)
            ax.set_ylabel("F/F* − 1")
            ax.grid(True, alpha=0.3)
        axes[0].legend(fontsize=6)
        fig.suptitle(fam)
        fig.tight_layout()
        path = out_dir / f"suite_{fam}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


def case_from_dict(d: dict) -> Case:
    return Case(**{f.name: d[f.name] for f in dataclasses.fields(Case) if f.name in d})
