"""Errors nestmg raises on purpose, all under the package-wide root :class:`NestmgError`.

The root is defined once in :mod:`solvers.errors` (the bottom of the import graph: ``solvers`` imports
neither ``cagegen`` nor ``nestmg``) and re-exported by :mod:`cagegen.errors`, so ``except NestmgError``
catches cage, meshing, input and solver errors alike. Input errors are also ``ValueError``.
"""

from __future__ import annotations

from cagegen.errors import NestmgError

__all__ = ["NestmgError", "NestmgInputError"]


class NestmgInputError(NestmgError, ValueError):
    """An argument of a nestmg function is invalid: a value out of range, an unknown name, a wrong shape.

    Raised before any work. Errors of the input *mesh* are :class:`cagegen.MeshInputError`; of the
    requested number of levels, :class:`cagegen.LevelsError`.
    """
