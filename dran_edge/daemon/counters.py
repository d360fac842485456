"""The daemon's typed counters: what it counts, under the key names status, checkpoints and the
rehearsal report have always used.

``DaemonCounters`` is the daemon's own record (checkpointed, so it survives restarts),
``IngestCounters`` the ingest server's (live only), ``TickStats`` the tick timing. Every record
serialises with ``as_dict()`` to a flat ``{key: int}`` mapping; every field is present (zero until
counted).
"""

from __future__ import annotations

import collections
import logging
from dataclasses import dataclass, field, fields

log = logging.getLogger(__name__)

#: Prefix of the per-event-type counts in the serialised form: ``applied_ObservationBatch``...
APPLIED_PREFIX = "applied_"


def _int_fields(obj: object) -> dict[str, int]:
    return {
        f.name: int(getattr(obj, f.name))
        for f in fields(obj)  # type: ignore[arg-type]
        if f.type in ("int", int)
    }


@dataclass
class DaemonCounters:
    """What the daemon counted since its first start (restored from the checkpoint)."""

    #: journalled records re-applied at start (not in the checkpoint)
    recovered_records: int = 0
    #: observation batches that did not encode as ingest records (dropped)
    observations_unencodable: int = 0
    #: live-view publishes that raised
    live_view_errors: int = 0
    #: outgoing messages with no transport configured (dropped)
    outgoing_without_transport: int = 0
    messages_sent: int = 0
    #: message and heartbeat sends that raised
    send_errors: int = 0
    heartbeats_sent: int = 0
    window_save_errors: int = 0
    window_saves: int = 0
    watchdog_pings: int = 0
    checkpoint_errors: int = 0
    checkpoints: int = 0
    #: size of the last checkpoint written
    checkpoint_bytes: int = 0
    #: journalled records applied to the core, per event type name (``applied_<Type>``)
    applied: collections.Counter = field(default_factory=collections.Counter)

    def as_dict(self) -> dict[str, int]:
        """The flat form of status and checkpoint: every field, then ``applied_<Type>``."""
        out = _int_fields(self)
        out.update({APPLIED_PREFIX + name: int(n) for name, n in sorted(self.applied.items())})
        return out

    @classmethod
    def from_dict(cls, saved: dict) -> DaemonCounters:
        """Back from ``as_dict()`` (a checkpoint's ``counters``); unknown keys are logged and
        dropped, missing ones are zero."""
        c = cls()
        known = set(_int_fields(c))
        for key, value in saved.items():
            if key in known:
                setattr(c, key, int(value))
            elif key.startswith(APPLIED_PREFIX):
                c.applied[key[len(APPLIED_PREFIX) :]] = int(value)
            else:
                log.warning("checkpoint counter %r is not a daemon counter; dropped", key)
        return c


@dataclass
class IngestCounters:
    """The ingest server's counts (plain ints, written by its thread, safe to read elsewhere)."""

    #: bytes received from clients
    bytes: int = 0
    #: framed records handed on (non-frame records)
    records: int = 0
    #: forwarded camera frames
    frames: int = 0
    #: records that did not decode (by reason in ``IngestServer.rejected``)
    rejected: int = 0
    clients_accepted: int = 0
    clients_refused: int = 0
    #: unexpected errors in the server's thread (it went on)
    handler_errors: int = 0

    def as_dict(self) -> dict[str, int]:
        return _int_fields(self)


@dataclass
class TickStats:
    """Tick timing: lag against the absolute deadline and duration of the round."""

    ticks: int = 0
    late: int = 0
    missed: int = 0
    lag_max_s: float = 0.0
    lag_last_s: float = 0.0
    round_last_s: float = 0.0
    round_max_s: float = 0.0
    round_total_s: float = 0.0
    agent_errors: int = 0
    durations: collections.deque = field(default_factory=lambda: collections.deque(maxlen=120))

    def as_dict(self) -> dict:
        return {
            "ticks": self.ticks,
            "late": self.late,
            "missed": self.missed,
            "lag_max_s": self.lag_max_s,
            "lag_last_s": self.lag_last_s,
            "solve_last_s": self.round_last_s,
            "solve_max_s": self.round_max_s,
            "solve_mean_s": self.round_total_s / self.ticks if self.ticks else 0.0,
            "agent_errors": self.agent_errors,
        }
