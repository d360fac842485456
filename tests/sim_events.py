"""One simulated robot's ingest events, time-ordered: shared by the RobotCore tests."""

from __future__ import annotations

import numpy as np

from dran_edge.sim import mission as sim
from dran_edge.events import (
    Keyframe,
    LoopClosure,
    ObjectObservation,
    ObservationBatch,
    OdometrySample,
)


def single_robot_events(seed: int):
    """(mission, robot, [(stamp_ns, order, event)]) of a 60 s one-robot mission with 4 objects,
    no VIO resets and no wrong loops; ties at a stamp ordered odometry, keyframe, loop, batch."""
    p = sim.SimParams(
        robots=1,
        objects=4,
        duration_s=60.0,
        arena_m=6.0,
        seed=seed,
        resets_per_min=0.0,
        loop_outlier_fraction=0.0,
    )
    m = sim.generate_mission(p)
    r = m.robots[0]
    events = [
        (int(s), 1, OdometrySample(int(s), T)) for s, T in zip(r.odom_stamps_ns, r.T_odom_body)
    ]
    kf_s = r.odom_stamps_ns[r.keyframes]
    events += [
        (int(kf_s[i]), 2, Keyframe(int(kf_s[i]), r.T_odom_body[k]))
        for i, k in enumerate(r.keyframes.tolist())
    ]
    events += [
        (int(kf_s[c]), 3, LoopClosure(int(kf_s[o]), int(kf_s[c]), T))
        for (o, c), T in zip(r.loops.tolist(), r.loop_T_old_cur)
    ]
    for stamp, obs in sim.direct_observations(m, r, np.random.default_rng(0)):
        events.append(
            (
                stamp,
                4,
                ObservationBatch(
                    stamp, tuple(ObjectObservation(stamp, oid, T, C) for oid, T, C in obs)
                ),
            )
        )
    events.sort(key=lambda e: (e[0], e[1]))
    return m, r, events
