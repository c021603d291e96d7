"""cagegen: hierarchies of cages around a closed surface, and their certification.

The one entry point is :func:`build_cages`::

    layers = build_cages(V, F, levels=3, method="nested")   # [(V0, F0), (V1, F1), (V2, F2)]

Layer 0 is the audited input; layer ``k+1`` is a coarser cage that strictly contains layer ``k``
(checked by :func:`verify_nesting`) for every method except the naive ``"decimate"`` baseline.
Backends are looked up by name in :mod:`cagegen.registry` and imported lazily; each has a typed options
class (:mod:`cagegen.options`: ``build_cages(V, F, 3, "sdf", options=SdfOptions(c=0.02))``).

Small helpers the pipeline shares with the backends: :func:`as_mesh_arrays` (validated float64 / int64
copies), :func:`bbox_diagonal` (overflow-safe bounding-box diagonal, the unit of every relative length),
:func:`normalize` (the one bounding-box normalisation) and :func:`in_temp_dir` (a throw-away working
directory for meshers that write into the current one).
"""

from __future__ import annotations

from . import _log, errors  # noqa: F401 -- _log: the cagegen loggers (NullHandler; ipctk's lines go there)
from ._geometry import as_mesh_arrays, bbox_diagonal, normalize
from ._tempdir import in_temp_dir
from .audit import MeshAudit, audit_mesh, audit_self_intersections, check_mesh, repair_mesh
from .build import UNCERTIFIED_METHODS, build_cages
from .components import build_cages_per_component, split_components
from .culling import CullingReport, cull_collisions, solids_intersect
from .errors import (
    BackendUnavailableError,
    CageError,
    CageOptionError,
    CageTypeError,
    LevelsError,
    MeshInputError,
    NestmgError,
    UnknownMethodError,
)
from .options import CageOptions, DecimateOptions, LazyOptions, NestedOptions, SdfOptions, SkeletonOptions
from .registry import available_backends, get_backend, options_class, register_backend, registered_backends
from .sizes import check_face_counts, default_face_counts
from .verify import NestingReport, PairReport, verify_nesting

__all__ = [
    "UNCERTIFIED_METHODS",
    "BackendUnavailableError",
    "CageError",
    "CageOptions",
    "CageOptionError",
    "CageTypeError",
    "CullingReport",
    "DecimateOptions",
    "LazyOptions",
    "LevelsError",
    "MeshAudit",
    "MeshInputError",
    "NestedOptions",
    "NestingReport",
    "NestmgError",
    "PairReport",
    "SdfOptions",
    "SkeletonOptions",
    "UnknownMethodError",
    "as_mesh_arrays",
    "audit_mesh",
    "audit_self_intersections",
    "available_backends",
    "bbox_diagonal",
    "build_cages",
    "build_cages_per_component",
    "check_face_counts",
    "check_mesh",
    "cull_collisions",
    "default_face_counts",
    "errors",
    "get_backend",
    "in_temp_dir",
    "normalize",
    "options_class",
    "register_backend",
    "registered_backends",
    "repair_mesh",
    "solids_intersect",
    "split_components",
    "verify_nesting",
]
