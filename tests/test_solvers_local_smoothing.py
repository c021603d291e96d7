"""Local (boundary-layer) Gauss–Seidel sweeps and per-level smoother lists in MultigridSolver."""

import numpy as np
import pytest

from solvers import SolverInputError
from solvers import multilevel as solvers_multilevel
from solvers.fem import boundary_layer_nodes, boundary_nodes, stiffness_matrix
from solvers.gallery import kuhn_cube_hierarchy
from solvers.multilevel import MultigridSolver
from solvers.smoothing import make_smoother, with_local_sweeps

N = 16


@pytest.fixture(scope="module")
def cube():
    meshes, Ps = kuhn_cube_hierarchy(N, 3)
    V, T = meshes[0]
    return V, T, stiffness_matrix(V, T), Ps


def _factor(ml, b):
    res = []
    ml.solve(b, tol=1e-10, maxiter=100, residuals=res)
    return (res[-1] / res[-6]) ** 0.2


def test_boundary_layer_counts(cube):
    _V, T, _, _ = cube
    assert np.array_equal(boundary_layer_nodes(T, 0), boundary_nodes(T))
    # (N+1)^3 grid nodes; boundary: all but the (N-1)^3 interior; one Kuhn tet ring deeper: (N-3)^3 left
    assert boundary_layer_nodes(T, 0).size == (N + 1) ** 3 - (N - 1) ** 3
    assert boundary_layer_nodes(T, 1).size == (N + 1) ** 3 - (N - 3) ** 3


def test_local_sweeps_symmetric_and_faster(cube, rng):
    V, T, K, Ps = cube
    b = rng.standard_normal(len(V))
    b -= b.mean()
    sgs = ("gauss_seidel", {"sweep": "symmetric", "iterations": 1})  # the V(1,1) the figures below are for
    plain = MultigridSolver(K, Ps, nullspace="constant", presmoother=sgs)
    local = MultigridSolver(K, Ps, nullspace="constant", local_nodes=boundary_layer_nodes(T, 1),
                            presmoother=sgs)
    assert local.symmetric_cycle
    M = local.aspreconditioner()
    x, y = rng.standard_normal(len(V)), rng.standard_normal(len(V))
    x -= x.mean()
    y -= y.mean()
    assert abs((M @ x) @ y - x @ (M @ y)) <= 1e-10 * abs(x @ (M @ y))
    f0, f1 = _factor(plain, b), _factor(local, b)
    # measured 0.249 -> 0.225 (structured mesh: deterministic)
    assert 0.23 < f0 < 0.27 and f1 < f0 - 0.015
    # the work model counts the extra rows: two local symmetric sweeps (pre and post) per level visit
    assert local.cycle_complexity() > plain.cycle_complexity() + 1.0
    x1 = local.solve(b, tol=1e-10, accel="cg")
    assert np.linalg.norm(K @ x1 - b) <= 1e-9 * np.linalg.norm(b)


def test_local_sets_follow_the_prolongation(cube):
    _V, T, K, Ps = cube
    nodes = boundary_nodes(T)
    ml = MultigridSolver(K, Ps, nullspace="constant", local_nodes=nodes, local_levels=2)
    L0, L1 = ml.levels[0], ml.levels[1]
    assert L0.presmoother.params["local_nodes"] == nodes.size
    # level 1 relaxes the coarse nodes that interpolate to the fine set: on the Kuhn cube, its boundary
    assert L1.presmoother.params["local_nodes"] == np.unique(Ps[0][nodes].indices).size
    assert L1.presmoother.params["local_nodes"] == (N // 2 + 1) ** 3 - (N // 2 - 1) ** 3


def test_with_local_sweeps_work_and_errors(cube):
    V, T, K, Ps = cube
    base = make_smoother(K, "symmetric_gauss_seidel")
    idx = boundary_nodes(T)
    sm = with_local_sweeps(base, K, idx, 2)
    rows = (K.indptr[idx + 1] - K.indptr[idx]).sum()
    assert sm.work == pytest.approx(base.work + 4.0 * rows / K.nnz)
    assert with_local_sweeps(base, K, idx, 0) is base
    with pytest.raises(SolverInputError, match="local smoothing nodes"):
        with_local_sweeps(base, K, [len(V)], 1)
    with pytest.raises(SolverInputError, match="mask"):
        MultigridSolver(K, Ps, nullspace="constant", local_nodes=np.ones(3, dtype=bool))
    with pytest.raises(SolverInputError, match="local_nodes must lie"):
        MultigridSolver(K, Ps, nullspace="constant", local_nodes=[-1])


def test_per_level_smoother_list(cube):
    _V, _T, K, Ps = cube
    spec = [("symmetric_gauss_seidel", {"iterations": 1}), ("symmetric_gauss_seidel", {"iterations": 2})]
    ml = MultigridSolver(K, Ps, nullspace="constant", presmoother=spec)
    its = [L.presmoother.params["iterations"] for L in ml.levels[:-1]]
    assert its == [1, 2]
    assert ml.symmetric_cycle
    # a (name, options) pair given as a list is still one spec for every level
    ml2 = MultigridSolver(K, Ps, nullspace="constant", presmoother=["gauss_seidel", {"sweep": "symmetric"}])
    assert [L.presmoother.params["sweep"] for L in ml2.levels[:-1]] == ["symmetric", "symmetric"]
    with pytest.raises(SolverInputError):
        MultigridSolver(K, Ps, nullspace="constant", presmoother=[])


def test_one_way_local_sweeps_adjoint_and_cheaper(cube, rng):
    """local_sweep="one-way": forward local pass after pre-smoothing, backward before post-smoothing. The
    cycle stays symmetric (a CG preconditioner), costs half the local work, and still beats no local
    sweeps with the forward/backward Gauss–Seidel cycle."""
    V, T, K, Ps = cube
    b = rng.standard_normal(len(V))
    b -= b.mean()
    fgs = ("gauss_seidel", {"sweep": "forward", "iterations": 1})
    L = boundary_layer_nodes(T, 1)
    kw = {"nullspace": "constant", "presmoother": fgs, "deflate": 0}  # local sweeps alone, no deflation
    plain = MultigridSolver(K, Ps, **kw)
    sym = MultigridSolver(K, Ps, **kw, local_nodes=L)
    one = MultigridSolver(K, Ps, **kw, local_nodes=L, local_sweep="one-way")
    assert one.symmetric_cycle
    assert one.levels[0].presmoother.params["local_sweep"] == "forward"
    assert one.levels[0].postsmoother.params["local_sweep"] == "backward"
    M = one.aspreconditioner()
    x, y = rng.standard_normal(len(V)), rng.standard_normal(len(V))
    x -= x.mean()
    y -= y.mean()
    assert abs((M @ x) @ y - x @ (M @ y)) <= 1e-10 * abs(x @ (M @ y))
    # half the local work of symmetric local sweeps
    extra_sym = sym.cycle_complexity() - plain.cycle_complexity()
    extra_one = one.cycle_complexity() - plain.cycle_complexity()
    assert abs(extra_one - 0.5 * extra_sym) <= 1e-9 * extra_sym
    f0, f1 = _factor(plain, b), _factor(one, b)
    assert f1 < f0 - 0.01, (f0, f1)
    x1 = one.solve(b, tol=1e-10, accel="cg")
    assert np.linalg.norm(K @ x1 - b) <= 1e-9 * np.linalg.norm(b)
    # a forward pre-smoother with a forward (non-adjoint) local post pass is detected as non-symmetric
    A = plain.levels[0].A
    pre = with_local_sweeps(make_smoother(A, fgs), A, L, sweep="forward")
    post = with_local_sweeps(make_smoother(A, ("gauss_seidel", {"sweep": "backward", "iterations": 1})), A, L,
                             first=True, sweep="forward")
    assert not solvers_multilevel._smoothers_adjoint(pre, post)
    with pytest.raises(SolverInputError, match="local_sweep"):
        MultigridSolver(K, Ps, nullspace="constant", local_nodes=L, local_sweep="both")
    with pytest.raises(SolverInputError, match="local sweep"):
        with_local_sweeps(make_smoother(A, fgs), A, L, sweep="sideways")


def test_local_rows_copy_gives_the_in_place_sweep(cube):
    """The sweeps relax a contiguous copy of the layer's rows: the same iterate as pyamg's indexed sweep
    on A itself; a pre/post pair can share one copy; a copy of other rows is refused."""
    from pyamg.relaxation import relaxation

    from solvers.smoothing import local_rows

    _V, T, K, _ = cube
    A = K.tocsr()
    idx = boundary_layer_nodes(T, 1)
    rng = np.random.default_rng(3)
    x0, b = rng.standard_normal(A.shape[0]), rng.standard_normal(A.shape[0])
    base = make_smoother(A, ("gauss_seidel", {"sweep": "forward", "iterations": 1}))
    rows = local_rows(A, idx)
    assert rows.nnz == int((A.indptr[idx + 1] - A.indptr[idx]).sum()) and rows.shape == A.shape
    for sweep in ("forward", "backward", "symmetric"):
        sm = with_local_sweeps(base, A, idx, 1, first=True, sweep=sweep, rows=rows)
        x1 = x0.copy()
        sm(A, x1, b)
        x2 = x0.copy()
        relaxation.gauss_seidel_indexed(A, x2, b, idx.astype(A.indices.dtype), iterations=1, sweep=sweep)
        base(A, x2, b)
        np.testing.assert_allclose(x1, x2, rtol=0, atol=1e-13)
    with pytest.raises(SolverInputError, match="local_rows"):
        with_local_sweeps(base, A, idx, rows=local_rows(A, idx[::2]))
