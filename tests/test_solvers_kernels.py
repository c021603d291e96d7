"""The optional compiled set-up loops (solvers._kernels) against their numpy fallbacks: the same arrays."""

import numpy as np
import pytest
import scipy.sparse as sp

import solvers._kernels as kernels
from solvers import MultigridSolver, fem
from solvers.gallery import kuhn_cube_hierarchy
from solvers.ordering import diagonal_first, locality_order, permute_symmetric_transpose
from solvers.subdomain import strongly_coupled
from solvers.transfer import _lower_half

needs_numba = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed (the fallback is tested)")


@pytest.fixture
def compiled(monkeypatch):
    """Run a function with the compiled kernels on and off: ``compiled(f)`` -> ``(f() on, f() off)``."""

    monkeypatch.setattr(kernels, "MIN_NNZ", 0)  # the test matrices are small

    def both(f):
        monkeypatch.setattr(kernels, "ENABLED", kernels.AVAILABLE)  # without numba: the fallback twice
        on = f()
        monkeypatch.setattr(kernels, "ENABLED", False)
        return on, f()

    return both


@pytest.fixture(scope="module")
def scattered():
    """A Neumann Poisson problem on the Kuhn cube (29^3 nodes, above the reordering's threshold), its fine
    nodes shuffled as a mesher's output may be, and a mass term so that every level is definite."""
    meshes, Ps = kuhn_cube_hierarchy(28, 3)
    V, T = meshes[0]
    A = fem.stiffness_matrix(V, T) + 1e-3 * fem.mass_matrix(V, T)
    q = np.random.default_rng(1).permutation(len(V))
    As = sp.csr_matrix(A[q][:, q])
    As.sort_indices()  # canonical, as the solver makes it (and as tolil() would, in place)
    return As, [sp.csr_matrix(Ps[0][q])] + list(Ps[1:])


def _asymmetric(A: sp.csr_matrix) -> sp.csr_matrix:
    """``A`` with one off-diagonal entry of row 5 raised by 1e-6 of the largest entry (the probe's prey)."""
    B = A.copy()
    row = B.indices[B.indptr[5]:B.indptr[6]]
    B[5, row[row != 5][0]] += 1e-6 * abs(A.data).max()
    return B


def _same(M: sp.csr_matrix, N: sp.csr_matrix) -> bool:
    return all(np.array_equal(getattr(M, f), getattr(N, f)) for f in ("indptr", "indices", "data"))


def _unsorted_with_missing_diagonal() -> sp.csr_matrix:
    """A canonical random matrix with rows shuffled internally and two rows without a diagonal entry."""
    rng = np.random.default_rng(3)
    A = sp.csr_matrix(sp.random(200, 200, density=0.05, random_state=rng) + 4.0 * sp.eye(200))
    A[7, 7] = 0.0
    A[150, 150] = 0.0
    A.eliminate_zeros()
    for i in range(A.shape[0]):  # each row's entries in a random order
        s, e = A.indptr[i], A.indptr[i + 1]
        o = s + rng.permutation(e - s)
        A.indices[s:e], A.data[s:e] = A.indices[o], A.data[o]
    A.has_sorted_indices = False
    return A


@needs_numba
@pytest.mark.parametrize("case", ["sorted", "unsorted"])
def test_lower_half_is_the_numpy_split(compiled, scattered, case):
    A = scattered[0] if case == "sorted" else _unsorted_with_missing_diagonal()
    (H1, d1, p1, h1), (H0, d0, p0, h0) = compiled(lambda: (*_lower_half(A, p := [], h := []), p, h))
    assert _same(H1, H0) and np.array_equal(d1, d0)
    if case == "sorted":
        assert np.array_equal(p1[0], p0[0]) and np.array_equal(h1[0], h0[0])
        assert np.array_equal(A.data[p1[0]], d1) and np.array_equal(H1.data[h1[0]], 0.5 * d1)
    else:  # two rows lack their diagonal: no positions, the diagonal read as 0 there
        assert p1 == p0 == [None] and h1 == h0 == [None] and d1[7] == d1[150] == 0.0


@needs_numba
def test_permutation_and_its_symmetry_verdict(compiled, scattered):
    """The same permuted matrix either way, symmetric; an asymmetric entry of 1e-6 is caught either way."""
    A, Ps = scattered
    p = locality_order(Ps)[0]
    (A1, s1), (A0, s0) = compiled(lambda: permute_symmetric_transpose(A, p))
    assert s1 and s0 and _same(A1, A0)
    B = _asymmetric(A)
    (B1, s1), (B0, s0) = compiled(lambda: permute_symmetric_transpose(B, p))
    assert not s1 and not s0 and _same(B1, B0)


@needs_numba
def test_strong_mask_is_the_numpy_mask(compiled, scattered):
    """Strongly coupled unknowns of a matrix with a few planted strong couplings, from the full matrix and
    from its lower triangle."""
    A = scattered[0].tolil()
    rng = np.random.default_rng(6)
    for i in rng.choice(A.shape[0] - 1, 25, replace=False):
        w = 0.9 * A[i, i]
        A[i, i + 1] = A[i + 1, i] = -w
    A = sp.csr_matrix(A)
    low, d = _lower_half(A)
    low.data[np.flatnonzero(low.indices == np.repeat(np.arange(A.shape[0]), np.diff(low.indptr)))] *= 2.0
    r1, r0 = compiled(lambda: strongly_coupled(A, 0.5, max_fraction=1.0))
    l1, l0 = compiled(lambda: strongly_coupled(A, 0.5, max_fraction=1.0, lower=(low, d)))
    assert 40 <= r1.size <= 50 and np.array_equal(r1, r0) and np.array_equal(l1, l0) and np.array_equal(r1, l1)


@needs_numba
def test_diagonal_first_swaps_the_same_entries(compiled, scattered):
    A = scattered[0]
    pos = np.flatnonzero(A.indices == np.repeat(np.arange(A.shape[0]), np.diff(A.indptr)))
    F1, F0 = compiled(lambda: diagonal_first(A, pos))
    assert _same(F1, F0) and not F1.has_sorted_indices and abs(F1 - A).max() == 0.0


@pytest.mark.parametrize("nullspace", [None, "constant"])
def test_solver_is_the_same_with_and_without_the_kernels(compiled, scattered, nullspace):
    """Bit for bit the same level operators, prolongations and iterates (without numba: twice the fallback),
    and Galerkin operators within 1e-12 of the plain triple product."""
    A, Ps = scattered
    if nullspace == "constant":  # the stiffness matrix alone: singular, constants in its kernel
        A = sp.csr_matrix(A - sp.diags(np.asarray(A.sum(axis=1)).ravel()))
        A.eliminate_zeros()
    b = np.random.default_rng(7).standard_normal(A.shape[0])
    b -= b.mean()
    m1, m0 = compiled(lambda: MultigridSolver(A, Ps, nullspace=nullspace))
    for L1, L0 in zip(m1.levels, m0.levels):
        assert _same(L1.A, L0.A)
    for L1, L0 in zip(m1.levels[:-1], m0.levels[:-1]):
        assert _same(L1.P, L0.P) and _same(L1.R, L0.R)
    assert np.array_equal(m1.solve(b, tol=1e-10, accel="cg"), m0.solve(b, tol=1e-10, accel="cg"))
    Ak = A[m1.perm][:, m1.perm]
    for L, Lc in zip(m1.levels[:-1], m1.levels[1:]):
        G = sp.csr_matrix(L.P.T @ Ak @ L.P)
        assert abs(Lc.A - G).max() <= 1e-12 * abs(G).max()
        Ak = G


@needs_numba
def test_locality_order_is_the_same(compiled, scattered):
    """The rows' lowest-ranked parents by one loop (:func:`solvers._kernels.row_min`): the same orders."""
    o1, o0 = compiled(lambda: locality_order(scattered[1]))
    assert len(o1) == len(o0) == 3 and all(np.array_equal(a, b) for a, b in zip(o1, o0))


@needs_numba
def test_galerkin_products_with_four_weights_per_row(compiled, scattered):
    """The compiled products, transposes and merge (a prolongation of four weights per row, then the nested
    ones): the same Galerkin operators as scipy's, and within 1e-12 of the plain triple product."""
    from solvers import galerkin_operators

    A, Ps = scattered
    rng = np.random.default_rng(9)
    n, m = A.shape[0], Ps[0].shape[1]
    cols = np.sort(rng.random((n, m)).argpartition(4, axis=1)[:, :4], axis=1)  # four distinct columns a row
    w = rng.uniform(0.1, 1.0, (n, 4))
    P0 = sp.csr_matrix(((w / w.sum(1, keepdims=True)).ravel(), cols.ravel(), np.arange(0, 4 * n + 1, 4)),
                       shape=(n, m))
    ops1, ops0 = compiled(lambda: galerkin_operators(A, [P0, *Ps[1:]], symmetric=True))
    assert len(ops1) == 3 and all(_same(a, b) for a, b in zip(ops1, ops0))
    G = A
    for P, Ac in zip([P0, *Ps[1:]], ops1[1:]):
        G = sp.csr_matrix(P.T @ G @ P)
        assert abs(Ac - G).max() <= 1e-12 * abs(G).max() and abs(Ac - Ac.T).max() == 0.0
        G = Ac


@needs_numba
def test_compiled_product_declines_beyond_the_bound(monkeypatch, scattered):
    """Past :data:`ONE_PASS_MAX_ENTRIES` the compiled product declines (None) and the scipy path runs."""
    from solvers import transfer

    A, Ps = scattered
    half, _ = _lower_half(A)
    monkeypatch.setattr(kernels, "MIN_NNZ", 0)
    monkeypatch.setattr(transfer, "ONE_PASS_MAX_ENTRIES", 10)
    assert transfer._symmetric_product_compiled(half, Ps[0], sp.csr_matrix(Ps[0].T), False) is None
    monkeypatch.setattr(kernels, "ENABLED", True)
    ops = transfer.galerkin_operators(A, Ps[:1], symmetric=True)
    G = sp.csr_matrix(Ps[0].T @ A @ Ps[0])
    assert abs(ops[1] - G).max() <= 1e-12 * abs(G).max()


def test_kernels_start_with_a_large_matrix(monkeypatch):
    """Off, or below :data:`MIN_NNZ` while numba is not loaded: the numpy path; once loaded, every size."""
    monkeypatch.setattr(kernels, "ENABLED", False)
    assert not kernels.wanted(10**9)
    monkeypatch.setattr(kernels, "ENABLED", True)
    monkeypatch.setitem(kernels._state, "loaded", False)
    assert kernels.wanted(kernels.MIN_NNZ) and not kernels.wanted(kernels.MIN_NNZ - 1)
    monkeypatch.setitem(kernels._state, "loaded", True)
    assert kernels.wanted(1)
