"""Memory estimate of a tet mesh *before* meshing: refuse a layer that would not fit.

The number of tets follows from the enclosed volume and the target edge length: a regular tet of
edge ``h`` has volume ``h³ / (6√2)``, and measured here on a sphere (diagonal 1, icosphere of 5120
faces) TetGen (quality 1.5) made 1.80x and 1.78x that many tets at ``h`` = 0.02 / 0.01 (192k /
1.53M tets), TetWild 1.02x at ``h`` = 0.03 (32k tets). Peak resident memory grew by ~410 bytes per
tet with TetGen and ~4.2 kB per tet with TetWild (its background mesh and envelope). The estimate
below takes 2.5x the regular count and 600 B / 6 kB per tet, plus the FEM matrices of the layer
(~15 non-zeros per node, ~5.5 tets per node), so it is an upper bound in those measurements.

The limit is ``$NESTMG_MEMORY_LIMIT`` or the system's available memory
(:func:`solvers.memory.available_memory`).
"""

from __future__ import annotations

import numpy as np

from solvers.errors import InsufficientMemoryError
from solvers.memory import check_memory

from .errors import NestmgInputError
from .tetmesh import TetMeshError

__all__ = ["TetMeshMemoryError", "check_tet_memory", "enclosed_volume", "estimate_tet_bytes", "estimate_tets"]

#: tets per regular-tet volume (measured 1.8 for TetGen, 1.0 for TetWild), taken with a margin
COUNT_FACTOR = 2.5
#: peak bytes per tet of the mesher (measured ~410 for TetGen, ~4200 for TetWild), with a margin
BYTES_PER_TET = {"tetgen": 600, "tetwild": 6000}
#: FEM stiffness + mass + prolongation per node: ~15 non-zeros x 16 bytes x 3 matrices
FEM_BYTES_PER_NODE = 15 * 16 * 3


class TetMeshMemoryError(TetMeshError, MemoryError):
    """A tet layer would not fit in the memory available (raised before meshing).

    Attributes
    ----------
    n_tets : int
        Estimated number of tets.
    needed, available : int
        Estimated and available bytes.
    """

    def __init__(self, message: str, n_tets: int, needed: int, available: int):
        super().__init__(message)
        self.n_tets, self.needed, self.available = int(n_tets), int(needed), int(available)


def signed_volume(V: np.ndarray, F: np.ndarray) -> float:
    """Signed volume of the triangles ``(V, F)`` (divergence theorem, one tet per face to the vertices'
    mean): the enclosed volume of a closed outward surface, negative for an inward one."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    c = V.mean(axis=0)
    a, b, d = V[F[:, 0]] - c, V[F[:, 1]] - c, V[F[:, 2]] - c
    return float(np.einsum("ij,ij->", a, np.cross(b, d)) / 6.0)


def enclosed_volume(V: np.ndarray, F: np.ndarray) -> float:
    """Volume enclosed by the closed, outward-oriented surface ``(V, F)`` (divergence theorem).

    Falls back to the bounding-box volume when the signed volume is not positive (inward faces).
    """
    V = np.asarray(V, dtype=np.float64)
    vol = signed_volume(V, F)
    if not vol > 0:
        vol = float(np.prod(V.max(axis=0) - V.min(axis=0)))
    return vol


def estimate_tets(V: np.ndarray, F: np.ndarray, edge_length: float) -> int:
    """Upper estimate of the number of tets of the solid bounded by ``(V, F)`` at target edge ``edge_length``.

    Parameters
    ----------
    V : (n,3) float array
    F : (m,3) int array
        Closed, outward-oriented surface (for another one the bounding-box volume is used).
    edge_length : float
        Target edge length (absolute).

    Returns
    -------
    int
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    vol = enclosed_volume(V, F)
    regular = edge_length**3 / (6.0 * np.sqrt(2.0))
    return int(min(COUNT_FACTOR * vol / regular + len(F), 2**62))


def estimate_tet_bytes(n_tets: int, mesher: str) -> int:
    """Peak bytes of meshing ``n_tets`` tets with ``mesher`` plus the layer's FEM matrices."""
    if mesher not in BYTES_PER_TET:
        raise NestmgInputError(f"unknown mesher {mesher!r}; choose from {sorted(BYTES_PER_TET)}")
    return int(n_tets * BYTES_PER_TET[mesher] + (n_tets / 5.5) * FEM_BYTES_PER_NODE)


def check_tet_memory(V: np.ndarray, F: np.ndarray, edge_length: float, mesher: str, *, layer: int | None = None,
                     limit: int | str | None = None) -> int:
    """Raise :class:`TetMeshMemoryError` if meshing ``(V, F)`` at ``edge_length`` would not fit.

    Returns
    -------
    int
        The estimated number of tets (when it fits).
    """
    n = estimate_tets(V, F, edge_length)
    need = estimate_tet_bytes(n, mesher)
    where = "" if layer is None else f" of layer {layer}"
    try:
        check_memory(need, f"the {mesher} tet mesh{where} (~{n:.3g} tets at edge length {edge_length:.3g})",
                     limit=limit)
    except InsufficientMemoryError as exc:
        raise TetMeshMemoryError(f"{exc}; use a larger edge length or fewer faces", n_tets=n,
                                 needed=exc.needed, available=exc.available) from None
    return n
