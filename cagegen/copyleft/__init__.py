"""Cage backends that load copyleft (GPL) code; optional, never imported by the core.

* :mod:`cagegen.copyleft.lazy` -- backend ``"lazy"``: Sellán et al.'s "lazy cage" (signed-distance
  offset, decimation, self-union, binary search on the offset) built from ``gpytoolbox`` (its
  ``copyleft.mesh_boolean`` is GPL; install the ``lazy`` extra: ``pip install "nestmg[lazy]"``).

Nothing here is imported eagerly: :mod:`cagegen.registry` imports a backend module the first time
its method is requested, so ``import cagegen`` works without any copyleft package installed, and a
missing one surfaces as :class:`cagegen.BackendUnavailableError` naming the package to install.
"""

__all__: list[str] = []
