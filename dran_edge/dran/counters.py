"""The DRAN agent's event counters as one typed record (checkpointed with the agent).

Every field is a plain ``int``; :meth:`AgentCounters.to_dict` gives ``{name: value}`` with the
field names as keys, the keys the agent's checkpoints have always used (the former ``dict`` of
counters wrote ``idle_rounds``, ``sor_rejected`` and ``obs_corroborated`` only once they had
been set; every key is written now). :meth:`AgentCounters.update` reads such a dict back (keys
it does not know are ignored; missing ones keep their value, so checkpoints written before a
counter existed still load).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass


@dataclass
class AgentCounters:
    """What one robot's agent has done and seen since it started (or was restored)."""

    rounds: int = 0
    """Ticks handled (rounds of Alg. 1, idle turns of the colour schedule included)."""
    accepted: int = 0
    """Local steps that decreased L̂_i and were kept."""
    rejected: int = 0
    """Rounds whose every damped trial failed to decrease L̂_i (the estimate was kept)."""
    linear_fail: int = 0
    """Damped trials whose linear system could not be solved (μ grew)."""
    stale_dropped: int = 0
    """Separator or object entries older than the one already held (dropped)."""
    objects_adopted: int = 0
    """Objects first heard of from a neighbour and adopted (Alg. 1, lines 3–8)."""
    unhandled_events: int = 0
    """Events of a type the agent does not handle."""
    obs_gated: int = 0
    """Own object observations dropped by the consistency gate (object_gate_m)."""
    obs_rejected: int = 0
    """Own observations the cross-robot association check drops this round."""
    consensus_conflicts: int = 0
    """Consensus pairs under the conflict kernel, summed over rounds."""
    obs_exclusion_clear: int = 0
    """Lone views used at once because no other object's view shares their place."""
    obs_shadowed: int = 0
    """Views held back because another object with as many views was seen at their place."""
    obs_pending: int = 0
    """Views held back until a neighbour's copy corroborates them."""
    obs_corroborated: int = 0
    """Held-back views in use this round (corroborated by a neighbour's copy, or latched)."""
    idle_rounds: int = 0
    """Rounds that were not this robot's turn in the colour schedule."""
    sor_rejected: int = 0
    """Over-relaxed steps undone because they raised L̂_i (sor_omega ≠ 1)."""

    def to_dict(self) -> dict[str, int]:
        """``{field name: value}`` (what checkpoints store)."""
        return dataclasses.asdict(self)

    def update(self, data: Mapping[str, int]) -> None:
        """Set the counters ``data`` names (a :meth:`to_dict`; unknown names are ignored)."""
        for f in dataclasses.fields(self):
            if f.name in data:
                setattr(self, f.name, int(data[f.name]))
