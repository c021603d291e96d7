"""Multigrid on a procedurally nested hierarchy (iso-surfaces of one implicit function)."""

import numpy as np
import pytest
import scipy.sparse as sp

from nestmg.problems import setup_problem
from nestmg.run import solve_on_hierarchy


def test_tet_layers_are_nested(torus_iso_tets):
    S, tets, P, reps = torus_iso_tets
    assert [r.n_outside for r in reps] == [0, 0, 0]  # TetGen keeps the boundary: no extrapolation at all
    for k, Pk in enumerate(P):
        Vf, Vc = tets[k][0], tets[k + 1][0]
        a = np.array([0.4, -1.0, 2.5])
        assert np.abs(Pk @ (Vc @ a) - Vf @ a).max() < 1e-10  # linear reproduction on every fine node
    ntets = [len(T) for _, T in tets]
    assert all(ntets[k] > ntets[k + 1] for k in range(3))


@pytest.mark.parametrize("problem", ["poisson-dirichlet", "poisson-neumann", "diffusion-neumann"])
def test_galerkin_operators_symmetric_psd(torus_iso_tets, problem):
    _, tets, P, _ = torus_iso_tets
    pr = setup_problem(tets, P, problem)
    A = pr.A
    for Pk in pr.P:
        A = (Pk.T @ A @ Pk).tocsr()
        assert abs(A - A.T).max() <= 1e-12 * abs(A).max()
        lam = np.linalg.eigvalsh(A.toarray())  # coarse levels are small (<= 2.5k nodes here)
        assert lam[0] > -1e-10 * lam[-1], lam[:3]
        if problem == "poisson-neumann":
            assert np.abs(A @ np.ones(A.shape[0])).max() < 1e-10 * abs(A).max()  # constants stay in the kernel


def test_dirichlet_vcycle_factor_small_and_flat(torus_iso_tets):
    _, tets, P, _ = torus_iso_tets
    factors = []
    for L in (2, 3, 4):
        r = solve_on_hierarchy(tets[:L], P[: L - 1], "poisson-dirichlet", cost=False)
        assert r["converged"] and r["residuals"][-1] < 1e-8
        factors.append(r["factor"])
    assert max(factors) <= 0.3, factors
    assert max(factors[1:]) <= factors[0] + 0.05, factors  # no growth with the number of levels


@pytest.mark.parametrize("coarse", ["galerkin", "rediscretized"])
def test_neumann_and_diffusion_converge(torus_iso_tets, coarse):
    _, tets, P, _ = torus_iso_tets
    for problem in ("poisson-neumann", "diffusion-neumann"):
        r = solve_on_hierarchy(tets, P, problem, coarse=coarse, maxiter=100, cost=False)
        assert r["converged"] and not r["diverged"], (problem, coarse, r["message"])
        assert r["factor"] < 0.8, (problem, coarse, r["factor"])


def test_neumann_solution_is_the_true_solution(torus_iso_tets):
    """The MG answer matches a direct solve of the (pinned) Neumann system, up to the constant."""
    from solvers import MultigridSolver

    _, tets, P, _ = torus_iso_tets
    pr = setup_problem(tets[:3], P[:2], "poisson-neumann")
    assert abs(pr.b.sum()) < 1e-12 * np.abs(pr.b).sum()
    x = MultigridSolver(pr.A, pr.P, nullspace="constant").solve(pr.b, tol=1e-10, maxiter=200)
    keep = np.arange(1, pr.A.shape[0])
    y = np.zeros(pr.A.shape[0])
    y[keep] = sp.linalg.spsolve(pr.A[keep][:, keep].tocsc(), pr.b[keep])
    y -= y.mean()
    assert abs(x.mean()) < 1e-12
    assert np.abs(x - y).max() < 1e-6 * np.abs(y).max()


def test_cycle_cost_reported(torus_iso_tets):
    _, tets, P, _ = torus_iso_tets
    r = solve_on_hierarchy(tets, P, "poisson-dirichlet")
    c = r["cycle_cost"]
    assert 3.0 < c["counted_spmv_units"] < 25.0
    assert c["measured_spmv_units"] > 1.0
