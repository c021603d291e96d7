"""Tests of solvers.krylov: PCG with residual history, and MG-PCG (``MultigridSolver.solve(accel="cg")``)."""

import numpy as np
import pytest
import scipy.sparse as sp

import solvers
from solvers import DEFAULT_MAXITER, MultigridSolver, fem, pcg, restrict_prolongations
from solvers.errors import SolverInputError
from solvers.gallery import kuhn_cube_hierarchy


@pytest.fixture(scope="module")
def system():
    meshes, Ps = kuhn_cube_hierarchy(16, 3)
    V, T = meshes[0]
    K, M = fem.stiffness_matrix(V, T), fem.mass_matrix(V, T)
    ds = fem.eliminate_dirichlet(K, fem.load_vector(M, 1.0), fem.boundary_nodes(T))
    Pf, _ = restrict_prolongations(Ps, ds.free)
    return ds, Pf, K, Ps, M


def test_pcg_plain_and_preconditioned(system):
    ds, Pf, *_ = system
    plain = pcg(ds.A, ds.b, tol=1e-8)
    ml = MultigridSolver(ds.A, Pf)
    pre = pcg(ds.A, ds.b, M=ml.aspreconditioner(), tol=1e-8)
    for r in (plain, pre):
        assert r.converged and r.residuals[0] == 1.0 and r.residuals[-1] <= 1e-8
        assert len(r.residuals) == r.iterations + 1
        assert np.linalg.norm(ds.b - ds.A @ r.x) <= 1.01e-8 * np.linalg.norm(ds.b)
    assert pre.iterations <= 10 and plain.iterations > 4 * pre.iterations


def test_mg_pcg_is_solve_with_accel_cg(system):
    """MG-PCG has one entry point, ``MultigridSolver.solve(accel="cg")``: every cycle type converges,
    and it takes the same steps as :func:`pcg` with the cycle as preconditioner."""
    ds, Pf, *_ = system
    ml = MultigridSolver(ds.A, Pf)
    for cycle in ("V", "W", "F"):
        x, info = ml.solve(ds.b, tol=1e-10, cycle=cycle, accel="cg", return_info=True)
        assert info["converged"] and info["iterations"] <= 12 and info["seconds"] > 0
        # residual history decreases overall by >= 10x every 3 iterations on average
        h = np.array(info["residuals"])
        assert (h[-1] / h[0]) ** (1 / info["iterations"]) < 0.3
        ref = pcg(ds.A, ds.b, M=ml.aspreconditioner(cycle), tol=1e-10)
        assert ref.iterations == info["iterations"] and np.allclose(ref.x, x, rtol=0, atol=1e-12)
    assert not hasattr(solvers, "mg_pcg")  # the 0.1 wrapper (another default maxiter) is gone


def test_one_default_maxiter():
    """Every multigrid entry point caps iterations at the same DEFAULT_MAXITER."""
    import inspect

    from nestmg import SolverOptions
    from nestmg.cli import build_parser
    from nestmg.geodesics import multigrid_solve
    from nestmg.timestepping import DiffusionStepper, implicit_diffusion
    from solvers.petsc import PetscMultigrid

    for f in (MultigridSolver.solve, PetscMultigrid.solve, multigrid_solve, DiffusionStepper.step,
              implicit_diffusion):
        assert inspect.signature(f).parameters["maxiter"].default == DEFAULT_MAXITER, f.__qualname__
    assert SolverOptions().maxiter == DEFAULT_MAXITER  # solve_on_hierarchy's and the CLI's
    args = build_parser().parse_args(["solve", "shape:torus"])
    assert args.maxiter == DEFAULT_MAXITER


def test_pcg_neumann_nullspace(system):
    _ds, _Pf, K, Ps, _M = system
    ml = MultigridSolver(K, Ps, nullspace="constant")
    b = fem.project_rhs(np.random.default_rng(0).standard_normal(K.shape[0]))
    r = pcg(K, b, M=ml.aspreconditioner(), tol=1e-9, nullspace="constant")
    assert r.converged and r.iterations <= 12 and abs(r.x.mean()) < 1e-14


def test_pcg_reports_nonfinite_preconditioner(system):
    ds, _Pf, *_ = system
    bad = sp.linalg.LinearOperator(ds.A.shape, matvec=lambda v: np.asarray(v, dtype=float) * np.nan)
    r = pcg(ds.A, ds.b, M=bad)
    assert r.nonfinite and not r.converged and r.iterations == 1


def test_pcg_input_errors(system):
    ds, *_ = system
    with pytest.raises(SolverInputError):
        pcg(ds.A, np.ones(3))
    with pytest.raises(SolverInputError):
        pcg(ds.A, np.full(ds.A.shape[0], np.inf))


def test_cg_below_the_attainable_accuracy_stops_with_its_best_iterate(system):
    """Asked for a residual round-off does not allow, MG-PCG stops after STALL_ITERATIONS iterations with
    no new minimum and returns its best iterate, instead of drifting until maxiter (on clamped elasticity
    at ν = 0.45, W-preconditioned, it ended at residual 1.9 after 500 iterations)."""
    ds, Pf, *_ = system
    ml = MultigridSolver(ds.A, Pf)
    with pytest.warns(solvers.ConvergenceWarning, match=r"stagnated.*round-off alone allows about"):
        x, info = ml.solve(ds.b, tol=1e-30, maxiter=200, accel="cg", return_info=True)
    assert not info["converged"] and info["iterations"] < 60
    rtrue = np.linalg.norm(ds.b - ds.A @ x) / np.linalg.norm(ds.b)
    assert rtrue < 1e-13 and info["residuals"][-1] == pytest.approx(rtrue, rel=1e-6)
    r = pcg(ds.A, ds.b, M=ml.aspreconditioner(), tol=1e-30, maxiter=200)
    assert r.stagnated and 1e-17 < r.attainable < 1e-12 and min(r.residuals[:-1]) <= 1e-13
    ok = pcg(ds.A, ds.b, M=ml.aspreconditioner(), tol=1e-10)
    assert ok.converged and not ok.stagnated and ok.attainable is None


def _counted(op):
    """``op`` as a LinearOperator that counts its applications."""
    import scipy.sparse.linalg as spla

    calls = [0]

    def mv(v):
        calls[0] += 1
        return op @ v if sp.issparse(op) else op.matvec(v)

    return spla.LinearOperator(op.shape, matvec=mv, dtype=np.float64), calls


@pytest.mark.parametrize("problem", ["dirichlet", "neumann"])
def test_pcg_takes_pyamgs_steps_without_the_wasted_work(system, problem):
    """Our PCG takes pyamg's CG steps (residual history equal to 1e-9 relative) but applies the cycle once
    per iteration (pyamg: once more, after the last residual) and ``A`` once per iteration plus once for
    the true final residual (pyamg: also ``b - A x0`` from a zero ``x0`` and every 8th residual again)."""
    from pyamg.krylov import cg as pyamg_cg

    ds, Pf, K, Ps, _ = system
    if problem == "dirichlet":
        A, b, ml = ds.A, ds.b, MultigridSolver(ds.A, Pf)
    else:
        b = fem.project_rhs(np.random.default_rng(1).standard_normal(K.shape[0]))
        A, ml = K, MultigridSolver(K, Ps, nullspace="constant")
    Ac, a_calls = _counted(A)
    Mc, m_calls = _counted(ml.aspreconditioner())
    nullspace = "constant" if problem == "neumann" else None
    r = pcg(Ac, b, M=Mc, tol=1e-8, nullspace=nullspace)
    assert r.converged and 5 <= r.iterations <= 12
    assert m_calls[0] == r.iterations, (m_calls[0], r.iterations)
    # the true residual is formed once, again after removing the mean (A times a constant is round-off)
    assert a_calls[0] == r.iterations + (2 if nullspace else 1)
    ref: list = []
    Ar, ar_calls = _counted(A)
    Mr, mr_calls = _counted(ml.aspreconditioner())
    pyamg_cg(Ar, b, x0=np.zeros_like(b), tol=1e-8, criteria="rr", M=Mr, residuals=ref)
    ref = np.array(ref) / np.linalg.norm(b)
    assert len(ref) == r.iterations + 1 and mr_calls[0] == r.iterations + 1
    assert ar_calls[0] >= r.iterations + 2
    assert np.abs(np.array(r.residuals[:-1]) - ref[:-1]).max() <= 1e-9 * ref[0]
    assert abs(r.residuals[-1] - ref[-1]) <= 1e-2 * ref[-1]  # ours: the true residual, pyamg's recursive one


def test_pcg_names_a_breakdown(system):
    """CG on an indefinite matrix stops at the first non-positive curvature and says which operator showed
    it (``breakdown``), and so does an indefinite preconditioner; neither reports convergence."""
    import scipy.sparse.linalg as spla

    ds, *_ = system
    n = ds.A.shape[0]
    signs = np.where(np.arange(n) % 2, 1.0, -1.0)
    indefinite = sp.csr_matrix(ds.A + sp.diags(5.0 * ds.A.diagonal() * (signs < 0)))
    indefinite = sp.csr_matrix(sp.diags(signs) @ indefinite @ sp.diags(np.ones(n)))
    indefinite = sp.csr_matrix((indefinite + indefinite.T) / 2)
    r = pcg(indefinite, ds.b, tol=1e-8, maxiter=200)
    assert not r.converged and r.breakdown is not None and r.breakdown.startswith("A is not positive definite")
    negative = spla.LinearOperator((n, n), matvec=lambda v: -v, dtype=np.float64)
    r = pcg(ds.A, ds.b, M=negative, tol=1e-8)
    assert not r.converged and r.iterations == 0
    assert r.breakdown is not None and r.breakdown.startswith("the preconditioner is not positive definite")
    ok = pcg(ds.A, ds.b, tol=1e-8)
    assert ok.converged and ok.breakdown is None
