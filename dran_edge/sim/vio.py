"""A small VIO-like event stream with ground truth, for tests and benchmarks of the local graph.

One robot drives laps of a wobbling circle among AprilTag objects. It produces, in time order,
the events a VINS-Mono bridge and the perception worker would produce: 10 Hz odometry with
random-walk drift, keyframes every ``keyframe_spacing_m``, DBoW2-like loops to keyframes at
least 50 keyframes older that are within ``loop_radius_m`` (relative pose with noise), tag
observation batches between keyframes, and optional VIO resets (a new odometry frame at the
origin, as VINS-Mono's ``clearState()``). Seeded and deterministic; pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dran_edge import geometry as geo
from dran_edge.events import (
    Keyframe,
    LoopClosure,
    ObjectObservation,
    ObservationBatch,
    OdometrySample,
    VioReset,
)


@dataclass(frozen=True)
class Mission:
    events: list
    """Events in time order."""
    keyframe_stamps_ns: np.ndarray
    T_world_body_true: np.ndarray
    """(K, 4, 4) ground truth at every keyframe stamp."""
    object_ids: np.ndarray
    T_world_object_true: np.ndarray


def vio_mission(
    n_keyframes: int,
    seed: int = 0,
    *,
    keyframe_spacing_m: float = 0.35,
    speed_mps: float = 0.5,
    radius_m: float = 5.0,
    n_objects: int = 9,
    drift_t: float = 0.01,
    drift_r: float = 0.002,
    loop_every: int = 5,
    loop_radius_m: float = 0.6,
    loop_sigma: tuple[float, float] = (0.03, 0.01),
    obs_sigma: tuple[float, float] = (0.03, 0.02),
    obs_range_m: float = 3.5,
    reset_at: tuple[int, ...] = (),
    t0_ns: int = 1_700_000_000_000_000_000,
) -> Mission:
    rng = np.random.default_rng(seed)
    dt_kf_ns = int(keyframe_spacing_m / speed_mps * 1e9)
    xyz, T_true = _true_path(n_keyframes, keyframe_spacing_m, radius_m)
    stamps = t0_ns + np.arange(n_keyframes).astype(np.int64) * dt_kf_ns
    resets = set(reset_at)
    T_odom = _vio_odometry(T_true, resets, rng, drift_t, drift_r)
    T_obj = _objects_on_circle(n_objects)
    events: list[Any] = []
    obs_cov = np.diag([obs_sigma[0] ** 2] * 3 + [obs_sigma[1] ** 2] * 3)
    for i in range(n_keyframes):
        if i in resets:
            events.append(VioReset(int(stamps[i] - dt_kf_ns // 2), "estimator_failure"))
        events += _odometry_samples(i, stamps, T_odom, dt_kf_ns, resets)
        events.append(Keyframe(int(stamps[i]), T_odom[i].copy()))
        if i % loop_every == 0 and i > 50:
            d = np.linalg.norm(xyz[: i - 50] - xyz[i], axis=1)
            j = int(np.argmin(d))
            if d[j] < loop_radius_m:
                rel = geo.se3_between(T_true[j], T_true[i])
                noise = np.concatenate(
                    [rng.normal(0, loop_sigma[0], 3), rng.normal(0, loop_sigma[1], 3)]
                )
                events.append(
                    LoopClosure(int(stamps[j]), int(stamps[i]), rel @ geo.se3_exp(noise), 60)
                )
        # tag observations at a frame stamp between keyframes (needs interpolation)
        if i + 1 < n_keyframes and (i + 1) not in resets:
            batch = _tag_observations(
                int(stamps[i] + dt_kf_ns // 3),
                stamps[i : i + 2],
                T_true[i : i + 2],
                T_obj,
                rng,
                obs_sigma,
                obs_cov,
                obs_range_m,
            )
            if batch is not None:
                # the frame arrives after the odometry that brackets it
                events.append(("after", int(stamps[i + 1]), batch))
    return Mission(_place_deferred(events), stamps, T_true, np.arange(n_objects), T_obj)


def _true_path(
    n_keyframes: int, keyframe_spacing_m: float, radius_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """(positions, T_world_body) of the keyframes on a wobbly circle, heading along it."""
    s = np.arange(n_keyframes) * keyframe_spacing_m
    theta = s / radius_m
    wobble = 1.0 + 0.15 * np.sin(0.37 * theta)
    xyz = np.stack(
        [
            radius_m * wobble * np.cos(theta),
            radius_m * wobble * np.sin(theta),
            0.05 * np.sin(0.5 * theta),
        ],
        axis=1,
    )
    yaw = theta + np.pi / 2
    R = geo.so3_exp(np.stack([np.zeros_like(yaw), np.zeros_like(yaw), yaw], axis=1))
    return xyz, geo.se3_from_rt(R, xyz)


def _vio_odometry(
    T_true: np.ndarray, resets: set[int], rng: np.random.Generator, drift_t: float, drift_r: float
) -> np.ndarray:
    """VIO: noisy increments, restarted at the origin frame at each reset keyframe."""
    T_odom = np.empty_like(T_true)
    T_odom[0] = T_true[0]
    for i in range(1, len(T_true)):
        if i in resets:
            T_odom[i] = np.eye(4)
            continue
        d = geo.se3_between(T_true[i - 1], T_true[i])
        noise = np.concatenate([rng.normal(0, drift_t, 3), rng.normal(0, drift_r, 3)])
        T_odom[i] = T_odom[i - 1] @ d @ geo.se3_exp(noise)
    return T_odom


def _objects_on_circle(n_objects: int) -> np.ndarray:
    """T_world_object of the objects on a 7.5 m circle, facing its centre."""
    ang = np.linspace(0, 2 * np.pi, n_objects, endpoint=False)
    obj_xyz = np.stack([7.5 * np.cos(ang), 7.5 * np.sin(ang), np.full(n_objects, 0.4)], axis=1)
    obj_R = geo.so3_exp(np.stack([np.zeros(n_objects), np.zeros(n_objects), ang + np.pi], 1))
    return geo.se3_from_rt(obj_R, obj_xyz)


def _odometry_samples(
    i: int, stamps: np.ndarray, T_odom: np.ndarray, dt_kf_ns: int, resets: set[int]
) -> list[OdometrySample]:
    """Odometry at 10 Hz up to keyframe ``i`` (within the same VIO frame); one sample at the
    keyframe itself for the first keyframe and after a reset."""
    if i == 0 or i in resets:
        return [OdometrySample(int(stamps[i]), T_odom[i].copy())]
    n_sub = max(1, dt_kf_ns // 100_000_000)
    st = [int(stamps[i - 1] + j * dt_kf_ns // n_sub) for j in range(1, n_sub + 1)]
    T, _ = geo.se3_interpolate(stamps[i - 1 : i + 1], T_odom[i - 1 : i + 1], np.array(st))
    return [OdometrySample(s, T_s) for s, T_s in zip(st, T)]


def _tag_observations(
    stamp_ns: int,
    stamps_pair: np.ndarray,
    T_true_pair: np.ndarray,
    T_obj: np.ndarray,
    rng: np.random.Generator,
    obs_sigma: tuple[float, float],
    obs_cov: np.ndarray,
    obs_range_m: float,
) -> ObservationBatch | None:
    """The noisy object poses seen (ahead, within range) at ``stamp_ns`` between two
    keyframes, or None when none is."""
    Tb, _ = geo.se3_interpolate(stamps_pair, T_true_pair, np.array([stamp_ns]))
    rel = geo.se3_between(Tb[0], T_obj)
    seen = np.flatnonzero(
        (np.linalg.norm(rel[:, :3, 3], axis=1) < obs_range_m) & (rel[:, 0, 3] > 0)
    )
    if not len(seen):
        return None
    obs = []
    for o in seen:
        noise = np.concatenate([rng.normal(0, obs_sigma[0], 3), rng.normal(0, obs_sigma[1], 3)])
        obs.append(ObjectObservation(stamp_ns, int(o), rel[o] @ geo.se3_exp(noise), obs_cov))
    return ObservationBatch(stamp_ns, tuple(obs))


def _place_deferred(events: list[Any]) -> list[Any]:
    """The events with each deferred ("after", stamp, batch) placed right after the keyframe
    that follows it."""
    out: list[Any] = []
    deferred: list[Any] = []
    for ev in events:
        if isinstance(ev, tuple):
            deferred.append(ev)
            continue
        out.append(ev)
        if isinstance(ev, Keyframe):
            while deferred and deferred[0][1] <= ev.stamp_ns:
                out.append(deferred.pop(0)[2])
    return out
