"""Trajectory and map metrics of the paper (Sec. 6.2) and the usual ones, on plain arrays.

Conventions: poses ``(..., 4, 4)``; the error of an estimate ``x`` against ground truth ``x̄``
is ``e = Log(x̄⁻¹ x)`` over the whole SE(3) tangent ``[ρ, φ]`` (translation in metres, rotation
in radians, summed as they are — the paper's definition, so these numbers mix units). Names
say which kind a function returns: ``*_log_*`` for the paper's tangent norm, ``*_trans_*`` in
metres, ``*_rot_*`` in degrees.

Paper definitions (Sec. 6.2; ``i`` robots 1..N, ``j`` poses 1..n_i or objects 1..m):

- ATE  = sqrt( 1/N Σ_i 1/n_i Σ_j ‖Log(x̄_ij⁻¹ x_ij)‖² )      — :func:`ate_log_rmse`
- SR_ATE = (ATE⁰ − ATEᵏ) / (ATE⁰ − ATE*) · 100 %              — :func:`sr_ate`
- SR_cost = (F_init − Fᵏ) / (F_init − F*) · 100 %             — :func:`sr_cost`
- F/F* and ATE/ATE* (not in the paper; reported beside SR_cost / SR_ATE, since those hide a
  gap that is small next to the initial one)    — :func:`cost_ratio`, :func:`ate_ratio`
- CE   = 1/N Σ_i 1/m Σ_j ‖Log(y_ij⁻¹ y_avg,j)‖²,
  y_avg = argmin_y 1/N Σ_i 1/m Σ_j ‖Log(y_ij⁻¹ y_j)‖²          — :func:`consistency_error`
- Bias = sqrt( 1/N Σ_i 1/m Σ_j ‖Log(ȳ_ij⁻¹ y_ij)‖² )           — :func:`object_bias`

Where a robot holds copies of only some objects (``present`` mask), ``1/m`` becomes ``1/m_i``
over the objects it holds, and robots holding none are left out of ``1/N``; ``y_avg`` is then
the minimiser of that same weighted sum (weights ``1/m_i``), so CE stays the minimum it is
defined as. The paper's text calls Bias "the error between the average and ground truth"
while its formula compares every robot's copy with ground truth; :func:`object_bias` is the
formula, :func:`object_bias_of_mean` the text.

Pure and vectorised (numpy only); no loops over poses.
"""

from __future__ import annotations

import numpy as np

from dran_edge import geometry as geo


def pose_error_log(T_est: np.ndarray, T_ref: np.ndarray) -> np.ndarray:
    """``Log(T_ref⁻¹ T_est)``, ``(..., 6)`` = [ρ (m), φ (rad)]."""
    return geo.se3_log(geo.se3_between(T_ref, T_est))


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """Angle of rotations ``(..., 3, 3)`` in degrees, in [0, 180]."""
    return np.degrees(np.linalg.norm(geo.so3_log(R), axis=-1))


def _group_mean(values: np.ndarray, group: np.ndarray | None) -> float:
    """1/N Σ_i mean(values of group i) (equal weight per group), or the plain mean."""
    values = np.asarray(values, dtype=np.float64)
    if group is None:
        return float(np.mean(values))
    group = np.asarray(group)
    _, inv = np.unique(group, return_inverse=True)
    sums = np.bincount(inv, weights=values)
    counts = np.bincount(inv)
    return float(np.mean(sums / counts))


def ate_log_rmse(T_est: np.ndarray, T_ref: np.ndarray, group: np.ndarray | None = None) -> float:
    """The paper's ATE: sqrt(1/N Σ_i 1/n_i Σ_j ‖Log(x̄⁻¹ x)‖²) over ``(n, 4, 4)`` matched poses.

    ``group`` ``(n,)`` names each pose's robot (each robot weighs 1/N whatever its length); with
    ``None`` all poses weigh the same (one robot).
    """
    e = pose_error_log(T_est, T_ref)
    return float(np.sqrt(_group_mean(np.sum(e * e, axis=-1), group)))


def ate_trans_rmse_m(
    T_est: np.ndarray, T_ref: np.ndarray, group: np.ndarray | None = None
) -> float:
    """Translation ATE (m): RMSE of ‖p_est − p_ref‖ (evo's APE translation part).

    With ``group`` each robot weighs 1/N, as in :func:`ate_log_rmse`.
    """
    d = np.asarray(T_est)[..., :3, 3] - np.asarray(T_ref)[..., :3, 3]
    return float(np.sqrt(_group_mean(np.sum(d * d, axis=-1), group)))


def ate_trans_stats_m(T_est: np.ndarray, T_ref: np.ndarray) -> dict[str, float]:
    """Translation error statistics (m) over matched poses: rmse, mean, median, std, max."""
    d = np.linalg.norm(np.asarray(T_est)[..., :3, 3] - np.asarray(T_ref)[..., :3, 3], axis=-1)
    return {
        "rmse_m": float(np.sqrt(np.mean(d * d))),
        "mean_m": float(np.mean(d)),
        "median_m": float(np.median(d)),
        "std_m": float(np.std(d)),
        "max_m": float(np.max(d)),
    }


def ate_rot_rmse_deg(T_est: np.ndarray, T_ref: np.ndarray) -> float:
    """RMSE of the rotation angle of ``R_ref⁻¹ R_est`` (degrees)."""
    R = np.swapaxes(np.asarray(T_ref)[..., :3, :3], -1, -2) @ np.asarray(T_est)[..., :3, :3]
    a = rotation_angle_deg(R)
    return float(np.sqrt(np.mean(a * a)))


def success_ratio(start, current, reference):
    """(start − current) / (start − reference) · 100 %, elementwise; NaN where start == reference."""
    start = np.asarray(start, dtype=np.float64)
    den = start - np.asarray(reference, dtype=np.float64)
    num = start - np.asarray(current, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(den != 0, 100.0 * num / np.where(den != 0, den, 1.0), np.nan)
    return out if out.ndim else float(out)


def sr_ate(ate_0, ate_k, ate_star):
    """SR_ATE (%) = (ATE⁰ − ATEᵏ) / (ATE⁰ − ATE*) · 100 (paper Sec. 6.2); arrays broadcast."""
    return success_ratio(ate_0, ate_k, ate_star)


def sr_cost(cost_init, cost_k, cost_star):
    """SR_cost (%) = (F_init − Fᵏ) / (F_init − F*) · 100 (paper Sec. 6.2); arrays broadcast."""
    return success_ratio(cost_init, cost_k, cost_star)


def ratio_to_reference(current, reference):
    """current / reference, elementwise; NaN where the reference is 0 or not finite.

    F/F* and ATE/ATE* (docs/eval.md): SR_cost compares the gain with the *initial* gap, so a
    run that starts 10⁴ × F* above the optimum shows 99.99 % while still 27 % above F*; the
    ratio to the reference does not hide that gap."""
    cur = np.asarray(current, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    ok = np.isfinite(ref) & (ref != 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(ok, cur / np.where(ok, ref, 1.0), np.nan)
    return out if out.ndim else float(out)


def cost_ratio(cost_k, cost_star):
    """F/F*: the objective over the centralized optimum's (1 at the optimum)."""
    return ratio_to_reference(cost_k, cost_star)


def ate_ratio(ate_k, ate_star):
    """ATE/ATE*: the ATE over the centralized solution's ATE (same metric, same ground truth)."""
    return ratio_to_reference(ate_k, ate_star)


def frechet_mean_se3(
    Y: np.ndarray, weights: np.ndarray, *, iters: int = 50, tol: float = 1e-12
) -> np.ndarray:
    """Weighted Fréchet (Karcher) mean on SE(3) under the paper's Log distance.

    ``Y`` ``(..., K, 4, 4)`` copies, ``weights`` ``(..., K)`` (0 = absent). Returns
    ``argmin_y Σ_k w_k ‖Log(Y_k⁻¹ y)‖²`` ``(..., 4, 4)`` by Gauss–Newton with the right
    retraction: ``e_k = Log(Y_k⁻¹ y)``, ``∂e_k/∂δ = J_r⁻¹(e_k)`` at ``y ⊕ δ``, started from the
    chordal mean (weighted average projected onto SO(3)). Batches with no weight get NaN.
    """
    Y = np.asarray(Y, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    wsum = w.sum(axis=-1)
    safe = np.where(w[..., None, None] > 0, Y, np.eye(4))
    wn = w / np.where(wsum > 0, wsum, 1.0)[..., None]
    Rm = geo.so3_project(np.sum(wn[..., None, None] * safe[..., :3, :3], axis=-3))
    pm = np.sum(wn[..., None] * safe[..., :3, 3], axis=-2)
    y = geo.se3_from_rt(Rm, pm)
    for _ in range(iters):
        e = geo.se3_log(geo.se3_between(safe, y[..., None, :, :]))  # (..., K, 6)
        J = geo.se3_right_jacobian_inv(e)  # (..., K, 6, 6)
        JtW = np.swapaxes(J, -1, -2) * wn[..., None, None]
        H = np.sum(JtW @ J, axis=-3)
        g = np.sum((JtW @ e[..., None])[..., 0], axis=-2)
        H = H + 1e-15 * np.eye(6)
        delta = -np.linalg.solve(H, g[..., None])[..., 0]
        y = geo.se3_retract(y, delta)
        if np.max(np.abs(delta)) < tol:
            break
    return np.where((wsum > 0)[..., None, None], y, np.nan)


def _robot_weights(present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-copy weights 1/m_i ``(N, m)`` and the mask of robots holding any object ``(N,)``."""
    present = np.asarray(present, dtype=bool)
    m_i = present.sum(axis=1)
    has = m_i > 0
    w = np.where(present, 1.0 / np.where(has, m_i, 1)[:, None], 0.0)
    return w, has


def object_mean(Y: np.ndarray, present: np.ndarray) -> np.ndarray:
    """y_avg ``(m, 4, 4)``: the CE minimiser over robots' copies ``Y`` ``(N, m, 4, 4)``."""
    w, _ = _robot_weights(present)
    return frechet_mean_se3(np.swapaxes(Y, 0, 1), w.T)


def consistency_error(Y: np.ndarray, present: np.ndarray) -> tuple[float, np.ndarray]:
    """(CE, y_avg ``(m, 4, 4)``) of the robots' object copies ``Y`` ``(N, m, 4, 4)``.

    CE = 1/N Σ_i 1/m_i Σ_j ‖Log(y_ij⁻¹ y_avg,j)‖² (paper Sec. 6.2; not a square root: units
    of m² + rad²). ``present`` ``(N, m)`` marks which copies exist.
    """
    present = np.asarray(present, dtype=bool)
    w, has = _robot_weights(present)
    if not has.any():
        return float("nan"), np.full(np.shape(Y)[1:], np.nan)
    y_avg = object_mean(Y, present)
    safe = np.where(present[..., None, None], Y, np.eye(4))
    ref = np.where(np.isfinite(y_avg), y_avg, np.eye(4))
    e = geo.se3_log(geo.se3_between(safe, ref[None]))
    per_robot = np.sum(w * np.sum(e * e, axis=-1), axis=1)
    return float(np.mean(per_robot[has])), y_avg


def object_bias(Y: np.ndarray, present: np.ndarray, Y_gt: np.ndarray) -> float:
    """Bias = sqrt(1/N Σ_i 1/m_i Σ_j ‖Log(ȳ_j⁻¹ y_ij)‖²) (the paper's formula, Sec. 6.2).

    ``Y`` ``(N, m, 4, 4)`` copies, ``present`` ``(N, m)``, ``Y_gt`` ``(m, 4, 4)`` ground truth
    (objects without ground truth: NaN poses; their copies are left out).
    """
    Y_gt = np.asarray(Y_gt, dtype=np.float64)
    present = np.asarray(present, bool) & np.all(np.isfinite(Y_gt), axis=(-1, -2))[None]
    w, has = _robot_weights(present)
    if not has.any():
        return float("nan")
    safe = np.where(present[..., None, None], Y, np.eye(4))
    gt = np.where(np.isfinite(Y_gt), Y_gt, np.eye(4))
    e = pose_error_log(safe, gt[None])
    per_robot = np.sum(w * np.sum(e * e, axis=-1), axis=1)
    return float(np.sqrt(np.mean(per_robot[has])))


def object_bias_of_mean(y_avg: np.ndarray, Y_gt: np.ndarray) -> float:
    """sqrt(1/m Σ_j ‖Log(ȳ_j⁻¹ y_avg,j)‖²): the error of the robots' mean map (objects with
    both a mean and ground truth)."""
    ok = np.all(np.isfinite(y_avg), axis=(-1, -2)) & np.all(np.isfinite(Y_gt), axis=(-1, -2))
    if not ok.any():
        return float("nan")
    e = pose_error_log(np.asarray(y_avg)[ok], np.asarray(Y_gt)[ok])
    return float(np.sqrt(np.mean(np.sum(e * e, axis=-1))))


def object_errors(
    Y: np.ndarray, present: np.ndarray, Y_gt: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-copy errors against ground truth: (translation (m), rotation (deg)), each ``(N, m)``,
    NaN where a copy or the ground truth is missing."""
    Y = np.asarray(Y, dtype=np.float64)
    Y_gt = np.asarray(Y_gt, dtype=np.float64)
    ok = np.asarray(present, bool) & np.all(np.isfinite(Y_gt), axis=(-1, -2))[None]
    safe = np.where(ok[..., None, None], Y, np.eye(4))
    gt = np.where(np.isfinite(Y_gt), Y_gt, np.eye(4))[None]
    trans = np.linalg.norm(safe[..., :3, 3] - gt[..., :3, 3], axis=-1)
    rot = rotation_angle_deg(np.swapaxes(gt[..., :3, :3], -1, -2) @ safe[..., :3, :3])
    return np.where(ok, trans, np.nan), np.where(ok, rot, np.nan)


def relative_errors(T_est_a, T_ref_a, T_est_b, T_ref_b) -> tuple[np.ndarray, np.ndarray]:
    """Errors of relative poses: ``E = (T_ref_a⁻¹ T_ref_b)⁻¹ (T_est_a⁻¹ T_est_b)``.

    Returns (translation ‖t_E‖ (m), rotation angle (deg)), each ``(n,)``. Invariant to any
    transformation applied to all estimates alike, hence no alignment is needed.
    """
    rel_est = geo.se3_between(T_est_a, T_est_b)
    rel_ref = geo.se3_between(T_ref_a, T_ref_b)
    E = geo.se3_between(rel_ref, rel_est)
    return np.linalg.norm(E[..., :3, 3], axis=-1), rotation_angle_deg(E[..., :3, :3])


def rpe(
    stamps_s: np.ndarray, T_est: np.ndarray, T_ref: np.ndarray, *, delta_s: float = 1.0
) -> dict[str, float]:
    """Relative pose error over pose pairs ``delta_s`` apart (the first pose at least
    ``delta_s`` later): translation RMSE (m), rotation RMSE (deg), pair count."""
    stamps_s = np.asarray(stamps_s, dtype=np.float64)
    j = np.searchsorted(stamps_s, stamps_s + delta_s - 1e-9, side="left")
    i = np.flatnonzero(j < len(stamps_s))
    if i.size == 0:
        return {
            "delta_s": delta_s,
            "pairs": 0,
            "trans_rmse_m": float("nan"),
            "rot_rmse_deg": float("nan"),
        }
    j = j[i]
    tr, rot = relative_errors(T_est[i], T_ref[i], T_est[j], T_ref[j])
    return {
        "delta_s": float(delta_s),
        "pairs": int(i.size),
        "trans_rmse_m": float(np.sqrt(np.mean(tr * tr))),
        "rot_rmse_deg": float(np.sqrt(np.mean(rot * rot))),
    }


def inter_robot_error(T_est_a, T_ref_a, T_est_b, T_ref_b) -> dict[str, float]:
    """Error of robot b's pose seen from robot a at the same instants (arrays ``(n, 4, 4)``):
    translation RMSE (m), rotation RMSE (deg), count. Needs no alignment."""
    tr, rot = relative_errors(T_est_a, T_ref_a, T_est_b, T_ref_b)
    return {
        "samples": int(len(tr)),
        "trans_rmse_m": float(np.sqrt(np.mean(tr * tr))) if len(tr) else float("nan"),
        "rot_rmse_deg": float(np.sqrt(np.mean(rot * rot))) if len(tr) else float("nan"),
    }
