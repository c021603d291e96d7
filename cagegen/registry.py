"""Backend registry: name -> :class:`BackendSpec`, backends imported lazily (like trimesh's boolean engines).

A backend registers one of two functions, and its options class (:mod:`cagegen.options`, a frozen
dataclass, imported eagerly: it has no optional dependency):

* a **per-layer** function (``BackendSpec.layer=True``; ``decimate``, ``sdf``, ``lazy``) ::

      layer(V, F, n_faces, *, unit, **opts) -> (U, G, info)

  one cage with ``n_faces`` faces around the closed surface ``(V, F)`` (the previous layer); ``unit`` is
  the input's bounding-box diagonal, the length that relative options refer to on every layer.
  :func:`cagegen.build_cages` owns the loop over the layers, the progress lines and the info keys. An
  optional ``schedule(V, F, face_counts, *, t0, **opts) -> [dict per layer]`` checks the whole run
  before any layer is built (``sdf``: even face counts, the time budget of all the layers) and returns
  each layer's extra keywords (``sdf``: its deadline);
* a **whole-hierarchy** function, for a backend that needs its own loop (``own_loop`` says why:
  ``nested``'s recovery nests intermediate layers, ``skeleton``'s outer cage is built around the nested
  layers) ::

      backend(V, F, face_counts, **opts) -> (layers, info)

  ``layers`` are the cages only, finest first; ``info`` a JSON-serialisable dict of the backend's figures.

``V`` (n,3) float64, ``F`` (m,3) int64 is the closed input, audited once by :func:`cagegen.build_cages`
(no backend audits it again). ``opts`` are the fields of the options class
but its common ones (:meth:`CageOptions.backend_kwargs`), validated before the backend is called. The
keywords :func:`cagegen.build_cages` adds are declared in ``BackendSpec.takes`` (no signature
inspection): ``progress`` (a callable), ``min_gap`` (the clearance the verifier will demand, which the
backend must build) and ``certify`` (False: the backend's own certification is skipped, the whole
hierarchy is verified once afterwards).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass

from .errors import BackendUnavailableError, CageTypeError, UnknownMethodError
from .options import CageOptions, DecimateOptions, LazyOptions, NestedOptions, SdfOptions, SkeletonOptions

#: the keywords :func:`cagegen.build_cages` may pass besides the options
TAKES = frozenset({"progress", "min_gap", "certify"})


@dataclass(frozen=True)
class BackendSpec:
    """How :func:`cagegen.build_cages` drives one backend.

    Attributes
    ----------
    target : str or callable
        ``"module:function"`` (imported on first use, so optional dependencies stay optional) or the
        function itself: the per-layer function if ``layer``, else the whole-hierarchy one.
    options : type
        Options class (a :class:`cagegen.CageOptions` subclass).
    layer : bool
        ``target`` builds one layer; :func:`cagegen.build_cages` loops.
    takes : frozenset of str
        Keywords of :data:`TAKES` the function accepts.
    own_loop : str
        Why a whole-hierarchy backend loops itself ("" for per-layer backends).
    schedule : str or callable, optional
        Per-layer backends: the run's plan, ``schedule(V, F, face_counts, *, t0, **opts)`` (the same
        keywords as the layer function) -> one dict per layer of keywords that override them.
    budget : str or callable, optional
        The run's time-budget check, ``budget(n_faces, face_counts, **opts) -> estimated seconds``:
        :func:`cagegen.build_cages` calls it on the input's face count *before* the input audit (whose exact
        self-intersection test takes seconds to a minute at 200-350k faces); it raises :class:`CageError`
        (``reason="time budget"``) when the estimate exceeds the options' ``cage_time_budget``.
    """

    target: str | Callable
    options: type[CageOptions] = CageOptions
    layer: bool = False
    takes: frozenset = frozenset()
    own_loop: str = ""
    schedule: str | Callable | None = None
    budget: str | Callable | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.options, type) and issubclass(self.options, CageOptions)):
            raise CageTypeError(f"options must be a subclass of cagegen.CageOptions, got {self.options!r}")
        if not set(self.takes) <= TAKES:
            raise CageTypeError(f"takes must be a subset of {sorted(TAKES)}, got {sorted(self.takes)}")


_BACKENDS: dict[str, BackendSpec | str | Callable] = {
    "decimate": BackendSpec("cagegen.decimate:decimate_layer", DecimateOptions, layer=True),
    "nested": BackendSpec("cagegen.nested:nested_backend", NestedOptions,
                          takes=frozenset({"progress", "min_gap", "certify"}),
                          own_loop="recovery: a failing layer is rebuilt through intermediate layers nested "
                                   "into each other, then a fallback",
                          budget="cagegen.nested.backend:budget_check"),
    "lazy": BackendSpec("cagegen.copyleft.lazy:lazy_layer", LazyOptions, layer=True,
                        takes=frozenset({"min_gap"})),
    "sdf": BackendSpec("cagegen.sdf:sdf_cage_layer", SdfOptions, layer=True, takes=frozenset({"min_gap"}),
                       schedule="cagegen.sdf:sdf_schedule", budget="cagegen.sdf.backend:budget_check"),
    "skeleton": BackendSpec("cagegen.skeleton:skeleton_backend", SkeletonOptions,
                            takes=frozenset({"progress", "min_gap", "certify"}),
                            own_loop="the finer layers are nested cages; the skeleton cage is inflated "
                                     "around the coarsest of them"),
}


def backend_spec(name: str) -> BackendSpec:
    """The :class:`BackendSpec` registered under ``name`` (nothing of the backend is imported).

    Raises
    ------
    UnknownMethodError
        If no backend of that name is registered (a ``ValueError``).
    """
    if name not in _BACKENDS:
        raise UnknownMethodError(f"unknown cage method {name!r}; registered: {sorted(_BACKENDS)}")
    entry = _BACKENDS[name]
    return entry if isinstance(entry, BackendSpec) else BackendSpec(entry)  # a bare whole-hierarchy function


def register_backend(name: str, target: str | Callable, options: type[CageOptions] = CageOptions, *,
                     layer: bool = False, takes=(), own_loop: str = "",
                     schedule: str | Callable | None = None, budget: str | Callable | None = None) -> None:
    """Register a backend under ``name`` (see the module docstring for the two contracts).

    Parameters
    ----------
    name : str
        Method name used in ``build_cages(..., method=name)``.
    target : str or callable
        Either ``"module:function"`` (imported lazily) or the function itself.
    options : type
        Its options class, a frozen dataclass deriving from :class:`cagegen.CageOptions` (default: the
        common options only).
    layer : bool
        ``target`` builds one layer (``layer(V, F, n_faces, *, unit, **opts)``); else the whole hierarchy.
    takes : iterable of str
        Keywords of :data:`TAKES` the function accepts.
    own_loop : str
        For a whole-hierarchy function: why it needs its own loop.
    schedule : str or callable, optional
        For a per-layer function: the run's plan (:class:`BackendSpec`).
    budget : str or callable, optional
        The run's time-budget check before the input audit (:class:`BackendSpec`).
    """
    _BACKENDS[name] = BackendSpec(target, options, layer=layer, takes=frozenset(takes), own_loop=own_loop,
                                  schedule=schedule, budget=budget)


def options_class(name: str) -> type[CageOptions]:
    """The options class registered with the backend ``name`` (nothing of the backend is imported).

    Raises
    ------
    UnknownMethodError
        If no backend of that name is registered.
    """
    return backend_spec(name).options


def get_backend(name: str) -> Callable:
    """Return the function registered under ``name`` (per-layer or whole-hierarchy: :func:`backend_spec`).

    Raises
    ------
    UnknownMethodError
        If no backend of that name is registered (a ``ValueError``).
    BackendUnavailableError
        If the backend's module (or one of its optional dependencies) cannot be imported.
    """
    return _resolve(backend_spec(name).target, name)


def get_schedule(name: str) -> Callable | None:
    """The per-layer backend's ``schedule`` function (:class:`BackendSpec`), or None."""
    target = backend_spec(name).schedule
    return None if target is None else _resolve(target, name)


def get_budget(name: str) -> Callable | None:
    """The backend's time-budget check (:class:`BackendSpec` ``budget``), or None."""
    target = backend_spec(name).budget
    return None if target is None else _resolve(target, name)


def _resolve(target: str | Callable, name: str) -> Callable:
    if callable(target):
        return target
    module, func = target.split(":")
    try:
        mod = importlib.import_module(module)
    except ImportError as exc:  # optional dependency missing
        raise BackendUnavailableError(f"cage method {name!r} is unavailable: {exc}") from exc
    return getattr(mod, func)


def registered_backends() -> list[str]:
    """Names of every registered backend (nothing is imported: an optional one may still be unavailable)."""
    return sorted(_BACKENDS)


def available_backends() -> list[str]:
    """Names of the registered backends whose imports succeed on this machine."""
    out = []
    for name in _BACKENDS:
        try:
            get_backend(name)
        except (BackendUnavailableError, AttributeError):
            continue
        out.append(name)
    return out
