"""Events into and outputs out of one robot's pure core (docs/architecture.md).

``Agent.handle(event) -> list[output]`` is the only way into a robot's logic. Every event
carries its own timestamp (int nanoseconds, ``_ns``); the core has no clock. Poses are
float64 ``(4, 4)`` arrays; ``T_a_b`` maps frame-b points into frame a. The body frame is the
IMU frame of VINS-Mono; ``odom`` is the VIO's own world frame of the current segment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dran_edge.messages import NeighbourMessage


# --------------------------------------------------------------------------- events in
@dataclass(frozen=True, eq=False)
class OdometrySample:
    """A VIO pose at ``stamp_ns``; ``covariance`` is 6x6 over [translation, rotation] or None."""

    stamp_ns: int
    T_odom_body: np.ndarray
    covariance: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Keyframe:
    """A VIO keyframe (VINS-Mono ``keyframe_pose``); the candidate pose-graph node."""

    stamp_ns: int
    T_odom_body: np.ndarray


@dataclass(frozen=True, eq=False)
class LoopClosure:
    """A DBoW2 loop: the current keyframe in the old keyframe's body frame (``T_old_cur``)."""

    stamp_old_ns: int
    stamp_cur_ns: int
    T_old_cur: np.ndarray
    inliers: int = 0


@dataclass(frozen=True)
class VioReset:
    """The VIO restarted (or a jump/gap was detected): a new odometry segment begins."""

    stamp_ns: int
    reason: str = ""


@dataclass(frozen=True, eq=False)
class ObjectObservation:
    """One object seen at ``stamp_ns``: its pose in the body frame, 6x6 covariance [t, r]."""

    stamp_ns: int
    object_id: int
    T_body_object: np.ndarray
    covariance: np.ndarray


@dataclass(frozen=True, eq=False)
class ObservationBatch:
    """All objects of one camera frame."""

    stamp_ns: int
    observations: tuple[ObjectObservation, ...]


@dataclass(frozen=True, eq=False)
class NeighbourData:
    """A decoded, authenticated neighbour message received at ``received_ns``."""

    received_ns: int
    message: NeighbourMessage


@dataclass(frozen=True)
class Tick:
    """The round clock (2 Hz on the robot): run one DRAN round at ``stamp_ns``."""

    stamp_ns: int


Event = OdometrySample | Keyframe | LoopClosure | VioReset | ObservationBatch | NeighbourData | Tick


# --------------------------------------------------------------------------- outputs
@dataclass(frozen=True, eq=False)
class Outgoing:
    """A message for the listed neighbours; the shell encodes and sends it."""

    message: NeighbourMessage
    to: tuple[int, ...]


@dataclass(frozen=True, eq=False)
class EstimateUpdate:
    """The robot's current estimate after a round (for logs, exports and status)."""

    stamp_ns: int
    round: int
    keyframe_stamps_ns: np.ndarray
    T_world_body: np.ndarray
    object_ids: tuple[int, ...]
    T_world_object: np.ndarray
    cost: float
    step_norm_u: float
    step_norm_v: float
    consensus_error: float
    converged: bool


@dataclass(frozen=True)
class Health:
    """Counters a shell reports (status socket, STATUS=, logs)."""

    stamp_ns: int
    counters: dict


Output = Outgoing | EstimateUpdate | Health
