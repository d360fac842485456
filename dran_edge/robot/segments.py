"""Odometry segments: where one VIO world frame ends and the next begins (docs/vins-mono.md).

VINS-Mono resets silently: after ``failureDetection()`` or an image gap the estimator clears
its state and re-initialises in a new world frame near the origin. The bridge forwards
``/feature_tracker/restart`` as a reset record, but an estimator failure without an image gap
publishes nothing. So a new segment starts on

- a reset record (``VioReset``),
- a stamp gap between consecutive odometry samples longer than ``segment_gap_s``,
- a jump between consecutive samples: translation > ``segment_jump_m`` or rotation >
  ``segment_jump_rad`` (a Dingo moves ~0.1 m between 15 Hz samples; a reset jumps to the origin).

Odometry edges are only ever built between keyframes of the same segment; segments are tied
together by loops and object observations. Keyframes arrive late (VINS publishes the keyframe of
window index WINDOW_SIZE-2), so a keyframe is assigned to the segment active at its own stamp.
Pure: no clock, no I/O.
"""

from __future__ import annotations

import bisect

import numpy as np

from dran_edge import geometry as geo
from dran_edge.config import GraphBounds

MAX_BOUNDARIES = 256


class Segmenter:
    """Tracks segment boundaries from the odometry stream and reset markers."""

    def __init__(self, bounds: GraphBounds):
        self.bounds = bounds
        self.starts_ns: list[int] = []  # start stamp of each kept segment (increasing)
        self.ids: list[int] = []  # segment id of each kept start
        self.reasons: list[str] = []
        self.next_id = 0
        self.last_stamp_ns: int | None = None
        self.last_T: np.ndarray | None = None
        self.stale_samples = 0

    @property
    def current(self) -> int:
        """Id of the newest segment (-1 before any data)."""
        return self.ids[-1] if self.ids else -1

    def _start(self, stamp_ns: int, reason: str) -> int:
        sid = self.next_id
        self.next_id += 1
        if self.starts_ns and stamp_ns <= self.starts_ns[-1]:
            stamp_ns = self.starts_ns[-1] + 1  # keep boundaries strictly increasing
        self.starts_ns.append(int(stamp_ns))
        self.ids.append(sid)
        self.reasons.append(reason)
        if len(self.starts_ns) > MAX_BOUNDARIES:
            del self.starts_ns[0], self.ids[0], self.reasons[0]
        return sid

    def reset(self, stamp_ns: int, reason: str = "reset") -> int:
        """A reset marker: a new segment from ``stamp_ns``; returns its id."""
        self.last_stamp_ns = None
        self.last_T = None
        return self._start(stamp_ns, reason or "reset")

    def odometry(self, stamp_ns: int, T_odom_body: np.ndarray) -> tuple[int, str | None]:
        """Feed one odometry sample; returns (segment id, reason if a new segment started).

        A sample not newer than the previous one (or older than the newest segment's start) is
        stale (counted, segment unchanged, and the
        caller should ignore it): returns (current, None).
        """
        b = self.bounds
        reason = None
        if (self.last_stamp_ns is not None and stamp_ns <= self.last_stamp_ns) or (
            self.starts_ns and stamp_ns < self.starts_ns[-1]
        ):
            self.stale_samples += 1
            return self.current, None
        if not self.ids:
            reason = "first odometry"
        elif self.last_stamp_ns is not None:
            gap_s = (stamp_ns - self.last_stamp_ns) * 1e-9
            assert self.last_T is not None  # set with last_stamp_ns
            d = geo.se3_between(self.last_T, T_odom_body)
            jump_m = float(np.linalg.norm(d[:3, 3]))
            jump_rad = float(geo.so3_angle(d[:3, :3]))
            if gap_s > b.segment_gap_s:
                reason = f"odometry gap {gap_s:.2f} s"
            elif jump_m > b.segment_jump_m:
                reason = f"odometry jump {jump_m:.2f} m"
            elif jump_rad > b.segment_jump_rad:
                reason = f"odometry jump {jump_rad:.2f} rad"
        if reason is not None:
            self._start(stamp_ns, reason)
        self.last_stamp_ns = int(stamp_ns)
        self.last_T = np.array(T_odom_body, dtype=np.float64)
        return self.current, reason

    def segment_at(self, stamp_ns: int) -> int:
        """The segment active at ``stamp_ns`` (the oldest kept one for older stamps)."""
        if not self.ids:
            return -1
        i = bisect.bisect_right(self.starts_ns, stamp_ns) - 1
        return self.ids[max(i, 0)]

    def to_state(self) -> dict:
        return {
            "starts_ns": np.array(self.starts_ns, dtype=np.int64),
            "ids": np.array(self.ids, dtype=np.int64),
            "reasons": list(self.reasons),
            "next_id": self.next_id,
            "last_stamp_ns": self.last_stamp_ns,
            "last_T": self.last_T,
            "stale_samples": self.stale_samples,
        }

    @classmethod
    def from_state(cls, bounds: GraphBounds, state: dict) -> Segmenter:
        s = cls(bounds)
        s.starts_ns = [int(v) for v in state["starts_ns"]]
        s.ids = [int(v) for v in state["ids"]]
        s.reasons = [str(v) for v in state["reasons"]]
        s.next_id = int(state["next_id"])
        s.last_stamp_ns = None if state["last_stamp_ns"] is None else int(state["last_stamp_ns"])
        last_T = state["last_T"]
        s.last_T = None if last_T is None else np.asarray(last_T, dtype=np.float64)
        s.stale_samples = int(state["stale_samples"])
        return s
