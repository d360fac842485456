"""The string choices of :class:`dran_edge.solver.lm.LMParams` (light: the CLI builds its
parsers from them without loading numpy)."""

from __future__ import annotations

from dran_edge.config import StrChoice


class Hessian(StrChoice):
    """The model's Hessian (see ``LMParams.hessian``)."""

    GAUSS_NEWTON = "gauss_newton"
    EXACT = "exact"


class NewtonDamping(StrChoice):
    """The exact model's damping (see ``LMParams.newton_damping``)."""

    SEPARATE = "separate"
    SHARED = "shared"


class LinearSolver(StrChoice):
    """The factorisation of A + μI (see ``LMParams.linear_solver``)."""

    SUPERLU = "superlu"
    CHOLESKY = "cholesky"
    AUTO = "auto"
