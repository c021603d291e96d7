"""The ``"skeleton"`` cage backend (Casti et al. 2019): coarse cages that follow a curve skeleton.

See :mod:`cagegen.skeleton.backend` for the steps and ``docs/skeleton.md`` for usage and figures.
"""

from .backend import SkeletonCage, skeleton_backend, skeleton_cage
from .graph import Skeleton, read_skeleton, write_skeleton

__all__ = ["Skeleton", "SkeletonCage", "read_skeleton", "skeleton_backend", "skeleton_cage", "write_skeleton"]
