"""Exact subdomain solves on the region of a level's slow modes (solvers.subdomain,
MultigridSolver(local_solve=))."""

import numpy as np
import pytest
import scipy.sparse as sp

from solvers import MultigridSolver
from solvers.errors import SolverInputError
from solvers.fem import stiffness_matrix
from solvers.gallery import kuhn_cube_hierarchy
from solvers.smoothing import make_smoother
from solvers.subdomain import slow_region, subdomain_factor, with_subdomain_solve

from conftest import energy_factor as _factor


def _flat_patch(n: int, half: float, squash: float = 0.1):
    """A Kuhn cube (n^3 cells, 3 levels) whose elements within ``half`` of the centre are assembled as if
    squashed ``squash`` times along z: strongly coupled along z, weakly across, like the flat elements of a
    thin lip one or two elements thick. Point Gauss–Seidel does not smooth the patch's modes that are smooth
    along z and rough across it, and the coarse levels (isotropic) do not represent them: a local family of
    slow modes, too many to deflate."""
    meshes, Ps = kuhn_cube_hierarchy(n, 3)
    V, T = meshes[0]
    patch = np.abs(V[T].mean(axis=1) - 0.5).max(axis=1) < half
    K = stiffness_matrix(V, T[~patch]) + stiffness_matrix(V * [1.0, 1.0, squash], T[patch])
    return K, Ps, np.unique(T[patch])


@pytest.fixture(scope="module")
def flat_patch():
    return _flat_patch(24, 0.1)


def test_slow_region_is_where_the_modes_live():
    """Modes on a few nodes of a path graph: the region is the nodes carrying 90% of their energy plus one
    ring of neighbours; modes spread over the whole graph have no region."""
    n = 400
    A = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    Z = np.zeros((n, 2))
    Z[200:205, 0] = [1, 2, 3, 2, 1]
    Z[201:204, 1] = [1, -1, 1]
    region = slow_region(Z, A)  # energy z_i (A z)_i: none at 200 and 204 (A z vanishes there), so the
    assert region is not None and region.tolist() == list(range(200, 205))  # core is 201-203, + one ring
    spread = np.sin(np.pi * np.outer(np.arange(1, n + 1), [1, 2]) / (n + 1))
    assert slow_region(spread, A) is None
    assert slow_region(np.zeros((n, 0)), A) is None


def test_subdomain_solve_is_exact_there_and_the_pair_adjoint():
    """After the correction the residual vanishes on the subdomain; pre then post is a symmetric operator."""
    K, _, nodes = _flat_patch(8, 0.2)
    K = K + sp.identity(K.shape[0], format="csr")  # nonsingular: x -> smoothed x is an affine map
    base = make_smoother(K, ("symmetric_gauss_seidel", {"iterations": 1}))
    pre = with_subdomain_solve(base, K, nodes)
    post = with_subdomain_solve(base, K, nodes, first=True)
    rng = np.random.default_rng(0)
    b = rng.standard_normal(K.shape[0])
    x = np.zeros_like(b)
    pre(K, x, b)
    assert np.abs((b - K @ x)[nodes]).max() <= 1e-10 * np.abs(b).max()
    assert pre.params["subdomain_nodes"] == nodes.size and pre.work > base.work

    def M(r):  # one pre- and one post-smoothing from zero: a symmetric approximate inverse of K
        y = np.zeros_like(r)
        pre(K, y, r)
        post(K, y, r)
        return y

    u, v = rng.standard_normal(K.shape[0]), rng.standard_normal(K.shape[0])
    assert abs(M(u) @ v - u @ M(v)) <= 1e-10 * abs(u @ M(v))


@pytest.mark.parametrize("bad", [np.array([3, 2]), np.array([-1, 4]), np.array([], dtype=int)])
def test_subdomain_nodes_are_checked(bad):
    K = sp.identity(10, format="csr")
    base = make_smoother(K, ("jacobi", {}))
    with pytest.raises(SolverInputError, match="subdomain nodes"):
        with_subdomain_solve(base, K, bad)


def test_local_solve_takes_a_family_too_large_to_deflate(flat_patch):
    """Measured: the patch's family is more than 8 slow modes (nothing deflated) and the V-cycle factor
    0.66; with the subdomain solve on the ~240 patch nodes the probe finds 0.26 and the factor is 0.26."""
    K, Ps, nodes = flat_patch
    plain = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True, local_solve=False)
    fixed = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True)
    assert plain.deflation[0]["slow_modes_found"] > 8 and _factor(plain) > 0.6
    assert _factor(fixed) <= 0.3
    local = fixed.deflation[0]["local_solve"]
    assert local["probe_factor"] <= 0.3 and local["nodes"] <= 0.1 * K.shape[0]
    assert f"level 0: local solve on {local['nodes']} unknowns" in repr(fixed)
    b = np.random.default_rng(0).standard_normal(K.shape[0])
    b -= b.mean()
    its = [ml.solve(b, tol=1e-8, accel="cg", return_info=True)[1]["iterations"] for ml in (plain, fixed)]
    assert its[1] <= its[0] - 4, its


def test_local_solve_replaces_deflation_of_a_small_family():
    """A smaller patch: 8 modes deflated without the subdomain solve, none with it, and a factor at least
    as good (measured 0.284 and 0.261)."""
    K, Ps, _ = _flat_patch(16, 0.1)
    plain = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True, local_solve=False)
    fixed = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True)
    assert plain.deflation[0]["vectors"] == 8 and fixed.deflation[0]["vectors"] == 0
    assert _factor(fixed) <= min(_factor(plain), 0.3)



def test_a_singular_block_is_refused():
    """A region holding a whole piece of a two-piece Neumann operator (the extra kernel of a rank-deficient
    coarse level looks like that: a local mode of factor 1) has a singular block: no factor, a clear error."""
    n = 50
    path = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tolil()
    path[0, 0] = path[n - 1, n - 1] = 1.0  # a Neumann path: constants in its kernel
    A = sp.block_diag([path, path[:5, :5].tocsr()]).tocsr()
    A[n + 4, n + 4] = 1.0
    piece = np.arange(n, n + 5)
    assert subdomain_factor(A, piece) is None
    assert subdomain_factor(A, np.arange(10, 20)) is not None  # a proper part of a piece: nonsingular
    base = make_smoother(A, ("jacobi", {}))
    with pytest.raises(SolverInputError, match="singular"):
        with_subdomain_solve(base, A, piece)
