"""Typed neighbour messages: what one robot's agent tells its neighbours (docs/architecture.md; on the wire: docs/wire-format.md).

The agent emits and consumes these; ``dran_edge.comms.codec`` turns them into
self-contained, authenticated datagrams and back. Poses are ``(4, 4)`` SE(3) or ``(3, 3)``
SE(2) float64 arrays in the fleet's common world frame. Nothing here does I/O.

Entry kinds
-----------
- ``SeparatorEntry``: a pose of the sender's trajectory that a neighbour's inter-robot
  measurement touches (paper Sec. 3.1, edge-based decoupling). Neighbours hold it fixed
  as an anchor in their ``f_inter`` for the next round.
- ``ObjectEntry``: the sender's current estimate of a public object (vertex-based
  decoupling) — its own local copy ``y_i`` or one it relays (``hop_count`` > 0,
  paper Sec. 4.2.2 dynamic map consensus).
- ``InitEntry``: a value of the two-stage distributed chordal initialisation
  (Sec. 4.2.1): stage ``ROTATION`` carries an unconstrained ``d x d`` relaxed rotation,
  stage ``TRANSLATION`` a pose whose rotation is already fixed.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np


class InitStage(enum.IntEnum):
    ROTATION = 1
    TRANSLATION = 2
    #: Warm-start frames (``linear_stage.LinearStage.frame_update``): a robot's whole-segment
    #: transform instead of its separators. ROTATION_FRAME: the d x d matrix G (X_v = X̂_v G);
    #: TRANSLATION_FRAME: a pose with identity rotation whose translation is the offset s
    #: (X_v = X̂_v + s). ``keyframe_id`` is 0.
    ROTATION_FRAME = 3
    TRANSLATION_FRAME = 4
    #: Substructuring (``dran_edge.dran.substructure``): chunks of d x d floats of a robot's
    #: condensed system (boundary ids, right-hand side, upper triangle of S_r), sent up the
    #: robot tree; ``owner_robot`` is the robot whose system it is, ``keyframe_id`` the chunk.
    ROTATION_SCHUR = 5
    TRANSLATION_SCHUR = 6
    #: Exact Gauss–Newton refinement (``dran_edge.dran.exact_gn``), d x d floats each:
    #: REFINE_SCHUR: chunks of a robot's condensed damped Gauss–Newton system and its cost
    #: scalars, up the robot tree (as the SCHUR stages); REFINE_STEP: the step of one boundary
    #: vertex (``keyframe_id``; its dof tangent values first, row-major, zero-padded) down the
    #: tree; REFINE_CONTROL: the root's decision (``keyframe_id`` 0), down the tree.
    REFINE_SCHUR = 7
    REFINE_STEP = 8
    REFINE_CONTROL = 9
    #: Selective-repeat acknowledgement (``dran_edge.comms.arq``): no value; ``keyframe_id``
    #: is the first sequence number of a run of the recipient's datagrams the sender of the
    #: ack received, ``owner_robot`` the run's length (≥ 1).
    ARQ_ACK = 10
    #: The refinement's iterative interface solve (``dran_edge.dran.interface_pcg``), d x d
    #: chunks of one packed float vector as the SCHUR stages: REFINE_PCG_UP a robot's vector
    #: up the robot tree (``owner_robot`` the robot it is from), REFINE_PCG_DOWN the root's
    #: vector for one robot down the tree (``owner_robot`` the robot it is for).
    REFINE_PCG_UP = 11
    REFINE_PCG_DOWN = 12

    @property
    def valueless(self) -> bool:
        """True when the entry carries no value on the wire (its id fields say it all)."""
        return self is InitStage.ARQ_ACK

    @property
    def matrix_valued(self) -> bool:
        """True when the value is a d x d matrix (else a pose)."""
        return not self.valueless and (
            self
            in (
                InitStage.ROTATION,
                InitStage.ROTATION_FRAME,
                InitStage.ROTATION_SCHUR,
                InitStage.TRANSLATION_SCHUR,
            )
            or not self.delta_allowed
        )

    @property
    def delta_allowed(self) -> bool:
        """False for the refinement stages: their values always travel absolute (float32),
        never as quantised deltas (a condensed system needs every digit float32 keeps)."""
        return self not in (
            InitStage.REFINE_SCHUR,
            InitStage.REFINE_STEP,
            InitStage.REFINE_CONTROL,
            InitStage.REFINE_PCG_UP,
            InitStage.REFINE_PCG_DOWN,
            InitStage.ARQ_ACK,
        )


@dataclass(frozen=True, eq=False)
class SeparatorEntry:
    owner_robot: int
    keyframe_id: int
    stamp_ns: int
    T_world_body: np.ndarray


@dataclass(frozen=True, eq=False)
class ObjectEntry:
    object_id: int
    T_world_object: np.ndarray
    origin_robot: int
    hop_count: int = 0
    #: own observations of the object that ``origin_robot`` uses (≥ 1 for a copy built from
    #: observations; relays forward their origin's count; 0 for a bare estimate that no
    #: observation in use stands behind): the weight of this copy's vote in the cross-robot
    #: association check (docs/dran.md, robustness)
    support: int = 1


@dataclass(frozen=True, eq=False)
class InitEntry:
    stage: InitStage
    owner_robot: int
    keyframe_id: int
    #: ROTATION: (d, d) relaxed rotation (not necessarily orthonormal);
    #: TRANSLATION: (d+1, d+1) pose with the stage-1 rotation and the current translation.
    value: np.ndarray


@dataclass(frozen=True, eq=False)
class NeighbourMessage:
    """One robot's message to its neighbours for one round (may span several datagrams)."""

    sender_id: int
    round: int
    stamp_ns: int
    separators: tuple[SeparatorEntry, ...] = ()
    objects: tuple[ObjectEntry, ...] = ()
    init: tuple[InitEntry, ...] = ()
    #: The sender's done counter (docs/notes/stopping-rule.md): 0 while its own stopping test
    #: fails, else one more than the smallest counter it holds from its neighbours (saturating
    #: at 255). None: not carried (no stop-status flag on the wire).
    done_count: int | None = None
    #: Filled by the codec on decode (None on messages the agent builds).
    fleet_id: int | None = None
    boot_epoch: int | None = None
    sequence: int | None = None
    extra: dict = field(default_factory=dict)

    @property
    def dim(self) -> int | None:
        """2 or 3 from the first pose carried, None for an empty message."""
        if self.separators:
            return int(self.separators[0].T_world_body.shape[-1]) - 1
        if self.objects:
            return int(self.objects[0].T_world_object.shape[-1]) - 1
        return None
