"""Foxglove messages of the robots' estimates (numpy in, ``foxglove.messages`` out).

Topics (the same live and in MCAP files, docs/viz.md)::

    /<robot>/path       PosesInFrame  the robot's keyframe trajectory (frame "world")
    /<robot>/objects    SceneUpdate   its object map: a cube and a label per object
    /<robot>/stats      JSON          round statistics and neighbour links
    /mocap/<robot>      PosesInFrame  ground truth of the robot's path (files of runs only)
    /mocap/objects      SceneUpdate   ground truth of the objects (files of runs only)
    /links              SceneUpdate   communication links between the robots' last positions

``foxglove`` is imported here only; callers import this module lazily (an optional extra).
"""

from __future__ import annotations

import numpy as np

from dran_edge import geometry as geo

FRAME = "world"
OBJECT_SIZE_M = 0.4
#: Distinct colours per robot (RGBA), cycled.
PALETTE = (
    (0.12, 0.47, 0.71),
    (1.0, 0.5, 0.05),
    (0.17, 0.63, 0.17),
    (0.84, 0.15, 0.16),
    (0.58, 0.4, 0.74),
    (0.55, 0.34, 0.29),
    (0.89, 0.47, 0.76),
    (0.5, 0.5, 0.5),
)

STATS_SCHEMA = {
    "type": "object",
    "properties": {
        "round": {"type": "integer"},
        "cost": {"type": "number"},
        "consensus_error": {"type": "number"},
        "converged": {"type": "boolean"},
        "keyframes": {"type": "integer"},
        "objects": {"type": "integer"},
        "neighbours": {"type": "object"},
    },
}


def stamp(t_ns: int):
    from foxglove.messages import Timestamp

    t_ns = int(t_ns)
    return Timestamp(sec=t_ns // 1_000_000_000, nsec=t_ns % 1_000_000_000)


def pose(T: np.ndarray):
    from foxglove.messages import Pose, Quaternion, Vector3

    a = geo.se3_to_xyz_quat_xyzw(np.asarray(T, np.float64))
    return Pose(
        position=Vector3(x=float(a[0]), y=float(a[1]), z=float(a[2])),
        orientation=Quaternion(x=float(a[3]), y=float(a[4]), z=float(a[5]), w=float(a[6])),
    )


def colour(k: int, alpha: float = 1.0):
    from foxglove.messages import Color

    r, g, b = PALETTE[k % len(PALETTE)]
    return Color(r=r, g=g, b=b, a=alpha)


def path_message(t_ns: int, T_world_body: np.ndarray):
    """The trajectory (N x 4 x 4, in time order) as one PosesInFrame."""
    from foxglove.messages import PosesInFrame

    return PosesInFrame(
        timestamp=stamp(t_ns), frame_id=FRAME, poses=[pose(T) for T in np.asarray(T_world_body)]
    )


def objects_message(
    t_ns: int, owner: str, k: int, object_ids, T_world_object: np.ndarray, alpha: float = 0.6
):
    """An object map as a SceneUpdate: one entity ``<owner>/<id>`` (cube + label) per object."""
    from foxglove.messages import (
        CubePrimitive,
        SceneEntity,
        SceneUpdate,
        TextPrimitive,
        Vector3,
    )

    ents = []
    for oid, T in zip(object_ids, np.asarray(T_world_object)):
        p = pose(T)
        ents.append(
            SceneEntity(
                timestamp=stamp(t_ns),
                frame_id=FRAME,
                id=f"{owner}/{int(oid)}",
                cubes=[
                    CubePrimitive(
                        pose=p,
                        size=Vector3(x=OBJECT_SIZE_M, y=OBJECT_SIZE_M, z=OBJECT_SIZE_M),
                        color=colour(k, alpha),
                    )
                ],
                texts=[
                    TextPrimitive(
                        pose=p,
                        billboard=True,
                        font_size=14.0,
                        scale_invariant=True,
                        color=colour(k),
                        text=f"{owner}:{int(oid)}",
                    )
                ],
            )
        )
    return SceneUpdate(entities=ents)


def links_message(t_ns: int, positions: dict[str, np.ndarray], edges: list[tuple[str, str]]):
    """Communication links as lines between the robots' given positions (3-vectors)."""
    from foxglove.messages import (
        Color,
        LinePrimitive,
        LinePrimitiveLineType,
        Point3,
        SceneEntity,
        SceneUpdate,
    )

    lines = []
    for a, b in edges:
        if a in positions and b in positions:
            pa, pb = positions[a], positions[b]
            lines.append(
                LinePrimitive(
                    type=LinePrimitiveLineType.LineList,
                    thickness=2.0,
                    scale_invariant=True,
                    points=[
                        Point3(x=float(pa[0]), y=float(pa[1]), z=float(pa[2])),
                        Point3(x=float(pb[0]), y=float(pb[1]), z=float(pb[2])),
                    ],
                    color=Color(r=0.3, g=0.3, b=0.3, a=0.8),
                )
            )
    return SceneUpdate(
        entities=[SceneEntity(timestamp=stamp(t_ns), frame_id=FRAME, id="links", lines=lines)]
    )
