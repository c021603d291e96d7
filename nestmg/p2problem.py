"""Model problems with quadratic elements (straight or curved P2) on top of a P1 multigrid hierarchy.

``setup_problem(tets, P, name, element="P2", curved=...)`` lands here. The fine level is P2 on the mesh
``tets[0]`` (its curved version :class:`nestmg.curved.CurvedMesh`, or straight); the next level is P1 on
the same tets through the exact P1 → P2 interpolation (p-multigrid: curved P1 functions lie in the
isoparametric P2 space), then the hierarchy's own levels. In the default pipeline (fine level = red
refinement of the TetWild mesh at 2 h_0) pass ``tets[1:], P[1:]``: P2 on the TetWild mesh has exactly
the refined P1 level's unknowns.

Boundary data live on the curved geometry: Dirichlet values are taken at the curved boundary nodes,
Neumann fluxes are integrated over the curved facets (:func:`solvers.fem_p2.p2_neumann_load`).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import scipy.sparse as sp

from solvers.fem_p2 import p2_load, p2_mass_matrix, p2_neumann_load, p2_stiffness_matrix
from solvers.multilevel import restrict_prolongations

from .curved import CurvedMesh, p2_nodes
from .errors import NestmgInputError

__all__ = ["setup_p2_problem"]


def _mesh(tets, curved: CurvedMesh | None) -> CurvedMesh:
    from .tetmesh import orient_tets

    V0, T0 = np.asarray(tets[0][0], dtype=np.float64), np.asarray(tets[0][1], dtype=np.int64)
    if curved is None:
        T = orient_tets(V0, T0)
        X, T10, E = p2_nodes(V0, T)
        return CurvedMesh(X, T, T10, E, {"straight": True})
    if curved.n_vertices != len(V0) or len(curved.T) != len(T0):
        raise NestmgInputError(f"curved mesh has {curved.n_vertices} vertices / {len(curved.T)} tets, "
                               f"tets[0] has {len(V0)} / {len(T0)}: curve tets[0] itself "
                               "(nestmg.curved.curve_mesh)")
    return curved


def _rhs(cm: CurvedMesh, M: sp.csr_matrix, f) -> np.ndarray:
    """``∫ f N_a``: quadrature for a callable ``f``, ``M f`` for nodal values, else the default source."""
    from .problems import default_rhs

    if f is None:
        return M @ default_rhs(cm.X)
    if callable(f):
        return p2_load(cm.X, cm.T10, f)
    f = np.asarray(f, dtype=np.float64)
    if f.shape != (len(cm.X),):
        raise NestmgInputError(f"f must be a function of points or have shape ({len(cm.X)},), got {f.shape}")
    return M @ f


def setup_p2_problem(tets: list, P: list, name: str = "poisson-dirichlet", *,
                     curved: CurvedMesh | None = None,
                     coarse: str = "galerkin", lam: float = 1e-2, f=None,
                     boundary_values: Callable[[np.ndarray], np.ndarray] | None = None,
                     flux: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None, prune: float = 0.2):
    """Assemble a P2 model problem on ``tets[0]`` (curved or straight) and its multigrid level data.

    Parameters
    ----------
    tets, P : as :func:`nestmg.setup_problem` (``Hierarchy.tets``, ``Hierarchy.P``).
    name : {"poisson-dirichlet", "poisson-neumann", "diffusion-neumann"}
    curved : CurvedMesh, optional
        ``curve_mesh(*tets[0], project)``; default: straight P2 on ``tets[0]``.
    coarse : "galerkin"
        Coarse operators ``Pᵀ A P`` (the only choice with P2).
    f : callable, (N,) array or None
        Source: a function of points (integrated by quadrature), values at the P2 nodes, or the
        default source of :func:`nestmg.problems.default_rhs` at the nodes.
    boundary_values : callable, optional
        Dirichlet data ``g(points)`` at the curved boundary nodes (``poisson-dirichlet``; default 0).
    flux : callable, optional
        Neumann flux ``g(points, normals)`` on the curved facets (``poisson-neumann``,
        ``diffusion-neumann``; default 0). A ``poisson-neumann`` right-hand side is then made
        compatible (its discrete mean removed).
    prune : float
        See :func:`nestmg.setup_problem`.

    Returns
    -------
    nestmg.Problem
        ``mesh`` is the :class:`~nestmg.curved.CurvedMesh`; ``expand`` puts the Dirichlet values back.
    """
    from .problems import PROBLEMS, Problem

    if name not in PROBLEMS:
        raise NestmgInputError(f"unknown problem {name!r} for element='P2'; choose from {PROBLEMS}")
    if coarse != "galerkin":
        raise NestmgInputError(f"element='P2' takes coarse='galerkin' only, got {coarse!r}")
    if len(P) != len(tets) - 1:
        raise NestmgInputError(f"need len(P) == len(tets) - 1, got {len(P)} and {len(tets)}")
    dirichlet = name == "poisson-dirichlet"
    if (boundary_values is not None and not dirichlet) or (flux is not None and dirichlet):
        raise NestmgInputError("boundary_values go with poisson-dirichlet, flux with the Neumann problems")
    cm = _mesh(tets, curved)
    K = p2_stiffness_matrix(cm.X, cm.T10)
    need_mass = name == "diffusion-neumann" or f is None or not callable(f)
    M = p2_mass_matrix(cm.X, cm.T10) if need_mass else None
    b = _rhs(cm, M, f)
    F6 = cm.boundary_facets()
    N = len(cm.X)
    fixed = np.zeros(N)
    if dirichlet:
        bnd = np.unique(F6.ravel())
        if boundary_values is not None:
            fixed[bnd] = np.asarray(boundary_values(cm.X[bnd]), dtype=np.float64)
        free0 = np.setdiff1d(np.arange(N), bnd, assume_unique=True)
        A = K[free0][:, free0].tocsr()
        b = b[free0] - K[free0][:, bnd] @ fixed[bnd]
    else:
        if flux is not None:
            b = b + (lam if name == "diffusion-neumann" else 1.0) * p2_neumann_load(cm.X, F6, flux)
        A = (lam * K + M).tocsr() if name == "diffusion-neumann" else K
        if name == "poisson-neumann":
            m = p2_load(cm.X, cm.T10, lambda x: np.ones(len(x)))  # ∫ N_a = M 1
            b = b - b.sum() * m / m.sum()  # compatible: 1ᵀ b = 0
        free0 = np.arange(N)
    Pr, free = _restrict(cm, P, free0, dirichlet, prune)
    local = None
    if not dirichlet:  # boundary layer: every node of a tet with a boundary facet
        local = np.unique(cm.T10[np.unique(np.r_[p2_boundary_tets(cm.T10)])].ravel())
    return Problem(name=name, A=A, b=np.asarray(b), P=Pr, coarse="galerkin", free=free, n_fine=N,
                   nullspace="constant" if name == "poisson-neumann" else None,
                   params={"lam": lam if name == "diffusion-neumann" else None, "coarse": coarse,
                           "prune": prune,
                           "element": "P2", "curved": not cm.report.get("straight", False)},
                   local_nodes=local, fixed_values=fixed if dirichlet else None, mesh=cm)


def _restrict(cm: CurvedMesh, P: list, free0: np.ndarray, dirichlet: bool, prune: float):
    """Prolongations on the free nodes: P2 -> P1 on the same tets (Dirichlet: interior vertices), then P."""
    n = cm.n_vertices
    p1_free = np.arange(n)
    if dirichlet:
        p1_free = np.setdiff1d(p1_free, np.unique(cm.boundary_facets()[:, :3]))
    Pa, fa = restrict_prolongations([cm.prolongation()], free0, coarse_free=[p1_free], support_only=True)
    if not P:
        return Pa, fa
    Pb, fb = restrict_prolongations(P, fa[1], min_column_sum=prune)
    return Pa + Pb, [fa[0], *fb]


def p2_boundary_tets(T10: np.ndarray) -> np.ndarray:
    """Indices of the tets with a boundary facet."""
    from solvers.fem import boundary_faces

    return np.unique(boundary_faces(np.asarray(T10)[:, :4])[1])
