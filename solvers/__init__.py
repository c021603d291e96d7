"""Sparse linear algebra for nestmg: P1 FEM on tets, geometric multigrid, Krylov wrappers, baselines.

Knows nothing of meshes' origins (cages): it takes node positions, tets, operators and
prolongation matrices as plain numpy/scipy arrays. ``solvers.baselines`` (pyamg, scipy, CHOLMOD) and
``solvers.gallery`` are imported on demand.
"""

from .errors import DivergenceError, IncompatibleRHSError, SolverError, SolverInputError
from .fem import (
    DirichletSystem,
    boundary_nodes,
    check_compatible,
    diffusion_matrix,
    eliminate_dirichlet,
    load_vector,
    mass_matrix,
    project_rhs,
    remove_mean,
    stiffness_matrix,
)
from .krylov import KrylovResult, mg_pcg, pcg
from .multilevel import (
    ConvergenceWarning,
    Level,
    MultigridSolver,
    convergence_factor,
    galerkin_operators,
    restrict_prolongations,
)
from .smoothing import SMOOTHERS, Smoother, make_smoother

__all__ = [
    "SolverError",
    "SolverInputError",
    "IncompatibleRHSError",
    "DivergenceError",
    "stiffness_matrix",
    "mass_matrix",
    "load_vector",
    "diffusion_matrix",
    "boundary_nodes",
    "DirichletSystem",
    "eliminate_dirichlet",
    "check_compatible",
    "project_rhs",
    "remove_mean",
    "MultigridSolver",
    "Level",
    "ConvergenceWarning",
    "restrict_prolongations",
    "galerkin_operators",
    "convergence_factor",
    "KrylovResult",
    "pcg",
    "mg_pcg",
    "SMOOTHERS",
    "Smoother",
    "make_smoother",
]
