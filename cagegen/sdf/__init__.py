"""The ``"sdf"`` cage backend (Qiu, Liao, Chen 2024): SDF envelope, constrained QEM simplification,
barrier-protected optimisation. See :mod:`cagegen.sdf.backend` and ``docs/sdf.md``."""

from .backend import sdf_cage_layer, sdf_schedule

__all__ = ["sdf_cage_layer", "sdf_schedule"]
