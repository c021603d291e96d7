"""Exception classes shared by every cage backend and the verifier.

:class:`NestmgError`, the root of every error the distribution raises on purpose, lives in
:mod:`solvers.errors` (the bottom of the import graph: it imports nothing of ours) and is re-exported
here; this is cagegen's only import from ``solvers``.
"""

from __future__ import annotations

from solvers.errors import NestmgError

__all__ = ["BackendUnavailableError", "CageError", "CageOptionError", "CageTypeError", "LevelsError", "MeshInputError", "NestmgError",
           "UnknownMethodError"]


class MeshInputError(NestmgError, ValueError):
    """The input surface is not a closed, manifold, single-piece, finite, non-degenerate triangle mesh."""


class CageError(NestmgError, RuntimeError):
    """A cage layer could not be built or could not be certified.

    Attributes
    ----------
    layer : int or None
        Index of the failing layer (0 = input surface, 1 = first cage, ...).
    reason : str
        Human readable explanation.
    """

    def __init__(self, message: str, layer: int | None = None, reason: str | None = None):
        super().__init__(message)
        self.layer = layer
        self.reason = reason if reason is not None else message


class BackendUnavailableError(NestmgError, ImportError):
    """A cage backend needs an optional dependency that is not installed."""


class UnknownMethodError(NestmgError, ValueError):
    """No cage backend is registered under the requested method name."""


class LevelsError(NestmgError, ValueError):
    """The requested hierarchy (number of levels, face counts) cannot be built from this input."""


class CageOptionError(NestmgError, ValueError):
    """An option of a cage backend, the verifier or a geometry helper has an invalid value (raised before any work)."""


class CageTypeError(CageOptionError, TypeError):
    """An argument of a cagegen function has the wrong type (also a ``TypeError``, as Python's own)."""
