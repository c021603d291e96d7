"""solvers.coarse: the LAPACK factors of a small coarsest level (full and band storage)."""

import numpy as np
import pytest
import scipy.sparse as sp

import solvers.coarse
from solvers import MultigridSolver, fem, restrict_prolongations
from solvers.coarse import _CoarseSolver, _DenseFactor
from solvers.errors import SolverError
from solvers.gallery import kuhn_cube_hierarchy


def _scattered_laplacian(m: int, seed: int, shift: float = 1.0) -> sp.csr_matrix:
    """Graph Laplacian of an ``m³`` grid (constants in its null space) plus ``shift`` times the identity,
    in a random node order (banded only after reverse Cuthill-McKee)."""
    d = np.full(m, 2.0)
    d[[0, -1]] = 1.0
    one = sp.diags([-np.ones(m - 1), d, -np.ones(m - 1)], [-1, 0, 1])
    eye = sp.eye(m)
    L = sp.kron(sp.kron(one, eye), eye) + sp.kron(sp.kron(eye, one), eye) + sp.kron(sp.kron(eye, eye), one)
    p = np.random.default_rng(seed).permutation(m**3)
    A = sp.csr_matrix(L + shift * sp.eye(m**3))[p][:, p]
    A.sort_indices()
    return sp.csr_matrix(A)


def test_band_cholesky_equals_the_full_factor(monkeypatch):
    """In the reverse Cuthill-McKee order the factor is a band of at most BAND_MAX_FRACTION n: same
    solutions as the full Cholesky (one and several right-hand sides, with a diagonal shift), fewer
    entries, and an indefinite matrix refused."""
    A = _scattered_laplacian(8, 0)
    n = A.shape[0]
    rng = np.random.default_rng(1)
    b, B = rng.standard_normal(n), rng.standard_normal((n, 3))
    shift = rng.uniform(0.5, 1.0, n)
    band = _DenseFactor(A, True, shift)
    assert band.perm is not None and band.c.shape[0] - 1 <= solvers.coarse.BAND_MAX_FRACTION * n
    assert band.nnz < n * (n + 1) / 2
    monkeypatch.setattr(solvers.coarse, "BAND_MAX_FRACTION", 0.0)
    full = _DenseFactor(A, True, shift)
    assert full.perm is None and full.nnz == n * (n + 1)
    exact = np.linalg.solve(A.toarray() + np.diag(shift), np.column_stack([b, B]))
    for f in (band, full):
        assert np.abs(f.solve(b) - exact[:, 0]).max() < 1e-12 * np.abs(exact).max()
        assert np.abs(f.solve(B) - exact[:, 1:]).max() < 1e-12 * np.abs(exact).max()
    monkeypatch.undo()
    with pytest.raises(SolverError):
        _DenseFactor(sp.csr_matrix(A - 3.0 * sp.eye(n)), True)


def test_band_factor_keeps_the_multigrid_iterations(monkeypatch):
    """The regularised coarsest factor in band storage (the cube's coarsest level) gives the same MG-PCG
    iterations and solution as in full storage."""
    meshes, Ps = kuhn_cube_hierarchy(8, 2)
    V, T = meshes[0]
    K = fem.stiffness_matrix(V, T)
    free = np.setdiff1d(np.arange(len(V)), fem.boundary_nodes(T))
    Pf, _ = restrict_prolongations(Ps, free)
    A = sp.csr_matrix(K[free][:, free])
    b = np.random.default_rng(2).standard_normal(len(free))
    runs = []
    monkeypatch.setattr(solvers.coarse, "PIVOTED_MAX", 0)
    for fraction in (solvers.coarse.BAND_MAX_FRACTION, 0.0):
        monkeypatch.setattr(solvers.coarse, "BAND_MAX_FRACTION", fraction)
        ml = MultigridSolver(A, Pf)  # "auto" without the pivoted step: the regularised LAPACK factor
        assert ml._coarse_solver.method == "regularized" and ml._coarse_solver.dense
        assert (ml._coarse_solver.lu.perm is not None) == (fraction > 0)
        runs.append(ml.solve(b, tol=1e-10, accel="cg", return_info=True))
    (x_band, info_band), (x_full, info_full) = runs
    assert info_band["iterations"] == info_full["iterations"]
    assert np.abs(x_band - x_full).max() < 1e-9 * np.abs(x_full).max()


def test_regularised_dense_step_factorises_in_band_storage(monkeypatch):
    """coarse_solver="auto" on a small singular (Neumann) coarsest level, without the pivoted step: the
    regularised factor (1e-9 diag(A) added to the band's diagonal) solves consistent right-hand sides to
    1e-6 on the range."""
    A = _scattered_laplacian(8, 3, shift=0.0)
    monkeypatch.setattr(solvers.coarse, "PIVOTED_MAX", 0)
    cs = _CoarseSolver(A, "constant", 1, "auto", symmetric=True)
    assert cs.method == "regularized" and cs.dense and cs.lu.perm is not None
    v = np.random.default_rng(4).standard_normal(512)
    v -= v.mean()
    assert np.abs(cs(A @ v) - v).max() < 1e-6 * np.abs(v).max()
