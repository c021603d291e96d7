"""Deflation of a cycle's slow modes (solvers.deflation, MultigridSolver(deflate=, probe_finest=))."""

import numpy as np
import pytest
import scipy.sparse as sp

from solvers import (MultigridSolver, NullspaceMultigridSolver, block_prolongation, elasticity_matrix,
                     rigid_body_modes)
import solvers.deflation as slow_modes_module
from solvers.deflation import DEFLATION_GOAL, LANCZOS_CYCLES, PROBE_CYCLES, slow_modes
from solvers.errors import SolverInputError
from solvers.fem import stiffness_matrix
from solvers.multilevel import AUTO_PROBE_MAX_COMPLEXITY
from solvers.gallery import kuhn_cube_hierarchy

from conftest import energy_factor as _factor


@pytest.fixture(scope="module")
def pieces():
    """A Kuhn cube (16^3 cells, 3 levels) with three small cubes wrapped in a skin 1000x less conductive:
    weakly attached pieces whose "piece moves, rest does not" modes the coarse levels cannot represent."""
    meshes, Ps = kuhn_cube_hierarchy(16, 3)
    V, T = meshes[0]
    c = V[T].mean(axis=1)
    w = np.ones(len(T))
    for centre in ([0.3, 0.3, 0.3], [0.7, 0.6, 0.4], [0.4, 0.7, 0.7]):
        d = np.abs(c - centre).max(axis=1)
        w[(d > 0.08) & (d < 0.08 + 1.2 / 16)] = 1e-3
    return stiffness_matrix(V, T, w), Ps


def test_slow_modes_of_a_known_operator():
    """E = diag(θ) with A = I: the Ritz pairs are exact; the modes above the goal come back, slowest first."""
    theta = np.r_[0.9, 0.6, 0.45, np.linspace(0.2, 0.01, 197)]
    Z, info = slow_modes(lambda x: x.__imul__(theta), sp.identity(200, format="csr"), max_vectors=8)
    assert info["vectors"] == 3 and info["cycles"] <= 24
    assert np.allclose(info["factors"], [0.9, 0.6, 0.45], atol=1e-8)
    assert np.allclose(Z.T @ Z, np.eye(3), atol=1e-10)  # A-orthonormal
    assert np.allclose(np.abs(Z[:3, :3]), np.eye(3), atol=1e-6) and np.abs(Z[3:]).max() < 1e-6
    assert info["probe_factor"] > DEFLATION_GOAL


def test_slow_modes_refuses_the_bulk_of_the_spectrum():
    """More slow modes than max_vectors is no outlier: nothing is returned (the probe still reports)."""
    theta = np.r_[np.linspace(0.8, 0.5, 20), np.full(80, 0.05)]
    Z, info = slow_modes(lambda x: x.__imul__(theta), sp.identity(100, format="csr"), max_vectors=4)
    assert Z.shape == (100, 0) and info["slow_modes_found"] > 4 and info["probe_factor"] > 0.7
    # the verdict is final as soon as more than max_vectors Ritz values are above the goal (interlacing):
    # the probe stops there, not after LANCZOS_CYCLES steps
    assert info["cycles"] == PROBE_CYCLES and info["slow_modes_found"] == 7
    Z, info = slow_modes(lambda x: x.__imul__(theta), sp.identity(100, format="csr"), max_vectors=12)
    assert Z.shape == (100, 0) and info["cycles"] == 14 and info["slow_modes_found"] == 13


def test_slow_modes_early_stop_keeps_a_late_verdict():
    """Six outliers and max_vectors 6: all 24 steps, six modes back; max_vectors 5: refused, early."""
    theta = np.r_[0.95, 0.9, 0.85, 0.8, 0.75, 0.7, np.linspace(0.2, 0.0, 194)]
    Z, info = slow_modes(lambda x: x.__imul__(theta), sp.identity(200, format="csr"), max_vectors=6)
    assert info["cycles"] == LANCZOS_CYCLES and info["vectors"] == 6
    assert np.allclose(info["factors"], theta[:6], atol=1e-8)
    Z, info = slow_modes(lambda x: x.__imul__(theta), sp.identity(200, format="csr"), max_vectors=5)
    assert Z.shape == (200, 0) and info["slow_modes_found"] == 6 and info["cycles"] < LANCZOS_CYCLES


def test_a_probe_below_the_goal_but_undecided_continues():
    """Two outliers (0.33, 0.31) above a dense spectrum up to 0.29: after the probe's 8 cycles the slowest
    Ritz value is still below the goal (a lower bound, by interlacing), but its residual could lift it above:
    the probe continues and finds both modes. A spectrum well below the goal stops at the probe."""
    theta = np.r_[0.33, 0.31, np.linspace(0.29, 0.0, 998)]
    Z, info = slow_modes(lambda x: x.__imul__(theta), sp.identity(1000, format="csr"), max_vectors=8)
    assert info["probe_factor"] < DEFLATION_GOAL < info["probe_factor"] + info["probe_residual"]
    assert info["cycles"] == LANCZOS_CYCLES and info["vectors"] == 2
    assert np.allclose(info["factors"], [0.33, 0.31], atol=1e-4)
    low = np.linspace(0.2, 0.0, 1000)
    Z, info = slow_modes(lambda x: x.__imul__(low), sp.identity(1000, format="csr"), max_vectors=8)
    assert info["cycles"] == PROBE_CYCLES and Z.shape == (1000, 0)
    assert info["probe_factor"] + info["probe_residual"] <= DEFLATION_GOAL


def test_deflation_fixes_weakly_attached_pieces(pieces):
    """Measured: V-cycle factor 0.853 without deflation, 0.281 with it (4 modes on the finest level)."""
    K, Ps = pieces
    plain = MultigridSolver(K, Ps, nullspace="constant", deflate=0)
    fixed = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True)
    assert _factor(plain) > 0.8
    assert _factor(fixed) <= 0.3
    used = [d for d in fixed.deflation if d["vectors"]]
    assert used and used[0]["level"] == 0 and used[0]["probe_factor"] > 0.8
    # the modes' energy spreads over the pieces' skins, more than a tenth of the level: no subdomain solve
    # (solvers.subdomain) is tried, deflation alone acts
    assert "local_solve" not in used[0]
    assert "level 0:" in repr(fixed)
    # still a symmetric preconditioner, and MG-PCG needs fewer iterations
    M = fixed.aspreconditioner()
    rng = np.random.default_rng(0)
    x, y = rng.standard_normal(K.shape[0]), rng.standard_normal(K.shape[0])
    x -= x.mean()
    y -= y.mean()
    assert abs((M @ x) @ y - x @ (M @ y)) <= 1e-10 * abs(x @ (M @ y))
    b = rng.standard_normal(K.shape[0])
    b -= b.mean()
    its = []
    for ml in (plain, fixed):
        _, info = ml.solve(b, tol=1e-8, accel="cg", return_info=True)
        assert info["converged"]
        its.append(info["iterations"])
    assert its[1] <= its[0] - 3, its
    # without probe_finest the finest level is not probed (its probe costs about one solve); the bare
    # constructor probes the coarse levels by default only within AUTO_PROBE_MAX_COMPLEXITY (deflate="auto")
    coarse = MultigridSolver(K, Ps, nullspace="constant", deflate=8)
    assert coarse.deflation and all(d["level"] > 0 for d in coarse.deflation)
    bare = MultigridSolver(K, Ps, nullspace="constant")
    assert bare.deflate == (8 if bare.operator_complexity() <= AUTO_PROBE_MAX_COMPLEXITY else 0)
    assert [d["level"] for d in bare.deflation] == ([d["level"] for d in coarse.deflation] if bare.deflate else [])


def test_no_deflation_where_the_cycle_is_fast():
    """A plain Poisson cube: every probe meets the goal, and the iterates equal those of deflate=0 bit for bit."""
    meshes, Ps = kuhn_cube_hierarchy(8, 3)
    K = stiffness_matrix(*meshes[0])
    b = np.random.default_rng(2).standard_normal(K.shape[0])
    b -= b.mean()
    res = []
    for d in (0, 8):
        ml = MultigridSolver(K, Ps, nullspace="constant", deflate=d, probe_finest=True)
        assert all(r["vectors"] == 0 for r in ml.deflation)
        r = []
        ml.solve(b, tol=1e-8, residuals=r)
        res.append(r)
    assert res[0] == res[1]


@pytest.mark.parametrize("bad", [-1, 1.5, True])
def test_deflate_must_be_a_count(pieces, bad):
    K, Ps = pieces
    with pytest.raises(SolverInputError, match="deflate"):
        MultigridSolver(K, Ps, nullspace="constant", deflate=bad)


def test_a_broken_cycle_is_not_probed_into_an_error():
    """A cycle producing NaN/inf leaves nothing deflated and no exception at setup (solve() reports it)."""
    def broken(x):
        x[:] = np.nan

    Z, info = slow_modes(broken, sp.identity(50, format="csr"))
    assert Z.shape == (50, 0) and info["non_finite"]


@pytest.fixture(scope="module")
def elastic_piece():
    """Pure-traction elasticity (ν = 0.3) on a Kuhn cube (16^3 cells, 3 levels) with one small cube wrapped
    in a skin 1000x softer: the piece's six rigid motions relative to the rest are slow for the cycle."""
    meshes, Ps = kuhn_cube_hierarchy(16, 3)
    V, T = meshes[0]
    d = np.abs(V[T].mean(axis=1) - [0.3, 0.3, 0.3]).max(axis=1)
    E = np.where((d > 0.08) & (d < 0.08 + 1.2 / 16), 1e-3, 1.0)
    K = elasticity_matrix(V, T, E, 0.3)
    return K, [block_prolongation(P) for P in Ps], [rigid_body_modes(Vk) for Vk, _ in meshes]


def test_constant_nullspace_equals_its_basis():
    """nullspace_basis = the normalised constant gives the Ritz values of constant_nullspace=True."""
    meshes, Ps = kuhn_cube_hierarchy(8, 3)
    K = stiffness_matrix(*meshes[0])
    ml = MultigridSolver(K, Ps, nullspace="constant", deflate=0)
    zero = np.zeros(K.shape[0])

    def cycle(x):
        ml._cycle(0, x, zero, "V")

    q = np.full((K.shape[0], 1), K.shape[0] ** -0.5)
    a = slow_modes(cycle, K, constant_nullspace=True, goal=0.0, max_vectors=30)[1]
    b = slow_modes(cycle, K, nullspace_basis=q, goal=0.0, max_vectors=30)[1]
    assert a["cycles"] == b["cycles"] and a["vectors"] == b["vectors"] > 5
    assert np.allclose(a["factors"], b["factors"], rtol=0, atol=1e-8)
    with pytest.raises(SolverInputError, match="nullspace_basis"):
        slow_modes(cycle, K, nullspace_basis=q[1:])


def test_rigid_modes_kept_out_of_the_probe(elastic_piece):
    """Without the kernel basis the Lanczos vectors, normalised in the A-norm, let the rigid modes (E z = z)
    grow until round-off shows a spurious factor-1 mode made of them (measured: 0.99991, |Z| ~ 1e8); the
    basis is then no longer A-orthonormal, and A-orthonormalising it fails too (huge vectors of tiny A-norm:
    ``Zᵀ A Z`` is lost to cancellation), so no mode is returned (``not_orthonormal``). With the kernel basis
    the slowest mode is the piece's (0.923) and Z has no kernel component."""
    K, Pb, Zs = elastic_piece
    ml = NullspaceMultigridSolver(K, Pb, Zs, deflate=0)
    zero = np.zeros(K.shape[0])

    def cycle(x):
        ml._cycle(0, x, zero, "V")

    Q = ml.nullspace_bases[0]
    Zb, blind = slow_modes(cycle, K, max_vectors=16)
    Z, seen = slow_modes(cycle, K, nullspace_basis=Q, max_vectors=16)
    assert Zb.shape[1] == 0 and blind["not_orthonormal"] > slow_modes_module.ORTHONORMAL_TOL
    assert blind["reorthonormalized"] > slow_modes_module.ORTHONORMAL_TOL
    assert 0.9 < seen["factors"][0] < 0.95 and seen["vectors"] >= 6
    assert np.linalg.norm(Q.T @ Z) <= 1e-12 * np.linalg.norm(Z)
    assert np.allclose(Z.T @ (K @ Z), np.eye(Z.shape[1]), atol=1e-8)  # A-orthonormal


def test_nullspace_solver_probes_on_one_blas_thread(elastic_piece, monkeypatch):
    """NullspaceMultigridSolver probes after MultigridSolver's set-up has returned (its projected coarse solve
    first): that probe runs on one BLAS thread too, and the caller's limits come back."""
    import threadpoolctl
    from conftest import blas_threads, record_blas_threads

    from solvers import multilevel

    K, Pb, Zs = elastic_piece
    probes = record_blas_threads(monkeypatch, multilevel, "slow_modes")
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        NullspaceMultigridSolver(K, Pb, Zs, deflate=8)
        after = blas_threads()
    assert probes and set(probes) == {1}
    assert after == before


def test_elasticity_deflation_cuts_mg_pcg_iterations(elastic_piece):
    """Measured: 21 MG-PCG iterations without deflation, 12 with the finest level's 12 slowest modes
    (probe 0.90 -> 0.51) and level 1's 9 deflated; the solution stays orthogonal to the rigid modes."""
    K, Pb, Zs = elastic_piece
    b = np.random.default_rng(0).standard_normal(K.shape[0])
    its, xs = [], []
    for kw in ({"deflate": 0}, {"deflate": 16, "probe_finest": True}):
        ml = NullspaceMultigridSolver(K, Pb, Zs, presmoother="symmetric_gauss_seidel", **kw)
        x, info = ml.solve(b, tol=1e-8, accel="cg", return_info=True, project=True)
        assert info["converged"]
        its.append(info["iterations"])
        xs.append(x)
    fine = ml.deflation[0]
    assert fine["level"] == 0 and 6 <= fine["vectors"] <= 16 and fine["probe_factor"] > 0.85
    assert fine["probe_after"] < 0.6 and not fine.get("reverted")
    assert "level 0:" in repr(ml) and "6 vectors per level (projected)" in repr(ml)
    assert its[0] >= 19 and its[1] <= 14, its
    Q = ml.nullspace_bases[0]
    bp = b - Q @ (Q.T @ b)
    for x in xs:
        assert np.linalg.norm(Q.T @ x) <= 1e-12 * np.linalg.norm(x)
        assert np.linalg.norm(bp - K @ x) <= 1.01e-8 * np.linalg.norm(bp)
    assert np.linalg.norm(xs[1] - xs[0]) <= 1e-5 * np.linalg.norm(xs[0])


def test_the_goal_decides_which_modes_are_deflated(pieces):
    """A goal above every slow mode deflates nothing; the default goal deflates the weakly attached pieces."""
    K, Ps = pieces
    lax = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True, deflate_goal=0.95)
    strict = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True)
    assert strict.deflate_goal == DEFLATION_GOAL
    assert lax.deflation[0]["probe_factor"] > 0.8 and all(d["vectors"] == 0 for d in lax.deflation)
    assert strict.deflation[0]["vectors"] > 0
    theta = np.r_[0.9, 0.6, 0.45, 0.25, np.linspace(0.15, 0.01, 196)]
    counts = [slow_modes(lambda x: x.__imul__(theta), sp.identity(200, format="csr"), goal=g)[1]["vectors"]
              for g in (0.3, 0.2)]
    assert counts == [3, 4]


@pytest.mark.parametrize("bad", [0.0, 1.0, -0.2])
def test_deflate_goal_must_be_a_factor(pieces, bad):
    K, Ps = pieces
    with pytest.raises(SolverInputError, match="deflate_goal"):
        MultigridSolver(K, Ps, nullspace="constant", deflate_goal=bad)


def test_probe_deferred_to_the_first_stationary_solve(pieces):
    """probe_at="stationary": the coarser levels are probed at set-up, the finest level not for MG-PCG or
    aspreconditioner(); the first stationary solve probes it and then cycles exactly as a solver that
    probed everything at set-up (same report, same residuals bit for bit)."""
    K, Ps = pieces
    b = np.random.default_rng(3).standard_normal(K.shape[0])
    b -= b.mean()
    eager = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True)
    lazy = MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_finest=True, probe_at="stationary")
    assert [d["level"] for d in lazy.deflation] == [1]
    _, info = lazy.solve(b, tol=1e-8, accel="cg", return_info=True)
    lazy.aspreconditioner() @ b
    assert info["converged"] and [d["level"] for d in lazy.deflation] == [1]
    r_eager, r_lazy = [], []
    eager.solve(b, tol=1e-8, residuals=r_eager)
    lazy.solve(b, tol=1e-8, residuals=r_lazy)
    assert [d["level"] for d in lazy.deflation] == [d["level"] for d in eager.deflation] == [0, 1]
    assert [d["vectors"] for d in lazy.deflation] == [d["vectors"] for d in eager.deflation]
    assert sum(d["vectors"] for d in lazy.deflation) >= 1
    assert r_lazy == r_eager and r_lazy[-1] <= 1e-8
    report = lazy.deflation
    assert lazy.probe() is report  # once only


def test_probe_at_must_be_named(pieces):
    K, Ps = pieces
    with pytest.raises(SolverInputError, match="probe_at"):
        MultigridSolver(K, Ps, nullspace="constant", deflate=8, probe_at="later")


def test_one_level_solver_with_a_deferred_probe_solves_directly():
    """A solver of one level (its coarsest, solved directly: no smoother, nothing to probe) with the finest
    level's probe deferred to stationary solves (``Problem.multigrid()``'s set-up) solves; it raised
    AttributeError in the probe's cycle before."""
    from solvers.fem import boundary_nodes

    meshes, _ = kuhn_cube_hierarchy(4, 1)
    V, T = meshes[0]
    free = np.setdiff1d(np.arange(len(V)), boundary_nodes(T))
    A = stiffness_matrix(V, T)[free][:, free].tocsr()
    b = np.linspace(1.0, 2.0, A.shape[0])
    ml = MultigridSolver(A, [], deflate=8, probe_finest=True, probe_at="stationary")
    x, info = ml.solve(b, tol=1e-10, accel=None, return_info=True)
    assert info["converged"] and info["iterations"] == 1 and ml.deflation == []
    assert np.linalg.norm(A @ x - b) <= 1e-12 * np.linalg.norm(b)
