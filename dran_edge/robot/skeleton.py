"""The bounded graph's skeleton: old nodes kept, spread evenly over the whole history.

A node that leaves the recent window (it is next in the removal order) stays as a *skeleton*
node when its key is a multiple of the current ``stride``; the skeleton holds at most
``capacity`` nodes. When it is full the stride doubles and the skeleton nodes whose key is no
longer a multiple of it are evicted (removed from the graph like any node). So the skeleton always covers the whole mission with
between ``capacity / 2`` and ``capacity`` nodes, evenly spaced in node count (a dyadic thinning),
whatever the mission's length: memory stays flat. A loop or observation that refers to a long
removed keyframe attaches to the kept node nearest in time through VIO odometry; with the
skeleton that node is at most ``stride / 2`` nodes away instead of at the window's edge
(docs/notes/solve-and-bounded-graph.md, section 4, which also says why it is off by default:
it made ATE worse on the missions measured). Pure: no numpy, no clock.
"""

from __future__ import annotations


class Skeleton:
    """Which old nodes are kept, and which to evict when full (module docstring)."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self.stride = 1
        self.nodes: set[int] = set()

    def __contains__(self, node: int) -> bool:
        return node in self.nodes

    def __len__(self) -> int:
        return len(self.nodes)

    def admits(self, node: int) -> bool:
        """Whether ``node``, leaving the window, is kept as a skeleton node."""
        return self.capacity > 0 and node % self.stride == 0

    def add(self, node: int) -> list[int]:
        """Keep ``node``; returns the skeleton nodes to evict (oldest first) so that at most
        ``capacity`` remain — every node whose key is not a multiple of the doubled stride."""
        self.nodes.add(int(node))
        return self.thin(self.capacity)

    def thin(self, keep_at_most: int) -> list[int]:
        """Double the stride until at most ``keep_at_most`` (≥ 1) nodes remain; returns the
        evicted nodes, oldest first (they are no longer skeleton nodes)."""
        evicted: list[int] = []
        while len(self.nodes) > max(keep_at_most, 1):
            self.stride *= 2
            out = sorted(k for k in self.nodes if k % self.stride)
            self.nodes.difference_update(out)
            evicted += out
        return sorted(evicted)

    def discard(self, node: int) -> None:
        self.nodes.discard(node)

    def to_state(self) -> dict:
        return {"nodes": sorted(self.nodes), "stride": self.stride}

    @classmethod
    def from_state(cls, capacity: int, state: dict | None) -> Skeleton:
        s = cls(capacity)
        if state:
            s.stride = int(state["stride"])
            s.nodes = {int(k) for k in state["nodes"]}
        return s
