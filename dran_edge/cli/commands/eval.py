"""``dran-edge eval``: score a run (or one trajectory) against OptiTrack motion capture."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dran_edge.errors import InputError

HELP = "score a run or a trajectory against OptiTrack mocap (ATE, SR, CE, Bias, plots)"

_USAGE = """\
  %(prog)s RUN_DIR [--mocap FILE.csv] [--align paper|se3|sim3|yaw|none] [options]
  %(prog)s traj EST.tum --mocap FILE.csv --body NAME [--align se3|sim3|yaw|paper|none] [--json]"""

_DESCRIPTION = """\
Two forms:

  RUN_DIR   score a replayed run (docs/run-format.md): reads mission.yaml, the Motive CSV
            and out/ (trajectory.tum, trajectory_init.tum, objects.csv, merged.g2o,
            rounds.csv, report.json); writes RUN_DIR/eval/report.json, summary.md and PNG
            plots. Default alignment: paper (mocap gives only each robot's initial frame).

  traj EST  score one TUM trajectory (stamp_s x y z qx qy qz qw) against one Motive rigid
            body; prints ate_rmse_m, ate_max_m, matched_poses, time_offset_s and more.
            Default alignment: se3 (like evo_ape -a).

Clock: t_mocap = t_est + offset. Without --time-offset the offset comes from mission.yaml
(mocap.start_ns) or is estimated by correlating angular speeds. Metrics are defined in
docs/eval.md."""


def build_parser(prog: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, usage=_USAGE, description=_DESCRIPTION,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("target", metavar="RUN_DIR|traj", help="a run directory, or 'traj'")
    p.add_argument("est", nargs="?", metavar="EST.tum", help="(traj) the estimated trajectory")
    p.add_argument("--mocap", metavar="FILE.csv", help="Motive CSV export (default: the run's)")
    p.add_argument("--body", metavar="NAME", help="(traj) Motive rigid body to compare with")
    p.add_argument("--align", choices=("paper", "se3", "sim3", "yaw", "none"),
                   help="alignment (default: paper for a run, se3 for traj)")
    p.add_argument("--time-offset", type=float, metavar="S",
                   help="t_mocap - t_est in seconds (default: mission.yaml or estimated)")
    p.add_argument("--T-body-marker", type=float, nargs=7, default=None,
                   metavar=("X", "Y", "Z", "QX", "QY", "QZ", "QW"),
                   help="(traj) the rigid body's pivot in the estimate's body frame "
                        "(default identity; for a run it comes from mission.yaml)")
    p.add_argument("--up-axis", choices=("y", "z"), default=None,
                   help="(traj) vertical axis of the Motive export (default y, Motive's)")
    p.add_argument("--max-gap", type=float, default=0.1, metavar="S",
                   help="longest mocap occlusion interpolated across (default 0.1 s)")
    p.add_argument("--rpe-delta", type=float, default=1.0, metavar="S",
                   help="pose spacing of the relative pose error (default 1 s)")
    p.add_argument("-o", "--out", metavar="DIR", help="(run) where to write (default RUN_DIR/eval)")
    p.add_argument("--no-plots", action="store_true", help="(run) skip the PNG plots")
    p.add_argument("--no-centralized", action="store_true",
                   help="(run) do not solve merged.g2o centrally (no SR_ATE / SR_cost)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    return p


def _run_traj(args: argparse.Namespace) -> int:
    from dran_edge.evaluation import score as evaluate
    from dran_edge.formats import motive, tum

    if not args.est:
        raise InputError("eval traj: expected the estimated trajectory EST.tum")
    if not args.mocap or not args.body:
        raise InputError("eval traj: expected --mocap FILE.csv and --body NAME")
    stamps, T = tum.read_tum(args.est)
    take = motive.read_motive_csv(args.mocap, up_axis=args.up_axis or "y")
    T_bm = None
    if args.T_body_marker is not None:
        import numpy as np

        from dran_edge import geometry as geo

        v = np.array(args.T_body_marker)
        if abs(np.linalg.norm(v[3:]) - 1.0) > 1e-3:
            raise InputError(f"--T-body-marker: expected a unit quaternion, got norm "
                             f"{np.linalg.norm(v[3:]):.6f}")
        T_bm = geo.se3_from_xyz_quat_xyzw(v)
    res = evaluate.evaluate_trajectory(
        stamps, T, take, args.body, T_body_marker=T_bm, align_kind=args.align or "se3",
        time_offset_s=args.time_offset, max_gap_s=args.max_gap, rpe_delta_s=args.rpe_delta)
    from dran_edge.evaluation.report import json_safe

    res = json_safe(res)
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    keys = ("ate_rmse_m", "ate_max_m", "ate_mean_m", "ate_median_m", "ate_rot_rmse_deg",
            "ate_log_rmse", "matched_poses", "estimated_poses", "time_offset_s",
            "time_offset_source")
    for k in keys:
        v = res[k]
        print(f"{k:<20}{v:.6f}" if isinstance(v, float) else f"{k:<20}{v}")
    print(f"{'align':<20}{res['align']['kind']} (scale {res['align']['scale']:.6f})")
    rpe = res["rpe"]
    print(f"{'rpe_trans_rmse_m':<20}{rpe['trans_rmse_m']:.6f}  (delta {rpe['delta_s']} s, "
          f"{rpe['pairs']} pairs)")
    return 0


def _run_dir(args: argparse.Namespace) -> int:
    from dran_edge.evaluation import score as evaluate

    if args.est:
        raise InputError(f"eval RUN_DIR takes no second argument, got {args.est!r} (did you "
                         "mean 'eval traj EST'?)")
    opt = evaluate.EvalOptions(
        align=args.align or "paper", mocap_path=args.mocap, time_offset_s=args.time_offset,
        max_gap_s=args.max_gap, rpe_delta_s=args.rpe_delta, centralized=not args.no_centralized,
        plots=not args.no_plots)
    print(f"evaluating {args.target} ...", file=sys.stderr)
    report = evaluate.evaluate_run(args.target, opt)
    out = Path(args.out) if args.out else Path(args.target) / "eval"
    written = evaluate.write_report(report, out, plots=opt.plots)
    if args.json:
        print(json.dumps({k: v for k, v in report.items() if k != "_"}, indent=2))
    else:
        print(evaluate.summary_markdown({k: v for k, v in report.items() if k != "_"}))
        print("wrote " + ", ".join(str(p) for p in written))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.target == "traj":
        return _run_traj(args)
    return _run_dir(args)
