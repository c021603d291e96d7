"""Tests of solvers.baselines: pyamg SA / energy SA / Ruge–Stüben, SuperLU, CHOLMOD (if installed)."""

import json

import numpy as np
import pytest

from solvers import fem
from solvers.baselines import (
    BASELINES,
    BaselineUnavailableError,
    cholmod,
    cholmod_available,
    pyamg_rs,
    pyamg_sa,
    run_baselines,
    scipy_direct,
)
from solvers.errors import IncompatibleRHSError, SolverInputError
from solvers.gallery import kuhn_cube_hierarchy


@pytest.fixture(scope="module")
def problems():
    meshes, Ps = kuhn_cube_hierarchy(12, 3)
    V, T = meshes[0]
    K, M = fem.stiffness_matrix(V, T), fem.mass_matrix(V, T)
    ds = fem.eliminate_dirichlet(K, fem.load_vector(M, 1.0), fem.boundary_nodes(T))
    bn = fem.project_rhs(fem.load_vector(M, np.cos(np.pi * V[:, 2])))
    return ds, K, bn, Ps


def test_all_baselines_agree_on_dirichlet(problems):
    ds, *_ = problems
    results = run_baselines(ds.A, ds.b, tol=1e-10)
    ref = results["scipy_splu"]
    assert ref.residuals[-1] < 1e-12 and ref.iterations == 0 and ref.info["factor_nnz"] > ds.A.nnz
    for name, r in results.items():
        if isinstance(r, str):
            assert name == "cholmod" and not cholmod_available()
            continue
        assert r.converged, name
        assert r.setup_seconds >= 0 and r.solve_seconds > 0
        assert np.abs(r.x - ref.x).max() < 1e-8 * np.abs(ref.x).max(), name
        json.dumps(r.to_dict())
    for name in ("pyamg_sa", "pyamg_sa_energy", "pyamg_rs"):
        assert 1 <= results[name].iterations <= 30, (name, results[name].iterations)
        assert results[name].residuals[-1] <= 1e-10


def test_neumann_baselines_zero_mean(problems):
    _ds, K, bn, Ps = problems
    xs = {}
    for f in (pyamg_sa, pyamg_rs, scipy_direct):
        r = f(K, bn, nullspace="constant")
        assert abs(r.x.mean()) < 1e-12
        # pyamg's CG on this singular system stalls near its tol (1e-8) in round-off: 2.1e-7 once in a CI
        # run (2026-12-05, not reproduced here) after the two restarts; a wrong solution is at ~1
        assert np.linalg.norm(K @ r.x - bn) <= 1e-6 * np.linalg.norm(bn)
        xs[r.name] = r.x
    from solvers import MultigridSolver

    x, info = MultigridSolver(K, Ps, nullspace="constant").solve(bn, tol=1e-10, accel="cg", return_info=True)
    assert info["converged"] and info["iterations"] <= 12
    assert np.abs(x - xs["scipy_splu"]).max() < 1e-7 * np.abs(xs["scipy_splu"]).max()
    with pytest.raises(IncompatibleRHSError):
        pyamg_sa(K, bn + 1.0, nullspace="constant")


def test_energy_smoothing_is_really_different(problems):
    ds, *_ = problems
    a = pyamg_sa(ds.A, ds.b, tol=1e-10)
    b = pyamg_sa(ds.A, ds.b, tol=1e-10, smooth="energy")
    assert a.name == "pyamg_sa" and b.name == "pyamg_sa_energy"
    assert a.residuals != b.residuals


def test_cholmod_optional(problems):
    ds, *_ = problems
    if cholmod_available():
        r = cholmod(ds.A, ds.b)
        assert r.residuals[-1] < 1e-12
    else:
        with pytest.raises(BaselineUnavailableError, match="scikit-sparse"):
            cholmod(ds.A, ds.b)
        assert isinstance(BaselineUnavailableError("x"), ImportError)


def test_baseline_errors(problems):
    ds, *_ = problems
    with pytest.raises(SolverInputError, match="unknown baseline"):
        run_baselines(ds.A, ds.b, names=["petsc"])
    with pytest.raises(SolverInputError):
        scipy_direct(ds.A, ds.b, method="umfpack")
    r = run_baselines(ds.A, ds.b, names=["scipy_splu"], max_direct_size=10)
    assert r["scipy_splu"].startswith("skipped")
    assert set(BASELINES) == {"pyamg_sa", "pyamg_sa_energy", "pyamg_rs", "scipy_splu", "cholmod"}
