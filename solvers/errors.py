"""Exception classes raised on purpose by :mod:`solvers`, and the root of every package's errors.

:class:`NestmgError` is the one root of the distribution: ``cagegen``, ``nestmg`` and ``solvers`` errors
all derive from it, so ``except NestmgError`` catches any error raised on purpose. It is defined here
because ``solvers`` is the bottom of the import graph (pure sparse linear algebra: it imports neither
``cagegen`` nor ``nestmg``, which both import it), so the root costs no upward import and no fourth
package; :mod:`cagegen.errors` re-exports it. Every ``solvers`` class derives from
:class:`SolverError`; input problems are also ``ValueError``.
"""

from __future__ import annotations


class NestmgError(Exception):
    """Base class of every error nestmg raises on purpose (bad input, failed certification, divergence...)."""


class SolverError(NestmgError, RuntimeError):
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


class OutsideCoarseMeshError(SolverError):
    """Fine nodes lie outside every tet of the first coarse mesh: the hierarchy is not nested there.

    Raised by :meth:`solvers.petsc.PetscMultigrid.from_distributed` on every MPI rank at once (the count
    is reduced over ranks), instead of extrapolating.

    Attributes
    ----------
    n_outside : int
        Fine nodes outside, summed over ranks.
    max_distance : float
        Largest distance of one of them to the coarse mesh.
    """

    def __init__(self, message: str, n_outside: int, max_distance: float):
        super().__init__(message)
        self.n_outside = int(n_outside)
        self.max_distance = float(max_distance)
