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
  %(prog)s traj EST (--mocap FILE.csv --body NAME | --ref REF) [--align se3|sim3|yaw|paper|none]
         [--format auto|tum|euroc|kitti] [--quat-order xyzw|wxyz] [--plot F.png]
         [--save-results F.zip] [--json]
  %(prog)s traj RUN_DIR/out/<robot>/<robot>.tum      (mocap, body, clock from mission.yaml)
  %(prog)s traj BAG --topic /odom --ref GT_BAG --ref-topic /vrpn_client_node/dingo1/pose"""

_DESCRIPTION = """\
Two forms:

  RUN_DIR   score a replayed run (docs/run-format.md): reads mission.yaml, the Motive CSV
            and out/ (<robot>/<robot>.tum, <robot>_init.tum, objects.csv, merged.g2o,
            rounds.csv, report.json); writes RUN_DIR/eval/report.json, summary.md and PNG
            plots. Default alignment: paper (mocap gives only each robot's initial frame).

  traj EST  score one trajectory against one Motive rigid body (--mocap, --body) or a
            reference trajectory file (--ref). EST and REF may be TUM, EuRoC/ASL CSV or
            KITTI poses, or a pose topic of a ROS 1/2 bag (--topic, --ref-topic)
            (docs/trajectory-formats.md); the format and quaternion order are
            detected from the layout or a header, else --format / --quat-order must say.
            A trajectory of a replayed run (RUN/out/<robot>/<robot>.tum) takes the mocap
            file, body, marker offset and clock from the run's mission.yaml. Prints
            ate_rmse_m, ate_max_m, matched_poses, time_offset_s (and how it was found) and
            more; --plot writes a PNG, --save-results an evo results zip (evo_res reads it).
            Default alignment: se3 (like evo_ape -a).

Clock: t_ref = t_est + offset. Without --time-offset: mission.yaml (mocap.start_ns); for a
reference file whose stamps overlap the estimate's, 0 (same clock, as evo assumes);
otherwise estimated by correlating angular speeds, then linear speeds (positions only or no
turning), then 0 if the clocks overlap. The output says which. Metrics: docs/eval.md."""


def build_parser(prog: str) -> argparse.ArgumentParser:
    # Long but flat: one add_argument per flag (the parser is the command's documentation).
    p = argparse.ArgumentParser(
        prog=prog,
        usage=_USAGE,
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("target", metavar="RUN_DIR|traj", help="a run directory, or 'traj'")
    p.add_argument("est", nargs="?", metavar="EST", help="(traj) the estimated trajectory")
    p.add_argument(
        "--ref",
        metavar="REF",
        help="(traj) reference trajectory file instead of --mocap (TUM, EuRoC/ASL CSV, KITTI)",
    )
    p.add_argument(
        "--format",
        default="auto",
        choices=("auto", "tum", "euroc", "kitti"),
        help="(traj) format of EST (default: detected)",
    )
    p.add_argument(
        "--ref-format",
        default="auto",
        choices=("auto", "tum", "euroc", "kitti"),
        help="(traj) format of REF (default: detected)",
    )
    p.add_argument(
        "--quat-order",
        choices=("xyzw", "wxyz"),
        help="(traj) quaternion order of EST when the format does not say",
    )
    p.add_argument(
        "--ref-quat-order",
        choices=("xyzw", "wxyz"),
        help="(traj) quaternion order of REF when the format does not say",
    )
    p.add_argument(
        "--topic",
        metavar="TOPIC",
        help="(traj) EST is a ROS 1/2 bag: read this pose topic (Odometry, "
        "PoseStamped, PoseWithCovarianceStamped)",
    )
    p.add_argument("--ref-topic", metavar="TOPIC", help="(traj) REF is a bag: read this pose topic")
    p.add_argument(
        "--kitti-rate-hz",
        type=float,
        default=10.0,
        help="(traj) pose rate of KITTI files, which have no stamps (default 10)",
    )
    p.add_argument("--plot", metavar="FILE.png", help="(traj) write a top view + error plot")
    p.add_argument(
        "--save-results",
        metavar="FILE.zip",
        help="(traj) write an evo results file (evo_res reads it)",
    )
    p.add_argument("--mocap", metavar="FILE.csv", help="Motive CSV export (default: the run's)")
    p.add_argument("--body", metavar="NAME", help="(traj) Motive rigid body to compare with")
    p.add_argument(
        "--align",
        choices=("paper", "se3", "sim3", "yaw", "none"),
        help="alignment (default: paper for a run, se3 for traj)",
    )
    p.add_argument(
        "--time-offset",
        type=float,
        metavar="S",
        help="t_mocap - t_est in seconds (default: mission.yaml or estimated)",
    )
    p.add_argument(
        "--T-body-marker",
        type=float,
        nargs=7,
        default=None,
        metavar=("X", "Y", "Z", "QX", "QY", "QZ", "QW"),
        help="(traj) the rigid body's pivot in the estimate's body frame "
        "(default identity; for a run it comes from mission.yaml)",
    )
    p.add_argument(
        "--up-axis",
        choices=("y", "z"),
        default=None,
        help="(traj) vertical axis of the Motive export (default y, Motive's)",
    )
    p.add_argument(
        "--max-gap",
        type=float,
        default=0.1,
        metavar="S",
        help="longest mocap occlusion interpolated across (default 0.1 s)",
    )
    p.add_argument(
        "--rpe-delta",
        type=float,
        default=1.0,
        metavar="S",
        help="pose spacing of the relative pose error (default 1 s)",
    )
    p.add_argument("-o", "--out", metavar="DIR", help="(run) where to write (default RUN_DIR/eval)")
    p.add_argument("--no-plots", action="store_true", help="(run) skip the PNG plots")
    p.add_argument(
        "--no-centralized",
        action="store_true",
        help="(run) do not solve merged.g2o centrally (no SR_ATE / SR_cost)",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    return p


def _run_of(est: Path):
    """(run, robot) when ``est`` is RUN/out/<robot>/<file> of a run directory, else None."""
    from dran_edge.formats import run_dir as rd

    robot_dir = est.resolve().parent
    root = robot_dir.parent.parent
    if robot_dir.parent.name != "out" or not (root / "mission.yaml").exists():
        return None
    mission = rd.read_mission(root / "mission.yaml")
    names = {r.name: r for r in mission.robots}
    if robot_dir.name not in names:
        return None
    return rd.Run(root, mission), names[robot_dir.name]


def _T_body_marker(args):
    import numpy as np

    from dran_edge import geometry as geo

    v = np.array(args.T_body_marker)
    if abs(np.linalg.norm(v[3:]) - 1.0) > 1e-3:
        raise InputError(
            f"--T-body-marker: expected a unit quaternion, got norm {np.linalg.norm(v[3:]):.6f}"
        )
    return geo.se3_from_xyz_quat_xyzw(v)


def _run_traj(args: argparse.Namespace) -> int:
    # Long: `eval traj`'s options -> readers -> alignment -> report, flat on purpose.
    from dran_edge.evaluation.traj_score import evaluate_trajectory
    from dran_edge.formats import motive
    from dran_edge.formats.trajectory import read_trajectory

    if not args.est:
        raise InputError("eval traj: expected the estimated trajectory EST")
    if args.topic:
        from dran_edge.formats.trajectory import read_bag_trajectory

        est = read_bag_trajectory(args.est, args.topic)
    else:
        est = read_trajectory(
            args.est, args.format, quat_order=args.quat_order, kitti_rate_hz=args.kitti_rate_hz
        )
    found = _run_of(Path(args.est))
    mocap, body, up = args.mocap, args.body, args.up_axis
    T_bm = _T_body_marker(args) if args.T_body_marker is not None else None
    offset, offset_src = args.time_offset, None
    if found is not None and not args.ref:
        run, robot = found
        mocap = mocap or (str(run.mocap_path) if run.mocap_path else None)
        body = body or robot.mocap_body
        up = up or run.mission.mocap_up_axis
        T_bm = T_bm if T_bm is not None else robot.T_body_marker
        own = (
            mocap is not None
            and run.mocap_path is not None
            and Path(mocap).resolve() == run.mocap_path.resolve()
        )
        if offset is None and run.mission.mocap_start_ns is not None and own:
            offset = -run.mission.mocap_start_ns * 1e-9
            offset_src = "mission.yaml mocap.start_ns"
    take = ref = None
    if args.ref:
        if args.mocap:
            raise InputError("eval traj: give --ref or --mocap, not both")
        if args.ref_topic:
            from dran_edge.formats.trajectory import read_bag_trajectory

            r = read_bag_trajectory(args.ref, args.ref_topic)
        else:
            r = read_trajectory(
                args.ref,
                args.ref_format,
                quat_order=args.ref_quat_order,
                kitti_rate_hz=args.kitti_rate_hz,
            )
        ref = (r.stamps_s, r.T)
        ref_name, ref_how = Path(args.ref).stem, f"{r.format} ({r.how})"
    else:
        if not mocap or not body:
            raise InputError(
                "eval traj: expected --mocap FILE.csv and --body NAME, or --ref "
                "REF (or a trajectory inside a run: RUN/out/<robot>/<robot>.tum)"
            )
        if est.format == "kitti" and not est.has_stamps:
            raise InputError(
                "eval traj: KITTI poses have no stamps; compare them with --ref "
                "(also KITTI) or convert them with stamps first"
            )
        take = motive.read_motive_csv(mocap, up_axis=up or "y")
        ref_name, ref_how = body, f"Motive CSV {mocap}"
    traj = evaluate_trajectory(
        est.stamps_s,
        est.T,
        take,
        body,
        T_body_marker=T_bm,
        align_kind=args.align or "se3",
        time_offset_s=offset,
        time_offset_source=offset_src,
        max_gap_s=args.max_gap,
        rpe_delta_s=args.rpe_delta,
        reference=ref,
    )
    est_name = Path(args.est).stem
    written = []
    if args.save_results:
        from dran_edge.evaluation.traj_outputs import write_evo_results

        written.append(write_evo_results(args.save_results, traj, est_name, ref_name))
    if args.plot:
        from dran_edge.evaluation.traj_outputs import plot_trajectory

        written.append(plot_trajectory(args.plot, traj, est_name, ref_name))
    from dran_edge.evaluation.report import json_safe

    res = json_safe(dict(traj.result))
    res["estimate"] = {
        "path": args.est,
        "format": est.format,
        "quat_order": est.quat_order,
        "how": est.how,
    }
    res["reference"] = ref_how
    _print_traj(args, est, ref_how, res, written)
    return 0


def _print_traj(args, est, ref_how: str, res: dict, written: list) -> None:
    if args.json:
        print(json.dumps(res, indent=2))
        return
    print(f"{'estimate':<20}{args.est}: {est.format}, {est.how}")
    print(f"{'reference':<20}{ref_how}")
    if res["positions_only"]:
        print(f"{'note':<20}the estimate has no orientations (all identity): positions only")
    keys = (
        "ate_rmse_m",
        "ate_max_m",
        "ate_mean_m",
        "ate_median_m",
        "ate_rot_rmse_deg",
        "ate_log_rmse",
        "matched_poses",
        "estimated_poses",
        "time_offset_s",
        "time_offset_source",
    )
    for k in keys:
        v = res[k]
        print(f"{k:<20}{v:.6f}" if isinstance(v, float) else f"{k:<20}{v}")
    print(f"{'align':<20}{res['align']['kind']} (scale {res['align']['scale']:.6f})")
    rpe = res["rpe"]
    print(
        f"{'rpe_trans_rmse_m':<20}{rpe['trans_rmse_m']:.6f}  (delta {rpe['delta_s']} s, "
        f"{rpe['pairs']} pairs)"
    )
    for p in written:
        print(f"{'wrote':<20}{p}")


def _run_dir(args: argparse.Namespace) -> int:
    from dran_edge.evaluation import score as evaluate

    if args.est:
        raise InputError(
            f"eval RUN_DIR takes no second argument, got {args.est!r} (did you "
            "mean 'eval traj EST'?)"
        )
    opt = evaluate.EvalOptions(
        align=args.align or "paper",
        mocap_path=args.mocap,
        time_offset_s=args.time_offset,
        max_gap_s=args.max_gap,
        rpe_delta_s=args.rpe_delta,
        centralized=not args.no_centralized,
        plots=not args.no_plots,
    )
    print(f"evaluating {args.target} ...", file=sys.stderr)
    evaluation = evaluate.evaluate_run(args.target, opt)
    out = Path(args.out) if args.out else Path(args.target) / "eval"
    written = evaluate.write_report(evaluation, out, plots=opt.plots)
    if args.json:
        print(json.dumps(evaluation.report, indent=2))
    else:
        print(evaluate.summary_markdown(evaluation.report))
        print("wrote " + ", ".join(str(p) for p in written))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.target == "traj":
        return _run_traj(args)
    return _run_dir(args)
