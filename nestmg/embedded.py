"""Embedded elasticity on one cage (after Xu & Barbič 2014; Nested Cages paper, Fig. 19).

The solid is simulated on the coarsest level of a hierarchy only -- the tet mesh of its outermost cage,
a few thousand nodes -- and the displacement is carried to the input through the hierarchy's
prolongations, ``u_0 = P_0 P_1 ... P_{L-2} u_{L-1}``, then to any query points (the input surface's
vertices) by barycentric interpolation in the finest tets. Nesting makes every transfer an
interpolation (no extrapolation: every finer node lies in a coarser tet).

Three coarse models (``model=``):

``"filled"``
    Xu & Barbič's embedding: the cage's tet mesh is the simulated solid, uniform material, gravity
    on its own (lumped) mass. Cheapest; the cage's extra volume makes it heavier and stiffer.
``"fraction"``
    Each coarse tet's Young's modulus is scaled by the fraction of its volume the input occupies (fine
    tet centroids located in the coarse tets), floored at ``min_fraction``; the load is the fine
    lumped gravity load restricted, ``b_c = Pᵀ b_0`` (the virtual work of the fine load on the embedded
    displacements).
``"galerkin"``
    The Ritz–Galerkin reduction of the fine problem, ``K_c = Pᵀ K_0 P``, ``b_c = Pᵀ b_0``: the best
    displacement in the coarse space (energy norm). Needs the fine stiffness matrix (assembly and one
    triple product, no fine solve).

Constraints: the coarse boundary nodes in the fine problem's clamped slab ``x <= x_min + band (x_max -
x_min)`` (the extent of the fine mesh, as :func:`nestmg.elasticity.clamped_nodes`) are fixed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .errors import NestmgInputError

__all__ = ["EMBEDDED_MODELS", "EmbeddedSolution", "embedded_solve"]

EMBEDDED_MODELS = ("filled", "fraction", "galerkin")


@dataclass
class EmbeddedSolution:
    """Result of :func:`embedded_solve`.

    Attributes
    ----------
    u_points : (p, 3) float
        Displacement at the query points.
    u_fine : (n_0, 3) float
        Displacement at the finest level's nodes (``P_0 ... P_{L-2} u_coarse``).
    u_coarse : (n_c, 3) float
        Displacement at the coarse (cage) mesh's nodes.
    fixed : (f,) int
        Clamped coarse nodes.
    info : dict
        Sizes, model, seconds per stage (``assemble``, ``solve``, ``transfer``, ``total``).
    """

    u_points: np.ndarray
    u_fine: np.ndarray
    u_coarse: np.ndarray
    fixed: np.ndarray
    info: dict = field(default_factory=dict)


def _slab_nodes(Vc: np.ndarray, Tc: np.ndarray, V0: np.ndarray, band: float) -> np.ndarray:
    """Coarse boundary nodes in the fine mesh's clamped slab (lowest ``band`` of the x extent)."""
    from solvers.fem import boundary_nodes

    if not 0.0 < band <= 1.0:
        raise NestmgInputError(f"band must be in (0, 1], got {band}")
    lo, hi = float(V0[:, 0].min()), float(V0[:, 0].max())
    bnd = boundary_nodes(Tc, n=len(Vc))
    fixed = np.sort(bnd[Vc[bnd, 0] <= lo + band * (hi - lo)])
    span = Vc[fixed] - Vc[fixed].mean(axis=0) if len(fixed) else np.zeros((0, 3))
    if len(fixed) < 3 or np.linalg.matrix_rank(span, tol=1e-9 * (hi - lo)) < 2:
        raise NestmgInputError(f"the clamped slab (band={band}) holds {len(fixed)} coarse boundary nodes, "
                               "not a "
                               "plane's worth: widen the band")
    return fixed


def _fine_fractions(V0, T0, Vc, Tc) -> np.ndarray:
    """Fraction of every coarse tet's volume covered by fine tets (centroids located in the coarse tets)."""
    import igl

    from .tetmesh import tet_volumes

    tree = igl.AABB()
    tree.init(Vc, Tc)
    where = igl.in_element(Vc, Tc, np.ascontiguousarray(V0[T0].mean(axis=1)), tree)
    ok = where >= 0
    vol = np.bincount(where[ok], weights=np.abs(tet_volumes(V0, T0))[ok], minlength=len(Tc))
    return np.clip(vol / np.abs(tet_volumes(Vc, Tc)), 0.0, 1.0)


def _coarse_system(model, tets, Ptot, E, nu, gravity, min_fraction):
    """Coarse stiffness (3 n_c square) and load for ``model``."""
    from solvers.elasticity import block_prolongation, elasticity_matrix
    from solvers.fem import mass_matrix

    (V0, T0), (Vc, Tc) = tets[0], tets[-1]
    g = np.asarray(gravity, dtype=np.float64)
    if model == "filled":
        m = mass_matrix(Vc, Tc).diagonal()
        return elasticity_matrix(Vc, Tc, E, nu), (m[:, None] * g).ravel()
    m0 = mass_matrix(V0, T0).diagonal()
    Pb = block_prolongation(Ptot)
    b = Pb.T @ (m0[:, None] * g).ravel()
    if model == "fraction":
        frac = np.maximum(_fine_fractions(V0, T0, Vc, Tc), min_fraction)
        return elasticity_matrix(Vc, Tc, E * frac, nu), b
    K0 = elasticity_matrix(V0, T0, E, nu)
    return sp.csr_matrix(Pb.T @ (K0 @ Pb)), b


def embedded_solve(
    tets: list[tuple[np.ndarray, np.ndarray]],
    P: list[sp.csr_matrix],
    interp: sp.spmatrix | None = None,
    *,
    model: str = "filled",
    E: float = 1.0,
    nu: float = 0.3,
    band: float = 0.05,
    gravity=(0.0, 0.0, -1.0),
    min_fraction: float = 1e-2,
) -> EmbeddedSolution:
    """Clamped elasticity under gravity solved on the coarsest level only, carried to the finest.

    Parameters
    ----------
    tets : list of (V, T)
        The hierarchy's tet levels, finest first (``Hierarchy.tets_in("normalized")``).
    P : list of (n_k, n_{k+1}) csr_matrix
        Nodal prolongations (``Hierarchy.P``).
    interp : (p, n_0) sparse, optional
        Interpolation from the finest nodes to the points where the displacement is wanted (e.g. the input
        surface's vertices): ``nestmg.prolongation(points, *tets[0])[0]``, computed once per input and
        reused. Default: none (``u_points`` is empty).
    model : {"filled", "fraction", "galerkin"}
        Coarse model (module docstring).
    E : float
        Young's modulus (constant).
    nu : float
        Poisson's ratio.
    band : float
        Clamped slab, fraction of the fine mesh's x extent.
    gravity : (3,) float
        Body force per unit volume.
    min_fraction : float
        ``"fraction"``: floor of the volume fraction (keeps empty coarse tets from making the stiffness
        singular).

    Returns
    -------
    EmbeddedSolution
    """
    from solvers.coarse import sparse_lu
    from solvers.elasticity import block_dofs

    if model not in EMBEDDED_MODELS:
        raise NestmgInputError(f"model must be one of {EMBEDDED_MODELS}, got {model!r}")
    if len(tets) < 2 or len(P) != len(tets) - 1:
        raise NestmgInputError(f"need >= 2 levels and len(P) == len(tets) - 1, got {len(tets)} and {len(P)}")
    t0 = time.perf_counter()
    Ptot = P[0]
    for Pk in P[1:]:
        Ptot = sp.csr_matrix(Ptot @ Pk)
    (V0, _), (Vc, Tc) = tets[0], tets[-1]
    fixed = _slab_nodes(Vc, Tc, V0, band)
    K, b = _coarse_system(model, tets, Ptot, E, nu, gravity, min_fraction)
    keep = np.arange(len(Vc))
    if model == "galerkin":  # coarse nodes whose hat reaches no fine node have empty rows in Pᵀ K P
        keep = np.flatnonzero(np.asarray(abs(Ptot).sum(axis=0)).ravel() > 0)
    free = block_dofs(np.setdiff1d(keep, fixed, assume_unique=True))
    Kf = K[free][:, free]
    t1 = time.perf_counter()
    x = np.zeros(3 * len(Vc))
    x[free] = sparse_lu(Kf, symmetric=True).solve(b[free])
    t2 = time.perf_counter()
    u_c = x.reshape(-1, 3)
    u0 = Ptot @ u_c
    u_pts = np.zeros((0, 3)) if interp is None else interp @ u0
    t3 = time.perf_counter()
    info = {"model": model, "coarse_nodes": len(Vc), "coarse_tets": len(Tc), "unknowns": int(len(free)),
            "seconds": {"assemble": t1 - t0, "solve": t2 - t1, "transfer": t3 - t2, "total": t3 - t0}}
    return EmbeddedSolution(u_pts, u0, u_c, fixed, info)
