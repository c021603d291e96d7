"""Column-blocked MG-PCG (solvers.multirhs): same answers as one solve per column, one set-up."""

from __future__ import annotations

import numpy as np
import pytest

from solvers import MultigridSolver, SolverInputError, restrict_prolongations
from solvers.fem import boundary_nodes, stiffness_matrix
from solvers.gallery import kuhn_cube_hierarchy
from solvers.multirhs import MULTI_RHS_SMOOTHER, solve_many


@pytest.fixture(scope="module")
def dirichlet():
    meshes, Ps = kuhn_cube_hierarchy(16, 3)
    V, T = meshes[0]
    free = np.setdiff1d(np.arange(len(V)), boundary_nodes(T))
    Pf, _ = restrict_prolongations(Ps, free)
    return stiffness_matrix(V, T)[free][:, free].tocsr(), Pf


def test_block_solve_matches_column_solves(dirichlet, rng):
    A, Pf = dirichlet
    ml = MultigridSolver(A, Pf, presmoother=MULTI_RHS_SMOOTHER)
    B = rng.standard_normal((A.shape[0], 7))
    B[:, 3] = 0.0  # a zero column stays zero and takes no iteration
    X, info = solve_many(ml, B, tol=1e-10, chunk=3, return_info=True)
    assert info["converged"] and info["iterations"][3] == 0 and np.all(X[:, 3] == 0)
    rel = np.linalg.norm(B - A @ X, axis=0) / np.maximum(np.linalg.norm(B, axis=0), 1e-300)
    assert rel.max() < 1e-9
    for j in (0, 6):
        x, one = ml.solve(B[:, j], tol=1e-10, accel="cg", return_info=True)
        assert np.linalg.norm(X[:, j] - x) <= 1e-8 * np.linalg.norm(x)
        assert abs(int(info["iterations"][j]) - one["iterations"]) <= 1
    assert info["iterations"].max() <= 15  # a multigrid rate, not plain CG's


def test_refuses_a_cycle_that_takes_one_vector(dirichlet):
    A, Pf = dirichlet
    with pytest.raises(SolverInputError, match="MULTI_RHS_SMOOTHER"):
        solve_many(MultigridSolver(A, Pf), np.ones((A.shape[0], 2)))
    ml = MultigridSolver(A, Pf, presmoother=MULTI_RHS_SMOOTHER)
    with pytest.raises(SolverInputError, match="shape"):
        solve_many(ml, np.ones((A.shape[0] + 1, 2)))
