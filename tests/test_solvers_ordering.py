"""MultigridSolver's defaults (the documented fast path) and its internal locality ordering."""

import inspect

import numpy as np
import pytest
import scipy.sparse as sp

import solvers
import solvers.coarse
from solvers import MultigridSolver, fem
from solvers.gallery import kuhn_cube_hierarchy
from solvers.multilevel import (AUTO_PROBE_MAX_COMPLEXITY, COARSE_SWEEPS, DEFAULT_DEFLATE, DEFAULT_SMOOTHER,
                               DENSE_LEVEL_ROWS)
from solvers.subdomain import STRONG_COUPLING
from solvers.ordering import (ORDER_MIN_N, index_spread, locality_order, permute_prolongation, permute_symmetric,
                              permute_symmetric_transpose)


@pytest.fixture(scope="module")
def scattered():
    """A Neumann Poisson problem on the Kuhn cube (29^3 = 24,389 nodes, >= ORDER_MIN_N) whose fine nodes
    are shuffled, as a mesher's output may be."""
    meshes, Ps = kuhn_cube_hierarchy(28, 3)
    V, T = meshes[0]
    K = fem.stiffness_matrix(V, T)
    q = np.random.default_rng(1).permutation(len(V))
    Ks = sp.csr_matrix(K[q][:, q])
    Ps = [sp.csr_matrix(Ps[0][q])] + list(Ps[1:])
    b = np.random.default_rng(2).standard_normal(len(V))
    return K, Ks, Ps, b - b.mean(), q, T


def test_constructor_defaults_are_the_documented_fast_path():
    """MultigridSolver(A, P) with no options is the cycle docs/usermesh.md measured fastest under CG:
    forward Gauss-Seidel x2 before, backward x2 after (x4 on sparse coarse levels, x1 on dense ones), locality ordering,
    dense coarsest solve, the coarse levels probed only within AUTO_PROBE_MAX_COMPLEXITY, an exact solve on
    the strongly coupled fine unknowns."""
    params = inspect.signature(MultigridSolver).parameters
    assert params["deflate"].default == "auto" and params["probe_finest"].default is False
    assert AUTO_PROBE_MAX_COMPLEXITY == 1.5 and DEFAULT_DEFLATE == 8
    assert params["strong_blocks"].default == STRONG_COUPLING == 0.5 and params["local_probe"].default == 0
    assert DEFAULT_SMOOTHER == ("gauss_seidel", {"sweep": "forward", "iterations": 2})
    assert params["presmoother"].default == DEFAULT_SMOOTHER and params["postsmoother"].default is None
    assert params["ordering"].default == "auto" and params["coarse_solver"].default == "auto"
    assert params["coarse"].default == "galerkin" and params["coarse_scaling"].default is None
    assert solvers.coarse.DENSE_MAX == 2000
    meshes, Ps = kuhn_cube_hierarchy(8, 3)
    V, T = meshes[0]
    ml = MultigridSolver(fem.stiffness_matrix(V, T), Ps, nullspace="constant")
    pre, post = ml.levels[0].presmoother.params, ml.levels[0].postsmoother.params
    assert (pre["sweep"], pre["iterations"]) == ("forward", 2)
    assert (post["sweep"], post["iterations"]) == ("backward", 2)
    assert COARSE_SWEEPS == 4 and len(ml.levels) == 3
    for L in ml.levels[1:-1]:  # as sparse as the fine level: a variable V-cycle
        pre, post = L.presmoother.params, L.postsmoother.params
        assert (pre["sweep"], pre["iterations"]) == ("forward", 4)
        assert (post["sweep"], post["iterations"]) == ("backward", 4)
    assert ml.symmetric_cycle and ml._coarse_solver.dense and ml.perm is None  # small: caller's order kept
    # a nested hierarchy's coarse levels are cheap: level 1 probed (here it is fast: nothing deflated)
    assert ml.operator_complexity() < 1.2 and ml.deflate == 8
    assert [d["level"] for d in ml.deflation] == [1] and ml.deflation[0]["vectors"] == 0
    assert ml.deflation[0]["probe_factor"] < 0.3
    assert ml.strong_blocks == {"theta": 0.5, "nodes": 0, "installed": False}  # a well-shaped mesh: none
    # a dense coarse level (more than DENSE_LEVEL_ROWS times the fine nonzeros per row) gets one sweep
    assert DENSE_LEVEL_ROWS == 2.0
    P0 = sp.csr_matrix(Ps[0])
    dense_P = sp.csr_matrix(P0 @ sp.csr_matrix(np.kron(np.eye(P0.shape[1] // 5 + 1), np.ones((5, 5)))
                                               [: P0.shape[1], : P0.shape[1]] / 5.0))  # smears each column
    md = MultigridSolver(fem.stiffness_matrix(V, T), [dense_P] + list(Ps[1:]), nullspace="constant")
    rows = [L.A.nnz / L.A.shape[0] for L in md.levels]
    for k, L in enumerate(md.levels[1:-1], start=1):
        want = 1 if rows[k] > 2.0 * rows[0] else 4
        assert L.presmoother.params["iterations"] == L.postsmoother.params["iterations"] == want
    assert md.levels[1].presmoother.params["iterations"] == 1, rows


def test_auto_probe_only_within_the_complexity_bound(monkeypatch):
    """``deflate="auto"`` probes the coarse levels (DEFAULT_DEFLATE modes, never the finest level) of a cheap
    hierarchy and not those of one whose coarse levels hold a large share of the nonzeros (a smoothed P, as
    a user's non-nested first level); the bound is AUTO_PROBE_MAX_COMPLEXITY, read at set-up."""
    from solvers import multilevel

    meshes, Ps = kuhn_cube_hierarchy(8, 3)
    V, T = meshes[0]
    K = fem.stiffness_matrix(V, T)
    S = sp.identity(K.shape[0]) - (2.0 / 3.0) * sp.diags(1.0 / K.diagonal()) @ K
    dense = [sp.csr_matrix(S @ (S @ Ps[0]))] + list(Ps[1:])  # rows still sum to 1: S 1 = 1
    md = MultigridSolver(K, dense, nullspace="constant")
    assert md.operator_complexity() > 1.6 and md.deflate == 0 and md.deflation == []
    ml = MultigridSolver(K, Ps, nullspace="constant")
    assert ml.operator_complexity() < 1.2 and ml.deflate == DEFAULT_DEFLATE
    assert [d["level"] for d in ml.deflation] == [1]
    assert MultigridSolver(K, Ps, nullspace="constant", deflate=0).deflation == []
    monkeypatch.setattr(multilevel, "AUTO_PROBE_MAX_COMPLEXITY", 1.1)
    low = MultigridSolver(K, Ps, nullspace="constant")
    assert low.deflate == 0 and low.deflation == []
    with pytest.raises(solvers.SolverInputError, match="deflate"):
        MultigridSolver(K, Ps, nullspace="constant", deflate="yes")


def test_default_solver_is_the_documented_cycle_spelled_out(scattered):
    """``MultigridSolver(A, P)`` with no options and with the documented fast path written out (V-cycle,
    forward Gauss-Seidel x2 / backward x2, x1 on levels denser than DENSE_LEVEL_ROWS times the fine one (x4 on
    the others),
    locality order, Galerkin operators, "auto" coarsest solve, the coarse probe only within
    AUTO_PROBE_MAX_COMPLEXITY) apply the same preconditioner
    and take the same CG steps, on a scattered Neumann problem whose first coarse level is dense."""
    _K, Ks, Ps, b, _q, _T = scattered
    P0 = sp.csr_matrix(Ps[0])
    nc = P0.shape[1]
    smear = sum(sp.csr_matrix((np.full(nc, 0.25), ((np.arange(nc) + s) % nc, np.arange(nc))), shape=(nc, nc))
                for s in range(4))  # each column spread over 4: rows still sum to 1, P^T A P denser
    Pd = [sp.csr_matrix(P0 @ smear)] + list(Ps[1:])
    ml = MultigridSolver(Ks, Pd, nullspace="constant")
    rows = [L.A.nnz / L.A.shape[0] for L in ml.levels]
    specs = [("gauss_seidel", {"sweep": "forward", "iterations": 2 if k == 0 else 1 if rows[k] > 2.0 * rows[0]
                               else 4}) for k in range(len(Pd))]
    assert [s[1]["iterations"] for s in specs] == [2, 1], rows  # the dense level is exercised
    spelled = MultigridSolver(Ks, Pd, nullspace="constant", presmoother=specs, postsmoother=None,
                              ordering="locality", coarse="galerkin", coarse_solver="auto",
                              deflate=DEFAULT_DEFLATE if ml.operator_complexity() <= 1.5 else 0,
                              probe_finest=False, cycle="V", strong_blocks=0.5, local_probe=0)
    assert ml.perm is not None and np.array_equal(ml.perm, spelled.perm)
    assert ml.levels[0].presmoother.smooth_residual is not None  # the cheap pre-smoother residual
    v = np.random.default_rng(5).standard_normal(len(b))
    v -= v.mean()
    z, zs = ml.aspreconditioner() @ v, spelled.aspreconditioner("V") @ v
    assert np.linalg.norm(z - zs) <= 1e-13 * np.linalg.norm(zs)
    r, rs = (m.solve(b, tol=1e-8, accel="cg", return_info=True)[1]["residuals"] for m in (ml, spelled))
    assert len(r) == len(rs) and np.allclose(r, rs, rtol=1e-8, atol=0), (r, rs)


def test_locality_order_is_a_permutation_that_gathers(scattered):
    K, Ks, Ps, _b, _q, _T = scattered
    orders = locality_order(Ps)
    assert [len(p) for p in orders] == [Ps[0].shape[0]] + [P.shape[1] for P in Ps]
    for p in orders:
        assert np.array_equal(np.sort(p), np.arange(len(p)))
    Ap = permute_symmetric(Ks, orders[0])
    assert Ap.has_canonical_format and abs(Ap - Ks[orders[0]][:, orders[0]]).max() == 0.0
    # shuffled: ~1/3 (random); after the order, far below the "auto" threshold
    assert index_spread(Ks) > 0.3 and index_spread(Ap) < 0.03, (index_spread(Ks), index_spread(Ap))


def test_one_transpose_permutation_and_its_symmetry_probe(scattered):
    """A symmetric matrix permuted with one transpose is the permuted matrix's transpose, canonical; the
    probe calls it symmetric at round-off and catches a single asymmetric entry; a non-symmetric matrix comes
    back as the permuted matrix itself."""
    K, Ks, Ps, _b, _q, _T = scattered
    p = locality_order(Ps)[0]
    Kp = Ks[p][:, p]
    Ap, sym = permute_symmetric_transpose(Ks, p)
    assert sym and Ap.has_canonical_format and abs(Ap - Kp.T).max() == 0.0
    exact = sp.csr_matrix(sp.tril(Ks) + sp.tril(Ks, -1).T)  # exactly symmetric
    Ae, sym_e = permute_symmetric_transpose(exact, p)
    assert sym_e and abs(Ae - exact[p][:, p]).max() == 0.0
    scale = abs(Ks.data).max()
    caught = 0
    for seed in range(20):  # one off-diagonal entry perturbed by 1e-6 of the largest entry, different rows
        i = int(np.random.default_rng(seed).integers(Ks.shape[0]))
        j = Ks.indices[Ks.indptr[i]] if Ks.indices[Ks.indptr[i]] != i else Ks.indices[Ks.indptr[i] + 1]
        Kb = Ks.copy()
        Kb[i, j] += 1e-6 * scale
        An, sym_n = permute_symmetric_transpose(Kb, p)
        caught += not sym_n
        if not sym_n:
            assert An.has_canonical_format and abs(An - Kb[p][:, p]).max() == 0.0
    assert caught == 20  # |x_j| < 1e-4 has probability 1e-4 per case
    As, told = permute_symmetric_transpose(Kb, p, probe=False)  # the caller's statement: not tested
    assert told and abs(As - Kb[p][:, p].T).max() == 0.0


def test_permuted_prolongation_and_restriction(scattered):
    _K, _Ks, Ps, _b, _q, _T = scattered
    orders = locality_order(Ps)
    P, R = permute_prolongation(Ps[0], orders[0], orders[1], with_transpose=True)
    ref = Ps[0][orders[0]][:, orders[1]]
    assert P.has_canonical_format and R.has_canonical_format
    assert abs(P - ref).max() == 0.0 and abs(R - ref.T).max() == 0.0


def test_permuted_prolongation_with_equal_rows_is_the_general_one():
    """Rows of equal length (a non-nested level's four barycentric weights) are gathered as one block: the
    same arrays as the row-by-row gather, bit for bit."""
    from solvers import ordering

    rng = np.random.default_rng(3)
    n, m = 500, 90
    cols = np.stack([rng.choice(m, 4, replace=False) for _ in range(n)])
    P = sp.csr_matrix((rng.random(4 * n), cols.ravel(), np.arange(0, 4 * n + 1, 4)), shape=(n, m))
    P.sort_indices()
    pf, pc = rng.permutation(n), rng.permutation(m)
    B = ordering._gathered_equal_rows(P, pf, pc)
    G = ordering._gathered(P, pf, pc)
    assert B is not None
    assert all(np.array_equal(getattr(B, a), getattr(G, a)) for a in ("indptr", "indices", "data"))
    got, R = permute_prolongation(P, pf, pc, with_transpose=True)
    ref = P[pf][:, pc]
    assert got.has_canonical_format and abs(got - ref).max() == 0.0 and abs(R - ref.T).max() == 0.0
    uneven = sp.csr_matrix(P[:, :m - 5])  # rows of 3 and 4 entries: the general path
    assert ordering._gathered_equal_rows(uneven, pf, pc[pc < m - 5]) is None


def test_reordered_solver_solves_in_the_callers_order(scattered):
    K, Ks, Ps, b, q, T = scattered
    assert Ks.shape[0] >= ORDER_MIN_N
    ml = MultigridSolver(Ks, Ps, nullspace="constant")
    plain = MultigridSolver(Ks, Ps, nullspace="constant", ordering=None)
    assert ml.perm is not None and plain.perm is None
    # the permuted matrix's transpose (Ks is symmetric up to round-off: the assembly's sums; one transpose
    # sorts the rows, which the sweeps need), each row's diagonal entry stored first (the smoothed levels)
    Kp = Ks[ml.perm][:, ml.perm]
    A0 = ml.levels[0].A
    assert np.array_equal(A0.indices[A0.indptr[:-1]], np.arange(A0.shape[0])) and abs(A0 - Kp.T).max() == 0.0
    assert all(np.array_equal(L.A.indices[L.A.indptr[:-1]], np.arange(L.A.shape[0])) for L in ml.levels[:-1])
    assert ml.levels[-1].A.has_canonical_format
    assert abs(ml.levels[0].A - Kp).max() <= 1e-15 * abs(Kp).max()
    x, info = ml.solve(b, tol=1e-10, accel="cg", return_info=True)
    xp, info_p = plain.solve(b, tol=1e-10, accel="cg", return_info=True)
    assert np.linalg.norm(Ks @ x - b) <= 1e-9 * np.linalg.norm(b)
    assert np.abs(x - xp).max() <= 1e-7 * np.abs(xp).max()
    assert abs(info["iterations"] - info_p["iterations"]) <= 1, (info["iterations"], info_p["iterations"])
    # the same coarse operators up to the permutation of the coarse levels (the products' round-off may
    # cancel a few entries to exact zeros in one order and not in the other)
    assert ml.operator_complexity() == pytest.approx(plain.operator_complexity(), rel=2e-3)
    # the public preconditioner works in the caller's order: symmetric, and scipy's CG converges with it
    M = ml.aspreconditioner()
    rng = np.random.default_rng(3)
    u, v = rng.standard_normal(len(b)), rng.standard_normal(len(b))
    u -= u.mean()
    v -= v.mean()
    assert abs((M @ u) @ v - u @ (M @ v)) <= 1e-10 * abs(u @ (M @ v))
    y = ml.solve(b, x0=x, tol=1e-10)  # x0 in the caller's order: already converged, no cycle needed
    assert np.abs(y - x).max() <= 1e-12 * np.abs(x).max() + 1e-300


def test_local_nodes_follow_the_permutation(scattered):
    K, Ks, Ps, b, q, T = scattered
    inv = np.empty_like(q)
    inv[q] = np.arange(len(q))
    layer = inv[fem.boundary_layer_nodes(T, 1)]  # the shuffled problem's boundary layer, caller's numbering
    ml = MultigridSolver(Ks, Ps, nullspace="constant", local_nodes=layer)
    mask = np.zeros(len(q), bool)
    mask[layer] = True
    mm = MultigridSolver(Ks, Ps, nullspace="constant", local_nodes=mask)
    assert ml.perm is not None
    assert ml.levels[0].presmoother.params["local_nodes"] == layer.size == mm.levels[0].presmoother.params[
        "local_nodes"]
    # the local rows are those of the boundary layer: their count of nonzeros is the layer's
    nnz_layer = int(np.diff(Ks.indptr)[layer].sum())
    extra = ml.cycle_complexity() - MultigridSolver(Ks, Ps, nullspace="constant").cycle_complexity()
    assert 0 < nnz_layer / Ks.nnz < extra
    r1 = ml.solve(b, tol=1e-8, accel="cg", return_info=True)[1]
    r2 = mm.solve(b, tol=1e-8, accel="cg", return_info=True)[1]
    assert r1["residuals"] == r2["residuals"]


def test_bad_ordering_name(scattered):
    _K, Ks, Ps, _b, _q, _T = scattered
    with pytest.raises(solvers.SolverInputError, match="ordering"):
        MultigridSolver(Ks, Ps, ordering="rcm")


def test_stable_argsort_is_numpys_stable_sort():
    """The radix path (one 16-bit pass, or two for keys up to 2**32) gives numpy's stable permutation."""
    from solvers.ordering import _stable_argsort

    rng = np.random.default_rng(4)
    for high in (7, 60_000, 70_000, 3_000_000_000):
        key = rng.integers(0, high, size=50_000).astype(np.int64)
        assert np.array_equal(_stable_argsort(key), np.argsort(key, kind="stable")), high
    assert _stable_argsort(np.zeros(0, np.int64)).size == 0


def test_index_spread_stride_estimates_the_full_mean(scattered):
    K, Ks, _Ps, _b, _q, _T = scattered
    for M in (K, Ks):
        full, est = index_spread(M), index_spread(M, stride=16)
        assert abs(est - full) <= 0.05 * full, (est, full)
    assert index_spread(sp.identity(5, format="csr"), stride=16) == 0.0


def test_callers_matrix_is_neither_modified_nor_shared(scattered):
    """A is validated without a copy when the reordering makes a new matrix, and copied when the caller's
    order is kept: the solver never holds the caller's arrays; an unsorted input is left as it was."""
    K, Ks, Ps, b, _q, _T = scattered
    for ordering in ("auto", None):
        A = Ks.copy()
        ml = MultigridSolver(A, Ps, nullspace="constant", ordering=ordering)
        assert (ml.perm is None) == (ordering is None)
        assert not np.may_share_memory(ml.levels[0].A.data, A.data)
        A.data[:] = 0.0  # the caller reuses its matrix: the solver's is untouched
        x, info = ml.solve(b, tol=1e-8, accel="cg", return_info=True)
        assert info["converged"] and np.linalg.norm(Ks @ x - b) <= 1e-8 * np.linalg.norm(b)
    U = Ks.copy()
    rev = np.concatenate([U.indices[U.indptr[i]:U.indptr[i + 1]][::-1] for i in range(U.shape[0])])
    revd = np.concatenate([U.data[U.indptr[i]:U.indptr[i + 1]][::-1] for i in range(U.shape[0])])
    U = sp.csr_matrix((revd, rev, U.indptr.copy()), shape=U.shape)  # rows in decreasing column order
    before = U.indices.copy()
    ml = MultigridSolver(U, Ps, nullspace="constant")
    assert np.array_equal(U.indices, before) and abs(ml.levels[0].A - Ks[ml.perm][:, ml.perm].T).max() == 0.0


def test_diagonal_first_swaps_the_diagonal_with_the_rows_first_entry():
    """Each row's diagonal entry first, the row's first entry in its place, every other entry where it was;
    the same matrix, and Gauss-Seidel on it agrees with the canonical matrix's to round-off. ``in_place``
    swaps in ``A``'s arrays, otherwise ``A`` is untouched."""
    from pyamg.relaxation.relaxation import gauss_seidel

    from solvers.ordering import diagonal_first

    rng = np.random.default_rng(5)
    n = 300
    A = sp.random(n, n, density=0.03, random_state=rng, format="csr") + sp.eye(n) * 10.0
    A = sp.csr_matrix(A)
    A.sum_duplicates()
    A.sort_indices()
    rows = np.repeat(np.arange(n), np.diff(A.indptr))
    pos = np.flatnonzero(A.indices == rows)
    start = A.indptr[:-1]
    assert (pos > start).sum() > n // 2  # most rows have entries left of the diagonal: a real test
    before = (A.indices.copy(), A.data.copy())
    F = diagonal_first(A, pos)
    assert np.array_equal(A.indices, before[0]) and np.array_equal(A.data, before[1])  # untouched
    assert np.array_equal(F.indptr, A.indptr) and np.array_equal(F.indices[start], np.arange(n))
    assert np.array_equal(F.indices[pos], A.indices[start]) and np.array_equal(F.data[pos], A.data[start])
    other = np.ones(A.nnz, dtype=bool)
    other[start] = other[pos] = False
    assert np.array_equal(F.indices[other], A.indices[other]) and np.array_equal(F.data[other], A.data[other])
    assert abs(F - A).max() == 0.0 and not F.has_sorted_indices
    x0, b = rng.standard_normal((2, n))
    x, y = x0.copy(), x0.copy()
    gauss_seidel(A, x, b, iterations=2, sweep="forward")
    gauss_seidel(F, y, b, iterations=2, sweep="forward")
    assert np.abs(x - y).max() <= 1e-13 * np.abs(x).max()
    G = diagonal_first(A, pos, in_place=True)
    assert G is A and np.array_equal(A.indices, F.indices) and np.array_equal(A.data, F.data)
    assert not A.has_sorted_indices
