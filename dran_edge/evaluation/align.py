"""Associate an estimated trajectory with mocap, estimate the clock offset, align the frames.

Time: ``t_mocap = t_est + time_offset_s``. Mocap poses are interpolated at the estimate's stamps
(translation lerp, rotation slerp; ``geometry.se3_interpolate``), never across an occlusion gap
longer than ``max_gap_s``: evo matches nearest stamps within ``t_max_diff``, which at 120 Hz mocap
leaves up to 4 ms of motion in the error; interpolation removes it.

Clock offset: the angular-speed magnitude ``‖Log(R_kᵀ R_k+1)‖ / Δt`` does not depend on the
world frame nor on the rotation between the mocap rigid body and the robot body, so the offset
that maximises the normalised cross-correlation of the two angular-speed signals is the clock
offset (docs/eval.md); the peak is refined to sub-sample precision with
a parabola through its neighbours.

Alignment (``kind``), a similarity ``p_ref = s R p_est + t`` applied to whole trajectories:

- ``none``: the estimate is already in the mocap world.
- ``se3`` / ``sim3``: Umeyama's least squares on positions (S. Umeyama, "Least-squares
  estimation of transformation parameters between two point patterns", IEEE TPAMI 13(4), 1991,
  eqs. 34–42), without / with scale — what ``evo_ape -a`` / ``-as`` do.
- ``yaw``: rotation about the vertical z axis plus translation (4-DoF), the alignment that
  suits VIO, whose roll and pitch are observable from gravity (rpg_trajectory_evaluation's
  ``posyaw``); roll/pitch errors stay visible in the result.
- ``paper``: the paper's protocol (Sec. 6.3): mocap gives only the initial world-to-robot frame,
  ``T_world_odom = T_world_body(t0) · T_odom_body(t0)⁻¹`` from the first associated pose.

Pure core module (numpy, scipy, stdlib).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dran_edge import geometry as geo
from dran_edge.errors import InputError

ALIGN_KINDS = ("none", "se3", "sim3", "yaw", "paper")


# --------------------------------------------------------------------------------------------
# association


@dataclass(frozen=True)
class Association:
    """Estimated poses paired with mocap poses interpolated at the same instants."""

    stamps_s: np.ndarray = field(repr=False)
    """``(m,)`` estimate stamps (the estimate's clock) of the matched poses."""
    index_est: np.ndarray = field(repr=False)
    """``(m,)`` indices of the matched poses in the estimate."""
    T_est: np.ndarray = field(repr=False)
    """``(m, 4, 4)`` estimated poses."""
    T_ref: np.ndarray = field(repr=False)
    """``(m, 4, 4)`` mocap poses at ``stamps_s + time_offset_s``."""
    time_offset_s: float
    """Offset used: ``t_mocap = t_est + time_offset_s``."""

    @property
    def matched_poses(self) -> int:
        return len(self.stamps_s)


def interpolate_track(
    time_s: np.ndarray,
    T: np.ndarray,
    query_s: np.ndarray,
    *,
    valid: np.ndarray | None = None,
    max_gap_s: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Poses of a track at ``query_s`` (lerp/slerp between the tracked samples around each).

    Returns ``(T_query (m, 4, 4), ok (m,))``; ``ok`` is False outside the tracked span and where
    the two tracked samples around the query are more than ``max_gap_s`` apart (occlusion).
    """
    time_s = np.asarray(time_s, dtype=np.float64)
    T = np.asarray(T, dtype=np.float64)
    query_s = np.asarray(query_s, dtype=np.float64).reshape(-1)
    keep = np.ones(len(time_s), bool) if valid is None else np.asarray(valid, bool)
    keep = keep & np.all(np.isfinite(T), axis=(-1, -2))
    ts, Ts = time_s[keep], T[keep]
    if len(ts) == 0:
        return np.full((len(query_s), 4, 4), np.nan), np.zeros(len(query_s), bool)
    # Integer nanoseconds relative to the first sample keep the interpolation exact for
    # epoch-sized stamps.
    t0 = ts[0]
    ns = np.round((ts - t0) * 1e9).astype(np.int64)
    qns = np.round((query_s - t0) * 1e9).astype(np.int64)
    Tq, ok = geo.se3_interpolate(ns, Ts, qns)
    if len(ts) > 1:
        hi = np.clip(np.searchsorted(ns, qns, side="left"), 1, len(ns) - 1)
        exact = ns[np.clip(np.searchsorted(ns, qns), 0, len(ns) - 1)] == qns
        gap_s = (ns[hi] - ns[hi - 1]) * 1e-9
        ok = ok & ((gap_s <= max_gap_s) | exact)
    return Tq, ok


def associate(
    stamps_est_s: np.ndarray,
    T_est: np.ndarray,
    time_ref_s: np.ndarray,
    T_ref: np.ndarray,
    *,
    valid_ref: np.ndarray | None = None,
    time_offset_s: float = 0.0,
    max_gap_s: float = 0.1,
    what: str = "estimate",
) -> Association:
    """Pair each estimated pose with the mocap pose interpolated at ``t_est + time_offset_s``.

    Raises InputError when the time ranges do not overlap or nothing matches.
    """
    stamps_est_s = np.asarray(stamps_est_s, dtype=np.float64)
    T_est = np.asarray(T_est, dtype=np.float64)
    time_ref_s = np.asarray(time_ref_s, dtype=np.float64)
    q = stamps_est_s + time_offset_s
    tr = time_ref_s if valid_ref is None else time_ref_s[np.asarray(valid_ref, bool)]
    if len(tr) == 0:
        raise InputError(f"{what}: the mocap body is never tracked (all frames occluded)")
    if q[-1] < tr[0] or q[0] > tr[-1]:
        raise InputError(
            f"{what}: time ranges do not overlap: the estimate covers [{q[0]:.3f}, {q[-1]:.3f}] s "
            f"on the mocap clock (offset {time_offset_s:+.6f} s) but the mocap covers "
            f"[{tr[0]:.3f}, {tr[-1]:.3f}] s; give --time-offset or check the clocks"
        )
    Tq, ok = interpolate_track(time_ref_s, T_ref, q, valid=valid_ref, max_gap_s=max_gap_s)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        raise InputError(
            f"{what}: no estimated pose falls within tracked mocap frames "
            f"(occlusion gaps longer than {max_gap_s} s everywhere)"
        )
    return Association(stamps_est_s[idx], idx, T_est[idx], Tq[idx], float(time_offset_s))


# --------------------------------------------------------------------------------------------
# clock offset


@dataclass(frozen=True)
class TimeOffset:
    """Result of :func:`estimate_time_offset`."""

    offset_s: float
    """``t_mocap = t_est + offset_s``."""
    correlation: float
    """Normalised cross-correlation at the peak (1 = identical angular-speed profiles)."""
    overlap_s: float
    """Length of the overlap the peak was computed on."""


def _angular_speed(time_s, T, valid, grid_s, max_gap_s, smooth_n):
    Tg, ok = interpolate_track(time_s, T, grid_s, valid=valid, max_gap_s=max_gap_s)
    dt = np.diff(grid_s)
    R = Tg[:, :3, :3]
    w = np.linalg.norm(geo.so3_log(np.swapaxes(R[:-1], -1, -2) @ R[1:]), axis=-1) / dt
    return _smooth(np.where(ok[:-1] & ok[1:], w, np.nan), smooth_n)


def _linear_speed(time_s, T, valid, grid_s, max_gap_s, smooth_n):
    Tg, ok = interpolate_track(time_s, T, grid_s, valid=valid, max_gap_s=max_gap_s)
    v = np.linalg.norm(np.diff(Tg[:, :3, 3], axis=0), axis=-1) / np.diff(grid_s)
    return _smooth(np.where(ok[:-1] & ok[1:], v, np.nan), smooth_n)


def _smooth(w, smooth_n):
    ok = np.isfinite(w)
    if smooth_n > 1:
        kernel = np.ones(smooth_n) / smooth_n
        filled = np.where(ok, w, 0.0)
        num = np.convolve(filled, kernel, mode="same")
        den = np.convolve(ok.astype(float), kernel, mode="same")
        w = np.where(ok & (den > 0), num / np.maximum(den, 1e-12), np.nan)
    return w


def _speed_signals(
    stamps_est_s: np.ndarray,
    T_est: np.ndarray,
    time_ref_s: np.ndarray,
    T_ref: np.ndarray,
    vr: np.ndarray,
    initial_offset_s: float,
    rate_hz: float,
    smooth_s: float,
    signal: str,
) -> tuple[np.ndarray, np.ndarray, int]:
    """(estimate speeds, mocap speeds, j0): both resampled at ``rate_hz`` on grids of the same
    phase in the estimate's clock, the mocap's shifted by ``initial_offset_s``; mocap sample 0
    is estimate grid step ``j0``. NaN where a signal is undefined."""
    step = 1.0 / rate_hz
    # Smooth over at least three estimate periods: differencing sparse, noisy poses at the grid
    # rate otherwise turns pose noise into large angular-speed spikes.
    est_period_s = float(np.median(np.diff(stamps_est_s)))
    smooth_n = max(1, int(round(max(smooth_s, 3.0 * est_period_s) * rate_hz)))
    est_grid = np.arange(stamps_est_s[0], stamps_est_s[-1], step)
    if len(est_grid) < 3:
        raise InputError("time offset: the estimate spans less than three resampling steps")
    # The mocap grid in the estimate's clock (shifted by the initial offset), same phase.
    lo = time_ref_s[vr][0] - initial_offset_s
    hi = time_ref_s[vr][-1] - initial_offset_s
    j0 = int(np.floor((lo - est_grid[0]) / step)) if len(est_grid) else 0
    j1 = int(np.ceil((hi - est_grid[0]) / step)) if len(est_grid) else 0
    ref_grid_est_clock = est_grid[0] + np.arange(j0, j1 + 1) * step
    speed = _angular_speed if signal == "angular" else _linear_speed
    e = speed(stamps_est_s, T_est, None, est_grid, 10 * step + 1.0, smooth_n)
    r = speed(time_ref_s, T_ref, vr, ref_grid_est_clock + initial_offset_s, 0.25, smooth_n)
    return e, r, j0


def _lag_correlation(
    e: np.ndarray, r: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(rho, n, var_e, var_r) per lag L = k − (len(e) − 1): the normalised cross-correlation
    of the finite samples of ``e`` and ``r`` over their overlap, its sample count and the
    (unnormalised) variances of both signals there."""
    from scipy.signal import correlate  # here: scipy.signal costs ~1 s to import

    me, mr = np.isfinite(e), np.isfinite(r)
    e0, r0 = np.where(me, e, 0.0), np.where(mr, r, 0.0)
    fe, fr = me.astype(float), mr.astype(float)
    # Sums over the overlap of each lag L (est sample i pairs with ref sample i + L), eq.:
    # z[k] = sum_i a[i + L] b[i] with L = k - (n_e - 1).
    S_er = correlate(r0, e0, mode="full", method="auto")
    n = correlate(fr, fe, mode="full", method="auto")
    S_e = correlate(fr, e0, mode="full", method="auto")
    S_ee = correlate(fr, e0 * e0, mode="full", method="auto")
    S_r = correlate(r0, fe, mode="full", method="auto")
    S_rr = correlate(r0 * r0, fe, mode="full", method="auto")
    n = np.round(n)
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = S_er - S_e * S_r / n
        ve = S_ee - S_e**2 / n
        vr_ = S_rr - S_r**2 / n
        rho = cov / np.sqrt(ve * vr_)
    return rho, n, ve, vr_


def _peak(rho: np.ndarray, ok: np.ndarray) -> tuple[int, float]:
    """(k, frac): the best admissible lag and its sub-sample refinement (a parabola through
    the peak and its neighbours, within ±0.5 step)."""
    rho_ok = np.where(ok, rho, -np.inf)
    k = int(np.argmax(rho_ok))
    frac = 0.0
    if 0 < k < len(rho) - 1 and ok[k - 1] and ok[k + 1]:
        a, b, c = rho[k - 1], rho[k], rho[k + 1]
        den = a - 2 * b + c
        if den < 0:
            frac = float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))
    return k, frac


def estimate_time_offset(
    stamps_est_s: np.ndarray,
    T_est: np.ndarray,
    time_ref_s: np.ndarray,
    T_ref: np.ndarray,
    *,
    valid_ref: np.ndarray | None = None,
    initial_offset_s: float | None = None,
    max_offset_s: float | None = None,
    rate_hz: float = 100.0,
    smooth_s: float = 0.05,
    min_overlap_s: float = 5.0,
    signal: str = "angular",
) -> TimeOffset:
    """Clock offset ``t_mocap − t_est`` maximising the correlation of angular speeds.

    ``signal="linear"`` correlates linear speeds ``‖p_k+1 − p_k‖/Δt`` instead (position
    correlation): for estimates without orientation (positions only) or robots that never
    turn; invariant to the world frame, not to a scale error's sign (it has none).

    The search is around ``initial_offset_s`` (default: the offset that lines up the first
    estimate stamp with the first tracked mocap frame), within ``±max_offset_s`` (default: any
    lag overlapping at least half of the shorter signal and ``min_overlap_s``). Raises
    InputError when the signals are too short or the robot never turns (flat angular speed).
    """
    stamps_est_s = np.asarray(stamps_est_s, dtype=np.float64)
    time_ref_s = np.asarray(time_ref_s, dtype=np.float64)
    vr = np.ones(len(time_ref_s), bool) if valid_ref is None else np.asarray(valid_ref, bool)
    if vr.sum() < 2 or len(stamps_est_s) < 2:
        raise InputError("time offset: need at least two estimated and two tracked mocap poses")
    if initial_offset_s is None:
        initial_offset_s = float(time_ref_s[vr][0] - stamps_est_s[0])
    step = 1.0 / rate_hz
    e, r, j0 = _speed_signals(
        stamps_est_s, T_est, time_ref_s, T_ref, vr, initial_offset_s, rate_hz, smooth_s, signal
    )
    n_e, n_r = len(e), len(r)
    min_n = int(min_overlap_s * rate_hz)
    if n_e < 3 or n_r < 3 or min(n_e, n_r) < min(min_n, 3):
        raise InputError("time offset: trajectories too short to correlate")
    rho, n, ve, vr_ = _lag_correlation(e, r)
    L = np.arange(n_e + n_r - 1) - (n_e - 1)
    offset_of_L = initial_offset_s + (L + j0) * step
    # A lag must overlap at least half of the shorter signal (and min_overlap_s when the signals
    # allow it): short overlaps give spurious high correlations.
    half = int(0.5 * min(np.isfinite(e).sum(), np.isfinite(r).sum()))
    need = max(half, min(min_n, 2 * half))
    ok = (n >= max(need, 3)) & np.isfinite(rho) & (ve > 1e-12 * n) & (vr_ > 1e-12 * n)
    if max_offset_s is not None:
        ok &= np.abs(offset_of_L - initial_offset_s) <= max_offset_s + 0.5 * step
    if not ok.any():
        raise InputError(
            f"time offset: no lag with enough overlap and {signal} motion (does "
            f"the robot {'turn' if signal == 'angular' else 'move'}? does the "
            "estimate overlap the reference in time?); give --time-offset S"
        )
    k, frac = _peak(rho, ok)
    return TimeOffset(float(offset_of_L[k] + frac * step), float(rho[k]), float(n[k] * step))


# --------------------------------------------------------------------------------------------
# alignment


@dataclass(frozen=True)
class Alignment:
    """A similarity taking estimate coordinates to the mocap world: ``p ↦ s R p + t``."""

    kind: str
    """One of ``ALIGN_KINDS``."""
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    """``(3, 3)`` rotation."""
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """``(3,)`` translation (m)."""
    scale: float = 1.0
    """Scale factor (1 except for ``sim3``)."""

    def apply(self, T: np.ndarray) -> np.ndarray:
        """Aligned poses: rotation ``R R_i``, position ``s R p_i + t``."""
        T = np.asarray(T, dtype=np.float64)
        out = T.copy()
        out[..., :3, :3] = self.R @ T[..., :3, :3]
        out[..., :3, 3] = self.scale * (T[..., :3, 3] @ self.R.T) + self.t
        return out

    def to_json(self) -> dict:
        return {
            "kind": self.kind,
            "R": self.R.tolist(),
            "t_m": self.t.tolist(),
            "scale": self.scale,
        }


def umeyama(
    src: np.ndarray, dst: np.ndarray, *, with_scale: bool = False
) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) minimising Σ‖dst_i − (s R src_i + t)‖² (Umeyama 1991, eqs. 34–42)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if len(src) < 3:
        raise InputError(f"alignment needs at least 3 matched positions, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    sigma = xd.T @ xs / len(src)  # eq. 38
    U, D, Vt = np.linalg.svd(sigma)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:  # eq. 39/43: reflection guard
        S[2, 2] = -1.0
    R = U @ S @ Vt  # eq. 40
    var_s = np.mean(np.sum(xs * xs, axis=1))  # eq. 36
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale else 1.0  # eq. 42
    t = mu_d - s * R @ mu_s  # eq. 41
    return R, t, s


def yaw_alignment(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Rz(ψ), t) minimising Σ‖dst_i − (Rz(ψ) src_i + t)‖² (closed form, 4-DoF)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if len(src) < 2:
        raise InputError(f"yaw alignment needs at least 2 matched positions, got {len(src)}")
    xs, xd = src - src.mean(0), dst - dst.mean(0)
    # d/dψ of the cost vanishes at tan ψ = Σ(x_s y_d − y_s x_d) / Σ(x_s x_d + y_s y_d).
    psi = np.arctan2(
        np.sum(xs[:, 0] * xd[:, 1] - xs[:, 1] * xd[:, 0]),
        np.sum(xs[:, 0] * xd[:, 0] + xs[:, 1] * xd[:, 1]),
    )
    c, s = np.cos(psi), np.sin(psi)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R, dst.mean(0) - R @ src.mean(0)


def fit_alignment(kind: str, T_est: np.ndarray, T_ref: np.ndarray) -> Alignment:
    """Fit an alignment of ``kind`` from matched poses ``(m, 4, 4)`` (estimate → mocap).

    ``paper`` uses the first matched pair only (the initial world-to-robot frame).
    """
    if kind not in ALIGN_KINDS:
        raise InputError(f"alignment must be one of {', '.join(ALIGN_KINDS)}, got {kind!r}")
    T_est = np.asarray(T_est, dtype=np.float64)
    T_ref = np.asarray(T_ref, dtype=np.float64)
    if kind == "none":
        return Alignment("none")
    if kind == "paper":
        if len(T_est) == 0:
            raise InputError("paper alignment needs at least one matched pose")
        A = T_ref[0] @ geo.se3_inverse(T_est[0])
        return Alignment("paper", A[:3, :3].copy(), A[:3, 3].copy(), 1.0)
    p_est, p_ref = T_est[:, :3, 3], T_ref[:, :3, 3]
    if kind == "yaw":
        R, t = yaw_alignment(p_est, p_ref)
        return Alignment("yaw", R, t, 1.0)
    R, t, s = umeyama(p_est, p_ref, with_scale=(kind == "sim3"))
    return Alignment(kind, R, t, s)
