"""Red refinement (the default fine level): exact nesting, exact prolongation, quality, and the solver."""

from __future__ import annotations

import igl
import numpy as np
import pytest

from nestmg import SolverOptions, shapes
from nestmg.refine import refine_tets
from nestmg.tetmesh import tet_quality, tet_volumes, tetrahedralize
from solvers.fem import boundary_faces


@pytest.fixture(scope="module")
def torus_tets():
    V, F = shapes.torus(res=16)
    return tetrahedralize(V, F, edge_length_abs=0.15)


def test_refinement_is_exactly_nested(torus_tets):
    V, T = torus_tets
    V2, T2, P = refine_tets(V, T)
    assert len(T2) == 8 * len(T)
    assert np.array_equal(V2[: len(V)], V)  # parent nodes first, unchanged
    vol = tet_volumes(V2, T2)
    assert vol.min() > 0  # every child positively oriented
    assert vol.sum() == pytest.approx(tet_volumes(V, T).sum(), rel=1e-12)  # same domain
    assert len(boundary_faces(T2)[0]) == 4 * len(boundary_faces(T)[0])  # conforming, boundary split in 4
    # P is exact linear interpolation: linear functions are reproduced to round-off
    a = np.array([1.0, -2.0, 0.5])
    assert np.abs(P @ (V @ a + 3.0) - (V2 @ a + 3.0)).max() < 1e-12
    assert np.allclose(np.asarray(P.sum(axis=1)).ravel(), 1.0)
    # nested P1 spaces: the Galerkin operator of the refined stiffness is the parent's own stiffness
    K, K2 = -igl.cotmatrix(V, T), -igl.cotmatrix(V2, T2)
    assert abs(P.T @ K2 @ P - K).max() < 1e-12 * abs(K).max()
    M, M2 = igl.massmatrix(V, T), igl.massmatrix(V2, T2)
    assert (P.T @ M2 @ P).sum() == pytest.approx(M.sum(), rel=1e-12)


def test_refinement_keeps_quality(torus_tets):
    """Shortest-diagonal splitting: the children's angles stay within a fixed factor of the parent's."""
    V, T = torus_tets
    V2, T2, _ = refine_tets(V, T)
    q, q2 = tet_quality(V, T), tet_quality(V2, T2)
    assert q2["min_dihedral_deg"] > 0.6 * q["min_dihedral_deg"]
    assert q2["n_slivers"] == 0
    # a second refinement does not degrade further (at most 3 similarity classes, Bey 1995)
    V3, T3, _ = refine_tets(V2, T2)
    assert tet_quality(V3, T3)["min_dihedral_deg"] > 0.95 * q2["min_dihedral_deg"]


def test_default_hierarchy_refines_and_converges():
    """`build_hierarchy` defaults on a small genus-2 solid: refined fine level, cage below, goals of issue 14."""
    from nestmg import build_hierarchy
    from nestmg.run import solve_on_hierarchy

    V, F = shapes.genus2(res=20)
    h = build_hierarchy(V, F, levels=3, method="nested", cache=False, progress=False)
    assert h.certified and h.n_outside == [0, 0]
    assert h.prolongation_reports[0].extrapolation.startswith("none")
    assert len(h.tets[0][1]) == 8 * len(h.tets[1][1])
    ratio = len(h.tets[1][1]) / len(h.tets[2][1])
    assert ratio > 3.0  # the cage level is coarser by a real factor (8 asked; small meshes keep more)
    tets = h.tets_in("normalized")
    res = {p: solve_on_hierarchy(tets, h.P, p, cost=False)
           for p in ("poisson-dirichlet", "poisson-neumann", "diffusion-neumann")}
    no_local = {p: solve_on_hierarchy(tets, h.P, p, SolverOptions(local=False), cost=False)
                for p in ("poisson-neumann", "diffusion-neumann")}
    # default cycle (boundary-layer sweeps + 2 coarse sweeps), measured over two TetWild runs:
    # 0.094-0.109 / 0.130-0.165 / 0.100-0.126; the plain V(1,1): 0.124-0.140 / 0.244-0.324 / 0.212-0.272
    # (one CI run of fa363c9 drew 0.202 for Neumann: hierarchies differ at round-off)
    assert res["poisson-dirichlet"]["factor"] <= 0.2
    assert res["poisson-neumann"]["factor"] <= 0.25
    assert res["diffusion-neumann"]["factor"] <= 0.2
    # the local sweeps are what removes the Neumann boundary error, where it shows: over 16 fresh hierarchies
    # (2026-12-05) the cycle without them had 0.236-0.266 (Neumann) / 0.201-0.236 (diffusion) in 11, and the
    # default 0.50-0.71 of that; in the others it was already at 0.16-0.19 / 0.15-0.16 (default 0.67-0.83 of
    # it, 0.92 once). A local sweep that did nothing would give exactly 1.
    for p in no_local:
        ratio, slow = res[p]["factor"] / no_local[p]["factor"], no_local[p]["factor"] > 0.2
        assert ratio <= (0.85 if slow else 1.0), (p, res[p]["factor"], no_local[p]["factor"])
    pcg = solve_on_hierarchy(tets, h.P, "poisson-neumann", SolverOptions(accel="cg"), cost=False)
    assert pcg["converged"] and pcg["iterations"] <= 9
