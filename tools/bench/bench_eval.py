"""Evaluation pipeline vs evo on the same trajectory files, same run; Motive CSV reading vs a
bare ``csv`` + ``float`` pass over the same file.

    .venv/bin/python tools/bench/bench_eval.py [--duration-s 300] [--repeats 3]
    .venv/bin/python tools/bench/bench_eval.py --quick     # 5 s of trajectory, one pass

Data: a ground-robot track (wobbly circle, varying yaw rate) sampled by mocap at 120 Hz (the
reference) and an estimate at 20 Hz whose stamps fall between mocap frames (a VIO clock is not
the mocap clock), in another world frame, with 2 cm / 0.5 deg noise. Both arms read the two TUM
files, associate, align with SE(3) Umeyama and compute the translation APE:

- evo arm: ``read_tum_trajectory_file`` x2, ``associate_trajectories`` (nearest stamp within
  10 ms), ``align``, ``APE(translation_part)``;
- our arm: ``tum.read_tum`` x2, ``align.associate`` (lerp/slerp of the reference at each
  estimate stamp), ``fit_alignment("se3")``, ``metrics.ate_trans_stats_m``.

It also scores a perfect estimate (the truth at the estimate's stamps, noise-free): the ATE each
arm reports then is pure association error. Times are process CPU time, the fastest of
``--repeats`` runs, arms interleaved.
"""

from __future__ import annotations

import argparse
import copy
import csv
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from dran_edge.evaluation import align, metrics
from dran_edge.formats import motive, motive_write, tum


def _track(t):
    yaw = 0.3 * t + 0.6 * np.sin(0.7 * t) + 0.3 * np.sin(1.9 * t)
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3] = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    T[:, :3, 3] = np.stack([2.0 * np.cos(0.15 * t), 1.5 * np.sin(0.15 * t), 0.1 + 0 * t], 1)
    return T


def make_files(d: Path, duration_s: float, noise: bool) -> tuple[Path, Path]:
    rng = np.random.default_rng(0)
    t_ref = np.arange(0, duration_s, 1 / 120)
    t_est = np.arange(0.5, duration_s - 0.5, 1 / 20) + 0.0031  # between mocap frames
    tum.write_tum(d / "ref.tum", t_ref, _track(t_ref))
    T = _track(t_est)
    if noise:
        dR = Rotation.from_rotvec(rng.normal(0, np.radians(0.5), (len(T), 3))).as_matrix()
        T[:, :3, :3] = T[:, :3, :3] @ dR
        T[:, :3, 3] += rng.normal(0, 0.02, (len(T), 3))
    G = np.eye(4)
    G[:3, :3] = Rotation.from_euler("z", 50, degrees=True).as_matrix()
    G[:3, 3] = [1.0, -2.0, 0.0]
    name = "est.tum" if noise else "perfect.tum"
    tum.write_tum(d / name, t_est, G @ T)
    return d / "ref.tum", d / name


def evo_arm(ref_path: Path, est_path: Path) -> tuple[float, int]:
    from evo.core import metrics as evo_metrics
    from evo.core import sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(ref_path))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    est = copy.deepcopy(est)
    est.align(ref)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return float(ape.get_statistic(evo_metrics.StatisticsType.rmse)), ref.num_poses


def our_arm(ref_path: Path, est_path: Path) -> tuple[float, int]:
    t_ref, T_ref = tum.read_tum(ref_path)
    t_est, T_est = tum.read_tum(est_path)
    a = align.associate(t_est, T_est, t_ref, T_ref)
    al = align.fit_alignment("se3", a.T_est, a.T_ref)
    return metrics.ate_trans_stats_m(al.apply(a.T_est), a.T_ref)["rmse_m"], a.matched_poses


def _time(fn, *args):
    t0 = time.process_time()
    out = fn(*args)
    return time.process_time() - t0, out


def csv_baseline(path: Path) -> int:
    """Every cell of every data row through float (blank -> NaN): the floor of any parser."""
    n = 0
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    for row in rows[7:]:
        [float(c) if c else float("nan") for c in row]
        n += 1
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration-s", type=float, default=300.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--quick",
        action="store_true",
        help="5 s of trajectory, one pass: checks the script, not speed",
    )
    args = ap.parse_args()
    if args.quick:
        args.duration_s, args.repeats = min(args.duration_s, 5.0), 1
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        ref, est = make_files(d, args.duration_s, noise=True)
        _, perfect = make_files(d, args.duration_s, noise=False)
        best = {"evo": np.inf, "ours": np.inf}
        res = {}
        for _ in range(args.repeats):
            for name, fn in (("evo", evo_arm), ("ours", our_arm)):
                dt, out = _time(fn, ref, est)
                best[name] = min(best[name], dt)
                res[name] = out
        print(
            f"trajectory: reference {int(args.duration_s * 120)} poses at 120 Hz, estimate "
            f"{res['ours'][1]} poses at 20 Hz"
        )
        print(
            f"  evo : {best['evo'] * 1e3:8.1f} ms  ATE {res['evo'][0]:.6f} m  "
            f"({res['evo'][1]} matched)"
        )
        print(
            f"  ours: {best['ours'] * 1e3:8.1f} ms  ATE {res['ours'][0]:.6f} m  "
            f"({res['ours'][1]} matched)"
        )
        print(f"  ratio evo/ours time: {best['evo'] / best['ours']:.2f}x")
        pe, po = evo_arm(ref, perfect)[0], our_arm(ref, perfect)[0]
        print(
            f"perfect estimate (association error only): evo {pe * 1e3:.3f} mm, "
            f"ours {po * 1e3:.6f} mm"
        )

        # Motive CSV: 6 robots + 9 boxes at 120 Hz for the duration, quaternions, 1 % occluded.
        n = int(args.duration_s * 120)
        t = np.arange(n) / 120.0
        rng = np.random.default_rng(1)
        bodies = {}
        for k in range(15):
            T = _track(t + 10 * k)
            T[rng.random(n) < 0.01] = np.nan
            bodies[f"body{k}"] = T
        mpath = d / "mocap.csv"
        motive_write.write_motive_csv(mpath, motive_write.make_take(t, bodies))
        size_mb = mpath.stat().st_size / 1e6
        b_ours = b_base = np.inf
        for _ in range(args.repeats):
            b_base = min(b_base, _time(csv_baseline, mpath)[0])
            b_ours = min(b_ours, _time(motive.read_motive_csv, mpath)[0])
        print(
            f"Motive CSV {n} rows x 15 rigid bodies ({size_mb:.1f} MB): read_motive_csv "
            f"{b_ours * 1e3:.0f} ms, csv+float baseline {b_base * 1e3:.0f} ms, ratio "
            f"baseline/ours {b_base / b_ours:.2f}x"
        )


if __name__ == "__main__":
    main()
