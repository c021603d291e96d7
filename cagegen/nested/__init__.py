"""Nested Cages (Sacht, Vouga, Jacobson 2015): flow + re-inflation cage backend ``"nested"``.

* :func:`nested_backend` — the registered backend ``backend(V, F, face_counts, **opts)``.
* :func:`nest_pair` — one pair: deform a decimation Ĉ into a cage nesting a fine surface.
* :func:`flow_inside` — signed-distance flow of the fine surface inside Ĉ (Sec. 3.1).
* :func:`reinflate` — reversed flow with the cage pushed by CCD + barrier (Sec. 3.2).
* :func:`estimate_seconds` — the time estimate ``cage_time_budget`` is checked against.
"""

from .backend import estimate_seconds, nest_pair, nested_backend, offset_surface
from .energies import ENERGIES, make_energy
from .flow import FlowResult, flow_inside
from .quadrature import quadrature_matrix, quadrature_points, triangle_rule
from .reinflate import ReinflateResult, reinflate

__all__ = [
    "ENERGIES",
    "FlowResult",
    "ReinflateResult",
    "estimate_seconds",
    "flow_inside",
    "make_energy",
    "nest_pair",
    "nested_backend",
    "offset_surface",
    "quadrature_matrix",
    "quadrature_points",
    "reinflate",
    "triangle_rule",
]
