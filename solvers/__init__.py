"""Sparse linear algebra for nestmg: P1 FEM on tets, geometric multigrid, Krylov wrappers, baselines.

Knows nothing of meshes' origins (cages): it takes node positions, tets, operators and
prolongation matrices as plain numpy/scipy arrays. ``solvers.baselines`` (pyamg, scipy, CHOLMOD) and
``solvers.gallery`` are imported on demand.
"""

from .elasticity import (
    NullspaceMultigridSolver,
    block_dofs,
    block_prolongation,
    elasticity_matrix,
    galerkin_nullspaces,
    lame_parameters,
    rigid_body_modes,
)
from .errors import (
    DivergenceError,
    IncompatibleRHSError,
    InsufficientMemoryError,
    NestmgError,
    OutsideCoarseMeshError,
    SolverError,
    SolverInputError,
)
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
from .krylov import KrylovResult, pcg
from .memory import available_memory, check_memory, galerkin_nnz_estimate
from .multilevel import (
    DEFAULT_MAXITER,
    ConvergenceWarning,
    Level,
    MultigridSolver,
    convergence_factor,
    galerkin_operators,
    prune_prolongations,
    reroute_to_pattern,
    restrict_prolongations,
    sparsified_galerkin_operators,
)
from .multirhs import MULTI_RHS_SMOOTHER, solve_many
from .smoothing import SMOOTHERS, Smoother, make_smoother

__all__ = [
    "DEFAULT_MAXITER",
    "MULTI_RHS_SMOOTHER",
    "SMOOTHERS",
    "ConvergenceWarning",
    "DirichletSystem",
    "DivergenceError",
    "IncompatibleRHSError",
    "InsufficientMemoryError",
    "KrylovResult",
    "Level",
    "MultigridSolver",
    "NestmgError",
    "NullspaceMultigridSolver",
    "OutsideCoarseMeshError",
    "Smoother",
    "SolverError",
    "SolverInputError",
    "available_memory",
    "block_dofs",
    "block_prolongation",
    "boundary_nodes",
    "check_compatible",
    "check_memory",
    "convergence_factor",
    "diffusion_matrix",
    "elasticity_matrix",
    "galerkin_nullspaces",
    "eliminate_dirichlet",
    "galerkin_nnz_estimate",
    "galerkin_operators",
    "lame_parameters",
    "load_vector",
    "make_smoother",
    "mass_matrix",
    "pcg",
    "project_rhs",
    "prune_prolongations",
    "remove_mean",
    "reroute_to_pattern",
    "rigid_body_modes",
    "restrict_prolongations",
    "solve_many",
    "sparsified_galerkin_operators",
    "stiffness_matrix",
]
