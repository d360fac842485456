"""A pose graph stored as arrays: variables of three kinds and blocks of factors.

Variables are indexed 0..n−1; their values live outside the graph in one ``(n, D, D)`` pose array
(D = 4 for SE(3), 3 for SE(2)), so the same structure serves many linearisation points. Each
variable is

- ``PRIVATE`` — eliminated first by the Schur complement (paper: trajectory poses ``x_i``, tangent
  ``u``),
- ``PUBLIC`` — kept in the reduced system (paper: object copies ``y_i``, tangent ``v``), or
- ``FIXED`` — a constant: gauge anchors, g2o FIX vertices, a neighbour's separator in f_inter.

The partition is general: which variables are public is the caller's choice. Factors are blocks
implementing :class:`dran_edge.solver.factors.Factor`; adding a new factor type needs no change here.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import IntEnum

import numpy as np

from dran_edge.solver.factors import Factor


class VariableKind(IntEnum):
    PRIVATE = 0
    PUBLIC = 1
    FIXED = 2


@dataclass(frozen=True, eq=False)
class PoseGraph:
    """Structure of a pose-graph problem (values are a separate ``(n, D, D)`` array)."""

    dim: int
    """2 for SE(2), 3 for SE(3)."""
    kinds: np.ndarray
    """(n,) int8 :class:`VariableKind` of each variable."""
    factors: tuple[Factor, ...] = field(default_factory=tuple)
    """Factor blocks; each block's ``variables`` index into 0..n−1."""

    def __post_init__(self) -> None:
        if self.dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {self.dim}")
        kinds = np.asarray(self.kinds, dtype=np.int8)
        if kinds.ndim != 1 or np.any((kinds < 0) | (kinds > 2)):
            raise ValueError("kinds must be a 1-D array of VariableKind values")
        object.__setattr__(self, "kinds", kinds)
        n = kinds.shape[0]
        for block in self.factors:
            v = np.asarray(block.variables)
            if v.ndim != 2 or (v.size and (v.min() < 0 or v.max() >= n)):
                raise ValueError(
                    f"factor block {getattr(block, 'label', type(block).__name__)!r} indexes "
                    f"variables outside 0..{n - 1}"
                )

    @property
    def num_variables(self) -> int:
        return int(self.kinds.shape[0])

    @property
    def dof(self) -> int:
        """Tangent size of one variable: 6 (SE(3)) or 3 (SE(2))."""
        return 6 if self.dim == 3 else 3

    @property
    def pose_size(self) -> int:
        """D: poses are (D, D) matrices."""
        return self.dim + 1

    def with_factors(self, *blocks: Factor) -> PoseGraph:
        """A copy with ``blocks`` appended."""
        return replace(self, factors=self.factors + tuple(blocks))

    def with_kinds(self, kinds: np.ndarray) -> PoseGraph:
        """A copy with another variable partition."""
        return replace(self, kinds=np.asarray(kinds, dtype=np.int8))


def kinds_array(
    n: int, public: np.ndarray | None = None, fixed: np.ndarray | None = None
) -> np.ndarray:
    """(n,) kinds: PRIVATE everywhere except the indices (or boolean masks) given."""
    kinds = np.full(n, VariableKind.PRIVATE, dtype=np.int8)
    if public is not None:
        kinds[public] = VariableKind.PUBLIC
    if fixed is not None:
        kinds[fixed] = VariableKind.FIXED
    return kinds
