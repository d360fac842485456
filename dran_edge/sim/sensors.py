"""The simulated robot's own sensors: VIO with drift and resets, keyframes, loop closures.

The models of :mod:`dran_edge.sim.mission`'s docstring (VIO after VINS-Mono, docs/vins-mono.md;
DBoW2-like loops), as pure numpy functions of :class:`~dran_edge.sim.mission.SimParams`, the
true trajectory and a random generator; :func:`dran_edge.sim.mission.generate_mission` calls
them per robot.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from dran_edge import geometry as geo

if TYPE_CHECKING:
    from dran_edge.sim.mission import SimParams


def yaw_pose(x: np.ndarray, y: np.ndarray, z: np.ndarray | float, yaw: np.ndarray) -> np.ndarray:
    """Planar poses (x, y, z, yaw about z) as (..., 4, 4)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.zeros(np.shape(yaw) + (4, 4))
    T[..., 0, 0], T[..., 0, 1], T[..., 1, 0], T[..., 1, 1] = c, -s, s, c
    T[..., 2, 2] = T[..., 3, 3] = 1.0
    T[..., 0, 3], T[..., 1, 3], T[..., 2, 3] = x, y, z
    return T


def yaw_of(T: np.ndarray) -> np.ndarray:
    return np.arctan2(T[..., 1, 0], T[..., 0, 0])


def stamps_at_rate(
    start_ns: int, duration_s: float, rate_hz: float, offset_s: float = 0.0
) -> np.ndarray:
    """Stamps (ns) every 1/rate_hz from ``start_ns + offset_s`` to the mission's end."""
    n = int(math.floor((duration_s - offset_s) * rate_hz)) + 1
    return start_ns + np.round((offset_s + np.arange(n) / rate_hz) * 1e9).astype(np.int64)


def simulate_vio(
    p: SimParams, T_world_body: np.ndarray, t_s: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, ...]:
    """VIO output with drift and resets.

    Returns (keep mask over samples, T_odom_body, segment, T_world_odom per segment).
    """
    n = len(t_s)
    lam = p.resets_per_min / 60.0 * max(p.duration_s - 40.0, 0.0)
    n_resets = int(rng.poisson(lam)) if lam > 0 else 0
    reset_t = np.sort(rng.uniform(20.0, max(p.duration_s - 20.0, 20.0), size=n_resets))
    keep = np.ones(n, bool)
    segment = np.zeros(n, np.int64)
    for k, tr in enumerate(reset_t):
        keep &= ~((t_s >= tr) & (t_s < tr + p.reset_gap_s))
        segment[t_s >= tr + p.reset_gap_s] = k + 1
    keep[0] = True
    # true increments, planar: yaw and body-frame translation
    yaw = yaw_of(T_world_body)
    dt = np.diff(t_s, prepend=t_s[0])
    rel = geo.se3_between(T_world_body[:-1], T_world_body[1:])
    d_xy = np.concatenate([np.zeros((1, 2)), rel[:, :2, 3]])
    d_yaw = np.concatenate([[0.0], np.diff(np.unwrap(yaw))])
    n_seg = int(segment.max()) + 1
    scale = 1.0 + p.scale_error_sigma * rng.standard_normal(n_seg)
    bias0 = p.yaw_bias_sigma_rad_s * rng.standard_normal(n_seg)
    walk = np.cumsum(p.yaw_bias_walk_rad_s_sqrt_s * np.sqrt(dt) * rng.standard_normal(n))
    yaw_err = d_yaw * 0 + (bias0[segment] + walk) * dt + p.step_noise_rad * rng.standard_normal(n)
    xy_noise = p.step_noise_m * rng.standard_normal((n, 2))
    z_walk = p.height_walk_m_sqrt_s * np.sqrt(dt) * rng.standard_normal(n)
    tilt = p.tilt_noise_rad * rng.standard_normal((n, 2))
    T_odom_body = np.empty((n, 4, 4))
    starts = np.flatnonzero(keep & np.r_[True, segment[1:] != segment[:-1]])
    T_world_odom = np.stack([T_world_body[s] for s in starts])
    for s_idx, s in enumerate(starts):
        end = starts[s_idx + 1] if s_idx + 1 < len(starts) else n
        sl = slice(s, end)
        inc_yaw = d_yaw[sl] + yaw_err[sl]
        inc_yaw[0] = 0.0
        est_yaw = np.cumsum(inc_yaw)
        # translation increments rotated by the estimated heading (before the step)
        heading = np.r_[0.0, est_yaw[:-1]]
        dxy = d_xy[sl] * scale[s_idx] + xy_noise[sl]
        dxy[0] = 0.0
        c, s_ = np.cos(heading), np.sin(heading)
        step = np.stack([c * dxy[:, 0] - s_ * dxy[:, 1], s_ * dxy[:, 0] + c * dxy[:, 1]], -1)
        xy = np.cumsum(step, axis=0)
        z = np.cumsum(z_walk[sl]) - z_walk[s]
        T = yaw_pose(xy[:, 0], xy[:, 1], z, est_yaw)
        R_tilt = geo.so3_exp(np.column_stack([tilt[sl], np.zeros(end - s)]))
        T[:, :3, :3] = T[:, :3, :3] @ R_tilt
        T_odom_body[sl] = T
    return keep, T_odom_body, segment, T_world_odom


def select_keyframes(
    p: SimParams, T: np.ndarray, t_s: np.ndarray, segment: np.ndarray
) -> np.ndarray:
    """Indices of VIO keyframes (sequential by nature: each depends on the last one)."""
    out = [0]
    last = 0
    xy, yaw = T[:, :2, 3], yaw_of(T)
    for i in range(1, len(t_s)):
        if segment[i] != segment[last]:
            out.append(i)
            last = i
            continue
        dyaw = abs(math.remainder(yaw[i] - yaw[last], 2 * math.pi))
        if (
            np.hypot(*(xy[i] - xy[last])) >= p.keyframe_distance_m
            or dyaw >= p.keyframe_angle_rad
            or t_s[i] - t_s[last] >= p.keyframe_interval_s
        ):
            out.append(i)
            last = i
    return np.asarray(out, dtype=np.int64)


def simulate_loops(
    p: SimParams, T_true_kf: np.ndarray, t_kf: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pairs (old, cur) of keyframe indices, measured T_old_cur, outlier flags) of the loops
    detected among the keyframes (module docstring of :mod:`dran_edge.sim.mission`)."""
    n = len(t_kf)
    xy, yaw = T_true_kf[:, :2, 3], yaw_of(T_true_kf)
    pairs, meas, outlier = [], [], []
    last_t = -1e9
    for cur in range(p.loop_min_age_kf, n):
        if t_kf[cur] - last_t < p.loop_min_interval_s:
            continue
        old = np.arange(cur - p.loop_min_age_kf + 1)
        d = np.hypot(*(xy[old] - xy[cur]).T)
        dyaw = np.abs(np.remainder(yaw[old] - yaw[cur] + np.pi, 2 * np.pi) - np.pi)
        cand = old[(d < p.loop_max_distance_m) & (dyaw < p.loop_max_yaw_rad)]
        if len(cand) == 0 or rng.random() >= p.loop_probability:
            continue
        if rng.random() < p.loop_outlier_fraction:
            o = int(rng.integers(0, cur - p.loop_min_age_kf + 1))
            T = geo.se3_from_rt(
                geo.so3_exp(np.array([0, 0, rng.uniform(-0.5, 0.5)])),
                np.r_[rng.uniform(-1.4, 1.4, size=2), 0.0],
            )
            pairs.append((o, cur))
            meas.append(T)
            outlier.append(True)
        else:
            o = int(cand[0])
            T_true = geo.se3_between(T_true_kf[o], T_true_kf[cur])
            xi = np.r_[
                p.loop_noise_m * rng.standard_normal(3), p.loop_noise_rad * rng.standard_normal(3)
            ]
            pairs.append((o, cur))
            meas.append(T_true @ geo.se3_exp(xi))
            outlier.append(False)
        last_t = t_kf[cur]
    if not pairs:
        return np.zeros((0, 2), np.int64), np.zeros((0, 4, 4)), np.zeros(0, bool)
    return np.asarray(pairs, np.int64), np.stack(meas), np.asarray(outlier)
