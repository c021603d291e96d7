"""Backend registry: name -> callable, imported lazily (like trimesh's boolean engines).

A backend is a function ::

    backend(V, F, face_counts, **opts) -> (layers, info)

* ``V`` (n,3) float64, ``F`` (m,3) int64: the closed input surface (layer 0), already audited.
* ``face_counts``: target face counts of the cages, finest first (len = levels - 1).
* ``layers``: list of ``(V_i, F_i)`` for the *cages only* (len = len(face_counts)), finest first.
* ``info``: dict of backend figures (timings per phase, recovery actions, ...), JSON-serialisable.

The backend does not certify: :func:`cagegen.build_cages` runs the verifier on every consecutive
pair and raises :class:`cagegen.CageError` for the first failing layer.

Each backend registers its options class (:mod:`cagegen.options`, a frozen dataclass; imported eagerly,
it has no optional dependency): ``opts`` are the fields of that class but its common ones
(:meth:`CageOptions.backend_kwargs`), validated before the backend is called.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

from .errors import BackendUnavailableError, UnknownMethodError
from .options import CageOptions, DecimateOptions, LazyOptions, NestedOptions, SdfOptions, SkeletonOptions

# name -> "module:function" (imported on first use so optional dependencies stay optional)
_BACKENDS: dict[str, str] = {
    "decimate": "cagegen.decimate:decimate_backend",
    "nested": "cagegen.nested:nested_backend",
    "lazy": "cagegen.copyleft.lazy:lazy_backend",
    "sdf": "cagegen.sdf:sdf_backend",
    "skeleton": "cagegen.skeleton:skeleton_backend",
}

# name -> options class
_OPTIONS: dict[str, type[CageOptions]] = {
    "decimate": DecimateOptions,
    "nested": NestedOptions,
    "lazy": LazyOptions,
    "sdf": SdfOptions,
    "skeleton": SkeletonOptions,
}


def register_backend(name: str, target: str | Callable, options: type[CageOptions] = CageOptions) -> None:
    """Register a backend under ``name``.

    Parameters
    ----------
    name : str
        Method name used in ``build_cages(..., method=name)``.
    target : str or callable
        Either ``"module:function"`` (imported lazily) or the backend function itself.
    options : type
        Its options class, a frozen dataclass deriving from :class:`cagegen.CageOptions` (default: the
        common options only).
    """
    if not (isinstance(options, type) and issubclass(options, CageOptions)):
        raise TypeError(f"options must be a subclass of cagegen.CageOptions, got {options!r}")
    _BACKENDS[name] = target  # type: ignore[assignment]
    _OPTIONS[name] = options


def options_class(name: str) -> type[CageOptions]:
    """The options class registered with the backend ``name`` (nothing of the backend is imported).

    Raises
    ------
    UnknownMethodError
        If no backend of that name is registered.
    """
    if name not in _BACKENDS:
        raise UnknownMethodError(f"unknown cage method {name!r}; registered: {sorted(_BACKENDS)}")
    return _OPTIONS.get(name, CageOptions)


def get_backend(name: str) -> Callable:
    """Return the backend callable registered under ``name``.

    Raises
    ------
    UnknownMethodError
        If no backend of that name is registered (a ``ValueError``).
    BackendUnavailableError
        If the backend's module (or one of its optional dependencies) cannot be imported.
    """
    if name not in _BACKENDS:
        raise UnknownMethodError(f"unknown cage method {name!r}; registered: {sorted(_BACKENDS)}")
    target = _BACKENDS[name]
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
