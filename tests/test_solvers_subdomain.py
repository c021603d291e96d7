"""Exact subdomain solves on the region of a level's slow modes (solvers.subdomain,
MultigridSolver(local_solve=))."""

import numpy as np
import pytest
import scipy.sparse as sp

from solvers import MultigridSolver, restrict_prolongations
from solvers.errors import SolverInputError
from solvers.fem import boundary_nodes, stiffness_matrix
from solvers.gallery import kuhn_cube_hierarchy
from solvers.smoothing import make_smoother
from solvers.subdomain import (concentrated_region, power_probe, slow_region, strongly_coupled,
                               subdomain_factor, with_subdomain_solve)

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
    # the probe's own local solve, without the default strong-coupling solve (which takes the patch too)
    plain = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True, local_solve=False,
                            strong_blocks=None)
    fixed = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True, strong_blocks=None)
    assert plain.deflation[0]["slow_modes_found"] > 8 and _factor(plain) > 0.6
    assert _factor(fixed) <= 0.3
    local = fixed.deflation[0]["local_solve"]
    assert local["probe_factor"] <= 0.3 and local["nodes"] <= 0.1 * K.shape[0]
    assert f"level 0: local solve on {local['nodes']} unknowns" in repr(fixed)
    b = np.random.default_rng(0).standard_normal(K.shape[0])
    b -= b.mean()
    its = [ml.solve(b, tol=1e-8, accel="cg", return_info=True)[1]["iterations"] for ml in (plain, fixed)]
    assert its[1] <= its[0] - 4, its


def test_strong_coupling_solve_finds_the_flat_patch_without_a_probe(flat_patch):
    """The strong-coupling solve finds the squashed patch from the matrix alone (its z-couplings), no probe.
    Measured factors: 0.66 without it, 0.60 at the default threshold 0.5 (88 unknowns, a third of the
    patch: its couplings are near the threshold), 0.30 at 0.3 (169)."""
    K, Ps, nodes = flat_patch
    plain = _factor(MultigridSolver(K, Ps, nullspace="constant", strong_blocks=None))
    ml = MultigridSolver(K, Ps, nullspace="constant")
    report = ml.strong_blocks
    assert report["installed"] and 0 < report["nodes"] <= 0.1 * K.shape[0]
    region = strongly_coupled(ml.levels[0].A)
    assert np.isin(region, nodes).mean() >= 0.9 and np.isin(nodes, region).mean() >= 0.25  # measured 1, 0.33
    assert plain > 0.6 and _factor(ml) <= plain - 0.04
    assert _factor(MultigridSolver(K, Ps, nullspace="constant", strong_blocks=0.3)) <= 0.32


def test_local_solve_replaces_deflation_of_a_small_family():
    """A smaller patch: 8 modes deflated without the subdomain solve, none with it, and a factor at least
    as good (measured 0.284 and 0.261)."""
    K, Ps, _ = _flat_patch(16, 0.1)
    plain = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True, local_solve=False,
                            strong_blocks=None)
    fixed = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True, strong_blocks=None)
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


def _path(n: int) -> sp.csr_matrix:
    return sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csr")


def test_concentrated_region_needs_concentrated_energy():
    """An error whose energy sits on a few nodes of a 1000-node path: the nodes carrying 70% of it plus one
    ring; an error spread over the path (a random one) has none, nor has zero."""
    n = 1000
    A = _path(n)
    e = 1e-3 * np.random.default_rng(0).standard_normal(n)
    e[500:503] += [1.0, -1.0, 1.0]
    region = concentrated_region(e, A)
    assert region is not None and 499 <= region[0] and region[-1] <= 503 and region.size <= 5
    assert concentrated_region(np.random.default_rng(1).standard_normal(n), A) is None
    assert concentrated_region(np.zeros(n), A) is None


def test_power_probe_returns_the_last_two_errors():
    """Three cycles of a halving map with the mean removed: the last two errors, both of zero mean."""
    A = _path(20)

    def project(v):
        v -= v.mean()

    prev, e = power_probe(lambda x: x.__imul__(0.5), A, 3, project)
    start = np.random.default_rng(0).standard_normal(20)
    start -= start.mean()
    assert np.allclose(prev, start / 4) and np.allclose(e, start / 8)


def test_subdomain_pre_smoother_keeps_the_cheap_residual():
    """The corrected pre-smoother returns its residual without a product with A (Gauss–Seidel's fast path
    plus the region's columns): the same iterate and residual as the plain path, from zero or not."""
    K, _, nodes = _flat_patch(8, 0.2)
    base = make_smoother(K, ("gauss_seidel", {"sweep": "forward", "iterations": 2}))
    pre = with_subdomain_solve(base, K, nodes)
    assert pre.smooth_residual is not None
    rng = np.random.default_rng(0)
    b = rng.standard_normal(K.shape[0])
    for x0 in (np.zeros_like(b), rng.standard_normal(K.shape[0])):
        x1, x2 = x0.copy(), x0.copy()
        r1 = pre.residual(K, x1, b, zero=not x0.any())
        pre(K, x2, b)
        assert np.allclose(x1, x2, atol=1e-12) and np.allclose(r1, b - K @ x2, atol=1e-12)


def test_cheap_probe_finds_the_patch(flat_patch):
    """Two cycles find the flat patch without Lanczos steps (measured: 175 unknowns, all within a ring of
    the patch's; CG 13 -> 9 iterations, factor 0.66 -> 0.43), and the keep test saw the gain."""
    K, Ps, nodes = flat_patch
    plain = MultigridSolver(K, Ps, nullspace="constant")
    fixed = MultigridSolver(K, Ps, nullspace="constant", local_probe=2)
    report = fixed.local_probe
    assert plain.local_probe is None and report["kept"] and report["ratio_after"] < 0.6 * report["ratio"]
    assert fixed.levels[0].presmoother.params["subdomain_nodes"] == report["nodes"]
    A = plain.levels[0].A  # the same seeded probe on the default cycle gives the solver's region
    zero = np.zeros(A.shape[0])
    _, e = power_probe(lambda x: plain._cycle(0, x, zero, "V"), A, 2, lambda v: v.__isub__(v.mean()))
    region = concentrated_region(e, A)
    near = np.zeros(A.shape[0], dtype=bool)
    near[A[nodes].indices] = True  # the patch and one ring
    assert region.size == report["nodes"] and near[region].all()
    assert f"level 0: local solve on {report['nodes']} unknowns (2-cycle probe)" in repr(fixed)
    assert _factor(fixed) < 0.5 < _factor(plain)
    b = np.random.default_rng(0).standard_normal(K.shape[0])
    b -= b.mean()
    its = [ml.solve(b, tol=1e-8, accel="cg", return_info=True)[1]["iterations"] for ml in (plain, fixed)]
    assert its[1] <= its[0] - 3, its


@pytest.mark.parametrize("neumann", [True, False])
def test_cheap_probe_adds_nothing_without_a_slow_region(neumann):
    """A plain Kuhn cube (Neumann, or Dirichlet on its interior): the probe's error is spread, no region is
    taken and the cycle is the default's (the same iterations and residuals)."""
    meshes, Ps = kuhn_cube_hierarchy(16, 3)
    V, T = meshes[0]
    K = stiffness_matrix(V, T)
    if not neumann:
        free = np.setdiff1d(np.arange(len(V)), boundary_nodes(T))
        K, (Ps, _) = K[free][:, free], restrict_prolongations(Ps, free)
    ns = "constant" if neumann else None
    plain = MultigridSolver(K, Ps, nullspace=ns)
    probed = MultigridSolver(K, Ps, nullspace=ns, local_probe=2)
    assert probed.local_probe == {"cycles": 2, "nodes": 0, "kept": False}
    assert "subdomain_nodes" not in probed.levels[0].presmoother.params
    b = np.random.default_rng(0).standard_normal(K.shape[0])
    b -= b.mean()
    res = [ml.solve(b, tol=1e-8, accel="cg", return_info=True)[1]["residuals"] for ml in (plain, probed)]
    assert np.allclose(res[0], res[1], rtol=1e-12)


@pytest.mark.parametrize("bad", [-1, 1.5, True])
def test_local_probe_is_checked(bad):
    K, Ps, _ = _flat_patch(8, 0.2)
    with pytest.raises(SolverInputError, match="local_probe"):
        MultigridSolver(K, Ps, nullspace="constant", local_probe=bad)
