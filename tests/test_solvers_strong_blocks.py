"""The exact solve on a fine level's strongly coupled unknowns (``MultigridSolver(strong_blocks=...)``)."""

import numpy as np
import pytest
import scipy.sparse as sp

from solvers import MultigridSolver, fem
from solvers.errors import SolverInputError
from solvers.gallery import kuhn_cube_hierarchy
from solvers.subdomain import strongly_coupled


def _reference(A: sp.csr_matrix, theta: float) -> list:
    """The definition, entry by entry."""
    Ad = A.toarray()
    d = np.diag(Ad)
    n = len(d)
    return [i for i in range(n) if any(j != i and Ad[i, j] != 0 and d[i] > 0 and d[j] > 0
                                       and Ad[i, j] ** 2 >= theta ** 2 * d[i] * d[j] for j in range(n))]


def test_strongly_coupled_is_the_definition_on_both_paths():
    """Random symmetric matrices with zero and negative diagonals and empty rows: the full scan and the
    lower-triangle scan give exactly the nodes of the definition."""
    rng = np.random.default_rng(1)
    found = 0
    for _ in range(150):
        n = int(rng.integers(2, 30))
        M = sp.random(n, n, density=0.25, random_state=int(rng.integers(1 << 30)), format="csr")
        d = rng.uniform(-0.5, 3.0, n)
        d[rng.random(n) < 0.2] = 0.0
        A = sp.csr_matrix(M + M.T + sp.diags(d))
        keep = sp.diags((rng.random(n) < 0.8).astype(float))  # some empty rows
        A = sp.csr_matrix(keep @ A @ keep)
        A.eliminate_zeros()
        theta = float(rng.uniform(0.05, 1.0))
        want = _reference(A, theta)
        got = strongly_coupled(A, theta, max_fraction=1.0)
        assert (got.tolist() if got is not None else []) == want
        low = sp.csr_matrix(sp.tril(A))
        got_low = strongly_coupled(A, theta, max_fraction=1.0, lower=(low, A.diagonal()))
        assert (got_low.tolist() if got_low is not None else []) == want
        found += bool(want)
    assert found > 50  # the draws exercise non-empty regions


def test_strongly_coupled_refuses_dense_regions_and_bad_thresholds():
    A = sp.csr_matrix(np.array([[2.0, -1.9, 0.0], [-1.9, 2.0, -0.1], [0.0, -0.1, 2.0]]))
    assert strongly_coupled(A, 0.5, max_fraction=1.0).tolist() == [0, 1]
    assert strongly_coupled(A, 0.5, max_fraction=0.5) is None  # 2 of 3 unknowns: not local
    assert strongly_coupled(A, 0.99, max_fraction=1.0) is None
    for bad in (0.0, 1.5, -0.2):
        with pytest.raises(SolverInputError, match="threshold"):
            strongly_coupled(A, bad)


@pytest.fixture(scope="module")
def stiff_pairs():
    """A Neumann Poisson matrix on the Kuhn cube plus stiff springs (100 diagonals) along 40 mesh edges:
    the coupling a flat tet gives its two nearly coincident nodes."""
    meshes, Ps = kuhn_cube_hierarchy(12, 3)
    V, T = meshes[0]
    K = fem.stiffness_matrix(V, T).tocsr()
    n = K.shape[0]
    rng = np.random.default_rng(0)
    edges = np.unique(np.sort(T[:, [0, 1]], axis=1), axis=0)
    pick = edges[rng.choice(len(edges), 40, replace=False)]
    w = 100.0 * K.diagonal()[pick[:, 0]]
    i, j = pick[:, 0], pick[:, 1]
    S = sp.coo_matrix((np.r_[w, w, -w, -w], (np.r_[i, j, i, j], np.r_[i, j, j, i])), shape=(n, n))
    b = rng.standard_normal(n)
    return sp.csr_matrix(K + S), Ps, b - b.mean(), np.unique(pick)


def test_default_solves_the_stiff_pairs_exactly(stiff_pairs):
    """The default finds exactly the springs' end nodes and cuts MG-PCG and the stationary cycle's
    iterations at least in half against the plain point smoother (measured: 33 -> 13 and 196 -> 36)."""
    A, Ps, b, ends = stiff_pairs
    ml = MultigridSolver(A, Ps, nullspace="constant")
    assert ml.strong_blocks == {"theta": 0.5, "nodes": ends.size, "installed": True}
    assert np.array_equal(strongly_coupled(A), ends)
    plain = MultigridSolver(A, Ps, nullspace="constant", strong_blocks=None)
    assert plain.strong_blocks is None
    for accel, maxiter in (("cg", 100), (None, 400)):
        x, info = ml.solve(b, tol=1e-8, accel=accel, return_info=True, maxiter=maxiter)
        _, info0 = plain.solve(b, tol=1e-8, accel=accel, return_info=True, maxiter=maxiter)
        assert info["converged"] and info["iterations"] <= info0["iterations"] // 2, (info, info0)
        r = b - A @ x
        assert np.linalg.norm(r) <= 1e-8 * np.linalg.norm(b) * 1.01
    assert ml.symmetric_cycle  # the solve sits between pre- and post-smoother: CG stays valid
    assert f"Strong couplings:     theta 0.5: exact solve on {ends.size} fine unknowns" in repr(ml)
    assert "Strong couplings:     off" in repr(plain)
    z = np.random.default_rng(3).standard_normal((2, A.shape[0]))
    z -= z.mean(axis=1, keepdims=True)
    M = ml.aspreconditioner()
    assert abs(z[0] @ (M @ z[1]) - z[1] @ (M @ z[0])) <= 1e-10 * abs(z[0] @ (M @ z[0]))


def test_strong_blocks_option_is_checked(stiff_pairs):
    A, Ps, _b, _ends = stiff_pairs
    for bad in (0.0, 2.0, True, "yes"):
        with pytest.raises(SolverInputError, match="strong_blocks"):
            MultigridSolver(A, Ps, nullspace="constant", strong_blocks=bad)


def test_a_strongly_coupled_majority_is_refused_not_factored():
    """An operator squashed along z everywhere (anisotropic: most unknowns strongly coupled) is not local:
    the solve is refused and says why (the squashed patch of test_solvers_subdomain.py gets it)."""
    meshes, Ps = kuhn_cube_hierarchy(8, 3)
    V, T = meshes[0]
    K = fem.stiffness_matrix(V * [1.0, 1.0, 0.1], T).tocsr()
    ml = MultigridSolver(K, Ps, nullspace="constant")
    report = ml.strong_blocks
    assert not report["installed"] and report.get("refused_size") and report["nodes"] > 0.1 * K.shape[0]
    assert "subdomain_nodes" not in ml.levels[0].presmoother.params
    assert f"theta 0.5: {report['nodes']} unknowns, not solved (more than a tenth of the unknowns)" in repr(ml)
