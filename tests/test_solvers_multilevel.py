"""Tests of solvers.multilevel.MultigridSolver on the exactly nested Kuhn cube hierarchy.

Convergence is measured by rates (factor per cycle, iteration counts flat in the number of levels),
not stored values.
"""

import doctest
import warnings

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import threadpoolctl

import solvers.multilevel
from solvers import (
    ConvergenceWarning,
    DivergenceError,
    IncompatibleRHSError,
    MultigridSolver,
    SolverError,
    SolverInputError,
    convergence_factor,
    fem,
    prune_prolongations,
    restrict_prolongations,
    transfer,
)
from solvers.gallery import kuhn_cube_hierarchy, kuhn_cube_mesh, kuhn_interpolation

from conftest import blas_threads, record_blas_threads

N = 16  # 17^3 = 4913 nodes, 3375 interior


@pytest.fixture(scope="module")
def cube():
    meshes, Ps = kuhn_cube_hierarchy(N, 4)
    V, T = meshes[0]
    K, M = fem.stiffness_matrix(V, T), fem.mass_matrix(V, T)
    return meshes, Ps, K, M


def _dirichlet(cube, levels):
    meshes, Ps, K, M = cube
    _V, T = meshes[0]
    ds = fem.eliminate_dirichlet(K, fem.load_vector(M, 1.0), fem.boundary_nodes(T))
    Pf, frees = restrict_prolongations(Ps[: levels - 1], ds.free)
    return ds, Pf, frees


def _factor(ml, b, cycle="V", tol=1e-11, **kw):
    res = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        ml.solve(b, tol=tol, maxiter=60, cycle=cycle, residuals=res, **kw)
    return convergence_factor(res, last=5), res


def _random_rhs(n, seed=0):
    return np.random.default_rng(seed).standard_normal(n)


def test_galerkin_operators_symmetric_and_psd(cube):
    _meshes, Ps, K, _M = cube
    ml = MultigridSolver(K, Ps, nullspace="constant")
    for k, L in enumerate(ml.levels[1:], start=1):
        A = L.A
        assert abs(A - A.T).max() == 0.0  # symmetrised exactly
        ev = np.linalg.eigvalsh(A.toarray()) if A.shape[0] <= 800 else spla.eigsh(A, 2, sigma=-1e-3)[0]
        assert ev.min() > -1e-10 * abs(A).max()
        assert np.abs(A @ np.ones(A.shape[0])).max() < 1e-12  # constants preserved (rows of P sum to 1)
    ds, Pf, _ = _dirichlet(cube, 4)
    mld = MultigridSolver(ds.A, Pf)
    for L in mld.levels[1:]:
        if L.A.shape[0] <= 800:
            assert np.linalg.eigvalsh(L.A.toarray()).min() > 0  # SPD after restriction


def test_dirichlet_vcycle_factor_small_and_flat(cube):
    factors = {}
    for levels in (2, 3, 4):
        ds, Pf, _ = _dirichlet(cube, levels)
        ml = MultigridSolver(ds.A, Pf)
        assert len(ml.levels) == levels
        factors[levels], res = _factor(ml, _random_rhs(ds.A.shape[0]))
        assert res[-1] < 1e-11
    assert max(factors.values()) <= 0.3, factors
    assert max(factors.values()) - min(factors.values()) <= 0.05, factors


def test_dirichlet_solution_matches_direct(cube):
    ds, Pf, _ = _dirichlet(cube, 4)
    ml = MultigridSolver(ds.A, Pf)
    x = ml.solve(ds.b, tol=1e-10)
    xd = spla.spsolve(ds.A.tocsc(), ds.b)
    assert np.abs(x - xd).max() < 1e-8 * np.abs(xd).max()


def test_neumann_converges_with_zero_mean(cube):
    meshes, Ps, K, M = cube
    V = meshes[0][0]
    f = np.cos(np.pi * V[:, 0]) * np.cos(2 * np.pi * V[:, 1])
    b = fem.project_rhs(fem.load_vector(M, f))
    ml = MultigridSolver(K, Ps, nullspace="constant")
    res = []
    x = ml.solve(b, tol=1e-9, residuals=res)
    assert convergence_factor(res) < 0.7
    assert res[-1] < 1e-8
    assert np.linalg.norm(b - K @ x) / np.linalg.norm(b) < 1e-8
    assert abs(x.mean()) < 1e-14
    # same solution as a direct solve with the constant removed
    keep = np.arange(1, len(V))
    xd = np.zeros(len(V))
    xd[keep] = spla.spsolve(K[keep][:, keep].tocsc(), b[keep])
    xd -= xd.mean()
    assert np.abs(x - xd).max() < 1e-7 * np.abs(xd).max()


def test_incompatible_neumann_rhs_raises_or_projects(cube):
    _meshes, Ps, K, M = cube
    ml = MultigridSolver(K, Ps, nullspace="constant")
    b = fem.load_vector(M, 1.0)  # ∫1 ≠ 0: no solution
    with pytest.raises(IncompatibleRHSError, match="incompatible"):
        ml.solve(b)
    x = ml.solve(b + 0.0, project=True, tol=1e-10)
    assert np.linalg.norm(K @ x - fem.project_rhs(b)) < 1e-9 * np.linalg.norm(b)
    assert isinstance(IncompatibleRHSError("x"), ValueError)


@pytest.mark.parametrize("problem", ["dirichlet", "neumann"])
def test_w_and_f_cycles_at_least_as_fast_as_v(cube, problem):
    _meshes, Ps, K, _M = cube
    # two sweeps on every level, the cycle measured below: with the default's four on the coarse levels the
    # V-cycle is as good as W and F here (Dirichlet V 0.204, W 0.202)
    two = [solvers.multilevel.DEFAULT_SMOOTHER] * 2
    if problem == "dirichlet":
        ds, Pf, _ = _dirichlet(cube, 4)
        ml, b = MultigridSolver(ds.A, Pf, presmoother=two), _random_rhs(ds.A.shape[0], 1)
    else:
        ml = MultigridSolver(K, Ps, nullspace="constant", presmoother=two)
        b = fem.project_rhs(_random_rhs(K.shape[0], 1))
    fv, _ = _factor(ml, b, "V")
    fw, _ = _factor(ml, b, "W")
    ff, _ = _factor(ml, b, "F")
    # measured (4 levels): Dirichlet V 0.224, W 0.203, F 0.203; Neumann V 0.243, W 0.217, F 0.217
    assert fw <= fv - 0.01 and ff <= fv - 0.01, (fv, fw, ff)
    assert ml.cycle_complexity("V") < ml.cycle_complexity("F") < ml.cycle_complexity("W")


@pytest.mark.parametrize("cycle, visits", [("V", [1, 1, 1]), ("W", [1, 2, 4]), ("F", [1, 2, 3])])
def test_cycle_visits_each_level_as_documented(cube, cycle, visits):
    """Count smoother calls per level in one cycle (5 levels: 4 smoothed + coarsest solve)."""
    meshes, Ps = kuhn_cube_hierarchy(16, 5)
    K = fem.stiffness_matrix(*meshes[0])
    ml = MultigridSolver(K, Ps, nullspace="constant")
    calls = np.zeros(len(ml.levels) - 1, dtype=int)
    for k, L in enumerate(ml.levels[:-1]):
        inner = L.presmoother.apply

        def counted(A, x, b, k=k, inner=inner):
            calls[k] += 1
            inner(A, x, b)

        L.presmoother.apply = counted
        L.presmoother.smooth_residual = None  # every visit through apply (the fast path bypasses it)
    ml.aspreconditioner(cycle) @ fem.project_rhs(_random_rhs(K.shape[0]))
    # levels 0..2 as listed; level 3 (next to the coarsest): V 1, W 8, F 4 (level 2's F visit
    # calls F and V on level 3, each of its two V visits calls V once)
    expected = visits + [{"V": 1, "W": 8, "F": 4}[cycle]]
    np.testing.assert_array_equal(calls, expected)
    np.testing.assert_array_equal(ml._visits(cycle)[:-1], expected)


def test_pcg_iterations_independent_of_levels(cube):
    its = {}
    for levels in (2, 3, 4):
        ds, Pf, _ = _dirichlet(cube, levels)
        ml = MultigridSolver(ds.A, Pf)
        x, info = ml.solve(ds.b, tol=1e-8, accel="cg", return_info=True)
        assert info["converged"] and np.linalg.norm(ds.b - ds.A @ x) <= 1e-8 * np.linalg.norm(ds.b)
        its[levels] = info["iterations"]
    assert max(its.values()) - min(its.values()) <= 2, its
    assert max(its.values()) <= 12, its


def test_aspreconditioner_with_scipy_cg(cube):
    ds, Pf, _ = _dirichlet(cube, 4)
    ml = MultigridSolver(ds.A, Pf)
    M = ml.aspreconditioner()
    assert isinstance(M, spla.LinearOperator) and M.shape == ds.A.shape
    counts = {"mg": 0, "none": 0}

    def cb(key):
        def f(xk):
            counts[key] += 1
        return f

    x, info = spla.cg(ds.A, ds.b, M=M, rtol=1e-8, callback=cb("mg"))
    assert info == 0 and np.linalg.norm(ds.b - ds.A @ x) <= 1e-8 * np.linalg.norm(ds.b)
    spla.cg(ds.A, ds.b, rtol=1e-8, callback=cb("none"))
    assert counts["mg"] <= 12 and counts["none"] > 4 * counts["mg"], counts
    # the preconditioner is symmetric: <M u, v> = <u, M v>
    rng = np.random.default_rng(3)
    u, v = rng.standard_normal((2, ds.A.shape[0]))
    assert abs((M @ u) @ v - u @ (M @ v)) < 1e-10 * abs(u @ (M @ v))


@pytest.mark.parametrize("lam", [1e-3, 1e-2, 1e-1, 1.0, 10.0])
def test_diffusion_converges_galerkin_and_rediscretized(cube, lam):
    meshes, Ps, K, M = cube
    A = fem.diffusion_matrix(K, M, lam)
    coarse = [fem.diffusion_matrix(fem.stiffness_matrix(V, T), fem.mass_matrix(V, T), lam) for V, T in meshes[1:]]
    b = M @ _random_rhs(K.shape[0], 2)
    for ml in (MultigridSolver(A, Ps), MultigridSolver(A, Ps, coarse=coarse)):
        f, res = _factor(ml, b)
        assert res[-1] < 1e-11 and f < 0.3, (lam, ml.coarse, f)


def test_rediscretized_coarse_operators_converge(cube):
    meshes, Ps, K, _M = cube
    Ks = [fem.stiffness_matrix(V, T) for V, T in meshes]
    # Neumann: coarse stiffness matrices on the coarse Kuhn meshes
    ml = MultigridSolver(K, Ps, coarse=Ks[1:], nullspace="constant")
    assert ml.coarse == "given"
    f, res = _factor(ml, fem.project_rhs(_random_rhs(K.shape[0], 4)), tol=1e-10)
    assert f < 0.7 and res[-1] < 1e-10
    # Dirichlet: eliminate the boundary on every level, coarse interior nodes free
    free = [np.setdiff1d(np.arange(len(V)), fem.boundary_nodes(T)) for V, T in meshes]
    Pf, frees = restrict_prolongations(Ps, free[0], coarse_free=free[1:])
    for fr, f_expected in zip(frees, free):
        np.testing.assert_array_equal(fr, f_expected)
    ml = MultigridSolver(Ks[0][free[0]][:, free[0]], Pf, coarse=[k[f][:, f] for k, f in zip(Ks[1:], free[1:])])
    f, res = _factor(ml, _random_rhs(free[0].size, 5))
    assert f < 0.3 and res[-1] < 1e-11


def test_nan_raises_divergence_error_naming_cycle_and_level(cube):
    ds, Pf, _ = _dirichlet(cube, 3)
    for accel in (None, "cg"):
        ml = MultigridSolver(ds.A, Pf)
        ml.levels[1].A.data[7] = np.nan  # corrupt the level-1 operator after setup
        with pytest.raises(DivergenceError, match="level 1") as ei:
            ml.solve(ds.b, accel=accel)
        assert ei.value.level == 1 and ei.value.cycle == 1


def test_growing_residual_raises_divergence_error(cube):
    ds, Pf, _ = _dirichlet(cube, 3)
    g = MultigridSolver(ds.A, Pf)
    # coarse operators 0.3x too weak: the coarse correction overshoots ~3x, the cycle diverges
    bad = MultigridSolver(ds.A, Pf, coarse=[0.3 * L.A for L in g.levels[1:]])
    with pytest.raises(DivergenceError, match="diverges") as ei:
        bad.solve(ds.b, maxiter=200)
    assert 2 <= ei.value.cycle < 200 and ei.value.residuals[-1] > 1e5


def test_bad_inputs(cube):
    meshes, Ps, K, _M = cube
    ds, Pf, _ = _dirichlet(cube, 3)
    with pytest.raises(SolverInputError, match="rows"):
        MultigridSolver(ds.A, Ps[:1])  # unrestricted P: wrong number of rows
    with pytest.raises(SolverInputError, match=r"coarse needs 2 matrices"):
        MultigridSolver(ds.A, Pf, coarse=[ds.A])
    with pytest.raises(SolverInputError, match="sum"):
        MultigridSolver(K, [0.9 * Ps[0]], nullspace="constant")
    with pytest.raises(SolverError, match="constants"):
        MultigridSolver(K, Ps[:1], coarse=[fem.mass_matrix(*meshes[1])], nullspace="constant")
    with pytest.raises(SolverInputError, match="NaN"):
        MultigridSolver(ds.A, Pf).solve(np.full(ds.A.shape[0], np.nan))
    with pytest.raises(SolverInputError, match="shape"):
        MultigridSolver(ds.A, Pf).solve(np.ones(3))
    with pytest.raises(SolverInputError, match="cycle"):
        MultigridSolver(ds.A, Pf).solve(ds.b, cycle="X")
    with pytest.raises(SolverInputError, match="smoother"):
        MultigridSolver(ds.A, Pf, presmoother="ilu")


def test_keeping_every_coarse_node_is_caught(cube):
    """Restricting only the fine rows leaves cube corners with empty Galerkin rows: those coarse nodes are
    dropped (as restrict_prolongations does); given coarse operators with an empty row are refused."""
    ds, Pf, _ = _dirichlet(cube, 2)
    _meshes, Ps, _K, _M = cube
    ml = MultigridSolver(ds.A, [Ps[0][ds.free]])
    assert ml.levels[1].A.shape == (Pf[0].shape[1],) * 2
    G = MultigridSolver(ds.A, Pf).levels[1].A
    assert abs(ml.levels[1].A - G).max() == 0.0
    bad = sp.csr_matrix((Ps[0].shape[1],) * 2)
    with pytest.raises(SolverError, match="restrict_prolongations"):
        MultigridSolver(ds.A, [Ps[0][ds.free]], coarse=[bad])


def test_dropping_unreached_columns_equals_restricting_to_every_node(cube):
    """The constructor's O(nnz) column drop gives restrict_prolongations' matrices (every fine node free)
    bit for bit, down the levels, with explicit zeros; a hierarchy without unreached columns is kept."""
    ds, _Pf, _ = _dirichlet(cube, 3)
    _meshes, Ps, _K, _M = cube
    raw = [sp.csr_matrix(Ps[0][ds.free])] + [sp.csr_matrix(P) for P in Ps[1:3]]
    raw[0].data[::7] = 0.0  # explicit zeros: restrict_prolongations drops them before taking the support
    want, _ = restrict_prolongations(raw, np.arange(raw[0].shape[0]))
    got = transfer._drop_unreached_columns(raw)
    assert [P.shape for P in got] == [P.shape for P in want]
    assert got[0].shape[1] < raw[0].shape[1] and got[1].shape[0] < raw[1].shape[0]
    for g, w in zip(got, want):
        assert np.array_equal(g.indptr, w.indptr) and np.array_equal(g.indices, w.indices)
        assert np.array_equal(g.data, w.data) and g.has_sorted_indices
    kept = transfer._drop_unreached_columns(want)
    assert all(a is b for a, b in zip(kept, want))


@pytest.mark.parametrize("cap", [transfer.ONE_PASS_MAX_ENTRIES, 11950, 0])  # 11950: the per-row bound
def test_one_pass_product_is_scipys_product(cube, monkeypatch, cap):
    """The Galerkin products' one-pass kernel gives scipy's A @ B bit for bit (empty rows, a row bound that
    exceeds the column count, the per-row bound, the fallback), and the Galerkin chain with it equals
    R (A P) symmetrised."""
    monkeypatch.setattr(transfer, "ONE_PASS_MAX_ENTRIES", cap)
    rng = np.random.default_rng(3)
    A = sp.random(300, 200, density=0.05, format="csr", random_state=rng)
    A.data[A.indptr[5]:A.indptr[6]] = 0.0  # an empty row
    A.eliminate_zeros()
    B = sp.random(200, 40, density=0.3, format="csr", random_state=rng)
    for X, Y in ((A, B), (B.T.tocsr(), A.T.tocsr()), (A[:, :0].tocsr(), B[:0].tocsr())):
        want, got = sp.csr_matrix(X @ Y), transfer._one_pass_product(X, Y)
        assert got.shape == want.shape
        assert np.array_equal(got.indptr, want.indptr) and np.array_equal(got.indices, want.indices)
        assert np.array_equal(got.data, want.data)
    _meshes, Ps, K, _M = cube
    ops = transfer.galerkin_operators(K, Ps[:2])
    for k, P in enumerate(Ps[:2]):
        P = sp.csr_matrix(P)
        ref = sp.csr_matrix(P.T @ (ops[k] @ P))
        ref = sp.csr_matrix(0.5 * (ref + ref.T))
        assert abs(ops[k + 1] - ref).max() <= 1e-14 * abs(ref).max()


def _barycentric_like(n: int, m: int, empty: int, rng) -> sp.csr_matrix:
    """(n, m) prolongation with 4 non-zeros per row summing to 1 and no entry in column ``empty``."""
    cols = np.array([rng.choice(np.setdiff1d(np.arange(m), [empty]), 4, replace=False) for _ in range(n)])
    w = rng.random((n, 4)) + 0.05
    w /= w.sum(axis=1, keepdims=True)
    return sp.csr_matrix((w.ravel(), cols.ravel(), np.arange(0, 4 * n + 1, 4)), shape=(n, m))


def test_symmetric_galerkin_product_equals_ptap():
    """The symmetric path (B + Bᵀ, B = Pᵀ (L + D/2) P) equals P.T @ A @ P to 1e-12 relative on a random
    sparse SPD A and on a symmetric A with an empty row and a row without its diagonal, with a
    barycentric-like P (4 non-zeros per row, rows summing to 1) that has an empty column: exactly
    symmetric, canonical, the empty column's row and column of Ac empty; and A's lower half mirrored gives
    A back exactly."""
    rng = np.random.default_rng(7)
    n, m, empty = 500, 70, 13
    S = sp.random(n, n, density=0.02, format="csr", random_state=rng)
    S = sp.csr_matrix(S + S.T)
    spd = sp.csr_matrix(S + sp.diags(abs(S).sum(axis=1).A.ravel() + 0.1))
    assert np.linalg.eigvalsh(spd.toarray()).min() > 0
    hole = sp.lil_matrix(spd)
    hole[7, :] = 0.0
    hole[:, 7] = 0.0
    hole[11, 11] = 0.0  # a row without its diagonal
    hole = sp.csr_matrix(hole)
    hole.eliminate_zeros()
    P = _barycentric_like(n, m, empty, rng)
    assert np.allclose(P.sum(axis=1), 1.0) and P.getcol(empty).nnz == 0
    for A in (spd, hole):
        A.sort_indices()
        half, d = transfer._lower_half(A)
        assert abs(half + half.T - A).max() == 0.0 and np.array_equal(d, A.diagonal())
        # rows in another order (a permuted fine matrix's): the same split
        shuffle = np.concatenate([A.indptr[i] + rng.permutation(A.indptr[i + 1] - A.indptr[i]) for i in range(n)])
        U = sp.csr_matrix((A.data[shuffle], A.indices[shuffle], A.indptr.copy()), shape=A.shape)
        U.has_sorted_indices = False
        half_u, d_u = transfer._lower_half(U)
        assert abs(half_u - half).max() == 0.0 and np.array_equal(d_u, d)
        Ac = transfer.galerkin_operators(A, [P])[1]
        ref = sp.csr_matrix(P.T @ A @ P)
        assert abs(Ac - ref).max() <= 1e-12 * abs(ref).max()
        assert abs(Ac - Ac.T).max() == 0.0 and Ac.has_canonical_format and Ac.has_sorted_indices
        assert Ac.getrow(empty).nnz == 0 and Ac.getcol(empty).nnz == 0
        assert np.array_equal(np.diff(Ac.indptr) > 0, np.diff(ref.indptr) > 0)


def test_galerkin_products_hand_their_lower_triangles_to_the_sweeps(cube, monkeypatch):
    """The symmetric Galerkin products keep each split's ``D + L`` (diagonal restored exactly, diagonal
    first) for the forward sweeps' residual shortcut, so no level is split again at the first cycle; the
    preconditioner equals the plain cycle's (every residual ``b - A x``) to round-off, Dirichlet and Neumann."""
    from solvers import smoothing, transfer

    ds, Pf, _ = _dirichlet(cube, 3)
    kept: list = []
    chain = transfer._galerkin_chain

    def spy(*args, lowers=None, **kw):
        out = chain(*args, lowers=lowers, **kw)
        kept.extend(lowers)
        return out

    monkeypatch.setattr("solvers.multilevel._galerkin_chain", spy)
    monkeypatch.setattr(smoothing, "triangular_split", lambda A: pytest.fail("a level was split again"))
    _, Ps, K, _ = cube
    for A, P, nullspace in ((ds.A, Pf, None), (K, Ps[:2], "constant")):
        kept.clear()
        ml = MultigridSolver(A, P, nullspace=nullspace)
        assert len(kept) == len(ml.levels) - 1
        for L, DL in zip(ml.levels[:-1], kept):
            assert abs(DL - sp.tril(L.A)).max() == 0.0 and DL.nnz == sp.tril(L.A).nnz
            assert np.array_equal(DL.indices[DL.indptr[:-1]], np.arange(L.A.shape[0]))  # diagonal first
        r = _random_rhs(A.shape[0], 3)
        if nullspace:
            r -= r.mean()
        fast = ml.aspreconditioner() @ r
        for L in ml.levels[:-1]:
            L.presmoother.smooth_residual = None
        plain = ml.aspreconditioner() @ r
        assert np.abs(fast - plain).max() <= 1e-12 * np.abs(plain).max()


def test_inputs_untouched_and_x0(cube):
    ds, Pf, _ = _dirichlet(cube, 3)
    A0, P0, b0 = ds.A.copy(), Pf[0].copy(), ds.b.copy()
    ml = MultigridSolver(ds.A, Pf)
    x0 = np.ones(ds.A.shape[0])
    x = ml.solve(ds.b, x0=x0, tol=1e-9)
    assert np.array_equal(x0, np.ones_like(x0)) and np.array_equal(ds.b, b0)
    assert abs(ds.A - A0).max() == 0 and abs(Pf[0] - P0).max() == 0
    res = []
    ml.solve(ds.b, x0=x, residuals=res, tol=1e-9)
    assert len(res) <= 2  # already converged from the previous solution


def test_maxiter_warns(cube):
    ds, Pf, _ = _dirichlet(cube, 3)
    ml = MultigridSolver(ds.A, Pf)
    with pytest.warns(ConvergenceWarning):
        _x, info = ml.solve(ds.b, tol=1e-14, maxiter=2, return_info=True)
    assert info["iterations"] == 2 and not info["converged"]


def test_single_level_is_a_direct_solve(cube):
    ds, _, _ = _dirichlet(cube, 2)
    ml = MultigridSolver(ds.A, [])
    res = []
    x = ml.solve(ds.b, residuals=res)
    assert len(res) == 2 and res[-1] < 1e-13
    _meshes, _Ps, K, _M = cube
    mln = MultigridSolver(K, [], nullspace="constant")
    b = fem.project_rhs(_random_rhs(K.shape[0]))
    x = mln.solve(b)
    assert np.linalg.norm(K @ x - b) < 1e-10 * np.linalg.norm(b) and abs(x.mean()) < 1e-14


def test_complexities_and_repr(cube):
    ds, Pf, _ = _dirichlet(cube, 4)
    ml = MultigridSolver(ds.A, Pf)
    nnz = [L.A.nnz for L in ml.levels]
    assert ml.operator_complexity() == pytest.approx(sum(nnz) / nnz[0])
    assert 1.0 < ml.operator_complexity() < 1.4
    # V(1,1) with symmetric GS: 2+2 sweeps + residual ≈ 5 SpMV on level 0, plus coarser levels and P's
    assert 5.0 < ml.cycle_complexity("V") < 9.0
    r = repr(ml)
    assert "Number of levels:     4" in r and f"{ml.levels[0].A.shape[0]:10d}" in r and "nnz(P)" in r


def test_forward_gauss_seidel_gets_adjoint_postsmoother(cube):
    ds, Pf, _ = _dirichlet(cube, 3)
    ml = MultigridSolver(ds.A, Pf, presmoother="gauss_seidel")
    assert ml.levels[0].postsmoother.params["sweep"] == "backward" and ml.symmetric_cycle
    _x, info = ml.solve(ds.b, accel="cg", return_info=True)
    assert info["converged"] and info["iterations"] <= 15
    nonsym = MultigridSolver(ds.A, Pf, presmoother="gauss_seidel", postsmoother="gauss_seidel")
    assert not nonsym.symmetric_cycle
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        nonsym.solve(ds.b, accel="cg", maxiter=5)
    assert any("non-symmetric" in str(w.message) for w in caught)


def test_restrict_prolongations_support_rule(cube):
    _meshes, Ps, _K, _M = cube
    ds, Pf, frees = _dirichlet(cube, 4)
    for k, P in enumerate(Pf):
        assert P.shape == (frees[k].size, frees[k + 1].size)
        assert np.all(np.diff(P.tocsc().indptr) > 0)  # every kept coarse node touches a free fine node
    # dropped coarse nodes really have no support on free fine nodes
    dropped = np.setdiff1d(np.arange(Ps[0].shape[1]), frees[1])
    assert dropped.size > 0 and Ps[0][ds.free][:, dropped].nnz == 0
    with pytest.raises(SolverInputError):
        restrict_prolongations(Ps, ds.free, coarse_free=[frees[1]])


@pytest.fixture(scope="module")
def jittered():
    """Non-nested fine level: Kuhn n=16 with interior nodes moved by up to 0.2 h, over exact Kuhn 8/4/2."""
    rng = np.random.default_rng(11)
    V, T = kuhn_cube_mesh(N)
    bnd = fem.boundary_nodes(T)
    inner = np.setdiff1d(np.arange(len(V)), bnd)
    V[inner] += rng.uniform(-0.2 / N, 0.2 / N, (inner.size, 3))
    coarse_meshes, coarse_Ps = kuhn_cube_hierarchy(N // 2, 3)
    Ps = [kuhn_interpolation(V, N // 2), *coarse_Ps]
    return V, T, bnd, coarse_meshes, Ps


@pytest.mark.parametrize("bc", ["dirichlet", "neumann", "mixed"])
@pytest.mark.parametrize("coarse", ["galerkin", "rediscretized"])
def test_unstructured_fine_level_converges(jittered, bc, coarse):
    """Measured: Galerkin 0.22 (all three BCs), re-discretised 0.27; MG-PCG 8 iterations (V(2,2) on every
    level: the default would smooth the denser Galerkin levels once, a faster preconditioner but a weaker
    stationary cycle, 0.33)."""
    V, T, bnd, meshes, Ps = jittered
    v22 = ("gauss_seidel", {"sweep": "forward", "iterations": 2})  # explicit: two sweeps on every level
    K, M = fem.stiffness_matrix(V, T), fem.mass_matrix(V, T)
    b_full = fem.load_vector(M, np.sin(3 * V[:, 0]) + V[:, 1])
    Kc = [fem.stiffness_matrix(*m) for m in meshes]
    if bc == "neumann":
        A, b, Pl = K, fem.project_rhs(b_full), Ps
        ops = Kc
        ml = MultigridSolver(A, Pl, nullspace="constant", coarse=ops if coarse != "galerkin" else "galerkin",
                             presmoother=v22)
    else:
        fixed = bnd if bc == "dirichlet" else np.flatnonzero(V[:, 0] < 1e-12)
        ds = fem.eliminate_dirichlet(K, b_full, fixed)
        A, b = ds.A, ds.b
        if coarse == "galerkin":
            Pl, _ = restrict_prolongations(Ps, ds.free)
            ops = "galerkin"
        else:
            # coarse Dirichlet nodes: the coarse nodes on the same part of the boundary
            frees = []
            for Vc, Tc in meshes:
                cb = fem.boundary_nodes(Tc) if bc == "dirichlet" else np.flatnonzero(Vc[:, 0] < 1e-12)
                frees.append(np.setdiff1d(np.arange(len(Vc)), cb))
            Pl, _ = restrict_prolongations(Ps, ds.free, coarse_free=frees)
            ops = [k[f][:, f] for k, f in zip(Kc, frees)]
        ml = MultigridSolver(A, Pl, coarse=ops, presmoother=v22)
    f, res = _factor(ml, b)
    assert res[-1] < 1e-11 and f < (0.3 if coarse == "galerkin" else 0.35), f
    _x, info = ml.solve(b, accel="cg", tol=1e-8, return_info=True)
    assert info["converged"] and info["iterations"] <= 10


def _split_column(P, j):
    """P with coarse column j split into two identical half columns: rows still sum to 1, rank - 1."""
    P = P.tocsc()
    half = 0.5 * P[:, [j]]
    return sp.hstack([P[:, :j], half, P[:, j + 1 :], half]).tocsr()


@pytest.mark.parametrize("bc", ["dirichlet", "neumann"])
@pytest.mark.parametrize("dense_max", [0, 1500])
def test_rank_deficient_prolongation(cube, bc, dense_max, monkeypatch):
    """Extra null vectors of P^T A P (rank-deficient P): pseudo-inverse and pivoted Cholesky cope, SuperLU
    refuses clearly; on a small coarsest level "auto" goes straight to the regularised dense factor."""
    import solvers.coarse

    monkeypatch.setattr(solvers.coarse, "DENSE_MAX", dense_max)
    _meshes, Ps, K, _M = cube
    Ps = Ps[:2]
    if bc == "neumann":
        A, b, nullspace = K, fem.project_rhs(_random_rhs(K.shape[0], 6)), "constant"
    else:
        ds, Ps, _ = _dirichlet(cube, 3)
        A, b, nullspace = ds.A, _random_rhs(ds.A.shape[0], 6), None
    j = Ps[1].shape[1] // 2
    bad = [Ps[0], _split_column(Ps[1], j)]
    ref = MultigridSolver(A, Ps, nullspace=nullspace)
    ml = MultigridSolver(A, bad, nullspace=nullspace)  # auto: SuperLU fails validation -> guarded regularised
    expected = 1 if nullspace == "constant" else 0
    if dense_max:  # dense: the regularised (band) factor first, no fallback
        assert ml._coarse_solver.method == "regularized" and ml._coarse_solver.dense and "(dense)" in repr(ml)
        assert not ml._coarse_solver.fallback and not ref._coarse_solver.fallback
    else:  # a well-conditioned range: the guard keeps the sparse regularised factor
        assert ml._coarse_solver.method == "guarded" and ml._coarse_solver.fallback and "fallback" in repr(ml)
        assert ml.coarsest_solver["method"] == "guarded" and ml.coarsest_solver["unknowns"] == Ps[1].shape[1] + 1
        assert not ml._coarse_solver.dense
        pv = MultigridSolver(A, bad, nullspace=nullspace, coarse_solver="pivoted")
        assert pv.coarse_nullity == expected + 1  # the pivoted factor sees the extra null vector too
    mp = MultigridSolver(A, bad, nullspace=nullspace, coarse_solver="pinv")
    assert mp.coarse_nullity == expected + 1  # the pseudo-inverse sees the extra null vector
    assert ref.coarse_nullity == (-1 if dense_max else expected)  # the regularised factor does not count
    fp, resp = _factor(mp, b)
    assert resp[-1] < 1e-11 and fp <= _factor(ref, b)[0] + 0.01
    assert ref._coarse_solver.method == ("regularized" if dense_max else "splu")
    assert not ref._coarse_solver.fallback
    f_ref, _ = _factor(ref, b)
    f, res = _factor(ml, b)
    assert res[-1] < 1e-11 and f <= f_ref + 0.01, (f, f_ref)  # the split column adds nothing, breaks nothing
    x, xr = ml.solve(b, tol=1e-10), ref.solve(b, tol=1e-10)
    assert np.abs(x - xr).max() < 1e-8 * np.abs(xr).max()
    with pytest.raises(SolverError, match="rank-deficient"):
        MultigridSolver(A, bad, nullspace=nullspace, coarse_solver="splu")


def test_guard_refuses_the_regularised_factor_on_an_ill_conditioned_range(monkeypatch):
    """"auto"'s guarded regularised factor: kept on a singular level whose range is well conditioned, refused
    (the pivoted Cholesky instead) when a range eigenvalue sits at 1e-8 of the diagonal, where the regularised
    solve is off by about 10 % along it."""
    import solvers.coarse
    from solvers.coarse import _CoarseSolver

    monkeypatch.setattr(solvers.coarse, "DENSE_MAX", 0)
    n = 300
    L = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    rng = np.random.default_rng(3)
    Z = np.linalg.qr(rng.standard_normal((n, 2)))[0]  # two null vectors, like a rank-deficient P
    Pz = np.eye(n) - Z @ Z.T
    good = sp.csr_matrix(Pz @ L.toarray() @ Pz)
    cs = _CoarseSolver(good, None, 2, "auto")
    assert cs.method == "guarded" and cs.fallback
    w, V = np.linalg.eigh(good.toarray())
    v = V[:, 2]  # the smallest range eigenvalue, 1e-4 of the diagonal: bring it down to 1e-8
    bad = sp.csr_matrix(good.toarray() - (w[2] - 1e-8 * good.diagonal().mean()) * np.outer(v, v))
    cs = _CoarseSolver(bad, None, 2, "auto")
    assert cs.method == "pivoted" and cs.nullity == 2
    b = bad @ v
    scale = np.abs(v).max()
    assert np.abs(cs(b) - v).max() < 1e-5 * scale  # exact along the small eigenvector ...
    reg = _CoarseSolver(bad, None, 2, "regularized")
    assert np.abs(reg(b) - v).max() > 0.05 * scale  # ... where the regularised solve is ~10 % off


def test_coarse_solvers_agree(cube, monkeypatch):
    import solvers.coarse

    _meshes, Ps, K, _M = cube
    b = fem.project_rhs(_random_rhs(K.shape[0], 8))
    xs = []
    for method in ("splu", "pinv", "pivoted", "regularized"):
        ml = MultigridSolver(K, Ps[:2], nullspace="constant", coarse_solver=method)
        assert ml._coarse_solver.method == method
        assert ml.coarse_nullity == (1 if method != "regularized" else -1)
        assert f"Coarsest solver:      {method}" in repr(ml)
        xs.append(ml.solve(b, tol=1e-11))
    for x, tol in zip(xs[1:], (1e-9, 1e-9, 1e-8)):
        assert np.abs(xs[0] - x).max() < tol * np.abs(xs[0]).max()
    # above PIVOTED_MAX and pinv_max the sparse regularised LU still copes with a rank-deficient coarsest
    # level
    bad = [Ps[0], _split_column(Ps[1], 10)]
    monkeypatch.setattr(solvers.coarse, "PIVOTED_MAX", 50)
    ml = MultigridSolver(K, bad, nullspace="constant", pinv_max=100)
    assert ml._coarse_solver.method == "regularized"
    assert np.abs(ml.solve(b, tol=1e-11) - xs[0]).max() < 1e-8 * np.abs(xs[0]).max()
    with pytest.raises(SolverInputError, match="coarse_solver"):
        MultigridSolver(K, Ps[:1], nullspace="constant", coarse_solver="cholesky")


def test_prune_prolongations_removes_weightless_coarse_nodes(cube):
    """A coarse node touching one fine node with weight 0.01: pruning restores the clean hierarchy."""
    _meshes, Ps, K, _M = cube
    P0 = Ps[0].tolil(copy=True)
    i = 1000
    P0[i, :] = 0.99 * P0[i, :].toarray()
    extra = sp.csr_matrix(([0.01], ([i], [0])), shape=(P0.shape[0], 1))
    P0 = sp.hstack([P0.tocsr(), extra]).tocsr()  # new coarse node n_1, column sum 0.01
    P1 = sp.vstack([Ps[1], sp.csr_matrix(Ps[1][:1].toarray())]).tocsr()  # its row on level 1
    bad = [P0, P1, Ps[2]]
    pruned, kept = prune_prolongations(bad, min_column_sum=0.2)
    assert kept[0].size == Ps[0].shape[1] and kept[0][-1] == Ps[0].shape[1] - 1
    for Pp, P in zip(pruned, Ps[:3]):
        assert Pp.shape == P.shape and abs(Pp - P).max() < 1e-15
    # the weightless node makes the Galerkin hierarchy worse-conditioned; pruned = the clean one
    b = fem.project_rhs(_random_rhs(K.shape[0], 9))
    f_clean, _ = _factor(MultigridSolver(K, Ps[:3], nullspace="constant"), b)
    f_pruned, _ = _factor(MultigridSolver(K, pruned, nullspace="constant"), b)
    assert f_pruned == pytest.approx(f_clean, abs=1e-12)
    # without renormalisation the row that lost weight no longer sums to 1
    raw, _ = prune_prolongations(bad, 0.2, renormalize=False)
    assert np.asarray(raw[0].sum(axis=1)).ravel()[i] == pytest.approx(0.99)
    with pytest.raises(SolverInputError, match="column sum"):
        prune_prolongations(Ps[:1], min_column_sum=100.0)


def test_convergence_factor_helper():
    r = [1.0 * 0.5**k for k in range(10)]
    assert convergence_factor(r) == pytest.approx(0.5)
    assert convergence_factor([1.0, 0.1, 0.01, 1e-17, 1e-18]) == pytest.approx(0.1)  # round-off tail ignored
    assert np.isnan(convergence_factor([1.0]))


def test_docstring_examples():
    failures, tests = doctest.testmod(solvers.multilevel, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert tests >= 4 and failures == 0
    failures, tests = doctest.testmod(transfer, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert tests >= 4 and failures == 0


# ----------------------------------------------------------------------------- issue 15: coarse scaling
def test_energy_scaling_recovers_galerkin_from_scaled_operators(cube):
    """Coarse operators 0.3x too soft diverge (test above); energy-scaled, they give the same cycle as
    energy-scaled Galerkin operators: every correction is ``1/0.3`` times larger and ``α`` undoes it.
    """
    ds, Pf, _ = _dirichlet(cube, 3)
    g = MultigridSolver(ds.A, Pf)
    ge = MultigridSolver(ds.A, Pf, coarse_scaling="energy")
    soft = [0.3 * L.A for L in g.levels[1:]]
    fixed = MultigridSolver(ds.A, Pf, coarse=soft, coarse_scaling="energy")
    assert fixed.coarse == "given" and fixed.coarse_scaling == "energy"
    f_g, _ = _factor(g, ds.b)
    f_ge, res_ge = _factor(ge, ds.b)
    f_s, res_s = _factor(fixed, ds.b)
    # identical up to round-off: the first 8 residuals agree to 1e-6; the factor (from the last ratios,
    # near 1e-8) to 1e-4 (the given operators are sorted, the Galerkin ones stored diagonal first: the
    # sweeps add each row in another order, 2e-5 apart here)
    assert f_s == pytest.approx(f_ge, abs=1e-4)
    assert np.allclose(res_s[:8], res_ge[:8], rtol=1e-6)
    # with Galerkin operators the scaling only tunes the step after inexact inner cycles (measured
    # 0.228 -> 0.202 on this 3-level cube)
    assert f_g < 0.3 and f_ge <= f_g + 1e-9
    # flexible MG-PCG with the scaled cycle converges like Galerkin MG-PCG
    its = [ml.solve(ds.b, tol=1e-8, accel="cg", return_info=True)[1]["iterations"] for ml in (g, fixed)]
    assert abs(its[0] - its[1]) <= 1 and its[1] <= 10


def test_coarse_keyword_is_the_only_spelling(cube):
    """Given coarse operators go through ``coarse=`` alone: the 0.1 alias ``coarse_operators=`` is gone."""
    ds, Pf, _ = _dirichlet(cube, 3)
    g = MultigridSolver(ds.A, Pf)
    ops = [L.A for L in g.levels[1:]]
    given = MultigridSolver(ds.A, Pf, coarse=ops)
    assert given.coarse == "given" and [L.A.nnz for L in given.levels] == [L.A.nnz for L in g.levels]
    with pytest.raises(TypeError, match="coarse_operators"):
        MultigridSolver(ds.A, Pf, coarse_operators=ops)
    with pytest.raises(SolverInputError, match="galerkin"):
        MultigridSolver(ds.A, Pf, coarse="weighted")  # named operators are built by nestmg
    with pytest.raises(SolverInputError, match="coarse_scaling"):
        MultigridSolver(ds.A, Pf, coarse_scaling="alpha")


def test_restrict_prolongations_prunes_with_orphan_rule(cube):
    """min_column_sum drops weak coarse nodes and renormalises rows, unless a row would lose all weight."""
    _meshes, Ps, _K, _M = cube
    P0 = Ps[0].tolil(copy=True)
    i = 1000
    P0[i, :] = 0.99 * P0[i, :].toarray()
    P0[1001, :] = 0
    extra = sp.csr_matrix(([0.01, 1.0], ([i, 1001], [0, 0])), shape=(P0.shape[0], 1))
    P0 = sp.hstack([P0.tocsr(), extra]).tolil()  # fine node 1001 hangs on the extra node only (an orphan if it were dropped)
    n0 = P0.shape[0]
    Pr, frees = restrict_prolongations([P0.tocsr()], np.arange(n0), min_column_sum=1.5)
    assert frees[1][-1] == P0.shape[1] - 1  # column sum 1.01 < 1.5, kept: row 1001 depends on it
    P0[1001, 5] = 1.0
    P0[1001, P0.shape[1] - 1] = 0.0
    Pr, frees = restrict_prolongations([P0.tocsr()], np.arange(n0), min_column_sum=1.5)
    assert frees[1][-1] != P0.shape[1] - 1  # now weak (0.01) and nobody's only support: dropped
    assert np.allclose(np.asarray(Pr[0].sum(axis=1)).ravel(), 1.0)


def test_galerkin_of_nonsymmetric_operator_is_exact():
    """Only symmetric operators get their Galerkin products symmetrised; a non-symmetric A keeps PᵀAP."""
    meshes, Ps = kuhn_cube_hierarchy(6, 2)
    K = fem.stiffness_matrix(*meshes[0])
    n = K.shape[0]
    N = sp.random(n, n, density=2e-3, random_state=1)
    A = (K + sp.eye(n) + 0.01 * (N - N.T)).tocsr()
    ops = transfer.galerkin_operators(A, Ps)
    assert abs(ops[1] - (Ps[0].T @ A @ Ps[0])).max() < 1e-14
    assert abs(ops[1] - ops[1].T).max() > 1e-3
    assert not MultigridSolver(A, Ps).symmetric
    S = transfer.galerkin_operators((K + sp.eye(n)).tocsr(), Ps)[1]
    assert abs(S - S.T).max() == 0.0 and MultigridSolver((K + sp.eye(n)).tocsr(), Ps).symmetric


def test_is_symmetric_fast_path_agrees_with_subtraction():
    # the canonical-CSR fast path (transpose, compare arrays) must decide exactly as |A - A^T| does
    rng = np.random.default_rng(5)
    R = sp.random(300, 300, density=0.02, random_state=7, format="csr")
    S = transfer._as_csr(R + R.T + sp.eye(300), "S")
    cases = {"symmetric": (S, True), "pattern asymmetric": (transfer._as_csr(R + sp.eye(300), "R"), False)}
    V = S.copy()
    i = int(np.flatnonzero(V.indices != np.repeat(np.arange(300), np.diff(V.indptr)))[0])
    V.data[i] *= 1.0 + 1e-6  # one off-diagonal value perturbed: same pattern, asymmetric values
    cases["values asymmetric"] = (V, False)
    W = S.copy()
    W.data[i] *= 1.0 + 1e-13  # below the 1e-10 relative tolerance: still symmetric
    cases["round-off"] = (W, True)
    Z = sp.csr_matrix(S.copy())
    Z.data[i] = 0.0
    Z.eliminate_zeros()  # a dropped entry: the general path, asymmetric
    cases["dropped entry"] = (transfer._as_csr(Z, "Z"), False)
    for name, (A, want) in cases.items():
        d = abs(A - A.T)
        ref = (d.max() if d.nnz else 0.0) <= 1e-10 * abs(A).max()
        assert ref == want, name
        assert transfer._is_symmetric(A) == want, name
    assert not transfer._is_symmetric(sp.csr_matrix(rng.standard_normal((3, 4))))


def test_sparse_lu_symmetric_mode_and_symmetric_hint(cube):
    from solvers.coarse import sparse_lu

    meshes, Ps, K, M = cube
    _V, T = meshes[0]
    ds = fem.eliminate_dirichlet(K, fem.load_vector(M, 1.0), fem.boundary_nodes(T))
    A = ds.A
    b = _random_rhs(A.shape[0], 2)
    x_ref = spla.spsolve(sp.csc_matrix(A), b)
    lu = sparse_lu(A)  # symmetric: SuperLU's symmetric mode, no pivoting
    assert np.abs(lu.solve(b) - x_ref).max() < 1e-10 * np.abs(x_ref).max()
    # the symmetric ordering keeps the fill of a Cholesky-like factor: no more than the pivoting LU's
    assert lu.L.nnz + lu.U.nnz <= spla.splu(sp.csc_matrix(A)).L.nnz + spla.splu(sp.csc_matrix(A)).U.nnz
    N_ = A + sp.triu(A, 1) * 0.3  # non-symmetric: the pivoting LU, still exact
    luN = sparse_lu(N_)
    xN = spla.spsolve(sp.csc_matrix(N_), b)
    assert np.abs(luN.solve(b) - xN).max() < 1e-10 * np.abs(xN).max()
    # the symmetric hint skips the tests and gives the same solver
    Pf, _ = restrict_prolongations(Ps[:3], ds.free)
    ops = transfer.galerkin_operators(A, Pf)
    x1 = MultigridSolver(A, Pf, coarse=ops[1:]).solve(b, tol=1e-10)
    ml2 = MultigridSolver(A, Pf, coarse=ops[1:], symmetric=True)
    assert ml2.symmetric and ml2.symmetric_cycle
    assert np.abs(ml2.solve(b, tol=1e-10) - x1).max() < 1e-9 * np.abs(x1).max()


def test_coarsest_symmetric_indefinite_falls_back_to_pivoting_lu():
    """A symmetric indefinite coarsest operator whose unpivoted (symmetric-mode) factor breaks down
    must still be solved exactly: the coarse solver retries SuperLU with pivoting."""
    from solvers.coarse import _CoarseSolver

    from solvers.coarse import sparse_lu

    # [[±1e-13, 1], [1, ∓1e-13]] blocks: symmetric, well-conditioned, tiny diagonal; the unpivoted factor
    # has growth ~1e13 (measured residual 5e-4), the pivoting LU is exact
    n = 40
    B = sp.kron(sp.eye(n // 2), sp.csr_matrix(np.array([[0.0, 1.0], [1.0, 0.0]])))
    A = sp.csr_matrix(B + 1e-13 * sp.diags(np.r_[np.ones(n // 2), -np.ones(n // 2)]))
    b = _random_rhs(n, 4)
    bad = np.linalg.norm(A @ sparse_lu(A, True).solve(b) - b) / np.linalg.norm(b)
    assert bad > 1e-6  # the symmetric mode alone would fail validation
    cs = _CoarseSolver(A, None, 1, "splu")
    assert np.linalg.norm(A @ cs(b) - b) <= 1e-12 * np.linalg.norm(b)
    # an SPD operator keeps the symmetric mode (no pivoting): fill equal to the symmetric factor's
    S = sp.csr_matrix(sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(n, n)))
    cs2 = _CoarseSolver(S, None, 1, "splu")
    assert cs2.nnz == sparse_lu(S, True).L.nnz + sparse_lu(S, True).U.nnz


def _semidefinite(n: int, small: float, nullity: int, seed: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """Dense SPSD ``Q diag(λ) Qᵀ`` with ``nullity`` zero eigenvalues, one eigenvalue ``small``, the rest in
    [0.1, 1]; and ``Q`` (the null space first, then the eigenvector of ``small``)."""
    rng = np.random.default_rng(seed)
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    lam = np.concatenate([np.zeros(nullity), [small], rng.uniform(0.1, 1.0, n - nullity - 1)])
    A = (Q * lam) @ Q.T
    return sp.csr_matrix((A + A.T) / 2), Q


def test_pivoted_cholesky_is_the_pseudo_inverse_on_the_range():
    """The rank-revealing Cholesky finds the null space and returns the minimum-norm solution, like the
    pseudo-inverse, also with an eigenvalue 1e-8 λ_max where the regularised factor is off by ~10 %
    (the clamped elasticity coarsest level of a cage hierarchy, solvers.coarse._PivotedCholesky)."""
    from solvers.coarse import _CoarseSolver

    A, Q = _semidefinite(300, 1e-8, 5, 0)
    Z = Q[:, :5]
    # consistent, its solution dominated by the small eigenvalue's mode (as a smoothed residual's is)
    b = A @ (Q[:, 5] + 0.01 * np.random.default_rng(1).standard_normal(300))
    cs = {m: _CoarseSolver(A, None, 1, m, symmetric=True) for m in ("pivoted", "pinv", "regularized")}
    assert cs["pivoted"].nullity == cs["pinv"].nullity == 5
    x, xp = cs["pivoted"](b), cs["pinv"](b)
    assert np.linalg.norm(A @ x - b) < 1e-9 * np.linalg.norm(b)
    assert np.abs(Z.T @ x).max() < 1e-7 * np.linalg.norm(x)  # no null components (cond 1e8): minimum norm
    assert np.linalg.norm(x - xp) < 1e-6 * np.linalg.norm(xp)
    assert np.linalg.norm(cs["regularized"](b) - xp) > 1e-2 * np.linalg.norm(xp)
    u, w = A @ np.ones(300), A @ np.arange(300.0)
    assert abs(u @ cs["pivoted"](w) - w @ cs["pivoted"](u)) < 1e-10 * abs(u @ cs["pivoted"](w))
    X = cs["pivoted"].lu.solve(np.column_stack([b, 2 * b]))  # columns, as solve_many passes them
    assert np.allclose(X[:, 1], 2 * x) and np.allclose(X[:, 0], x)


def test_pivoted_cholesky_refuses_an_indefinite_operator():
    from solvers.coarse import _CoarseSolver, _DenseFactor

    A, _ = _semidefinite(100, 1e-3, 0, 2)
    A = A - 0.5 * sp.eye(100)  # eigenvalues from -0.5 to 0.5
    with pytest.raises(SolverError, match="pivoted Cholesky residual"):
        _CoarseSolver(sp.csr_matrix(A), None, 1, "pivoted", symmetric=True)
    auto = _CoarseSolver(sp.csr_matrix(A), None, 1, "auto", symmetric=True)  # dense: regularised -> LU
    assert auto.method == "regularized" and isinstance(auto.lu, _DenseFactor) and not auto.lu.symmetric
    b = A @ np.ones(100)
    assert np.linalg.norm(A @ auto(b) - b) < 1e-8 * np.linalg.norm(b)


def test_setup_and_deferred_probe_run_with_one_blas_thread(cube, monkeypatch):
    """The set-up (operators, factor, coarse probes) and the deferred finest probe run on one BLAS thread
    and give the caller's limit back: the probe's tall-skinny products beside its cycles gained nothing from
    OpenBLAS's threads and lost to their spinning (lucy.ply's Neumann set-up 5.2 s against 2.9 s, loaded)."""
    import solvers.multilevel as multilevel

    ds, Pf, _ = _dirichlet(cube, 3)
    checks = record_blas_threads(monkeypatch, multilevel, "_check_operators")
    probes = record_blas_threads(monkeypatch, multilevel, "slow_modes")
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        ml = MultigridSolver(ds.A, Pf, deflate=8, probe_finest=True, probe_at="stationary")
        coarse_probes = len(probes)
        ml.probe()
        after = blas_threads()
    assert checks and set(checks) == {1}
    assert coarse_probes >= 1 and len(probes) > coarse_probes and set(probes) == {1}
    assert after == before


def test_cycles_run_with_one_blas_thread(cube, monkeypatch):
    """solve() and aspreconditioner() run their cycles on one BLAS thread and give the caller's limit back
    (OpenBLAS threads spinning beside the cycle's short BLAS calls slowed MG-PCG solves down)."""
    ds, Pf, _ = _dirichlet(cube, 3)
    ml = MultigridSolver(ds.A, Pf)
    inside = record_blas_threads(monkeypatch, ml, "_one")
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        ml.solve(ds.b, tol=1e-8, accel="cg")
        ml.solve(ds.b, tol=1e-8)
        ml.aspreconditioner().matvec(ds.b)
        after = blas_threads()
    assert inside and set(inside) == {1}
    assert after == before
