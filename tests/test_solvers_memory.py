"""solvers.memory: size bounds before allocating, and a clear MemoryError subclass when they do not fit."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from solvers import InsufficientMemoryError, MultigridSolver, SolverError
from solvers.errors import SolverInputError
from solvers.fem import boundary_nodes, stiffness_matrix
from solvers.gallery import kuhn_cube_hierarchy
from solvers.memory import available_memory, check_memory, galerkin_bytes, galerkin_nnz_estimate, parse_bytes
from solvers.multilevel import restrict_prolongations


@pytest.fixture(scope="module")
def cube():
    meshes, Ps = kuhn_cube_hierarchy(8, 3)
    V, T = meshes[0]
    return stiffness_matrix(V, T), Ps


def test_galerkin_estimate_exact_on_small_levels(cube):
    A, Ps = cube
    Ak = A
    for P in Ps:  # 729 -> 125 -> 27 nodes: the coarse rows are all formed (<= 256)
        nnz_ap, nnz_c = galerkin_nnz_estimate(Ak, P, sample=256)
        Ac = sp.csr_matrix(P.T @ (Ak @ P))
        assert Ac.nnz <= nnz_c <= 1.05 * Ac.nnz  # structural count >= numeric (a few cancel)
        if Ak.shape[0] <= 256:
            assert nnz_ap >= (Ak @ P).nnz
        else:
            assert abs(nnz_ap - (Ak @ P).nnz) <= 0.2 * (Ak @ P).nnz
        assert galerkin_bytes(Ak, P) >= 16 * ((Ak @ P).nnz + 3 * Ac.nnz)
        Ak = Ac


def test_galerkin_estimate_sampled_within_20_percent():
    meshes, Ps = kuhn_cube_hierarchy(16, 2)  # 4913 fine nodes, 729 coarse: both sampled
    V, T = meshes[0]
    A = stiffness_matrix(V, T)
    nnz_ap, nnz_c = galerkin_nnz_estimate(A, Ps[0], sample=256)
    assert abs(nnz_ap - (A @ Ps[0]).nnz) <= 0.2 * (A @ Ps[0]).nnz
    Ac = sp.csr_matrix(Ps[0].T @ A @ Ps[0])
    assert abs(nnz_c - Ac.nnz) <= 0.2 * Ac.nnz
    ap, c = galerkin_nnz_estimate(A, Ps[0], sample=10**6)  # every row formed: upper bounds
    assert ap >= (A @ Ps[0]).nnz and Ac.nnz <= c <= 1.05 * Ac.nnz


def test_parse_and_check(monkeypatch):
    assert parse_bytes("512M") == 512 * 1024**2 and parse_bytes("2G") == 2 * 1024**3
    assert parse_bytes("1.5e3") == 1500 and parse_bytes(4096) == 4096 and parse_bytes("3KiB") == 3072
    for bad in ("lots", "-1G", "0", "nanM"):
        with pytest.raises(SolverInputError):
            parse_bytes(bad)
    monkeypatch.delenv("NESTMG_MEMORY_LIMIT", raising=False)
    avail, source = available_memory()
    assert avail is not None and 10 * 1024**2 < avail and source == "available system memory"
    check_memory(1024, "a kilobyte")  # fits
    monkeypatch.setenv("NESTMG_MEMORY_LIMIT", "1M")
    assert available_memory() == (1024**2, "$NESTMG_MEMORY_LIMIT")
    with pytest.raises(InsufficientMemoryError) as ei:
        check_memory(3 * 1024**2, "three megabytes")
    e = ei.value
    assert isinstance(e, MemoryError) and isinstance(e, SolverError)
    assert e.needed == 3 * 1024**2 and e.available == 1024**2
    assert "three megabytes needs about 3.0 MB but only 1.0 MB" in str(e) and "NESTMG_MEMORY_LIMIT" in str(e)


def test_multigrid_setup_refuses_a_galerkin_level_that_does_not_fit(cube, monkeypatch):
    A, Ps = cube
    meshes, _ = kuhn_cube_hierarchy(8, 3)
    V, T = meshes[0]
    free = np.setdiff1d(np.arange(len(V)), boundary_nodes(T))
    Pf, _ = restrict_prolongations(Ps, free)
    Af = A[free][:, free]
    need1 = galerkin_bytes(Af, Pf[0])
    # just below what level 1 needs: refused before the product, naming the level
    monkeypatch.setenv("NESTMG_MEMORY_LIMIT", str(need1 - 1))
    with pytest.raises(InsufficientMemoryError, match=r"Galerkin operator of level 1 "):
        MultigridSolver(Af, Pf)
    # enough for level 1 but not level 2? level 2 is smaller, so both fit at need1
    monkeypatch.setenv("NESTMG_MEMORY_LIMIT", str(need1))
    ml = MultigridSolver(Af, Pf)
    x = ml.solve(np.ones(len(free)), tol=1e-8)
    assert np.linalg.norm(np.ones(len(free)) - Af @ x) <= 1e-8 * np.sqrt(len(free))
