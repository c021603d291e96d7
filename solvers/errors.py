"""Exception classes raised on purpose by :mod:`solvers`.

`solvers` is pure sparse linear algebra and must not import `cagegen`, so it has its own small
hierarchy. Every class derives from :class:`SolverError`; input problems are also ``ValueError``.
"""

from __future__ import annotations


class SolverError(RuntimeError):
    """Base class of every error the :mod:`solvers` package raises on purpose."""


class SolverInputError(SolverError, ValueError):
    """An argument has the wrong shape, dtype, size, or contains NaN/inf."""


class IncompatibleRHSError(SolverError, ValueError):
    """A singular (pure Neumann) system was given a right-hand side outside the operator's range.

    For a symmetric operator whose null space is the constants, ``b`` is compatible iff
    ``sum(b) == 0`` (up to round-off). Pass ``project=True`` to project ``b`` instead.
    """


class DivergenceError(SolverError):
    """An iteration produced NaN/inf or a residual that grew past the divergence tolerance.

    Attributes
    ----------
    cycle : int
        1-based index of the cycle (or Krylov iteration) where the problem was detected.
    level : int or None
        Level on which a non-finite value first appeared (0 = finest), when it could be located.
    residuals : list of float
        Relative residual history up to the failure.
    """

    def __init__(self, message: str, cycle: int, level: int | None = None, residuals=None):
        super().__init__(message)
        self.cycle = cycle
        self.level = level
        self.residuals = list(residuals) if residuals is not None else []


class InsufficientMemoryError(SolverError, MemoryError):
    """A structure would not fit in the memory available; raised *before* allocating it.

    Attributes
    ----------
    needed : int
        Estimated bytes (an upper bound).
    available : int
        Bytes available (``$NESTMG_MEMORY_LIMIT`` or the system's available memory).
    """

    def __init__(self, message: str, needed: int, available: int):
        super().__init__(message)
        self.needed = int(needed)
        self.available = int(available)
