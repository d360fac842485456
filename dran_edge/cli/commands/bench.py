"""``dran-edge bench``: the paper's experiments (Table 1 on g2o graphs; the object simulation).

Size: over ~500 lines because the parsers and drivers of the four ``bench`` subcommands, one
flag per line; a subcommand per module is the next split if it grows.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from typing import Any

from dran_edge.cli.progress import ProgressBar, note
from dran_edge.config import Residual

# One BLAS thread: the local steps are small dense products, and OpenBLAS's thread pool on a
# busy 2-core machine made them ~75x slower (measured, docs/notes/benchmarks-history.md).
# Must precede numpy.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

HELP = "run the paper's experiments: Table 1 on a g2o graph, or the object simulation sweeps"


def build_parser(prog: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description=(
            "Benchmarks of the DRAN agent (docs/dran.md, docs/benchmarks.md).\n\n"
            "  g2o DATASET.g2o   split the graph into --robots contiguous segments (Table 1), run the\n"
            "                    distributed chordal init, the exact distributed LM refinement where a\n"
            "                    step is cheap (--refine auto, the default) and DRAN (or the DGS\n"
            "                    baseline) over encoded datagrams; report objective (SE-Sync\n"
            "                    convention), F/F*, rounds, bytes.\n"
            "  objects           the Ego-like simulation (21 robots, 60 objects): SR_ATE, SR_cost, CE,\n"
            "                    Bias, F/F*, ATE/ATE* against the centralized LM, per rho and per noise\n"
            "                    level (--refine as for g2o; --refine off: DRAN's rounds alone).\n\n"
            "examples:\n"
            "  dran-edge bench g2o CSAIL.g2o --robots 5 --json\n"
            "  dran-edge bench objects --rho 0.3 --outliers 0.2 --json     # 20 % wrong ids / loops\n"
            "  dran-edge bench objects --rho 0.3 --robust --json           # same settings, no outliers\n"
            "  dran-edge bench suite --quick --out /tmp/suite              # generated graph families"
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="what", required=True, metavar="{g2o,objects,suite}")
    _add_g2o_parser(sub)
    _add_objects_parser(sub)
    _add_suite_parser(sub)
    return parser


def _add_g2o_parser(sub: Any) -> None:
    g = sub.add_parser("g2o", help="Table 1 protocol on one g2o file")
    g.add_argument("dataset", help="a g2o file (VERTEX_SE2/SE3:QUAT, EDGE_SE2/SE3:QUAT)")
    g.add_argument("--robots", type=int, default=5, help="number of robots (default 5)")
    g.add_argument(
        "--method",
        choices=("dran", "dgs"),
        default="dran",
        help="dran (default) or the DGS baseline of Choudhary et al. 2017: the same "
        "initialisation, then one Gauss-Newton step by distributed Gauss-Seidel",
    )
    g.add_argument(
        "--max-rounds",
        type=int,
        default=None,
        help="cap on DRAN rounds (default: K_max=500 local steps per robot, i.e. 500 x "
        "the number of colours in the colour schedule)",
    )
    g.add_argument(
        "--plain",
        action="store_true",
        help="Alg. 1 as printed: every robot every round, no over-relaxation, absolute "
        "values on the wire (default: colour schedule, SOR, delta entries; "
        "docs/dran.md)",
    )
    g.add_argument(
        "--stop",
        choices=("tail", "steps"),
        default="tail",
        help="stopping rule: tail (default; stops only when every robot's predicted "
        "remaining decrease is below 1e-3 of its cost and its neighbours agree, "
        "docs/notes/stopping-rule.md) or steps (the paper's step-norm test with "
        "the relative-decrease stop: what tools/bench/bench_table1.py runs)",
    )
    g.add_argument(
        "--residual",
        choices=sorted(m.value for m in Residual),
        default="chordal",
        help="residual of the local problems (chordal optimises the reported F exactly)",
    )
    g.add_argument(
        "--no-reference",
        action="store_true",
        help="skip the centralized solve (F*): F/F* is then reported as n/a "
        "(default: solve the graph centrally, chordal init + exact LM, as "
        "'dran-edge solve' does, and report F/F* beside the objective)",
    )
    g.add_argument(
        "--init",
        choices=("auto", "always", "never"),
        default="auto",
        help="distributed init per stage: solve it exactly by substructuring where "
        "that costs at most 20 block iterations' values (auto, default), always, "
        "or block Gauss-Seidel iterations only (never; docs/dran.md)",
    )
    _add_refine_options(g)
    g.add_argument(
        "--loss",
        type=float,
        default=0.0,
        help="datagram loss probability on every link (default 0); the substructured init "
        "and the refinement then go through the selective-repeat ARQ (docs/dran.md, "
        "'Over lossy links')",
    )
    g.add_argument(
        "--curve",
        action="store_true",
        help="dran: add 'curve', [rounds after the init, bytes sent so far (init included), "
        "F] at the init's end, at each accepted refinement point and after every DRAN "
        "round (F of the merged estimate each round: slower), then the polish's points",
    )
    g.add_argument(
        "--polish",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="dran: after DRAN's rounds stop, exact distributed Newton steps from its estimate "
        "(near the optimum: the exact Hessian from the first step until a trial is rejected, "
        "Marquardt mu from 1e-10, "
        "the iterative interface solve unless --refine-interface dense; --refine-tol, "
        "--refine-steps and --refine-pcg-eta apply; docs/dran.md). Default: on, unless "
        "--refine off or --plain, and skipped when the refinement before DRAN converged",
    )
    g.add_argument("-o", "--out", metavar="MERGED.g2o", help="write the merged estimate as g2o")
    g.add_argument("--json", action="store_true", help="print one JSON object")


def _add_objects_parser(sub: Any) -> None:
    # Long but flat: one add_argument per flag (the parser is the command's documentation).
    o = sub.add_parser(
        "objects",
        help="object simulation sweeps",
        description="The paper's object simulation (Sec. 6.2): robots on trajectories "
        "through random objects, an observation whenever an object is "
        "within 5 m; DRAN for --rounds rounds over the in-process bus, "
        "scored against the centralized LM (docs/benchmarks.md).",
    )
    o.add_argument(
        "--rho",
        type=float,
        nargs="+",
        default=[round(0.1 * k, 1) for k in range(1, 11)],
        help="communication edge probabilities (default 0.1 … 1.0)",
    )
    o.add_argument(
        "--noise",
        type=float,
        nargs="+",
        default=[1.0],
        help="noise multipliers of (1 deg, 0.005 m) (default 1)",
    )
    o.add_argument("--loss", type=float, default=0.0, help="datagram loss probability")
    o.add_argument(
        "--outliers",
        type=float,
        default=0.0,
        help="fraction of wrong object ids / loops; also turns on the robust settings "
        "(Cauchy kernel of scale 0.05 on loops and 1.0 on object observations; "
        "--min-views 2 with the spatial exclusion). Everything else (trajectories, noise) is "
        "the same --seed's outlier-free scenario, so the two runs compare",
    )
    o.add_argument(
        "--robust",
        action="store_true",
        help="the robust settings of --outliers (Cauchy kernels; --min-views 2) "
        "without outliers: the outlier-free run with the same agent settings",
    )
    o.add_argument(
        "--outlier-kinds",
        choices=("both", "ids", "loops"),
        default="both",
        help="what --outliers injects: wrong object ids, false loops, or both",
    )
    o.add_argument(
        "--outlier-ids",
        choices=("add", "relabel"),
        default="add",
        help="how a wrong object id enters: 'add' reports an observation a second time "
        "under a wrong id (the right one stays: the run has every observation of "
        "the outlier-free run); 'relabel' replaces its id (a misread tag; the run "
        "also loses those observations). Default add",
    )
    o.add_argument(
        "--min-views",
        type=int,
        default=None,
        help="AgentConfig.object_min_views: own observations that must agree before an "
        "object observation is used unless a neighbour's copy corroborates it, "
        "or no view of another object lies within 0.5 m of it "
        "(default: 2 with --outliers, which rejects lone wrong tag ids; else 1)",
    )
    o.add_argument(
        "--beta",
        type=float,
        default=None,
        help="consensus penalty β (default: the paper's 1.0; "
        "docs/notes/benchmarks-history.md measures smaller ones on this "
        "unit-information simulation)",
    )
    o.add_argument("--eta", type=float, default=None, help="dual step η (default: the paper's 0.1)")
    o.add_argument(
        "--dual-momentum",
        type=float,
        default=None,
        help="heavy-ball momentum θ on the dual update (AgentConfig.dual_momentum; "
        "default 0: off; docs/notes/object-simulation.md measures it)",
    )
    o.add_argument(
        "--rounds",
        type=int,
        default=150,
        help="DRAN rounds per run (default 150; a run ends earlier when every robot "
        "meets the stopping rule)",
    )
    o.add_argument(
        "--history-every",
        type=int,
        default=0,
        metavar="N",
        help="also report the metrics every N rounds (JSON key 'history'; the ATE "
        "after 150 rounds is still a transient, docs/notes/benchmarks-history.md)",
    )
    o.add_argument("--robots", type=int, default=21, help="robots (default 21, as the paper)")
    o.add_argument("--objects", type=int, default=60, help="objects (default 60, as the paper)")
    o.add_argument(
        "--seed",
        type=int,
        default=0,
        help="scenario seed; the communication graph uses seed + 1 (default 0)",
    )
    _add_refine_options(o)
    o.add_argument("--json", action="store_true", help="print one JSON object per run")
    o.add_argument("--plot", metavar="DIR", help="write a PNG per sweep into DIR")


def _add_suite_parser(sub: Any) -> None:
    from dran_edge.experiments.suite import CHECKPOINTS, FAMILIES

    s = sub.add_parser(
        "suite",
        help="generalisation suite: generated graph families, DRAN vs DGS vs centralized",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Generate pose-graph families DRAN was not tuned on (long 2D/3D odometry "
        "chains with 1-3 % loops, dense grid worlds, 0.1 rad rotation noise, "
        "anisotropic information; 3-20 robots, contiguous and interleaved splits), "
        "run the distributed init + DRAN (Table 1 setup), DGS and the centralized "
        "solver on each, and report per graph F/F* at rounds "
        + "/".join(map(str, CHECKPOINTS))
        + ", where the stopping rule fired, "
        "bytes, ATE against ground truth, F_init/F_chordal (docs/benchmarks.md).\n\n"
        "families: " + ", ".join(FAMILIES) + "\n\n"
        "examples:\n"
        "  dran-edge bench suite --quick --out /tmp/suite\n"
        "  dran-edge bench suite --families car2d city2d --seeds 1 2 --rounds 500 "
        "--out runs/s",
    )
    s.add_argument(
        "--quick", action="store_true", help="two small graphs, 200 rounds (a smoke run, < 60 s)"
    )
    s.add_argument(
        "--families",
        nargs="+",
        choices=sorted(FAMILIES),
        metavar="FAMILY",
        help="only these families (default: the whole suite)",
    )
    s.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3], help="seeds (default 1 2 3)")
    s.add_argument(
        "--poses",
        type=int,
        default=None,
        help="poses per graph (default: the suite's own cases, 2000-4000 by seed for "
        "chains, 2000 grids; --families/--robots/--split then filter them)",
    )
    s.add_argument(
        "--robots",
        type=int,
        nargs="+",
        default=None,
        help="robot counts (default: 5, plus the 3/10/20-robot and interleaved cases)",
    )
    s.add_argument(
        "--split",
        choices=("contiguous", "interleaved"),
        nargs="+",
        default=None,
        help="splits (default: contiguous, plus the interleaved cases)",
    )
    s.add_argument(
        "--rounds",
        type=int,
        default=None,
        help="DRAN rounds per graph (default 1000; 200 with --quick); DRAN keeps "
        "running after its stopping rule fires so both are reported",
    )
    s.add_argument(
        "--init",
        choices=("auto", "always", "never"),
        default="auto",
        help="InitParams.direct: substructured exact init where it is cheap (auto), "
        "always, or the block Gauss-Seidel iterations only (never)",
    )
    _add_refine_options(s)
    s.add_argument(
        "--stop",
        choices=("tail", "steps"),
        default="tail",
        help="the agents' stopping rule: tail (default, as bench g2o) or steps (Table 1's)",
    )
    s.add_argument(
        "--until-decided",
        action="store_true",
        help="end a graph's DRAN run once F <= 1.001 F* has been reached and the run's stop "
        "is known (the refinement converged or the stopping rule fired); values at the end "
        "are then at that round (ended_round), not at --rounds",
    )
    s.add_argument("--no-dgs", action="store_true", help="skip the DGS baseline")
    s.add_argument(
        "-o",
        "--out",
        metavar="DIR",
        default=None,
        help="write suite.json, suite.md and the plots (suite_FAMILY.png) here",
    )
    s.add_argument("--json", action="store_true", help="print one JSON object per graph")


def _add_refine_options(p) -> None:
    p.add_argument(
        "--refine",
        choices=("off", "auto", "always"),
        default=None,
        help="exact distributed Levenberg-Marquardt steps by substructuring after the "
        "init (dran_edge/dran/exact_gn.py, docs/dran.md): auto (default) where one step "
        "costs at most 100 rounds' separator values and the run is least squares, always, "
        "or off (DRAN's rounds alone, as in the paper; the default with bench g2o --plain)",
    )
    p.add_argument(
        "--refine-steps",
        type=int,
        default=200,
        metavar="K",
        help="at most K refinement trials after the start point (default 200, a safety "
        "cap: the refinement stops on --refine-tol)",
    )
    p.add_argument(
        "--refine-tol",
        type=float,
        default=1e-5,
        help="stop refining after an accepted step lowering F by less than this "
        "fraction (default 1e-5)",
    )
    p.add_argument(
        "--refine-hessian",
        choices=("gauss_newton", "exact"),
        default="gauss_newton",
        help="the refinement's model: Gauss-Newton (default) or the exact Hessian (damped "
        "Newton once a step gains < 1 %%, Gauss-Newton where not positive definite)",
    )
    p.add_argument(
        "--refine-frozen",
        action="store_true",
        help="frozen-Hessian (chord) refinement steps: after one full gather of the condensed "
        "systems only the condensed gradients travel, solved with the kept factors, until a "
        "step is rejected or slows down (RefineParams.frozen)",
    )
    p.add_argument(
        "--refine-interface",
        choices=("dense", "pcg"),
        default=None,
        help="how the refinement solves for the robots' boundary poses: dense (default: every "
        "robot's condensed system gathered at the root) or pcg (conjugate gradients over the "
        "robot tree with a two-level Neumann-Neumann preconditioner: only boundary vectors "
        "travel; dran_edge/dran/interface_pcg.py)",
    )
    p.add_argument(
        "--refine-pcg-eta",
        type=float,
        default=0.1,
        metavar="ETA",
        help="--refine-interface pcg: relative residual at which CG stops (default 0.1)",
    )


def _polish_params(args):
    """``bench g2o --polish`` (on by default, unless --refine off or --plain): Newton steps
    from DRAN's estimate (near the optimum): the exact Hessian from the first step until a trial
    is rejected (then Gauss–Newton first, as the refinement), Marquardt μ from 1e-10, the
    iterative interface solve unless --refine-interface dense is given."""
    from dran_edge.dran.exact_gn import RefineParams
    from dran_edge.errors import InputError

    if args.polish is False or (args.polish is None and (args.refine == "off" or args.plain)):
        return None
    if not 0.0 < args.refine_pcg_eta < 1.0:
        raise InputError(f"--refine-pcg-eta must be in (0, 1), got {args.refine_pcg_eta}")
    return RefineParams(
        mode="always",
        max_steps=args.refine_steps,
        rel_tol=args.refine_tol,
        hessian="exact",
        newton_first=True,
        mu_init=1e-10,
        interface=args.refine_interface or "pcg",
        pcg_eta=args.refine_pcg_eta,
    )


def _refine_params(args):
    from dran_edge.dran.exact_gn import RefineParams
    from dran_edge.errors import InputError

    if args.refine == "off":
        return None
    if args.refine_steps < 0:
        raise InputError(f"--refine-steps must be at least 0, got {args.refine_steps}")
    if args.refine_frozen and args.refine_interface == "pcg":
        raise InputError("--refine-frozen needs --refine-interface dense")
    if not 0.0 < args.refine_pcg_eta < 1.0:
        raise InputError(f"--refine-pcg-eta must be in (0, 1), got {args.refine_pcg_eta}")
    return RefineParams(
        mode=args.refine,
        max_steps=args.refine_steps,
        rel_tol=args.refine_tol,
        hessian=args.refine_hessian,
        frozen=args.refine_frozen,
        interface=args.refine_interface or "dense",
        pcg_eta=args.refine_pcg_eta,
    )


def run_g2o(args) -> int:
    from pathlib import Path

    from dran_edge.experiments.dgs import run_g2o_dgs
    from dran_edge.comms.bus import BusParams
    from dran_edge.dran.dist_init import InitParams
    from dran_edge.errors import InputError
    from dran_edge.formats.g2o import read_g2o, write_g2o
    from dran_edge.experiments.fleet import TABLE1_DELTA_EVERY, run_g2o_dran, table1_setup

    g = read_g2o(args.dataset)
    init_params = InitParams(gauss_seidel=True, direct=args.init)
    if args.robots < 1 or args.robots > g.num_vertices:
        raise InputError(f"--robots must be in 1..{g.num_vertices}, got {args.robots}")
    if args.method == "dran":
        cfg, run_kw = table1_setup(g.dim, args.residual, plain=args.plain, stop=args.stop)

        bar = ProgressBar()
        rec, part = _curve_recorder(g, args.robots) if args.curve else (None, None)

        def cb(k, fleet):  # progress on stderr; stdout stays the report
            if k == 1:
                note(
                    f"initialisation done: {fleet.round - 1} rounds, "
                    f"{fleet.traffic.bytes_total} bytes so far"
                )
            bar("DRAN rounds", k, args.max_rounds or k)
            if rec is not None:
                rec(k, fleet)

        res = run_g2o_dran(
            g,
            args.robots,
            cfg,
            max_rounds=args.max_rounds,
            callback=cb,
            init_params=init_params,
            refine=_refine_params(args),
            polish=_polish_params(args),
            links=BusParams(loss_probability=args.loss) if args.loss > 0 else None,
            partition=part,
            **run_kw,
        )
        if rec is not None:
            from dran_edge.experiments.suite import curve_after_init

            if not rec.curve:  # no DRAN round (the refinement ended the run)
                rec.curve.append((0, None, None))
            curve, _ = curve_after_init(rec, res, res["rounds_total"], args.refine != "off")
            if res.get("polish_used"):  # the polish's accepted points and its end, after DRAN
                b0, k0 = res["bytes_total"] - res["polish_bytes"], curve[-1][0]
                curve += [(k0 + k, b0 + b, f) for k, b, f in res["polish_curve"][1:]]
                curve.append(
                    (k0 + res["polish_rounds"], res["bytes_total"], res["objective_final"])
                )
            res["curve"] = [list(p) for p in curve]
    else:
        res = run_g2o_dgs(
            g,
            args.robots,
            delta_every=0 if args.plain else TABLE1_DELTA_EVERY,
            init_params=init_params,
            links=BusParams(loss_probability=args.loss) if args.loss > 0 else None,
        )
    if args.out:
        write_g2o(args.out, g, res["poses"])
    report = {
        "dataset": Path(args.dataset).stem,
        "method": args.method,
        "robots": args.robots,
        "init": args.init,
    }
    if args.refine != "off":
        report["refine"] = args.refine
        if args.refine_hessian != "gauss_newton":
            report["refine_hessian"] = args.refine_hessian
        if args.refine_frozen:
            report["refine_frozen"] = True
        if args.refine_interface == "pcg":
            report["refine_interface"] = args.refine_interface
            report["refine_pcg_eta"] = args.refine_pcg_eta
    if args.method == "dran" and _polish_params(args) is not None:
        report["polish"] = True
    if args.loss > 0:
        report["loss"] = args.loss
    report.update(
        {k: v for k, v in res.items() if k not in ("poses", "poses_init", "poses_refined")}
    )
    report.update(_reference(g, res, skip=args.no_reference))
    if args.json:
        print(json.dumps(report))
    else:
        for k, v in report.items():
            print(f"{k:>24}: {'n/a' if v is None else v}")
    return 0


def _curve_recorder(g, robots: int):
    """``bench g2o --curve``: a ``suite.CurveRecorder`` of F (SE-Sync) per DRAN round on the
    contiguous split (the one ``run_g2o_dran`` makes by default), and that split."""
    from dran_edge.dran.partition import partition_contiguous
    from dran_edge.experiments.suite import CurveRecorder
    from dran_edge.solver.objective import sesync_objective, sesync_weights

    kappa, tau = sesync_weights(g.dim, g.information)
    part = partition_contiguous(g.edges, g.num_vertices, robots)
    shape = (g.num_vertices, g.dim + 1, g.dim + 1)

    def F(T):
        return sesync_objective(T, g.edges, g.measurements, kappa, tau)

    return CurveRecorder(part, shape, F), part


def _reference(g, res: dict, skip: bool) -> dict:
    """F* by the centralized solver and F/F* of the run's initial and final estimates (None:
    not computed, printed as n/a)."""
    from dran_edge.evaluation import metrics
    from dran_edge.solver.centralized import solve_g2o

    if skip:
        return {"F_star": None, "F_over_Fstar": None, "F_init_over_Fstar": None}
    note("centralized solve for F* (--no-reference skips it)")
    F_star = solve_g2o(g).objective_final
    return {
        "F_star": F_star,
        "F_over_Fstar": metrics.cost_ratio(res["objective_final"], F_star),
        "F_init_over_Fstar": metrics.cost_ratio(res["objective_init"], F_star),
    }


def run_objects_cmd(args) -> int:
    # Long: the objects command's driver (options -> runs -> table/JSON), flat on purpose.
    from dran_edge.comms.bus import BusParams, random_connected_graph
    from dran_edge.errors import ConfigError, InputError
    from dran_edge.experiments.objects import SimParams, bench_config, make_scenario, run_objects

    if args.rounds < 1:
        raise InputError(f"--rounds must be at least 1, got {args.rounds}")
    if args.history_every < 0:
        raise InputError(
            f"--history-every must be 0 (off) or a round count, got {args.history_every}"
        )
    robust = args.outliers > 0 or args.robust
    cfg = bench_config(robust, args.min_views)
    for name in ("beta", "eta", "dual_momentum"):
        if getattr(args, name) is not None:
            try:  # AgentConfig's own range check, reported with the flag's name
                cfg = dataclasses.replace(cfg, **{name: getattr(args, name)})
            except ConfigError as exc:
                raise InputError(f"--{name.replace('_', '-')}: {exc}") from None
    rows = []
    bar = ProgressBar()
    for noise in args.noise:
        base = SimParams(
            num_robots=args.robots,
            num_objects=args.objects,
            seed=args.seed,
            outlier_ratio=args.outliers,
            outlier_kinds=args.outlier_kinds,
            outlier_ids=args.outlier_ids,
        )
        params = dataclasses.replace(
            base, sigma_rot_rad=base.sigma_rot_rad * noise, sigma_trans_m=base.sigma_trans_m * noise
        )
        sc = make_scenario(params)
        for rho in args.rho:
            graph = random_connected_graph(range(args.robots), rho, seed=args.seed + 1)
            label = f"rho={rho:g} noise={noise:g}"

            def progress(stage, done, total, label=label):
                bar(f"{label} {stage}", done, total)

            out = run_objects(
                sc,
                cfg,
                graph,
                BusParams(loss_probability=args.loss),
                max_rounds=args.rounds,
                seed=args.seed,
                history_every=args.history_every,
                progress=progress,
                refine=_refine_params(args),
            )
            row = {
                "rho": rho,
                "noise": noise,
                "loss": args.loss,
                "outliers": args.outliers,
                "outlier_ids": args.outlier_ids if args.outliers > 0 else None,
                "robust": robust,
                "min_views": cfg.object_min_views,
                "beta": cfg.beta,
                "eta": cfg.eta,
            }
            if args.refine != "off":
                row["refine"] = args.refine
            if cfg.dual_momentum:
                row["dual_momentum"] = cfg.dual_momentum
            row.update({k: v for k, v in out.items() if k != "history" or args.history_every})
            rows.append(row)
            if args.json:
                print(json.dumps(row), flush=True)
            else:
                stop = (
                    f" (stopped: {row['stopped_by']})" if row.get("stopped_by") else " (round cap)"
                )
                print(
                    f"rho={rho:.1f} noise={noise:g}: SR_cost={row['SR_cost']:.2f}% "
                    f"F/F*={row['F_over_Fstar']:.4f} SR_ATE={row['SR_ATE']:.2f}% "
                    f"ATE/ATE*={row['ATE_over_ATEstar']:.3f} CE={row['CE']:.3g} "
                    f"Bias={row['Bias']:.3g} ATE={row['ATE']:.4f} ATE*={row['ATE_star']:.4f} "
                    f"bytes={row['bytes']} rounds={row['rounds']}{stop}"
                    + (
                        f" refine: {row['refine_reason']}, {row['refine_steps']} steps, "
                        f"{row['refine_rounds']} rounds, {row['refine_bytes']} bytes"
                        if args.refine != "off"
                        else ""
                    )
                    + (f" consensus_conflicts={row['consensus_conflicts']}" if robust else ""),
                    flush=True,
                )
                for h in row.get("history", ()):
                    print(
                        f"  round {h['round']}: SR_cost={h['SR_cost']:.2f}% "
                        f"F/F*={h['F_over_Fstar']:.4f} ATE={h['ATE']:.4f} "
                        f"ATE/ATE*={h['ATE_over_ATEstar']:.3f} CE={h['CE']:.3g} "
                        f"bytes={h['bytes']}",
                        flush=True,
                    )
    if args.plot:
        _plot(rows, args.plot)
    return 0


def _plot(rows: list, out_dir: str) -> None:
    from pathlib import Path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    Path(out_dir).mkdir(parents=True, exist_ok=True)
    for key, other in (("rho", "noise"), ("noise", "rho")):
        xs = sorted({r[key] for r in rows})
        if len(xs) < 2:
            continue
        fig, ax = plt.subplots(figsize=(5, 3.5))
        for ov in sorted({r[other] for r in rows}):
            sel = [r for r in rows if r[other] == ov]
            sel.sort(key=lambda r: r[key])
            ax.plot(
                [r[key] for r in sel],
                [r["SR_cost"] for r in sel],
                "o-",
                label=f"SR_cost {other}={ov:g}",
            )
            ax.plot(
                [r[key] for r in sel],
                [r["SR_ATE"] for r in sel],
                "s--",
                label=f"SR_ATE {other}={ov:g}",
            )
        ax.set_xlabel(key)
        ax.set_ylabel("success ratio (%)")
        ax.legend(fontsize=7)
        ax.grid(True, alpha=0.3)
        fig.tight_layout()
        fig.savefig(Path(out_dir) / f"objects_sweep_{key}.png", dpi=120)
        plt.close(fig)


def run_suite_cmd(args) -> int:
    from pathlib import Path

    from dran_edge.errors import InputError
    from dran_edge.experiments import suite

    rounds = args.rounds or (200 if args.quick else 1000)
    if rounds < 1:
        raise InputError(f"--rounds must be at least 1, got {rounds}")
    cases = suite.select_cases(
        args.quick, args.seeds, args.families, args.robots, args.split, args.poses
    )
    if not cases:
        raise InputError("no suite case matches --families/--robots/--split (add --poses)")
    rows = []
    for k, case in enumerate(cases):
        note(f"[{k + 1}/{len(cases)}] {case.name}")
        row = suite.run_case(
            case,
            rounds=rounds,
            init_direct=args.init,
            dgs=not args.no_dgs,
            refine=_refine_params(args),
            stop_rule=args.stop,
            until_decided=args.until_decided,
        )
        rows.append(row)
        if args.json:
            print(json.dumps({k: v for k, v in row.items() if k != "curve"}), flush=True)
        if args.out:  # after every graph: a long run leaves its partial results
            Path(args.out).mkdir(parents=True, exist_ok=True)
            (Path(args.out) / "suite.json").write_text(
                json.dumps(
                    {"rounds": rounds, "init": args.init, "refine": args.refine, "rows": rows},
                    indent=1,
                )
            )
    table = suite.markdown_table(rows)
    worst = suite.worst_by_family(rows)
    if not args.json:
        print(table)
        print()
        for fam, w in worst.items():
            print(
                f"worst {fam}: "
                + ", ".join(
                    f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in w.items()
                )
            )
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "suite.json").write_text(
            json.dumps(
                {
                    "rounds": rounds,
                    "init": args.init,
                    "refine": args.refine,
                    "rows": rows,
                    "worst": worst,
                },
                indent=1,
            )
        )
        (out / "suite.md").write_text(table + "\n")
        suite.plot(rows, out)
        note(f"wrote {out}/suite.json, suite.md and the plots")
    return 0


def run(args) -> int:
    if args.refine is None:  # auto unless the paper's algorithm as printed was asked for
        args.refine = "off" if getattr(args, "plain", False) else "auto"
    if args.what == "suite":
        return run_suite_cmd(args)
    return run_g2o(args) if args.what == "g2o" else run_objects_cmd(args)
