"""nestmg: geometric multigrid for PDEs on 3D shapes, with nested cages as coarse levels.

Pipeline (one function call per arrow, plain arrays in between)::

    (V, F) --cagegen.build_cages--> surfaces --tetrahedralize--> tet layers --prolongation--> P_k
           --solvers.MultigridSolver--> V-cycles

:func:`build_hierarchy` runs the first three stages (cached), :func:`setup_problem` assembles a model
problem and the level data, :func:`solve_on_hierarchy` does both plus a measured solve. Each stage takes
one typed options object (:class:`SizingOptions`, :class:`MeshingOptions`, the cage method's
``cagegen.CageOptions`` class, :class:`SolverOptions`).
"""

from .errors import NestmgError, NestmgInputError
from .hierarchy import Hierarchy, build_hierarchy, tet_hierarchy
from .io import load_mesh, load_tet_mesh, normalize, save_mesh, save_tet_mesh
from .options import MeshingOptions, OptionError, SizingOptions, SolverOptions
from .problems import PROBLEMS, Problem, setup_problem
from .prolongation import ProlongationReport, prolongation
from .run import solve_on_hierarchy
from .tetmesh import TetMeshError, tetrahedralize
from .usermesh import hierarchy_from_tets, load_hierarchy, save_hierarchy, write_vtu_levels

__version__ = "0.1.0"

__all__ = [
    "PROBLEMS",
    "Hierarchy",
    "MeshingOptions",
    "NestmgError",
    "NestmgInputError",
    "OptionError",
    "Problem",
    "ProlongationReport",
    "SizingOptions",
    "SolverOptions",
    "TetMeshError",
    "build_hierarchy",
    "hierarchy_from_tets",
    "load_hierarchy",
    "load_mesh",
    "load_tet_mesh",
    "normalize",
    "prolongation",
    "save_hierarchy",
    "save_mesh",
    "save_tet_mesh",
    "setup_problem",
    "solve_on_hierarchy",
    "tet_hierarchy",
    "tetrahedralize",
    "write_vtu_levels",
]
