"""Embedded elasticity on the coarsest level (nestmg.embedded)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from nestmg import NestmgInputError
from nestmg.elasticity import setup_elasticity
from nestmg.embedded import embedded_solve
from solvers.gallery import kuhn_cube_hierarchy


def _fine_solution(tets, P):
    prob = setup_elasticity(tets, P, "elasticity-clamped", nu=0.3)
    if not P:
        return prob.expand(sp.linalg.spsolve(prob.A, prob.b))
    x = prob.multigrid().solve(prob.b, tol=1e-10, accel="cg", maxiter=300)
    return prob.expand(x)


def _box(meshes):
    return [(V * [2.0, 1.0, 1.0], T) for V, T in meshes]  # a 2 x 1 x 1 beam, clamped at x = 0


def test_identity_prolongation_gives_the_fine_solution():
    meshes, _ = kuhn_cube_hierarchy(4, 1)
    tets = _box(meshes) * 2
    u_f = _fine_solution(tets[:1], [])
    for model in ("filled", "fraction", "galerkin"):
        sol = embedded_solve(tets, [sp.identity(len(tets[0][0]), format="csr")], model=model)
        assert np.abs(sol.u_fine - u_f).max() <= 1e-10 * np.abs(u_f).max()


def test_nested_kuhn_levels_fractions_and_galerkin(rng):
    meshes, Ps = kuhn_cube_hierarchy(8, 3)
    tets = _box(meshes)
    frac = embedded_solve(tets, Ps, model="fraction")
    gal = embedded_solve(tets, Ps, model="galerkin")
    # same domain, exactly nested: every coarse tet is full and P^T K P is the coarse stiffness
    assert np.abs(frac.u_coarse - gal.u_coarse).max() <= 1e-9 * np.abs(gal.u_coarse).max()
    u_f = _fine_solution(tets, Ps)
    pts = rng.uniform([0, 0, 0], [2, 1, 1], (50, 3))
    from nestmg.prolongation import prolongation

    S, _ = prolongation(pts, *tets[0])
    sol = embedded_solve(tets, Ps, S, model="filled")
    assert np.allclose(sol.u_points, S @ sol.u_fine)
    err = np.linalg.norm(sol.u_fine - u_f) / np.linalg.norm(u_f)
    assert 1e-3 < err < 0.6  # a coarse (2x2x2-cell) beam: stiffer, but the same deflection's scale


def test_cage_embedding_on_a_nested_torus():
    pytest.importorskip("tetgen")
    from nestmg import shapes
    from nestmg import MeshingOptions, SizingOptions
    from nestmg.hierarchy import tet_hierarchy

    S = shapes.nested_isosurfaces("torus", [0.0, 0.1, 0.3], [20, 12, 8])
    tets, P, _, _ = tet_hierarchy(S, sizing=SizingOptions(coarsening=None),
                                  meshing=MeshingOptions(mesher="tetgen"), cache=False, progress=False)
    u_f = _fine_solution(tets, P)
    errs = {}
    for model in ("filled", "fraction", "galerkin"):
        sol = embedded_solve(tets, P, model=model)
        assert sol.u_fine.shape == u_f.shape and np.all(np.isfinite(sol.u_fine))
        errs[model] = np.linalg.norm(sol.u_fine - u_f) / np.linalg.norm(u_f)
    assert errs["galerkin"] < errs["filled"] and errs["galerkin"] < 0.5  # the energy-best coarse answer


def test_bad_inputs_are_refused():
    meshes, Ps = kuhn_cube_hierarchy(4, 2)
    with pytest.raises(NestmgInputError, match="model"):
        embedded_solve(meshes, Ps, model="cage")
    with pytest.raises(NestmgInputError, match="len"):
        embedded_solve(meshes, [])
    with pytest.raises(NestmgInputError, match="band"):
        embedded_solve(meshes, Ps, band=0.0)
