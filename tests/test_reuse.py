"""Reuse across time steps (issue 15, item 5): sparse-sum Galerkin operators and warm-started MG-PCG steps."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from nestmg import SolverOptions


@pytest.fixture(scope="module")
def torus3():
    """A small procedurally nested 3-level torus hierarchy (iso-surfaces at growing offsets), TetGen."""
    pytest.importorskip("tetgen")
    from nestmg import MeshingOptions, SizingOptions, shapes
    from nestmg.hierarchy import tet_hierarchy

    S = shapes.nested_isosurfaces("torus", [0.0, 0.08, 0.2], [24, 14, 10])
    tets, P, reps, _ = tet_hierarchy(S, sizing=SizingOptions(edge_length=0.04, coarsening=None),
                                     meshing=MeshingOptions(mesher="tetgen"), cache=False, progress=False)
    assert [r.n_outside for r in reps] == [0, 0]
    return tets, P


def test_sparse_sum_equals_galerkin_of_the_step_matrix(torus3):
    from nestmg.problems import setup_problem
    from nestmg.timestepping import diffusion_stepper
    from solvers import galerkin_operators

    tets, P = torus3
    st = diffusion_stepper(tets, P)
    assert st.family.n_levels == 3
    # the stepper's fine matrices are those of setup_problem: A(lam) = M + lam K
    ref_prob = setup_problem(tets, P, "diffusion-neumann", lam=1.0)
    assert abs(ref_prob.A - (st.M + 1.0 * st.K)).max() < 1e-12 * abs(ref_prob.A).max()
    assert all(abs(a - b).max() == 0 for a, b in zip(st.problem.P, ref_prob.P))  # same pruned prolongations
    for dt in (1e-4, 3.7e-2, 2.0):
        ops = st.family.operators(1.0, dt)
        ref = galerkin_operators(st.M + dt * st.K, st.problem.P)
        for k, (A, R) in enumerate(zip(ops, ref)):
            assert A.shape == R.shape
            err = abs(A - R).max() / abs(R).max()
            assert err < 1e-12, (dt, k, err)
    # the coarse operators are not trivially equal: mass and stiffness parts both matter
    o1, o2 = st.family.operators(1.0, 1e-3)[2], st.family.operators(1.0, 1.0)[2]
    assert abs(o1 - o2).max() > 0.1 * abs(o2).max()


def test_time_stepping_matches_direct_solves(torus3):
    from nestmg.timestepping import diffusion_stepper

    tets, P = torus3
    V0 = tets[0][0]
    st = diffusion_stepper(tets, P)
    rng = np.random.default_rng(3)
    dts = 10.0 ** rng.uniform(-4, -1, size=4)
    u = np.exp(-20 * np.sum((V0 - V0[0]) ** 2, axis=1))
    u_ref = u.copy()
    iters = []
    for dt in dts:
        u, info = st.step(u, dt, tol=1e-10)
        assert info["converged"] and info["final_residual"] <= 1.01e-10
        iters.append(info["iterations"])
        u_ref = spla.spsolve(sp.csc_matrix(st.M + dt * st.K), st.M @ u_ref)
        assert np.abs(u - u_ref).max() <= 1e-6 * np.abs(u_ref).max()
    # a multigrid-preconditioned solve, not a Krylov crawl: few iterations per step
    assert max(iters) <= 25, iters
    # diffusion conserves the mass-weighted integral (natural boundary)
    m = st.M.diagonal()
    u0 = np.exp(-20 * np.sum((V0 - V0[0]) ** 2, axis=1))
    assert abs(m @ u - m @ u0) <= 1e-6 * (m @ u0)


def test_stepper_rejects_bad_input(torus3):
    from nestmg.timestepping import diffusion_stepper
    from solvers import SolverInputError
    from solvers.shifted import ShiftedGalerkin

    tets, P = torus3
    st = diffusion_stepper(tets, P)
    n = st.M.shape[0]
    with pytest.raises(ValueError, match="time step"):
        st.step(np.zeros(n), -1.0)
    with pytest.raises(ValueError, match="shape"):
        st.step(np.zeros(n + 1), 0.1)
    with pytest.raises(SolverInputError, match="same shape"):
        ShiftedGalerkin(st.M, st.K[:-1, :-1], st.problem.P)


def test_stepper_with_user_matrices_and_both_cycles(torus3):
    """A simulation code's own K and M (here: a consistent mass matrix and a conductivity of 3) and the
    two cycle presets: same states to the tolerance; the fast cycle is the textbook V(1,1) (forward GS,
    no local sweeps), the robust one needs fewer iterations."""
    from nestmg.timestepping import diffusion_stepper
    from solvers.fem import stiffness_matrix

    tets, P = torus3
    V0, T0 = tets[0]
    K = 3.0 * stiffness_matrix(V0, T0)
    # consistent P1 mass matrix: vol/20 (1 + delta_ij) per tet
    e = V0[T0[:, 1:]] - V0[T0[:, :1]]
    vol = np.abs(np.linalg.det(e)) / 6.0
    rows = np.repeat(T0, 4, axis=1).ravel()
    cols = np.tile(T0, (1, 4)).ravel()
    vals = (vol[:, None] / 20.0 * (1.0 + np.eye(4).ravel()[None, :])).ravel()
    Mc = sp.csr_matrix((vals, (rows, cols)), shape=(len(V0), len(V0)))
    fast = diffusion_stepper(tets, P, K=K, M=Mc)
    assert fast.setup_seconds["assembly"] < 0.5 and fast.problem.local_nodes is None
    robust = diffusion_stepper(tets, P, K=K, M=Mc, smoothing="robust")
    assert robust.problem.local_nodes is not None and len(robust.problem.local_nodes) > 0
    u0 = np.exp(-20 * np.sum((V0 - V0[0]) ** 2, axis=1))
    dt = 3e-3
    uf, i_f = fast.step(u0, dt, tol=1e-10)
    ur, i_r = robust.step(u0, dt, tol=1e-10)
    ref = spla.spsolve(sp.csc_matrix(Mc + dt * K), Mc @ u0)
    for u in (uf, ur):
        assert np.abs(u - ref).max() <= 1e-7 * np.abs(ref).max()
    assert i_r["iterations"] <= i_f["iterations"] <= 30
    ml = fast.problem.multigrid(SolverOptions(smoothing="fast"))
    assert ml.levels[0].presmoother.params.get("sweep") == "forward" and "local_nodes" not in ml.levels[0].presmoother.params
    with pytest.raises(ValueError, match="smoothing"):
        diffusion_stepper(tets, P, smoothing="quick")
    with pytest.raises(ValueError, match="shape"):
        diffusion_stepper(tets, P, K=K[:-1, :-1], M=Mc)
