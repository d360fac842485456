"""Covariance consistency of tag poses: NEES over many rendered frames with known poses.

    .venv/bin/python tools/bench/nees_perception.py [--frames 300]
    .venv/bin/python tools/bench/nees_perception.py --quick     # 12 frames per condition

For each imaging condition (grey noise, blur), a calibration set and a disjoint test set of
single-tag renders (16 cm tag, 0.5-3 m, yaw +-60 deg, pitch +-30 deg, any roll) are detected.
``corner_sigma_px`` is set on the calibration set from reprojection residuals only (no ground
truth: what ``dran-edge detect``'s summary reports on a real camera), and the test set's poses
are estimated with it, without (``residual``) and with (``residual+birge``) the per-pose
inflation by the reduced chi-square (``TagPoseParams.inflate_by_residual``, the default). The
test set's NEES = d^T Sigma^-1 d, d = Log(T_est^-1 T_true), is summarised (mean; median;
share above the chi2(6) 95 % quantile 12.59; mean per distance band). A consistent covariance
has a mean near 6, a median near 5.35, about 5 % above 12.59, and no trend with distance.
"""

from __future__ import annotations

import argparse

import numpy as np
from dran_edge.perception.covariance import corner_sigma_from_residuals
from dran_edge.perception.detector import TagDetector, to_gray
from dran_edge.perception.render import TagRenderer
from dran_edge.perception.tagpose import TagPoseParams, estimate_tag_poses

from dran_edge import geometry as geo

K = np.array([[615.0, 0, 320], [0, 615.0, 240], [0, 0, 1]])
SIZE_M = 0.16
CHI2_6_95 = 12.5916


def random_pose(rng: np.random.Generator) -> np.ndarray:
    yaw, pitch, roll = np.deg2rad(
        [rng.uniform(-60, 60), rng.uniform(-30, 30), rng.uniform(-180, 180)]
    )
    R = (
        geo.so3_exp(np.array([0, yaw, 0]))
        @ geo.so3_exp(np.array([pitch, 0, 0]))
        @ geo.so3_exp(np.array([0, 0, roll]))
    )
    z = rng.uniform(0.5, 3.0)
    return geo.se3_from_rt(
        R, np.array([rng.uniform(-0.25, 0.25) * z, rng.uniform(-0.15, 0.15) * z, z])
    )


def sample(renderer, detector, rng, n, noise, blur):
    """(T_true, detections) for each frame whose single tag was detected."""
    out = []
    for _ in range(n):
        T = random_pose(rng)
        colour, _ = renderer.render(
            K, 640, 480, [T], [11], SIZE_M, noise_sigma=noise, blur_sigma_px=blur, rng=rng
        )
        det = detector.detect(to_gray(colour))
        if len(det) == 1:
            out.append((T, det))
    return out


def poses(samples, params):
    """(T_true, TagPoses) of the accepted tags, estimated with ``params``."""
    out = []
    for T, det in samples:
        tp = estimate_tag_poses(det, K, [SIZE_M], (640, 480), params=params)
        if tp.accepted[0]:
            out.append((T, tp))
    return out


def residual_sigma(accepted, ref_edge_px: float) -> float:
    sq = np.array([4 * tp.rms_px[0] ** 2 * tp.min_edge_px[0] / ref_edge_px for _, tp in accepted])
    return corner_sigma_from_residuals(sq, np.full(sq.size, 4))


def nees(accepted) -> tuple[np.ndarray, np.ndarray]:
    """NEES per accepted sample and each sample's range."""
    T_est = np.stack([tp.T_camera_tag[0] for _, tp in accepted])
    T_true = np.stack([T for T, _ in accepted])
    cov = np.stack([tp.covariance[0] for _, tp in accepted])
    d = geo.se3_log(geo.se3_between(T_est, T_true))
    e = np.einsum("ni,ni->n", d, np.linalg.solve(cov, d[..., None])[..., 0])
    return e, T_true[:, 2, 3]


def summary(e: np.ndarray, z: np.ndarray) -> dict:
    bands = [
        (lo, hi, float(e[(z >= lo) & (z < hi)].mean()))
        for lo, hi in ((0.5, 1.0), (1.0, 2.0), (2.0, 3.0))
    ]
    return {
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "above_95": float(np.mean(e > CHI2_6_95)),
        "bands": bands,
    }


def run(frames: int, noise: float, blur: float, seed: int = 5) -> dict:
    renderer, detector = TagRenderer(), TagDetector()
    rng = np.random.default_rng(seed)
    cal = sample(renderer, detector, rng, frames // 2, noise, blur)
    test = sample(renderer, detector, rng, frames, noise, blur)
    base = TagPoseParams()
    s_res = residual_sigma(poses(cal, base), base.corner_sigma_ref_edge_px)
    out = {"noise": noise, "blur": blur, "sigma_residual": s_res}
    for name, inflate in (("residual", False), ("residual+birge", True)):
        params = TagPoseParams(corner_sigma_px=s_res, inflate_by_residual=inflate)
        accepted = poses(test, params)
        out["n_test"] = len(accepted)
        out[name] = summary(*nees(accepted))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument(
        "--quick",
        action="store_true",
        help="12 frames per condition: checks the script; the statistics mean nothing",
    )
    args = ap.parse_args()
    if args.quick:
        args.frames = min(args.frames, 12)
    for noise, blur in ((2.0, 0.0), (3.0, 0.8), (8.0, 1.2)):
        r = run(args.frames, noise, blur)
        print(
            f"noise {noise:g} blur {blur:g} px: test frames {r['n_test']}, sigma from residuals "
            f"{r['sigma_residual']:.3f} px"
        )
        for name in ("residual", "residual+birge"):
            x = r[name]
            bands = ", ".join(f"{lo:g}-{hi:g} m {m:.2f}" for lo, hi, m in x["bands"])
            print(
                f"  {name:<15} NEES mean {x['mean']:.2f} median {x['median']:.2f}  "
                f">chi2_95 {x['above_95']:.3f}  "
                f"by range: {bands}"
            )


if __name__ == "__main__":
    main()
